"""Shared fixtures: paths to the real datasets (skipped when absent) and synthetic scenes."""

from __future__ import annotations

import gc
import os
import socket
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

PROJECT_ROOT = Path(__file__).resolve().parents[1]
DATASETS = PROJECT_ROOT.parent / "shared" / "datasets"
FLOOR_DATASETS = ("robot-hand-floor", "hospital-ground", "umd-drivable-toy")


def dataset_dir(name: str) -> Path:
    """The shared dataset folder ``name``, or skip the test with the reason."""
    path = DATASETS / name
    if not path.is_dir():
        pytest.skip(f"shared dataset {path} is absent (CI clones ../shared beside the project)")
    return path


def room_scene(
    width: int = 160, height: int = 120, *, horizon_frac: float = 0.45, seed: int = 0
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """A synthetic room: a grey-blue wall above a brown floor, a red box standing on the
    floor at the left, mild noise. Returns the BGR image and its true floor mask."""
    rng = np.random.default_rng(seed)
    image = np.empty((height, width, 3), np.uint8)
    horizon = int(horizon_frac * height)
    image[:horizon] = (170, 160, 150)
    image[horizon:] = (60, 100, 140)
    truth = np.zeros((height, width), bool)
    truth[horizon:] = True
    box_x0, box_x1 = width // 10, width // 10 + width // 6
    box_y0, box_y1 = horizon - height // 10, horizon + height // 5
    image[box_y0:box_y1, box_x0:box_x1] = (30, 30, 200)
    truth[box_y0:box_y1, box_x0:box_x1] = False
    noise = rng.integers(-4, 5, image.shape)
    return np.clip(image.astype(int) + noise, 0, 255).astype(np.uint8), truth


@pytest.fixture
def room() -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    return room_scene()


def pytest_configure(config: pytest.Config) -> None:
    """Tests do not depend on the environment they run in: a CI runner under systemd may
    set $NOTIFY_SOCKET / $WATCHDOG_USEC (the daemon would ping it), and any
    FLOORNAV_<SECTION>__<KEY> would change every configuration the tests build."""
    for name in list(os.environ):
        if name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID") or (
            name.startswith("FLOORNAV_") and "__" in name
        ):
            del os.environ[name]


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze everything collection imported (~250k objects): a full garbage collection
    over them takes ~150 ms, which stalls the in-process simulated Uno and event loops
    past their 50 ms ACK and 200 ms silence deadlines, failing timing tests at random.
    The daemon does the same after start-up (app/daemon.py)."""
    gc.collect()
    gc.freeze()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Browser tests last: Playwright's sync API keeps an event loop running in the main
    thread once its session starts, and pytest-asyncio tests cannot run after that."""
    items.sort(key=lambda item: item.get_closest_marker("browser") is not None)


def free_port() -> int:
    """A TCP port on localhost that nothing listens on right now (for test servers)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])
