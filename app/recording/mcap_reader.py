"""Reading floornav's MCAP recordings back (`app.recording.mcap_writer` writes them).

Everything here reads the file front to back as a stream, so a recording that was cut
short (the daemon was killed, the disk filled) gives every message up to its last
complete chunk, then `TruncatedRecordingError` saying where it stopped; a file that is
no MCAP at all is a `RecordingError` at once.
"""

from __future__ import annotations

import base64
import json
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from app.recording.mcap_writer import CAMERA_TOPIC, CLOCK_METADATA

MCAP_SUFFIX = ".mcap"
MAX_RECORD_BYTES = 256 << 20
"""Larger records are refused (a corrupt length must not allocate gigabytes)."""
_READ_ERRORS = (
    McapError,
    struct.error,
    zlib.error,
    zstandard.ZstdError,
    ValueError,  # the mcap library's CRC errors among them
    RuntimeError,
)
"""What reading a damaged or cut-short file raises."""


class RecordingError(Exception):
    """The file cannot be read as an MCAP recording."""


class TruncatedRecordingError(RecordingError):
    """The recording ends before its end: cut short or damaged after ``messages``
    readable messages."""

    def __init__(self, path: Path, messages: int, detail: str) -> None:
        super().__init__(
            f"{path}: recording cut short or damaged after {messages} readable messages ({detail})"
        )
        self.messages = messages


def _describe(exc: Exception) -> str:
    if isinstance(exc, EndOfFile):
        return "the file ends mid-way"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def is_mcap(path: str | Path) -> bool:
    """Whether ``path`` names an MCAP file (by its suffix)."""
    return Path(path).suffix.lower() == MCAP_SUFFIX


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema_name: str
    log_time_ns: int
    data: bytes
    """The message as stored (JSON)."""

    def decoded(self) -> dict[str, Any]:
        value = json.loads(self.data)
        if not isinstance(value, dict):
            raise RecordingError(f"{self.topic}: a message is not a JSON object")
        return value


@dataclass(frozen=True)
class RecordedImage:
    log_time_ns: int
    data: bytes
    """The encoded image (JPEG or PNG bytes)."""
    format: str
    frame_id: str


def image_of(message: RecordedMessage) -> RecordedImage:
    """The image a ``foxglove.CompressedImage`` message holds."""
    try:
        value = message.decoded()
        data = base64.b64decode(value["data"], validate=True)
        return RecordedImage(
            message.log_time_ns, data, str(value["format"]), str(value.get("frame_id", ""))
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{message.topic}: not a compressed image: {exc}") from exc


def iter_messages(path: str | Path, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
    """Every message (of ``topics``, or all) in file order.

    Raises `RecordingError` when the file is missing or no MCAP, and
    `TruncatedRecordingError` after the last readable message of a file cut short."""
    path = Path(path)
    count = 0
    channels: dict[int, tuple[str, str]] = {}
    schemas: dict[int, str] = {}
    try:
        handle = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror or exc}") from exc
    with handle:
        reader = StreamReader(handle, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES)
        records = reader.records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except _READ_ERRORS as exc:
                detail = _describe(exc)
                if count == 0 and not channels:
                    raise RecordingError(f"{path}: not a readable MCAP file ({detail})") from exc
                raise TruncatedRecordingError(path, count, detail) from exc
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
            elif isinstance(record, Message):
                topic, schema_name = channels.get(record.channel_id, ("", ""))
                if topics is None or topic in topics:
                    count += 1
                    yield RecordedMessage(topic, schema_name, record.log_time, record.data)
            elif isinstance(record, Footer):
                return


def iter_images(path: str | Path, topic: str = CAMERA_TOPIC) -> Iterator[RecordedImage]:
    """The images of ``topic`` in file (= capture) order; errors as `iter_messages`."""
    for message in iter_messages(path, {topic}):
        yield image_of(message)


@dataclass
class RecordingSummary:
    """What a recording holds, read front to back."""

    path: Path
    messages: dict[str, int] = field(default_factory=dict)
    """Messages per topic."""
    schemas: dict[str, str] = field(default_factory=dict)
    """Each topic's schema name."""
    start_ns: int | None = None
    end_ns: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = True
    problem: str = ""
    """Why the file is not complete ("" when it is)."""

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def monotonic_offset_s(self) -> float | None:
        """Unix minus monotonic seconds of the recording daemon (None if not stored)."""
        value = self.metadata.get(CLOCK_METADATA, {}).get("monotonic_to_unix_offset_s")
        return float(value) if value is not None else None


def summarize(path: str | Path) -> RecordingSummary:
    """Count a recording's messages per topic; a file cut short is summarised up to
    where it stops (``complete`` False, ``problem`` says why). Raises `RecordingError`
    for a file that is no MCAP at all."""
    path = Path(path)
    summary = RecordingSummary(path)
    channels: dict[int, str] = {}
    schemas: dict[int, str] = {}
    try:
        handle = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror or exc}") from exc
    with handle:
        records = StreamReader(
            handle, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES
        ).records
        footer = False
        while True:
            try:
                record = next(records)
            except StopIteration:
                break
            except _READ_ERRORS as exc:
                if not channels:
                    raise RecordingError(
                        f"{path}: not a readable MCAP file ({_describe(exc)})"
                    ) from exc
                summary.problem = f"cut short or damaged: {_describe(exc)}"
                break
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = record.topic
                summary.schemas[record.topic] = schemas.get(record.schema_id, "")
                summary.messages.setdefault(record.topic, 0)
            elif isinstance(record, Message):
                topic = channels.get(record.channel_id, "")
                summary.messages[topic] = summary.messages.get(topic, 0) + 1
                t = record.log_time
                summary.start_ns = t if summary.start_ns is None else min(summary.start_ns, t)
                summary.end_ns = t if summary.end_ns is None else max(summary.end_ns, t)
            elif isinstance(record, Metadata):
                summary.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Footer):
                footer = True
        if not footer:
            summary.complete = False
            summary.problem = summary.problem or "no footer: the writer never finished"
    return summary
