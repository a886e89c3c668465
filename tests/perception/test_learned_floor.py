"""floornet's second pass relative to a floor colour learned on the way."""

from __future__ import annotations

import numpy as np

from app.config import DEFAULT_CONFIG_PATH, load_config
from app.mapping.floor_memory import bgr_to_scaled_lab
from app.mapping.frames import Pose2D
from app.perception.floor_net import (
    OUTPUT_HEIGHT_PX,
    OUTPUT_WIDTH_PX,
    FloorNetOutput,
    LearnedPassBackoff,
    choose_learned_reference,
    connected_to,
    learned_floor_unsure,
)
from app.perception.pipeline import FloorSegmenter
from app.sim.setup import renderer_from_config


def test_connected_to_keeps_only_parts_touching_the_anchor_or_the_bottom() -> None:
    extra = np.zeros((6, 6), bool)
    extra[0:2, 0:2] = True  # floating: dropped
    extra[2:4, 4:6] = True  # touches the anchor (diagonally): kept
    extra[5, 0] = True  # on the bottom row: kept
    anchor = np.zeros((6, 6), bool)
    anchor[4, 3] = True
    kept = connected_to(extra, anchor)
    expected = np.zeros((6, 6), bool)
    expected[2:4, 4:6] = True
    expected[5, 0] = True
    assert np.array_equal(kept, expected)


def test_the_reference_is_the_learned_colour_that_explains_the_missed_floor() -> None:
    lab = np.zeros((10, 10, 3), np.float32)
    lab[:5] = (0.5, 0.1, 0.1)  # the missed part has colour A
    first = np.zeros((10, 10), bool)
    first[5:] = True  # the first pass found the lower half (colour 0)
    zone = np.zeros(3, np.float32)
    a, b = (0.5, 0.1, 0.1), (-0.5, 0.0, 0.0)
    assert choose_learned_reference(lab, ~first, zone, (b, a)) == a
    assert choose_learned_reference(lab, ~first, zone, (b,)) is None
    # A learned colour like the safe zone's adds nothing: not chosen.
    assert choose_learned_reference(lab, ~first, zone, ((0.01, 0.0, 0.0),)) is None
    # Nor one that matches only cells the pass may not change (the near field).
    assert choose_learned_reference(lab, np.zeros_like(first), zone, (b, a)) is None


def test_a_learned_tile_colour_makes_the_kitchen_floor_from_the_wood_floor() -> None:
    config = load_config(DEFAULT_CONFIG_PATH)
    renderer = renderer_from_config(config)
    # In the living room, 0.45 m from the doorway, looking into the tiled kitchen.
    frame = renderer.render(Pose2D(4.05, 2.8, 0.0))
    segmenter = FloorSegmenter(config.perception, method="floornet")
    truth = frame.floor_mask

    def scores() -> tuple[float, float]:
        mask = segmenter.segment(frame.image).floor_mask
        return float((mask & truth).sum() / (mask | truth).sum()), float(
            (mask & truth).sum() / max(mask.sum(), 1)
        )

    iou_before, _ = scores()
    assert segmenter.segment(frame.image).learned_floor_reference is None
    tiles = bgr_to_scaled_lab(np.array([[0xBA, 0xC8, 0xCF]], np.float32))[0]
    segmenter.learned_floor = (tuple(float(v) for v in tiles),)  # type: ignore[assignment]
    iou_after, precision_after = scores()
    assert iou_after >= iou_before + 0.2, (iou_before, iou_after)
    assert precision_after >= 0.98
    result = segmenter.segment(frame.image)
    assert result.learned_floor_reference is not None
    assert result.learned_floor_added_share >= 0.1
    assert result.unsure_mask is None

    # Deferred (the daemon's budget): the first pass's mask, and where the pass would
    # have looked is unsure: it covers the floor the pass adds and none of the first's.
    segmenter.learned_pass_due = False
    deferred = segmenter.segment(frame.image)
    first = deferred.floor_mask
    assert deferred.learned_floor_reference is None
    assert deferred.unsure_mask is not None
    assert not (deferred.unsure_mask & first).any()
    added = result.floor_mask & ~first
    assert (deferred.unsure_mask & added).sum() >= 0.9 * added.sum()
    assert not deferred.unsure_mask[round(0.6 * first.shape[0]) :].any()  # not the near field
    segmenter.learned_pass_due = True
    segmenter.learned_floor = ()
    assert scores()[0] == iou_before


def test_a_colour_whose_pass_adds_nothing_sits_out_doubling_spans() -> None:
    backoff = LearnedPassBackoff()
    wall, tiles = (0.3, 0.0, 0.0), (0.5, 0.1, 0.1)
    learned = (wall, tiles)
    runs = []
    for frame in range(100):
        eligible = backoff.eligible(learned)
        assert tiles in eligible  # the other colour is never held back
        if wall in eligible:
            runs.append(frame)
            backoff.observe(wall, 0.0)  # the pass for the wall colour adds nothing
        else:
            backoff.observe(None, 0.0)
    # It sits out 4, 8, 16, then 32 frames (the cap) each time.
    assert runs == [0, 5, 14, 31, 64, 97]


def test_a_pass_that_adds_floor_clears_its_colour_and_none_ran_changes_nothing() -> None:
    backoff = LearnedPassBackoff()
    tiles = (0.5, 0.1, 0.1)
    backoff.observe(tiles, 0.0)
    assert backoff.eligible((tiles,)) == ()
    for _ in range(4):
        backoff.observe(None, 0.0)
    assert backoff.eligible((tiles,)) == (tiles,)
    backoff.observe(tiles, 0.05)  # it added floor this time: no more skipping
    assert backoff.eligible((tiles,)) == (tiles,)
    backoff.observe(tiles, 0.0)  # and the next miss starts from the first span again
    for _ in range(3):
        assert backoff.eligible((tiles,)) == ()
        backoff.observe(None, 0.0)
    backoff.observe(None, 0.0)
    assert backoff.eligible((tiles,)) == (tiles,)


def test_unsure_cells_are_the_far_open_cells_of_the_learned_colour_grown_by_one() -> None:
    h, w = OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX
    tiles, wall = (0.5, 0.1, 0.1), (-0.5, 0.0, 0.0)
    lab = np.zeros((h, w, 3), np.float32)  # the wood, as the safe zone
    lab[10:22, 30:42] = tiles  # a patch of the kitchen's tiles, far ahead
    lab[0:5] = wall
    probability = np.zeros((h, w), np.float32)
    probability[30:] = 0.9  # the first pass found the wood from row 30 down
    first = FloorNetOutput(probability, 0.9)
    zone = np.zeros(3, np.float32)
    # At output size the frame is already the network's size: lab_scaled == lab_out.
    big = np.repeat(np.repeat(lab, 2, axis=0), 2, axis=1)
    unsure = learned_floor_unsure(big, first, zone, (tiles,))
    assert unsure is not None
    expected = np.zeros((h, w), bool)
    expected[9:23, 29:43] = True
    assert np.array_equal(unsure, expected)
    # No learned colour, or none that explains open far cells: nothing is unsure.
    assert learned_floor_unsure(big, first, zone, ()) is None
    assert learned_floor_unsure(big, first, zone, ((0.0, 0.5, -0.5),)) is None


def test_only_colours_whose_last_pass_added_floor_are_fruitful() -> None:
    backoff = LearnedPassBackoff()
    wall, tiles = (0.3, 0.0, 0.0), (0.5, 0.1, 0.1)
    assert backoff.fruitful((wall, tiles)) == ()  # not tried yet: the first pass stands
    backoff.observe(tiles, 0.05)
    backoff.observe(wall, 0.0)
    assert backoff.fruitful((wall, tiles)) == (tiles,)
    backoff.observe(tiles, 0.0)  # its latest pass added nothing
    assert backoff.fruitful((wall, tiles)) == ()
    backoff.observe(tiles, 0.05)
    backoff.eligible((wall,))  # tiles no longer learned: forgotten
    assert backoff.fruitful((wall, tiles)) == ()
