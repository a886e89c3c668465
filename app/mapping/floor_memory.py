"""Floor the robot knows is floor, and the floor appearances it learned on the way.

A colour method ends the floor wherever the floor's look changes (a rug, the kitchen's
tiles, a threshold), and a map fed only by it keeps every such edge as a wall. This
module is the map's memory of geometry and experience, beside the log-odds grid:

* ``confirmed``: world cells known to be flat floor, because the robot's footprint drove
  over them or motion parallax found them on the floor plane. On such a cell a colour
  boundary is not an obstacle (`FloorMemory.correct_patch` turns it back into floor)
  until geometry (parallax) shows something standing there (`FloorMemory.mark_standing`).
* ``driven``: the cells the robot has driven over, with the cells its centre crossed
  (its track): where the robot's body fitted, so the frontier search may cross the
  track's free cells with the body's clearance alone (`app.mapping.frontiers`). It is
  history, not proof: the pose it was marked at may be a cell or two off, so a standing
  mark still takes a driven cell out of the known floor. (Tried and not kept: keeping
  driven cells floor until a foot was seen there three times. With the pose 0.1-0.2 m
  off, the footprint lands on the edges of boxes the robot passed, and the two-room
  run lost its boxes from the map and hit one.)
* a colour layer: each world cell's mean colour as the camera saw it from close by (a
  cell's colour is only known while it is ahead of the robot, not when the robot stands
  on it).
* ``appearances``: the colours of confirmed floor (in the floor network's scaled CIELAB),
  clustered, each with the number of cells behind it. Perception uses them as extra
  safe-zone references (the thesis's safe zone, extended over time and space), so after
  one look at the kitchen's tiles they are floor in every later frame. A colour seen
  standing up is unlearned.

Pure computation on arrays; not thread-safe (the mapping stage owns it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D

# Appearances are kept in the floor network's scaled CIELAB, to be handed to it as they are.
from app.perception.floor_net import LAB_CENTER, LAB_SCALE

DRIVEN_FOOTPRINT = 1
"""`FloorMemory.driven` bit: the robot's footprint covered the cell."""
DRIVEN_TRACK = 2
"""`FloorMemory.driven` bit: the robot's centre passed within one cell of the cell's."""


@dataclass(frozen=True)
class FloorMemoryParams:
    """Attributes
    ----------
    near_m : float, cells farther than this ahead of the robot add no colour (far cells
        are few pixels, blurred, and their ground position is least certain)
    colour_rate : float in (0, 1], the weight of a new sighting in a cell's running mean
        colour once the cell has been seen a few times
    merge_distance : float, scaled-Lab distance within which a colour joins an existing
        appearance (0.12 is about 5 CIELAB units of lightness)
    min_cells : int, cells an appearance needs before perception uses it (about 0.1 m²
        at 5 cm cells: a lucky sighting of one plank does not make a material)
    max_appearances : int, the smallest appearance is dropped beyond this
    unlearn_distance : float, scaled-Lab distance within which a colour seen standing
        takes cells from an appearance
    unlearn_share : float in (0, 1], an appearance is unlearned from what stands only
        when at least this share of its colours is that appearance's: what parallax
        finds standing are mostly edges, and an edge's pixels include the floor beside
        it, so a minority of floor-coloured pixels says nothing against the floor
    standing_min_marks : int >= 1, geometric tests that must mark a cell standing (net of
        the tests that saw floor there) before it joins the `FloorMemory.standing` layer:
        one test's foot lands wherever its frame's colour floor happened to end (a
        threshold, a shadow), a real foot is found there again
    standing_max_marks : int >= standing_min_marks, the count saturates here, so a mark
        that held for minutes still leaves after a few tests that see floor there
    """

    near_m: float = 1.5
    colour_rate: float = 0.3
    merge_distance: float = 0.12
    min_cells: int = 40
    max_appearances: int = 8
    unlearn_distance: float = 0.10
    unlearn_share: float = 0.5
    standing_min_marks: int = 2
    standing_max_marks: int = 3

    def __post_init__(self) -> None:
        if not (self.near_m > 0 and 0 < self.colour_rate <= 1):
            raise ValueError("FloorMemoryParams: need near_m > 0 and 0 < colour_rate <= 1")
        if not 0 < self.unlearn_share <= 1:
            raise ValueError("FloorMemoryParams: unlearn_share must be in (0, 1]")
        if not (self.merge_distance > 0 and self.unlearn_distance > 0):
            raise ValueError("FloorMemoryParams: distances must be > 0")
        if self.min_cells < 1 or self.max_appearances < 1:
            raise ValueError("FloorMemoryParams: min_cells and max_appearances must be >= 1")
        if not 1 <= self.standing_min_marks <= self.standing_max_marks <= 255:
            raise ValueError(
                "FloorMemoryParams: need 1 <= standing_min_marks <= standing_max_marks <= 255"
            )


@numba.njit(cache=True, nogil=True)
def _patch_world_index(
    patch_x: NDArray[np.float64],
    patch_y: NDArray[np.float64],
    cos_t: float,
    sin_t: float,
    tx: float,
    ty: float,
    world_x_max: float,
    world_y_max: float,
    world_cell: float,
    w_rows: int,
    w_cols: int,
) -> NDArray[np.int64]:
    out = np.empty((patch_x.shape[0], patch_y.shape[0]), dtype=np.int64)
    inv = 1.0 / world_cell
    for i in range(patch_x.shape[0]):
        row_base = (world_x_max - (cos_t * patch_x[i] + tx)) * inv
        col_base = (world_y_max - (sin_t * patch_x[i] + ty)) * inv
        for j in range(patch_y.shape[0]):
            r = math.floor(row_base + sin_t * patch_y[j] * inv)
            c = math.floor(col_base - cos_t * patch_y[j] * inv)
            out[i, j] = r * w_cols + c if 0 <= r < w_rows and 0 <= c < w_cols else -1
    return out


def patch_world_index(
    patch_grid: GroundGrid, world_grid: GroundGrid, T_world_robot: Pose2D
) -> NDArray[np.int64]:
    """(patch rows, patch cols) int64: the flat world-grid index of each robot-frame
    patch cell's centre seen from ``T_world_robot`` (-1 off the world grid). The same
    mapping `app.mapping.occupancy.fuse_patch_labels` fuses with."""
    patch_x = patch_grid.x_max_m - (np.arange(patch_grid.rows) + 0.5) * patch_grid.cell_m
    patch_y = patch_grid.y_max_m - (np.arange(patch_grid.cols) + 0.5) * patch_grid.cell_m
    return np.asarray(
        _patch_world_index(
            patch_x.astype(np.float64),
            patch_y.astype(np.float64),
            math.cos(T_world_robot.theta_rad),
            math.sin(T_world_robot.theta_rad),
            float(T_world_robot.x_m),
            float(T_world_robot.y_m),
            float(world_grid.x_max_m),
            float(world_grid.y_max_m),
            float(world_grid.cell_m),
            world_grid.rows,
            world_grid.cols,
        )
    )


def bgr_to_scaled_lab(bgr: NDArray[np.floating]) -> NDArray[np.float32]:
    """(N, 3) BGR in [0, 255] -> (N, 3) CIELAB scaled as the floor network's input."""
    pixels = np.asarray(bgr, dtype=np.float32).reshape(-1, 1, 3) * np.float32(1.0 / 255.0)
    lab = cv2.cvtColor(pixels, cv2.COLOR_BGR2Lab).reshape(-1, 3)
    return np.asarray((lab - LAB_CENTER) / LAB_SCALE, dtype=np.float32)


@dataclass(frozen=True, eq=False)
class FloorMemoryState:
    """What a map file keeps of the memory (the colour layer is rebuilt by looking).

    Attributes
    ----------
    confirmed : (rows, cols) uint8, 1 = confirmed flat floor
    appearances : (k, 4) float32, scaled-Lab colour and cell count of each appearance
    standing_marks, seen_foot_marks : (rows, cols) uint8, `FloorMemory.standing_marks`
        and `FloorMemory.seen_foot_marks` (the standing layer follows from them); None
        for a map saved without them
    driven : (rows, cols) uint8, `FloorMemory.driven` (`DRIVEN_FOOTPRINT` |
        `DRIVEN_TRACK` bits); None for a map saved without it
    """

    confirmed: NDArray[np.uint8]
    appearances: NDArray[np.float32]
    standing_marks: NDArray[np.uint8] | None = None
    seen_foot_marks: NDArray[np.uint8] | None = None
    driven: NDArray[np.uint8] | None = None


class FloorMemory:
    """The confirmed-floor layer, the colour layer and the learned appearances of one
    world grid (see the module docstring)."""

    def __init__(self, world_grid: GroundGrid, params: FloorMemoryParams | None = None) -> None:
        self.world_grid = world_grid
        self.params = params if params is not None else FloorMemoryParams()
        n = world_grid.rows * world_grid.cols
        self.confirmed = np.zeros(world_grid.shape, dtype=np.uint8)
        self.standing = np.zeros(world_grid.shape, dtype=np.uint8)
        """1 where geometry saw something standing, in at least
        `FloorMemoryParams.standing_min_marks` more tests than saw floor there (not kept
        from its marks in map files): not known floor, and where its feet were seen there
        (`standing_seen`), an edge the frontier search does not probe."""
        self.standing_marks = np.zeros(world_grid.shape, dtype=np.uint8)
        """Tests that marked the cell standing, less those that saw floor there."""
        self.seen_foot_marks = np.zeros(world_grid.shape, dtype=np.uint8)
        """Of `standing_marks`, those whose foot was seen where the thing stands (the
        standing pixels' own lowest one), not placed where a frame's floor ended below a
        gap of not-floor (a plain wall's lower part, or another floor): counted and
        lost as those are (`mark_standing`'s ``seen_cells``)."""
        self.driven = np.zeros(world_grid.shape, dtype=np.uint8)
        """`DRIVEN_FOOTPRINT` where the robot's footprint covered the cell, `DRIVEN_TRACK`
        where its centre passed (module docstring)."""
        self._colour = np.zeros((n, 3), dtype=np.float32)
        self._sightings = np.zeros(n, dtype=np.uint16)
        self._appearance_lab = np.zeros((0, 3), dtype=np.float32)
        self._appearance_cells = np.zeros(0, dtype=np.float64)
        self.learned_cells = 0
        """Confirmed cells whose colour joined an appearance (for the report)."""
        self.unlearned = 0
        """Appearances dropped because their colour was seen standing."""

    # -- the colour layer ----------------------------------------------------------------

    def observe_colours(
        self,
        patch_bgr: NDArray[np.uint8],
        patch: NDArray[np.uint8],
        index: NDArray[np.int64],
        near: NDArray[np.bool_],
    ) -> None:
        """Blend one frame's bird's-eye colours (``patch_bgr``, same raster as ``patch``)
        into the cells ``index`` maps them to, for seen cells where ``near`` holds."""
        use = near & (patch != UNSEEN) & (index >= 0)
        cells = index[use]
        if cells.size == 0:
            return
        # Count over the span of flat indices this frame touches, not the whole world
        # grid: four world-sized bincounts a frame were mapping's largest cost (py-spy).
        first = int(cells.min())
        local = cells - first
        counts = np.bincount(local)
        hit_local = np.flatnonzero(counts)
        hit = hit_local + first
        colours = patch_bgr[use].astype(np.float64)
        means = np.empty((hit.size, 3), dtype=np.float32)
        for ch in range(3):
            sums = np.bincount(local, weights=colours[:, ch], minlength=counts.size)
            means[:, ch] = sums[hit_local] / counts[hit_local]
        seen = self._sightings[hit].astype(np.float32)
        rate = np.maximum(np.float32(self.params.colour_rate), 1.0 / (seen + 1.0))
        self._colour[hit] += (means - self._colour[hit]) * rate[:, None]
        self._sightings[hit] = np.minimum(seen + 1, 60000).astype(np.uint16)

    def colour_of(self, cells: NDArray[np.int64]) -> NDArray[np.float32]:
        """(N, 3) mean BGR of flat cell indices (undefined where never seen)."""
        return self._colour[cells]

    # -- confirmed floor -------------------------------------------------------------------

    def confirm_cells(self, cells: NDArray[np.int64]) -> int:
        """Mark flat cell indices as confirmed floor; the newly confirmed ones that have
        been seen teach their colour. Returns how many were new."""
        cells = np.unique(cells[cells >= 0])
        flat = self.confirmed.reshape(-1)
        new = cells[flat[cells] == 0]
        flat[new] = 1
        self.standing.reshape(-1)[cells] = 0
        self.standing_marks.reshape(-1)[cells] = 0
        self.seen_foot_marks.reshape(-1)[cells] = 0
        seen = new[self._sightings[new] > 0]
        if seen.size:
            self._learn(bgr_to_scaled_lab(self._colour[seen]))
            self.learned_cells += int(seen.size)
        return int(new.size)

    def drive_over(self, T_world_robot: Pose2D, radius_m: float) -> int:
        """The robot stands on the cells within ``radius_m`` of its centre: floor, and
        driven over (its own cell and those within one cell of its centre are its track).
        Returns how many cells were newly confirmed."""
        grid = self.world_grid
        inv = 1.0 / grid.cell_m
        r0 = (grid.x_max_m - T_world_robot.x_m) * inv
        c0 = (grid.y_max_m - T_world_robot.y_m) * inv
        span = max(radius_m * inv, 1.0)
        rows = np.arange(max(math.floor(r0 - span), 0), min(math.ceil(r0 + span), grid.rows))
        cols = np.arange(max(math.floor(c0 - span), 0), min(math.ceil(c0 + span), grid.cols))
        if rows.size == 0 or cols.size == 0:
            return 0
        dr = rows[:, None] + 0.5 - r0
        dc = cols[None, :] + 0.5 - c0
        distance2 = dr * dr + dc * dc
        inside = distance2 <= (radius_m * inv) ** 2
        # One cell around the centre: successive poses' tracks join side by side (4-
        # connected), so a search without corner cutting can follow a diagonal track.
        track = distance2 <= 1.0
        own_r, own_c = math.floor(r0), math.floor(c0)
        if 0 <= own_r < grid.rows and 0 <= own_c < grid.cols:
            track[own_r - int(rows[0]), own_c - int(cols[0])] = True
        rr, cc = np.nonzero(inside)
        tr, tc = np.nonzero(track)
        self.driven[rows[rr], cols[cc]] |= DRIVEN_FOOTPRINT
        self.driven[rows[tr], cols[tc]] |= DRIVEN_TRACK
        return self.confirm_cells(rows[rr] * grid.cols + cols[cc])

    def track(self) -> NDArray[np.bool_]:
        """(rows, cols) bool, the cells the robot's centre has crossed (`drive_over`)."""
        return np.asarray((self.driven & DRIVEN_TRACK) != 0, dtype=np.bool_)

    def mark_standing(
        self,
        cells: NDArray[np.int64],
        standing_bgr: NDArray[np.generic] | None = None,
        seen_cells: NDArray[np.int64] | None = None,
    ) -> None:
        """Geometry saw something standing on these cells: they are no longer known
        floor, and an appearance of its colour is unlearned (a floor-coloured box).

        ``standing_bgr`` : (N, 3) colours of the image pixels seen standing. Without
        them the cells' own colour layer stands in; with them the standing thing's
        own colours decide (the cells a standing pixel projects to through the floor
        homography lie behind it, and their colour is the floor's there).
        ``seen_cells`` : those of ``cells`` whose foot was seen where the thing stands
        (None: all of them; `seen_feet`)."""
        cells = np.unique(cells[cells >= 0])
        if cells.size == 0:
            return
        seen = cells if seen_cells is None else np.intersect1d(cells, seen_cells)
        seen_marks = self.seen_foot_marks.reshape(-1)
        seen_marks[seen] = np.minimum(seen_marks[seen] + 1, self.params.standing_max_marks)
        self.confirmed.reshape(-1)[cells] = 0
        marks = self.standing_marks.reshape(-1)
        marks[cells] = np.minimum(marks[cells] + 1, self.params.standing_max_marks)
        sure = cells[marks[cells] >= self.params.standing_min_marks]
        self.standing.reshape(-1)[sure] = 1
        if self._appearance_lab.shape[0] == 0:
            return
        if standing_bgr is None:
            seen = cells[self._sightings[cells] > 0]
            colours = self._colour[seen]
        else:
            colours = np.asarray(standing_bgr, dtype=np.float32).reshape(-1, 3)
        if colours.shape[0] == 0:
            return
        lab = bgr_to_scaled_lab(colours)
        distance = np.linalg.norm(lab[:, None, :] - self._appearance_lab[None, :, :], axis=2)
        votes = (distance <= self.params.unlearn_distance).sum(axis=0)
        votes[votes < self.params.unlearn_share * colours.shape[0]] = 0
        # A standing colour costs twice what a floor sighting gives: the floor must be
        # confirmed again, more than it stood, to come back.
        self._appearance_cells -= 2.0 * votes
        keep = self._appearance_cells > 0
        self.unlearned += int(np.count_nonzero(~keep & (votes > 0)))
        self._appearance_lab = self._appearance_lab[keep]
        self._appearance_cells = self._appearance_cells[keep]

    def see_floor(self, cells: NDArray[np.int64]) -> None:
        """A geometric test saw floor, not a foot, on these cells: each loses one mark,
        and leaves the standing layer below `FloorMemoryParams.standing_min_marks`."""
        cells = np.unique(cells[cells >= 0])
        if cells.size == 0:
            return
        seen_marks = self.seen_foot_marks.reshape(-1)
        seen = cells[seen_marks[cells] > 0]
        seen_marks[seen] -= 1
        marks = self.standing_marks.reshape(-1)
        marked = cells[marks[cells] > 0]
        if marked.size == 0:
            return
        marks[marked] -= 1
        gone = marked[marks[marked] < self.params.standing_min_marks]
        self.standing.reshape(-1)[gone] = 0

    def standing_seen(self) -> NDArray[np.bool_]:
        """The `standing` cells whose foot was seen there in at least
        `FloorMemoryParams.standing_min_marks` tests (net of those that saw floor): a
        real edge. The rest were placed where a frame's floor ended, and an edge probe
        may look closer."""
        return np.asarray(
            (self.standing != 0) & (self.seen_foot_marks >= self.params.standing_min_marks),
            dtype=np.bool_,
        )

    def known_share(self, cells: NDArray[np.int64]) -> float:
        """Of these flat world-cell indices (-1: off the map, counted as not known), the
        share that is confirmed floor (a standing mark takes a cell out of it); 0 for
        none."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1)
        if cells.size == 0:
            return 0.0
        known = self.confirmed.reshape(-1)[cells[cells >= 0]] == 1
        return float(np.count_nonzero(known)) / cells.size

    def correct_patch(self, patch: NDArray[np.uint8], index: NDArray[np.int64]) -> int:
        """In place: patch cells the colour method calls not-floor on confirmed floor
        become floor. Returns how many were changed."""
        on_map = index >= 0
        known = np.zeros(patch.shape, dtype=bool)
        known[on_map] = self.confirmed.reshape(-1)[index[on_map]] == 1
        change = known & (patch == NOT_FLOOR)
        patch[change] = FLOOR
        return int(np.count_nonzero(change))

    # -- appearances --------------------------------------------------------------------

    def _learn(self, lab: NDArray[np.float32]) -> None:
        """Cluster new floor colours into the appearances (leader clustering on colours
        rounded to a quarter of the merge distance, so a frame costs a few dozen steps)."""
        step = self.params.merge_distance / 4
        keys, counts = np.unique(np.round(lab / step).astype(np.int32), axis=0, return_counts=True)
        for key, count in zip(keys, counts, strict=True):
            colour = key.astype(np.float32) * np.float32(step)
            if self._appearance_lab.shape[0]:
                distance = np.linalg.norm(self._appearance_lab - colour, axis=1)
                best = int(np.argmin(distance))
                if distance[best] <= self.params.merge_distance:
                    total = self._appearance_cells[best] + count
                    self._appearance_lab[best] += (
                        (colour - self._appearance_lab[best]) * count / total
                    ).astype(np.float32)
                    self._appearance_cells[best] = total
                    continue
            self._appearance_lab = np.vstack([self._appearance_lab, colour[None]])
            self._appearance_cells = np.append(self._appearance_cells, float(count))
        if self._appearance_lab.shape[0] > self.params.max_appearances:
            order = np.argsort(-self._appearance_cells)[: self.params.max_appearances]
            self._appearance_lab = self._appearance_lab[order]
            self._appearance_cells = self._appearance_cells[order]

    def appearances(self) -> tuple[tuple[float, float, float], ...]:
        """The learned floor colours perception may use (scaled Lab), largest first."""
        ready = np.flatnonzero(self._appearance_cells >= self.params.min_cells)
        order = ready[np.argsort(-self._appearance_cells[ready])]
        return tuple((float(c[0]), float(c[1]), float(c[2])) for c in self._appearance_lab[order])

    def appearance_cells(self) -> NDArray[np.float64]:
        """Cell counts in the order of the internal list (tests, status)."""
        return self._appearance_cells.copy()

    # -- persistence ----------------------------------------------------------------------

    def state(self) -> FloorMemoryState:
        table = np.column_stack([self._appearance_lab, self._appearance_cells]).astype(np.float32)
        return FloorMemoryState(
            self.confirmed.copy(),
            table.reshape(-1, 4),
            self.standing_marks.copy(),
            self.seen_foot_marks.copy(),
            self.driven.copy(),
        )

    def restore(self, state: FloorMemoryState) -> None:
        """Continue from a saved map's memory (the colour layer starts empty; without
        saved marks, so does the standing layer; without a saved driven layer, so does
        that).

        Raises
        ------
        ValueError : a layer of another shape or a malformed appearance table
        """
        layers = {
            "confirmed floor": state.confirmed,
            "standing marks": state.standing_marks,
            "seen foot marks": state.seen_foot_marks,
            "driven": state.driven,
        }
        for name, layer in layers.items():
            if layer is not None and layer.shape != self.world_grid.shape:
                raise ValueError(
                    f"{name} layer: shape {layer.shape}, grid is {self.world_grid.shape}"
                )
        table = np.asarray(state.appearances, dtype=np.float32)
        if table.ndim != 2 or table.shape[1] != 4 or not np.isfinite(table).all():
            raise ValueError(f"floor appearances: expected finite (k, 4), got {table.shape}")
        if (table[:, 3] <= 0).any():
            raise ValueError("floor appearances: every cell count must be > 0")
        self.confirmed[...] = state.confirmed != 0
        top = self.params.standing_max_marks
        for saved, layer in (
            (state.standing_marks, self.standing_marks),
            (state.seen_foot_marks, self.seen_foot_marks),
        ):
            layer[...] = 0 if saved is None else np.minimum(saved, top)
        self.standing[...] = self.standing_marks >= self.params.standing_min_marks
        self.driven[...] = (
            0 if state.driven is None else state.driven & (DRIVEN_FOOTPRINT | DRIVEN_TRACK)
        )
        self._appearance_lab = table[:, :3].copy()
        self._appearance_cells = table[:, 3].astype(np.float64)
        self._colour.fill(0.0)
        self._sightings.fill(0)

    def reset(self) -> None:
        self.confirmed.fill(0)
        self.standing.fill(0)
        self.standing_marks.fill(0)
        self.seen_foot_marks.fill(0)
        self.driven.fill(0)
        self._colour.fill(0.0)
        self._sightings.fill(0)
        self._appearance_lab = np.zeros((0, 3), dtype=np.float32)
        self._appearance_cells = np.zeros(0, dtype=np.float64)
