"""The safe-zone premise alone (`app.runtime.drive.zone_blocks`): perception's doubt
blocks the way unless the fresh map knows the zone's ground is floor."""

from __future__ import annotations

import numpy as np
import pytest

from app.config import FloornavConfig
from app.mapping.frames import GroundGrid, Pose2D
from app.messages import FloorMsg, MapMsg
from app.runtime.drive import zone_blocks

CONFIG = FloornavConfig.model_validate(
    {
        "perception": {"zone_min_floor_confidence": 0.5, "zone_min_known_floor": 0.6},
        "safety": {"perception_max_age_s": 0.5},
    }
)
NOW = 100.0


def floor(confidence: float, age_s: float = 0.05) -> FloorMsg:
    image = np.zeros((4, 4, 3), np.uint8)
    return FloorMsg(1, NOW - age_s, NOW, image, np.ones((4, 4), bool), "floornet", {}, confidence)


def map_msg(known: float | None, age_s: float = 0.08) -> MapMsg:
    return MapMsg(
        seq=1,
        capture_s=NOW - age_s,
        done_s=NOW,
        T_odom_robot=Pose2D(0.0, 0.0, 0.0),
        window_cells=np.zeros((2, 2), np.int8),
        window_grid=GroundGrid(0.1, 0.1, 0.1, 2, 2),
        path_xy=None,
        goal_xy=None,
        frontier_reason="",
        clearance_ahead_m=1.0,
        zone_known_floor=known,
    )


@pytest.mark.parametrize(
    ("confidence", "known", "blocks"),
    [
        (0.9, None, False),  # perception sees floor
        (0.5, 0.0, False),  # at the minimum is floor
        (0.2, None, True),  # perception doubts it, the map says nothing
        (0.2, 0.0, True),  # ...or knows none of it (or saw something standing there)
        (0.2, 0.59, True),  # ...or too little of it
        (0.2, 0.6, False),  # the map knows enough of it is floor: geometry over colour
        (0.2, 1.0, False),
    ],
)
def test_perceptions_doubt_blocks_unless_the_map_knows_the_zone_is_floor(
    confidence: float, known: float | None, blocks: bool
) -> None:
    assert zone_blocks(CONFIG, floor(confidence), map_msg(known), NOW) is blocks


def test_only_fresh_results_count() -> None:
    # A stale floor result blocks nothing here (the stale-perception stop holds then).
    assert not zone_blocks(CONFIG, floor(0.1, age_s=0.6), map_msg(None), NOW)
    assert not zone_blocks(CONFIG, None, None, NOW)
    # A stale map's knowledge does not lift a fresh doubt, and no map is no knowledge.
    assert zone_blocks(CONFIG, floor(0.1), map_msg(1.0, age_s=0.6), NOW)
    assert zone_blocks(CONFIG, floor(0.1), None, NOW)
