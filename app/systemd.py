"""systemd's notify protocol without a dependency: ``READY=1`` once the daemon serves,
``WATCHDOG=1`` pings while it is healthy, ``STOPPING=1`` on the way out.

The protocol is one datagram of ``KEY=VALUE`` lines sent to the unix socket named by
``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace). Outside systemd
the variable is unset and every call is a no-op, so the daemon calls these
unconditionally.
"""

from __future__ import annotations

import os
import socket


def _socket_address(value: str) -> str | bytes:
    # "@name" names a socket in Linux's abstract namespace: a leading NUL byte.
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


def notify(state: str) -> bool:
    """Send ``state`` (e.g. ``"READY=1"`` or ``"WATCHDOG=1\\nSTATUS=exploring"``) to the
    service manager. Returns False when not run under systemd (no ``$NOTIFY_SOCKET``) or
    the socket cannot be reached; never raises for those."""
    target = os.environ.get("NOTIFY_SOCKET", "")
    if not target:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            # Never block the event loop: a datagram socket whose reader stopped reading
            # blocks the sender once ~10 datagrams are queued. Then the message is lost.
            sock.setblocking(False)
            sock.connect(_socket_address(target))
            sock.send(state.encode())
    except OSError:  # BlockingIOError included
        return False
    return True


def watchdog_interval_s() -> float | None:
    """How often to send ``WATCHDOG=1``: half of ``$WATCHDOG_USEC`` (systemd's advice), or
    None when the watchdog is off or meant for another process (``$WATCHDOG_PID``)."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    return value / 2_000_000.0
