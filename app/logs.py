"""Structured logging: one line per event, as text or as JSON objects.

Events carry their fields in ``extra={"event": NAME, ...}``; the text form appends them
as ``key=value`` so both forms hold the same facts.

One record is one line: control characters (Unicode category Cc, and the line and
paragraph separators U+2028/U+2029) in the message and the fields are escaped
(`escape_control`), so text a client sent (an e-stop's label, a URL) can neither forge a
log line nor put a NUL or a terminal escape into the log. Only a traceback keeps its
newlines.
"""

from __future__ import annotations

import json
import logging
import re
import sys
import time
from typing import Any

_STANDARD = set(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {"message", "asctime"}

_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")
_CONTROL_BUT_NEWLINE = re.compile("[\x00-\x09\x0b-\x1f\x7f-\x9f\u2028\u2029]")
_NAMED = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _escape(match: re.Match[str]) -> str:
    char = match.group()
    return _NAMED.get(char) or (
        f"\\x{ord(char):02x}" if ord(char) < 0x100 else f"\\u{ord(char):04x}"
    )


def escape_control(text: str) -> str:
    """``text`` with every control character (Unicode category Cc, U+2028, U+2029)
    written as a Python-style escape (``\\n``, ``\\x00``, ``\\u2028``): one printable line."""
    return _CONTROL.sub(_escape, text)


def _escape_traceback(text: str) -> str:
    return _CONTROL_BUT_NEWLINE.sub(_escape, text)


def _fields(record: logging.LogRecord) -> dict[str, Any]:
    return {k: v for k, v in record.__dict__.items() if k not in _STANDARD}


class TextFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        extra = " ".join(
            f"{escape_control(k)}={escape_control(str(v))}"
            for k, v in _fields(record).items()
            if k != "event"
        )
        message = escape_control(record.getMessage())
        line = f"{stamp}.{int(record.msecs):03d} {record.levelname:<7} {message}"
        if extra:
            line += f"  [{extra}]"
        if record.exc_info:
            line += "\n" + _escape_traceback(self.formatException(record.exc_info))
        return line


class JsonFormatter(logging.Formatter):
    """One JSON object per line. ``json.dumps`` already escapes control characters in
    the line; they are escaped in the values as well, so a consumer that prints a
    decoded message still gets one line."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "t": round(record.created, 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": escape_control(record.getMessage()),
        }
        for key, value in _fields(record).items():
            doc[escape_control(key)] = escape_control(value) if isinstance(value, str) else value
        if record.exc_info:
            doc["exc"] = _escape_traceback(self.formatException(record.exc_info))
        return json.dumps(doc, default=str)


def setup_logging(level: str = "info", *, json_lines: bool = False) -> None:
    """Log to stderr (journald and Docker collect it) in the chosen form."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if json_lines else TextFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    # Third-party chatter stays at warnings unless debugging.
    for noisy in ("uvicorn.access", "websockets", "httpx", "asyncio"):
        logging.getLogger(noisy).setLevel(logging.DEBUG if level == "debug" else logging.WARNING)
