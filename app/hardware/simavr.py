"""Run our Uno firmware inside simavr (``firmware/sim/harness``) as a serial device.

The harness prints ``PTY /dev/pts/N`` and waits for ``START`` before running the CPU;
it then reports ``MOTOR t_ms=.. left=.. right=..`` lines whenever the H-bridge outputs
change. `SimavrUno` builds the firmware if needed, starts the harness, starts the CPU
and follows its motor reports, so the daemon can use the real firmware in place of a
real Uno (``[serial] backend = "simavr"``).
"""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path
from types import TracebackType
from typing import Self

from app.hardware.interfaces import MotorPlant

PROJECT_ROOT = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = PROJECT_ROOT / "firmware"
ELF_PATH = PROJECT_ROOT / "build" / "firmware" / "uno" / "floornav_uno.elf"
HARNESS_PATH = PROJECT_ROOT / "build" / "firmware" / "sim" / "harness"


class SimavrError(RuntimeError):
    """The firmware could not be built or the simulator did not start; says why."""


def build_firmware(timeout_s: float = 300.0) -> None:
    """``make -C firmware`` (the sketch and the harness); raises `SimavrError`."""
    try:
        result = subprocess.run(
            ["make", "-C", str(FIRMWARE_DIR)], capture_output=True, text=True, timeout=timeout_s
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SimavrError(f"cannot build the firmware: {exc}") from exc
    if result.returncode != 0:
        tail = (result.stdout + result.stderr)[-2000:]
        raise SimavrError(
            "make -C firmware failed (install the toolchain with "
            f"scripts/install-firmware-deps):\n{tail}"
        )


class SimavrUno:
    """The firmware running in simavr, its UART on a pty.

    Parameters
    ----------
    plant : optional `MotorPlant` that receives every motor change the harness reports
        (the simulated robot's wheels); its encoder counts are fed back to the firmware
        as quadrature pulses, caught up every ``encoder_period_s`` (as often as the
        simulated Uno's process is fed; the harness spreads each catch-up over a period,
        so the firmware's counts trail the wheels by at most about two periods)
    build : run ``make -C firmware`` first (a no-op when up to date)
    """

    def __init__(
        self,
        plant: MotorPlant | None = None,
        *,
        build: bool = True,
        encoder_period_s: float = 0.02,
    ) -> None:
        self.plant = plant
        self.build = build
        self.encoder_period_s = encoder_period_s
        self._stop = threading.Event()
        self._stdin_lock = threading.Lock()
        self.port = ""
        self.pwm = (0, 0)
        self._proc: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None

    def start(self, timeout_s: float = 10.0) -> Self:
        if self.build:
            build_firmware()
        if not HARNESS_PATH.is_file() or not ELF_PATH.is_file():
            raise SimavrError(f"firmware not built: {HARNESS_PATH} / {ELF_PATH} missing")
        # A session (and so a scheduler autogroup) of its own, like the simulated Uno's
        # process: the daemon's busy threads cannot starve the emulated board. It ends
        # with its stdin, i.e. with us.
        self._proc = subprocess.Popen(
            [str(HARNESS_PATH), str(ELF_PATH)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            bufsize=1,
            start_new_session=True,
        )
        assert self._proc.stdout is not None and self._proc.stdin is not None
        ready = threading.Event()
        lines: list[str] = []

        def read_first() -> None:
            assert self._proc is not None and self._proc.stdout is not None
            lines.append(self._proc.stdout.readline())
            ready.set()

        threading.Thread(target=read_first, daemon=True).start()
        if not ready.wait(timeout_s) or not lines[0].startswith("PTY "):
            self.close()
            raise SimavrError(f"simavr harness did not report its pty: {lines[:1]!r}")
        self.port = lines[0].split()[1]
        # The host handshakes with HELLO after it opens the port, so the CPU may start
        # now: a boot banner sent before the port is opened is simply not needed.
        self._send("START")
        self._reader = threading.Thread(target=self._follow, name="simavr-motors", daemon=True)
        self._reader.start()
        if self.plant is not None:
            threading.Thread(
                target=self._feed_encoders, name="simavr-encoders", daemon=True
            ).start()
        return self

    def _send(self, line: str) -> None:
        proc = self._proc
        if proc is None or proc.stdin is None:
            return
        with self._stdin_lock:
            try:
                proc.stdin.write(line + "\n")
                proc.stdin.flush()
            except (OSError, ValueError):
                pass  # the harness is gone; close() reports nothing more to do

    def _feed_encoders(self) -> None:
        """The plant's encoder counts become the harness's encoder targets (``ENCPOS``,
        one count per cycle of channel A). Counts, not rates: a rate computed over the
        nominal period and applied for the next one drops the step under way at every
        change and miscounts whenever this thread wakes late (a busy daemon), so the
        firmware's count would drift from the wheels'; a target is met exactly."""
        assert self.plant is not None
        sent: tuple[int, int] | None = None
        while not self._stop.wait(self.encoder_period_s):
            counts = self.plant.read_encoders()
            if counts != sent:
                self._send(f"ENCPOS {counts[0]} {counts[1]}")
                sent = counts

    def _follow(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            if not line.startswith("MOTOR "):
                continue
            fields = dict(item.split("=", 1) for item in line.split()[1:])
            left, right = int(fields["left"]), int(fields["right"])
            self.pwm = (left, right)
            if self.plant is not None:
                self.plant.apply_pwm(left, right)

    def close(self) -> None:
        self._stop.set()
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            if proc.stdin is not None:
                proc.stdin.close()  # the harness exits on end of stdin
            proc.wait(timeout=2.0)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait(timeout=2.0)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
