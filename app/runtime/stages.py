"""The pipeline's stages, one small class each: capture, perception, mapping, steering,
odometry. Each has one ``async def run()`` that the `Runtime` starts in its task group,
reads its input slot and publishes on its output slot (see `app.runtime.core`'s
diagram). CPU work goes to a `StageWorker` thread (OpenCV, numpy and numba release the
GIL); the stage itself only waits and hands over frozen messages."""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import time
from collections.abc import Callable
from typing import Generic, NamedTuple, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from app.channels import SlotReader
from app.config import PerceptionConfig
from app.control.steering import Steering
from app.hardware.device_clock import DeviceClock
from app.mapping.frames import FLOOR, GroundGrid, Pose2D
from app.mapping.frontiers import FrontierGoal, FrontierSearch, path_to_point
from app.mapping.ground_map import (
    FrontierInputs,
    GeometryMode,
    GeometryOutcome,
    GroundMapper,
    MapUpdate,
    run_geometry_job,
    search_frontiers,
)
from app.mapping.occupancy import classify_log_odds
from app.messages import FloorMsg, FrameMsg, MapMsg, WorldMapMsg
from app.perception.floor_net import LearnedPassBackoff
from app.perception.image_checks import ImageError
from app.perception.pipeline import FloorResult, trapezoid_from_config
from app.perception.safe_zone import SafeZoneError, Trapezoid, safe_zone_mask
from app.runtime.context import Shared
from app.runtime.drive import premise_broken, zone_not_floor
from app.runtime.exploration import (
    CoverageClock,
    Exploration,
    GoalPatience,
    Phase,
    PhaseChange,
)
from app.runtime.telemetry import FloatWindow
from app.workers import StageWorker

log = logging.getLogger("floornav.runtime")

CAPTURE_POLL_S = 0.002
"""How often capture looks for a new frame (the cameras publish from their threads)."""
WORLD_MAP_PERIOD_S = 0.5
"""The whole-map snapshot for the web and other readers: at most 2 Hz."""


class Segmenter(Protocol):
    """What perception needs (`FloorSegmenter`; tests pass slow or failing ones)."""

    def segment(self, image: NDArray[np.uint8]) -> FloorResult: ...


@runtime_checkable
class LearnsFloor(Protocol):
    """A segmenter that uses floor colours learned on the way (`FloorSegmenter`)."""

    learned_floor: tuple[tuple[float, float, float], ...]
    learned_pass_due: bool


# -- pure helpers (the mapping thread, the web and the benchmarks use them) -------------


def clearance_ahead_m(
    patch: NDArray[np.uint8],
    patch_grid: GroundGrid,
    robot_radius_m: float,
    max_range_m: float,
    *,
    blocked_fraction: float = 0.25,
) -> float:
    """Free floor ahead of the robot's front edge in a bird's-eye patch: the distance to
    the nearest row of the robot-wide corridor in which at least ``blocked_fraction`` of
    the cells are not floor (unseen counts as not floor). The fraction keeps a few
    misclassified cells (a plank seam, a reflection) from stopping the robot; anything
    a quarter of the robot's width wide does."""
    x, y = patch_grid.cell_centers()
    corridor = np.abs(y[0]) <= robot_radius_m
    rows_x = x[:, 0]
    ahead = rows_x > 0
    not_floor = patch[:, corridor] != FLOOR
    blocked_rows = ahead & (not_floor.mean(axis=1) >= blocked_fraction)
    nearest = float(rows_x[blocked_rows].min()) if blocked_rows.any() else max_range_m
    return max(0.0, nearest - patch_grid.cell_m / 2 - robot_radius_m)


def crop_window(
    grid: GroundGrid, center_xy: tuple[float, float], side_m: float
) -> tuple[slice, slice, GroundGrid]:
    """Rows, columns and geometry of the square of ``side_m`` around ``center_xy`` in
    ``grid`` (clipped to it; one corner cell when the centre lies outside)."""
    half = math.ceil(side_m / 2 / grid.cell_m)
    row, col = (int(v) for v in grid.cell_of(np.array([center_xy]))[0])
    r0, r1 = max(0, row - half), min(grid.rows, row + half + 1)
    c0, c1 = max(0, col - half), min(grid.cols, col + half + 1)
    if r0 >= r1 or c0 >= c1:
        r0, r1, c0, c1 = 0, 1, 0, 1
    window = GroundGrid(
        grid.x_max_m - r0 * grid.cell_m,
        grid.y_max_m - c0 * grid.cell_m,
        grid.cell_m,
        r1 - r0,
        c1 - c0,
    )
    return slice(r0, r1), slice(c0, c1), window


def map_window(
    log_odds: NDArray[np.float32],
    grid: GroundGrid,
    center_xy: tuple[float, float],
    side_m: float,
    *,
    free_threshold: float,
    occupied_threshold: float,
) -> tuple[NDArray[np.int8], GroundGrid]:
    """Classes of the square of ``side_m`` around ``center_xy`` (clipped to the grid)."""
    rows, cols, window = crop_window(grid, center_xy, side_m)
    cells = classify_log_odds(
        log_odds[rows, cols], free_threshold=free_threshold, occupied_threshold=occupied_threshold
    )
    return cells, window


def path_to_xy(goal: FrontierGoal | None, grid: GroundGrid) -> NDArray[np.float64] | None:
    """The path to a goal as (n, 2) world points, or None without a goal."""
    if goal is None:
        return None
    rc = goal.path_cells
    xs = grid.x_max_m - (rc[:, 0] + 0.5) * grid.cell_m
    ys = grid.y_max_m - (rc[:, 1] + 0.5) * grid.cell_m
    return np.column_stack((xs, ys))


# -- stages -------------------------------------------------------------------------------


class CaptureStage:
    """Camera -> ``frames``. Sets ``shared.camera_ok`` for the health stage."""

    def __init__(self, shared: Shared) -> None:
        self.shared = shared

    async def run(self) -> None:
        shared = self.shared
        camera = shared.devices.camera
        last_seq = -1
        while True:
            frame = camera.latest(shared.config.safety.camera_max_age_s)
            if frame is not None and frame.seq != last_seq:
                if last_seq >= 0 and frame.seq > last_seq + 1:
                    shared.counters.frames_skipped += frame.seq - last_seq - 1
                last_seq = frame.seq
                shared.counters.frames_captured += 1
                shared.frames.publish(
                    FrameMsg(frame.image, frame.timestamp_s, frame.seq, frame.arrived_s)
                )
            shared.camera_ok = frame is not None
            await asyncio.sleep(CAPTURE_POLL_S)


class PerceptionStage:
    """``frames`` -> floor mask -> ``floors``, in its own thread."""

    def __init__(
        self, shared: Shared, segmenter_factory: Callable[[PerceptionConfig], Segmenter]
    ) -> None:
        self.shared = shared
        self.segmenter_factory = segmenter_factory
        self.worker = StageWorker("perception")
        self.frame_ages = FloatWindow()
        """How old each frame was when perception picked it up (seconds)."""
        self._rebuild = False

    def rebuild_segmenter(self) -> None:
        """Use the (new) perception configuration from the next frame on."""
        self._rebuild = True

    async def run(self) -> None:
        shared = self.shared
        segmenter = self.segmenter_factory(shared.config.perception)
        backoff = LearnedPassBackoff()
        next_pass_s = -math.inf
        reader = SlotReader(shared.frames)
        while True:
            frame = await reader.next()
            if self._rebuild:
                self._rebuild = False
                segmenter = self.segmenter_factory(shared.config.perception)
            start = shared.clock()
            self.frame_ages.append(start - frame.capture_s)
            if isinstance(segmenter, LearnsFloor):
                # A second pass is a whole network run on the way to the motors: at most
                # one per period; between them only colours that have added floor hold
                # back the map's evidence (a fruitless one, a wall's, must not).
                due = start >= next_pass_s
                segmenter.learned_pass_due = due
                segmenter.learned_floor = (
                    backoff.eligible(shared.floor_appearances)
                    if due
                    else backoff.fruitful(shared.floor_appearances)
                )
            try:
                result = await self.worker.run(segmenter.segment, frame.image)
            except (ImageError, SafeZoneError) as exc:
                shared.counters.bad_frames += 1
                log.warning("frame %d rejected: %s", frame.seq, exc, extra={"event": "bad_frame"})
                continue
            done = shared.clock()
            shared.stages.add("perception", done - start)
            shared.counters.frames_perceived += 1
            backoff.observe(result.learned_floor_reference, result.learned_floor_added_share)
            if result.learned_floor_reference is not None:
                next_pass_s = start + shared.config.perception.learned_floor_pass_period_s
                shared.counters.learned_floor_passes += 1
                if result.learned_floor_added_share >= backoff.MIN_ADDED_SHARE:
                    shared.counters.learned_floor_passes_adding += 1
            shared.floors.publish(
                FloorMsg(
                    frame.seq,
                    frame.capture_s,
                    done,
                    frame.image,
                    result.floor_mask,
                    result.method,
                    result.timings_ms,
                    result.zone_floor_confidence,
                    result.unsure_mask,
                    frame.arrived_s,
                )
            )


PROBE_ARRIVED_M = 0.25
"""An edge probe's goal this close is reached (`MappingStage._track_goal`)."""


FOLLOW_FLOOR_MAX_DEFERRED = 3
"""Floor odometry gives way to a newer frame at most this many frames in a row: longer,
and the key frame would fall out of reach (`FLOOR_ODOMETRY_KEY_TRIES` steps)."""


_R = TypeVar("_R")


BACKGROUND_NICER_BY = 10
"""The mapping stage's background thread runs this much nicer than the daemon: on busy
cores it gets about a tenth of the stages' share (its jobs can wait; frames cannot)."""


class _Beside(Generic[_R]):
    """One kind of the mapping stage's work that runs beside the mapping thread, on its
    background worker, one at a time; its result is taken in between mapping steps."""

    def __init__(self, shared: Shared, worker: StageWorker, name: str) -> None:
        self.shared = shared
        self.worker = worker
        self.name = name
        self._running: tuple[GroundMapper, asyncio.Task[_R]] | None = None

    @property
    def running(self) -> bool:
        return self._running is not None

    def start(self, mapper: GroundMapper, fn: Callable[[], _R]) -> None:
        """Run ``fn`` on the worker; its wall time (queue included) is stage ``name``."""
        shared = self.shared

        async def timed() -> _R:
            start = shared.clock()
            result = await self.worker.run(fn)
            shared.stages.add(self.name, shared.clock() - start)
            return result

        self._running = (mapper, asyncio.create_task(timed(), name=self.name))

    def handover(self, mapper: GroundMapper) -> tuple[bool, _R | None]:
        """For the next mapping step: whether a new one may start (none is running, or
        the one that ran is taken now) and the finished result, if any (`take`)."""
        busy = self.running
        result = self.take(mapper)
        return not busy or result is not None, result

    def take(self, mapper: GroundMapper) -> _R | None:
        """The finished result, once (None while it runs, or when it failed or its map
        has been replaced)."""
        if self._running is None or not self._running[1].done():
            return None
        ran_on, task = self._running
        self._running = None
        if task.cancelled() or ran_on is not mapper:
            return None
        error = task.exception()
        if error is not None:
            log.error("%s failed: %s", self.name, error, exc_info=error, extra={"event": self.name})
            return None
        return task.result()

    def drop(self) -> None:
        """Forget the running one (its thread finishes it; nobody waits)."""
        if self._running is not None:
            self._running[1].cancel()
            self._running = None


class _SearchResult(NamedTuple):
    """A frontier search done beside, with what it was started for."""

    search: FrontierSearch
    home_goal: FrontierGoal | None
    exploration: Exploration
    returning: bool
    started_s: float


class MappingStage:
    """``floors`` -> occupancy grid -> ``maps`` (the window steering needs, every frame)
    and ``world_maps`` (the whole map, at most 2 Hz), in its own thread. Runs the
    frontier search every ``steering.frontier_period_s`` and gives up goals that stay
    out of reach."""

    def __init__(self, shared: Shared) -> None:
        self.shared = shared
        self.worker = StageWorker("mapping")
        self.background = StageWorker("mapping-background", nicer_by=BACKGROUND_NICER_BY)
        """Runs the mapping stage's work that is not on the way to the motors beside the
        mapping thread: the geometric tests (parallax, walls; on the mapping thread they
        held up every fifth frame's map by 10-25 ms) and the frontier search. Each gets
        copies from the mapping thread and hands copies back."""
        self._geometry: _Beside[GeometryOutcome] = _Beside(shared, self.background, "geometry")
        self._search: _Beside[_SearchResult] = _Beside(shared, self.background, "planning")
        self.frontier: FrontierSearch | None = None
        self.goals_given_up = 0
        """Goals given up this run (each map keeps its own, `GroundMapper.given_up`)."""
        self.clusters_given_up = 0
        """Of them, the failures that gave up their whole frontier (`GivenUpGoals.add`)."""
        self.probes_opened = 0
        """Edge probes that opened their edge (not counted as goals given up)."""
        self._patience = GoalPatience()
        self._frontier_due_s = 0.0
        self._snapshot_due_s = 0.0
        self._floor_deferred = 0
        """Frames in a row whose floor odometry step waited for a newer frame."""
        self.exploration = self._new_exploration()
        self.floor_waits = FloatWindow()
        """How long each floor mask waited for the mapping thread (seconds)."""
        self.home_goal: FrontierGoal | None = None
        """While returning: the path home from the newest frontier search."""
        self.on_phase: Callable[[PhaseChange], None] | None = None
        """Told every exploration phase change (the runtime stops and saves the map)."""
        self._zone: tuple[tuple[tuple[int, ...], Trapezoid], NDArray[np.bool_]] | None = None
        """The safe zone's pixel mask for a frame size and trapezoid (`_safe_zone_px`)."""

    def _new_exploration(self) -> Exploration:
        steering = self.shared.config.steering
        return Exploration(
            explored_after_s=steering.explored_after_s,
            home_tolerance_m=steering.home_tolerance_m,
            return_home=steering.return_home,
            return_timeout_s=steering.return_timeout_s,
        )

    def forget_frontier(self) -> None:
        """After a new calibration or map: the old search means nothing."""
        self.frontier = None
        self._search.drop()
        self._patience.reset()
        self.home_goal = None
        self.exploration = self._new_exploration()

    def step(
        self,
        mapper: GroundMapper,
        floor: FloorMsg,
        pose: Pose2D,
        now_pose: Pose2D,
        geometry: GeometryMode = "inline",
        geometry_outcome: GeometryOutcome | None = None,
    ) -> tuple[MapMsg, MapUpdate]:
        """In the mapping thread, on the way to the motors: fuse the frame and cut the
        window steering reads, with the goal of the latest frontier search (searched
        beside, `plan`: a search is up to 0.5 s old anyway)."""
        config = self.shared.config
        update = mapper.update(
            floor.floor_mask,
            pose,
            floor.capture_s,
            floor.image,
            unsure_mask=floor.unsure_mask,
            geometry=geometry,
            geometry_outcome=geometry_outcome,
            safe_zone_px=self._safe_zone_px(floor.floor_mask.shape),
        )
        if update.correction is not None:
            # The frame went into the map at the corrected pose; odometry follows in `run`.
            now_pose = update.correction.compose(now_pose)
        params = mapper.grid.params
        world = mapper.grid.world_grid
        cells, window = map_window(
            mapper.grid.log_odds,
            world,
            (now_pose.x_m, now_pose.y_m),
            config.steering.local_window_m,
            free_threshold=params.free_threshold,
            occupied_threshold=params.occupied_threshold,
        )
        clearance = clearance_ahead_m(
            update.patch,
            mapper.birdseye.grid,
            config.mapping.robot_radius_m,
            config.mapping.max_range_m,
        )
        goal, reason = self._goal_and_reason(self.frontier, self.home_goal)
        msg = MapMsg(
            seq=floor.seq,
            capture_s=floor.capture_s,
            done_s=time.monotonic(),
            T_odom_robot=update.correction.compose(pose) if update.correction else pose,
            window_cells=cells,
            window_grid=window,
            path_xy=path_to_xy(goal, world),
            goal_xy=goal.xy if goal is not None else None,
            frontier_reason=reason,
            clearance_ahead_m=clearance,
            zone_known_floor=update.zone_known_floor,
            arrived_s=floor.arrived_s,
        )
        return msg, update

    def _safe_zone_px(self, shape: tuple[int, ...]) -> NDArray[np.bool_] | None:
        """Perception's safe zone on frames of this shape (one array while neither the
        shape nor the configured zone changes, so the mapper keeps its projection);
        None when it does not fit the frame (perception rejects such frames anyway)."""
        key = (shape, trapezoid_from_config(self.shared.config.perception.safe_zone))
        if self._zone is None or self._zone[0] != key:
            try:
                zone = safe_zone_mask((shape[0], shape[1]), key[1])
            except SafeZoneError:
                return None
            zone.setflags(write=False)
            self._zone = (key, zone)
        return self._zone[1]

    def _goal_and_reason(
        self, frontier: FrontierSearch | None, home_goal: FrontierGoal | None
    ) -> tuple[FrontierGoal | None, str]:
        if self.returning_home:
            if home_goal is not None:
                return home_goal, "returning to the start"
            return None, "no path to the start"
        if frontier is None:
            return None, "not searched yet"
        return frontier.goal, frontier.reason

    def plan(
        self,
        mapper: GroundMapper,
        floor: FloorMsg,
        now_pose: Pose2D,
        frontier_due: bool,
        snapshot_due: bool,
    ) -> tuple[FrontierInputs | None, WorldMapMsg | None]:
        """In the mapping thread, after the frame's message is out: maybe copy what a
        frontier search reads (the search runs beside, `_start_search`), maybe copy the
        whole map for readers (with the newest search's goal)."""
        inputs = mapper.frontier_inputs(now_pose) if frontier_due else None
        snapshot = None
        if snapshot_due:
            world = mapper.grid.world_grid
            frontier = self.frontier
            goal, reason = self._goal_and_reason(frontier, self.home_goal)
            # The map as the robot knows it: faded cells at their last class, as it
            # plans on them (`OccupancyGrid.remembered_classes`).
            whole = mapper.grid.remembered_classes()
            whole.setflags(write=False)
            snapshot = WorldMapMsg(
                seq=floor.seq,
                done_s=time.monotonic(),
                cells=whole,
                grid=world,
                T_odom_robot=now_pose,
                path_xy=path_to_xy(goal, world),
                goal_xy=goal.xy if goal is not None else None,
                frontier_reason=reason,
                frontier_clusters=len(frontier.clusters) if frontier is not None else 0,
            )
        return inputs, snapshot

    @property
    def returning_home(self) -> bool:
        return self.exploration.phase is Phase.RETURNING and self.shared.autonomous

    async def run(self) -> None:
        try:
            await self._run()
        finally:
            for beside in (self._geometry, self._search):
                beside.drop()

    async def _run(self) -> None:
        shared = self.shared
        reader = SlotReader(shared.floors)
        while True:
            floor = await reader.next()
            mapper = shared.mapper
            if mapper is None or shared.calibrating:
                continue
            start = shared.clock()
            self.floor_waits.append(start - floor.done_s)
            pose = shared.odometry.pose_at(floor.capture_s)
            # While a job runs beside, no other is cut (its tests stay due).
            may_start, geometry_outcome = self._geometry.handover(mapper)
            msg, update = await self.worker.run(
                self.step,
                mapper,
                floor,
                pose,
                shared.odometry.pose,
                "defer" if may_start else "hold",
                geometry_outcome,
            )
            if mapper is not shared.mapper:
                continue  # recalibrated or replaced meanwhile: this map is gone
            if update.correction is not None:
                shared.odometry.correct(update.correction)  # here: odometry is the loop's
                pose = update.correction.compose(pose)
            if update.match_s is not None:
                shared.stages.add("scan_match", update.match_s)
            shared.stages.add("mapping", shared.clock() - start)
            shared.counters.frames_mapped += 1
            perception = shared.config.perception
            confidence = floor.zone_floor_confidence
            if confidence < perception.zone_min_floor_confidence and not premise_broken(
                perception, confidence, msg.zone_known_floor
            ):
                shared.counters.zone_known_floor_frames += 1
            shared.maps.publish(msg)
            if update.geometry_job is not None:
                job = update.geometry_job
                self._geometry.start(mapper, functools.partial(run_geometry_job, job))
            await self._follow_floor(mapper, floor, pose, newer_waiting=reader.pending)
            await self._plan(mapper, floor)

    async def _follow_floor(
        self, mapper: GroundMapper, floor: FloorMsg, pose: Pose2D, *, newer_waiting: bool
    ) -> None:
        """Floor odometry and the building's axis (`GroundMapper.follow_floor`) for the
        frame just mapped at ``pose``, on the mapping thread but
        off the motors' path (its map is already out), its correction onto odometry at
        once: the pose of every later frame needs it, so it does not wait behind the
        background work (there, on a quiet machine, steps arrived 85 ms late at the
        median and the pose drifted further). Put off while a newer frame waits to be
        mapped (the key frame is then compared with a later one), but at most
        `FOLLOW_FLOOR_MAX_DEFERRED` frames in a row."""
        shared = self.shared
        if not mapper.floor_odometry and mapper.heading_axis is None:
            return
        if newer_waiting and self._floor_deferred < FOLLOW_FLOOR_MAX_DEFERRED:
            self._floor_deferred += 1
            return
        self._floor_deferred = 0
        steps, start = mapper.floor_odometry_steps, shared.clock()
        correction = await self.worker.run(
            mapper.follow_floor, floor.image, floor.floor_mask, pose, floor.capture_s
        )
        if mapper.floor_odometry_steps > steps:
            shared.stages.add("floor_odometry", shared.clock() - start)
        if correction is not None and mapper is shared.mapper:
            shared.odometry.correct(correction)

    async def _plan(self, mapper: GroundMapper, floor: FloorMsg) -> None:
        """The frontier search and the whole-map copy, when due (off the motors' path:
        the search runs beside, on the background worker; a finished one is taken in
        here, between mapping steps)."""
        shared = self.shared
        self._adopt_search(mapper)
        now = shared.clock()
        frontier_due = now >= self._frontier_due_s and not self._search.running
        if frontier_due:
            self._frontier_due_s = now + shared.config.steering.frontier_period_s
        snapshot_due = now >= self._snapshot_due_s
        if snapshot_due:
            self._snapshot_due_s = now + WORLD_MAP_PERIOD_S
        if not (frontier_due or snapshot_due):
            return
        inputs, snapshot = await self.worker.run(
            self.plan, mapper, floor, shared.odometry.pose, frontier_due, snapshot_due
        )
        if mapper is not shared.mapper:
            return
        if inputs is not None:
            self._start_search(mapper, inputs, now)
        if snapshot is not None:
            shared.floor_appearances = mapper.memory.appearances()
            shared.world_maps.publish(snapshot)

    def _start_search(self, mapper: GroundMapper, inputs: FrontierInputs, started_s: float) -> None:
        exploration = self.exploration
        returning = self.returning_home
        home_xy = exploration.home_xy if returning else None
        tolerance_m = self.shared.config.steering.home_tolerance_m / 2

        def search() -> _SearchResult:
            # With home_xy (returning home) the goal is the way there, found anew.
            found = search_frontiers(inputs)
            home_goal = (
                None if home_xy is None else path_to_point(found, inputs.grid, home_xy, tolerance_m)
            )
            return _SearchResult(found, home_goal, exploration, returning, started_s)

        self._search.start(mapper, search)

    def _adopt_search(self, mapper: GroundMapper) -> None:
        """Take a finished frontier search in (dropped if the map was replaced)."""
        done = self._search.take(mapper)
        if done is None:
            return
        shared = self.shared
        self.frontier = done.search
        self.home_goal = done.home_goal
        if shared.autonomous and not shared.mux.estopped:
            self._track_goal(mapper, done.search, done.started_s)
            if done.exploration is self.exploration:
                change = self.exploration.observe(
                    done.search,
                    done.started_s,
                    shared.odometry.pose,
                    home_reachable=done.home_goal is not None or not done.returning,
                )
                if change is not None and self.on_phase is not None:
                    self.on_phase(change)
        else:
            self._patience.reset()  # patience counts only while exploring

    def _give_up(
        self,
        mapper: GroundMapper,
        xy: tuple[float, float],
        cluster_cells: NDArray[np.int64] | None = None,
    ) -> bool:
        # Between mapping steps (this loop awaits each one), so the worker is not reading.
        whole = mapper.given_up.add(xy, cluster_cells)
        self.goals_given_up += 1
        self.clusters_given_up += int(whole)
        return whole

    def _track_goal(self, mapper: GroundMapper, search: FrontierSearch, now: float) -> None:
        """Give up on a goal the robot has come no closer to for
        ``steering.goal_patience_s`` (`GoalPatience`): it cannot be seen from where the
        robot can go."""
        goal = search.goal
        patience_s = self.shared.config.steering.goal_patience_s
        if goal is None:
            self._patience.reset()
            return
        pose = self.shared.odometry.pose
        if goal.probe and math.dist(goal.xy, (pose.x_m, pose.y_m)) < PROBE_ARRIVED_M:
            # An edge probe has had its look on the way there (parallax needs motion).
            # If it opened its edge, only that edge is done: the next one, just past it,
            # is seen close from the floor it opened.
            edge = goal.edge_cells
            opened = edge is not None and mapper.probe_opened(edge)
            if edge is not None and opened:
                mapper.given_up.looked_at(edge)
                self.probes_opened += 1
            else:
                self._give_up(mapper, goal.xy)
            log.info(
                "edge probe at (%.2f, %.2f) done: %s",
                goal.xy[0],
                goal.xy[1],
                "its edge is open" if opened else "its edge stays",
                extra={"event": "probe_done", "opened": opened},
            )
            self._patience.reset()
            return
        if self._patience.observe(goal.xy, goal.path_length_m, now, patience_s):
            cluster = (
                search.clusters[goal.cluster_index].cells
                if 0 <= goal.cluster_index < len(search.clusters)
                else None
            )
            whole = self._give_up(mapper, goal.xy, cluster)
            log.info(
                "%s (%.2f, %.2f) given up: no closer in %.0f s%s",
                "edge probe" if goal.probe else "frontier goal",
                goal.xy[0],
                goal.xy[1],
                patience_s,
                f", and its frontier of {len(cluster)} cells (a second failure there)"
                if whole and cluster is not None
                else "",
                extra={"event": "goal_given_up"},
            )


class SteeringStage:
    """``maps`` -> steering decision -> the mux's autonomy input (while exploring)."""

    def __init__(self, shared: Shared, steering: Steering) -> None:
        self.shared = shared
        self.steering = steering
        # Its polar scan is numpy on small arrays, mostly interpreter time: in a thread
        # it yields the GIL every switch interval instead of holding the loop (py-spy
        # found it at 11 % of the loop's time).
        self.worker = StageWorker("steering")
        self.reasons: dict[str, int] = {}
        """How often each steering decision reason came up."""
        self.map_waits = FloatWindow()
        """How long each map message waited for the steering thread (seconds)."""

    async def run(self) -> None:
        shared = self.shared
        reader = SlotReader(shared.maps)
        while True:
            msg = await reader.next()
            if not shared.autonomous or shared.mux.estopped:
                continue
            start = shared.clock()
            self.map_waits.append(start - msg.done_s)
            decision = await self.worker.run(
                functools.partial(
                    self.steering.decide,
                    blocked_ahead=zone_not_floor(shared, start) is not None,
                ),
                msg.window_cells,
                msg.window_grid,
                shared.odometry.pose,
                msg.path_xy,
            )
            if not shared.autonomous or shared.mux.estopped:
                continue  # stopped meanwhile: this decision must not re-arm autonomy
            shared.stages.add("steering", shared.clock() - start)
            self.reasons[decision.reason] = self.reasons.get(decision.reason, 0) + 1
            shared.decisions.publish(decision)
            shared.mux.autonomy(
                decision.twist, shared.clock(), origin_s=msg.capture_s, arrived_s=msg.arrived_s
            )
            shared.wake_drive.set()


class OdometryStage:
    """The Uno's encoder telemetry -> wheel odometry (the pose mapping and steering use)."""

    def __init__(self, shared: Shared) -> None:
        self.shared = shared
        self.device_clock = DeviceClock()
        """Times each reading by the Uno's own clock, not by when it arrived: a frame's
        pose (`WheelOdometry.pose_at`) is only as good as the readings' times."""

    async def run(self) -> None:
        link = self.shared.link
        assert link is not None
        async for telemetry in link.telemetry_updates():
            data = telemetry.data
            read_s = self.device_clock.host_time_s(data.uptime_ms, telemetry.received_s)
            self.shared.odometry.update(data.encoder_left, data.encoder_right, read_s)
            if self.shared.pose_error is not None:
                # Now, while the truth is of the same instant as the encoder counts.
                self.shared.pose_error.sample(self.shared.odometry.pose, telemetry.received_s)


class CoverageStage:
    """On the simulator: how much of the floor the robot can reach the map calls free,
    every ``period_s`` from the newest whole-map snapshot (the report's
    ``time_to_coverage_s``). The truth mask is computed once, both in a thread."""

    def __init__(self, shared: Shared, period_s: float = 2.0) -> None:
        self.shared = shared
        self.period_s = period_s
        self.clock = CoverageClock()

    async def run(self) -> None:
        from app.sim.truth import coverage_of_mask, reachable_free_mask

        shared = self.shared
        sim = shared.devices.sim
        if sim is None or shared.devices.camera is not sim.camera:
            return
        truth: tuple[GroundGrid, NDArray[np.bool_]] | None = None
        last_seq = -1
        while True:
            await asyncio.sleep(self.period_s)
            snapshot = shared.world_maps.peek()
            if snapshot is None or snapshot.seq == last_seq or shared.started_s is None:
                continue
            last_seq = snapshot.seq
            elapsed_s = shared.clock() - shared.started_s
            if truth is None or truth[0].cell_m != snapshot.grid.cell_m:
                truth = await asyncio.to_thread(
                    reachable_free_mask,
                    sim.world,
                    snapshot.grid.cell_m,
                    shared.config.mapping.robot_radius_m,
                )
            coverage = await asyncio.to_thread(
                coverage_of_mask, snapshot.cells, snapshot.grid, sim.T_plan_odom, *truth
            )
            self.clock.sample(coverage, elapsed_s)


COLLISION_EVENTS_KEPT = 50
"""The report keeps the first this many collisions with what the host was doing."""


class CollisionStage:
    """On the simulator: tells about every collision the simulated robot has, with what
    the host was doing when it happened (the command it sent and why, the clearance it
    believed in, how old its map was), so a collision in a long run can be explained.

    Polls the robot every ``period_s``; the context is the host's newest at that moment,
    at most ``period_s`` after the contact (the robot stops at contact, so it changes
    little)."""

    def __init__(self, shared: Shared, period_s: float = 0.1) -> None:
        self.shared = shared
        self.period_s = period_s
        self.events: list[dict[str, object]] = []

    async def run(self) -> None:
        shared = self.shared
        sim = shared.devices.sim
        if sim is None:
            return
        seen = sim.robot.collisions
        while True:
            await asyncio.sleep(self.period_s)
            if sim.robot.collisions == seen:
                continue
            contacts = sim.robot.contacts
            for contact in contacts:
                if contact.number <= seen:
                    continue
                event = self._describe(contact.as_dict())
                if len(self.events) < COLLISION_EVENTS_KEPT:
                    self.events.append(event)
                log.warning(
                    "collision %d in the simulator: %s",
                    contact.number,
                    event,
                    extra={"event": "sim_collision"},
                )
            if contacts:
                seen = max(seen, contacts[-1].number)

    def _describe(self, contact: dict[str, float | int | None]) -> dict[str, object]:
        shared = self.shared
        now = shared.clock()
        drive = shared.drives.peek()
        decision = shared.decisions.peek()
        map_msg = shared.maps.peek()
        stop = shared.protective_stop
        return {
            **contact,
            "run_time_s": round(now - shared.started_s, 2) if shared.started_s else None,
            "command": None
            if drive is None
            else {
                "source": drive.source,
                "v_m_s": round(drive.twist.v_m_s, 3),
                "omega_rad_s": round(drive.twist.omega_rad_s, 3),
                "age_ms": round((now - drive.sent_s) * 1000, 1),
            },
            "steering_reason": decision.reason if decision is not None else None,
            "steering_range_ahead_m": None
            if decision is None
            else round(decision.range_ahead_m, 3),
            "map_clearance_ahead_m": None
            if map_msg is None
            else round(map_msg.clearance_ahead_m, 3),
            "map_age_ms": None if map_msg is None else round((now - map_msg.capture_s) * 1000, 1),
            "protective_stop": stop.cause if stop is not None else None,
        }
