"""`compile_kernels` leaves numba nothing to compile on the robot's time: every kernel in
app/ the daemon calls has machine code afterwards, and one more frame through the
daemon's own paths adds no signature anywhere (a type mismatch would recompile)."""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path
from typing import Any

import pytest

import app
from app.config import FloornavConfig
from app.jit import KERNEL_MODULES, METHODS_WITHOUT_NUMBA, JitReport, compile_kernels
from app.mapping.frames import Pose2D
from app.mapping.ground_map import GroundMapper
from app.perception.pipeline import METHODS, FloorSegmenter
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

NEVER_CALLED = {
    "app.perception.slic._record_runs": "fills the run table for _relabel_connected, a "
    "test helper; the daemon's SLIC records its runs inside _iterate",
}
"""Kernels the daemon never calls, and why."""
PARALLAX_ONLY = {
    "app.perception.planar._extend_columns",
    "app.perception.planar._gauss_newton_system",
    "app.perception.planar._parallax_search",
}
"""Called only with mapping.parallax_floor (on by default, off with a lens model; its own
test below)."""

_DECORATOR = re.compile(r"^@(numba\.)?n?jit\b", re.MULTILINE)


def kernel_dispatchers() -> dict[str, Any]:
    """Every numba dispatcher defined in app/, found from the sources (not from
    KERNEL_MODULES, which this checks)."""
    from numba.core.registry import CPUDispatcher

    root = Path(app.__file__).parent
    found: dict[str, Any] = {}
    for path in sorted(root.rglob("*.py")):
        if not _DECORATOR.search(path.read_text(encoding="utf-8")):
            continue
        name = ".".join(path.relative_to(root.parent).with_suffix("").parts)
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == name:
                found[f"{name}.{attr}"] = value
    return found


def signature_counts(dispatchers: dict[str, Any]) -> dict[str, int]:
    return {name: len(dispatcher.signatures) for name, dispatcher in dispatchers.items()}


def compiles_so_far(dispatchers: dict[str, Any]) -> int:
    return sum(sum(d.stats.cache_misses.values()) for d in dispatchers.values())


@pytest.fixture(scope="module")
def warmed() -> JitReport:
    # Scan matching ships off but is one setting away: its kernels must be warmed too
    # (alone, this file once passed only after other tests had compiled them).
    return compile_kernels(FloornavConfig(mapping={"scan_matching": True}))


def test_kernel_modules_list_every_module_with_kernels() -> None:
    modules = {name.rsplit(".", 1)[0] for name in kernel_dispatchers()}
    assert modules == set(KERNEL_MODULES)


def test_every_kernel_the_daemon_calls_is_ready(warmed: JitReport) -> None:
    """A kernel is ready with a signature of its own, or when a ready kernel calls it:
    a caller loaded from numba's cache carries its callees' code, so those never get a
    signature of their own (nor need one)."""
    dispatchers = kernel_dispatchers()
    sources = {name: inspect.getsource(d.py_func) for name, d in dispatchers.items()}

    def callers(name: str) -> list[str]:
        module, short = name.rsplit(".", 1)
        call = re.compile(rf"\b{re.escape(short)}\(")
        return [
            other
            for other, source in sources.items()
            if other != name
            and other.rsplit(".", 1)[0] == module
            and call.search(source.split("\n", 2)[-1])  # past the decorator and def line
        ]

    def ready(name: str, seen: frozenset[str] = frozenset()) -> bool:
        if dispatchers[name].signatures:
            return True
        return any(ready(c, seen | {name}) for c in callers(name) if c not in seen)

    not_ready = [
        name
        for name in dispatchers
        if name not in NEVER_CALLED and name not in PARALLAX_ONLY and not ready(name)
    ]
    assert not_ready == [], f"compile_kernels left these for the robot's time: {not_ready}"
    # Compiled or loaded now, or already by an earlier test of this session (then neither).
    assert warmed.kernels > 0
    assert set(NEVER_CALLED) | PARALLAX_ONLY <= set(dispatchers), "stale exception list"


def test_one_more_daemon_frame_compiles_nothing(warmed: JitReport) -> None:
    """A rendered frame at another pose through every segmentation method (the method
    can change live), then moving mapper updates and frontier searches, as the daemon's
    perception and mapping stages run them."""
    config = FloornavConfig()
    dispatchers = kernel_dispatchers()
    before, compiles_before = signature_counts(dispatchers), compiles_so_far(dispatchers)

    renderer = renderer_from_config(config)
    start = renderer.world.start_pose
    image = renderer.render(Pose2D(start.x_m + 0.3, start.y_m, start.theta_rad + 0.2)).image
    results = {
        method: FloorSegmenter(config.perception, method=method).segment(image)
        for method in METHODS
    }
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    floor_mask = results[config.perception.method].floor_mask
    for step in range(4):
        pose = Pose2D(0.05 * step, 0.01 * step, 0.03 * step)
        mapper.update(floor_mask, pose, 0.1 * step, image)
        mapper.given_up.add((1.0, 0.5))
        mapper.frontiers(pose)
    mapper.grid.classify()

    added = {
        name: (before[name], count)
        for name, count in signature_counts(dispatchers).items()
        if count != before[name]
    }
    assert added == {}, f"compiled on the robot's time (signatures before, after): {added}"
    assert compiles_so_far(dispatchers) == compiles_before


def test_methods_without_numba_call_no_kernel(warmed: JitReport) -> None:
    """The methods compile_kernels skips unless configured indeed use no kernel (were
    one added, the daemon would compile it when the method is switched on live)."""
    dispatchers = kernel_dispatchers()
    before = signature_counts(dispatchers), compiles_so_far(dispatchers)
    config = FloornavConfig()
    image = renderer_from_config(config).render(Pose2D()).image
    for method in METHODS_WITHOUT_NUMBA:
        FloorSegmenter(config.perception, method=method).segment(image)
    assert (signature_counts(dispatchers), compiles_so_far(dispatchers)) == before


def test_parallax_kernel_is_compiled_when_configured() -> None:
    base = FloornavConfig()
    config = base.model_copy(
        update={"mapping": base.mapping.model_copy(update={"parallax_floor": True})}
    )
    compile_kernels(config)
    for name in PARALLAX_ONLY:
        module, short = name.rsplit(".", 1)
        assert getattr(importlib.import_module(module), short).signatures, name
    # Then moving frames through a mapper that runs the test compile nothing more.
    dispatchers = kernel_dispatchers()
    before = signature_counts(dispatchers)
    renderer = renderer_from_config(config)
    start = renderer.world.start_pose
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    for step in range(5):
        pose = Pose2D(0.04 * step, 0.0, 0.0)
        frame = renderer.render(start.compose(pose)).image
        floor_mask = FloorSegmenter(config.perception).segment(frame).floor_mask
        mapper.update(floor_mask, pose, 0.3 * step, frame)
    assert mapper.parallax_frames > 0
    assert signature_counts(dispatchers) == before


@pytest.mark.parametrize(
    ("compiled", "loaded", "text"),
    [
        (0, 15, "15 kernels ready in 0.9 s (cache)"),
        (33, 0, "15 kernels ready in 0.9 s (compiled)"),
        (6, 11, "15 kernels ready in 0.9 s (6 compiled, 11 from cache)"),
    ],
)
def test_report_summary(compiled: int, loaded: int, text: str) -> None:
    report = JitReport(0.94, 15, compiled, loaded, "")
    assert report.summary() == text
    assert report.banner_line() == f"  jit      {text}"


def test_warmup_command_prints_the_report(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from app import cli, jit

    seen: list[FloornavConfig] = []

    def fake_compile(config: FloornavConfig) -> JitReport:
        seen.append(config)
        return JitReport(1.25, 15, 0, 15, "")

    monkeypatch.setattr(jit, "compile_kernels", fake_compile)
    config_file = tmp_path / "config.toml"
    config_file.write_text('[perception]\nmethod = "thesis"\n')
    assert cli.main(["warmup", "--config", str(config_file)]) == 0
    assert capsys.readouterr().out == "jit      15 kernels ready in 1.2 s (cache)\n"
    assert seen[0].perception.method == "thesis"


def test_daemon_banner_shows_the_report() -> None:
    from app.daemon import banner

    text = banner(FloornavConfig(), "config.toml", {}, JitReport(0.9, 41, 0, 41, ""))
    assert "  jit      41 kernels ready in 0.9 s (cache)" in text.splitlines()


def test_a_real_camera_is_warmed_without_the_simulator(tmp_path: Path) -> None:
    """With a webcam configured (and no calibration file yet) nothing is rendered or
    opened, a stand-in calibration fits the configured size, and a camera frame through
    the same paths afterwards compiles nothing."""
    from app.jit import daemon_floor_calibration, synthetic_room

    base = FloornavConfig()
    config = base.model_copy(
        update={
            "camera": base.camera.model_copy(
                update={"source": "device", "width_px": 320, "height_px": 240}
            ),
            "perception": base.perception.model_copy(update={"method": "floornav"}),
            "mapping": base.mapping.model_copy(
                update={"floor_calibration_file": str(tmp_path / "absent.json")}
            ),
        }
    )
    report = compile_kernels(config)
    assert report.kernels > 0
    dispatchers = kernel_dispatchers()
    before = signature_counts(dispatchers)
    image = synthetic_room(320, 240, seed=3)
    floor_mask = FloorSegmenter(config.perception).segment(image).floor_mask
    mapper = GroundMapper(daemon_floor_calibration(config), config.mapping, config.camera)
    for step in range(3):
        pose = Pose2D(0.05 * step, 0.0, 0.02 * step)
        mapper.update(floor_mask, pose, 0.1 * step, image)
        mapper.frontiers(pose)
    assert signature_counts(dispatchers) == before
