"""JSON schemas (MCAP schema encoding ``jsonschema``) of the messages floornav records.

The Foxglove ones carry Foxglove's own names and fields (``foxglove.CompressedImage``,
``foxglove.PoseInFrame``, ``foxglove.Log``, ``foxglove.Grid``), so Foxglove's panels
(Image, 3D, Log, Map) show them as they are. The optional ``message_id`` / ``lineage``
fields of recent Foxglove schemas are left out (floornav never sets them). In the JSON
message encoding every ``bytes`` field is a base64 string (``contentEncoding``).

floornav's own messages: ``floornav.DriveCommand`` (a command as sent to the Uno) and
``floornav.StopEvent`` (a stop and its cause, `app.runtime.stops`).
"""

from __future__ import annotations

from typing import Any

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

TIME: dict[str, Any] = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}

VECTOR3: dict[str, Any] = {
    "title": "foxglove.Vector3",
    "type": "object",
    "properties": {
        "x": {"type": "number"},
        "y": {"type": "number"},
        "z": {"type": "number"},
    },
    "required": ["x", "y", "z"],
}

QUATERNION: dict[str, Any] = {
    "title": "foxglove.Quaternion",
    "type": "object",
    "properties": {
        "x": {"type": "number"},
        "y": {"type": "number"},
        "z": {"type": "number"},
        "w": {"type": "number"},
    },
    "required": ["x", "y", "z", "w"],
}

POSE: dict[str, Any] = {
    "title": "foxglove.Pose",
    "type": "object",
    "properties": {"position": VECTOR3, "orientation": QUATERNION},
    "required": ["position", "orientation"],
}

COMPRESSED_IMAGE: dict[str, Any] = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "Timestamp of image"},
        "frame_id": {"type": "string", "description": "Frame of reference for the image"},
        "data": {
            "type": "string",
            "contentEncoding": "base64",
            "description": "Compressed image data",
        },
        "format": {
            "type": "string",
            "description": "Image format\n\nSupported values: `jpeg`, `png`, `webp`, `avif`",
        },
    },
    "required": ["timestamp", "frame_id", "data", "format"],
}

POSE_IN_FRAME: dict[str, Any] = {
    "title": "foxglove.PoseInFrame",
    "description": "A timestamped pose for an object or reference frame in 3D space",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "Timestamp of pose"},
        "frame_id": {
            "type": "string",
            "description": "Frame of reference for pose position and orientation",
        },
        "pose": POSE,
    },
    "required": ["timestamp", "frame_id", "pose"],
}

LOG_LEVELS = {"UNKNOWN": 0, "DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "FATAL": 5}
"""``foxglove.LogLevel``."""

LOG: dict[str, Any] = {
    "title": "foxglove.Log",
    "description": "A log message",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "Timestamp of log message"},
        "level": {
            "title": "foxglove.LogLevel",
            "description": "Log level",
            "oneOf": [{"title": name, "const": value} for name, value in LOG_LEVELS.items()],
        },
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "description": "Line number in the file"},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}

NUMERIC_TYPES = {
    "UNKNOWN": 0,
    "UINT8": 1,
    "INT8": 2,
    "UINT16": 3,
    "INT16": 4,
    "UINT32": 5,
    "INT32": 6,
    "FLOAT32": 7,
    "FLOAT64": 8,
}
"""``foxglove.NumericType``."""

GRID: dict[str, Any] = {
    "title": "foxglove.Grid",
    "description": "A 2D grid of data",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "Timestamp of grid"},
        "frame_id": {"type": "string", "description": "Frame of reference"},
        "pose": {
            **POSE,
            "description": "Origin of grid's corner relative to frame of reference; grid is "
            "positioned in the x-y plane relative to this origin",
        },
        "column_count": {
            "type": "integer",
            "minimum": 0,
            "description": "Number of grid columns",
        },
        "cell_size": {
            "title": "foxglove.Vector2",
            "type": "object",
            "properties": {"x": {"type": "number"}, "y": {"type": "number"}},
            "description": "Size of single grid cell along x and y axes, relative to `pose`",
        },
        "row_stride": {
            "type": "integer",
            "minimum": 0,
            "description": "Number of bytes between rows in `data`",
        },
        "cell_stride": {
            "type": "integer",
            "minimum": 0,
            "description": "Number of bytes between cells within a row in `data`",
        },
        "fields": {
            "type": "array",
            "items": {
                "title": "foxglove.PackedElementField",
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "offset": {"type": "integer", "minimum": 0},
                    "type": {
                        "title": "foxglove.NumericType",
                        "oneOf": [
                            {"title": name, "const": value} for name, value in NUMERIC_TYPES.items()
                        ],
                    },
                },
            },
            "description": "Fields in `data`",
        },
        "data": {
            "type": "string",
            "contentEncoding": "base64",
            "description": "Grid cell data, interpreted using `fields`, in row-major "
            "(y-major) order",
        },
    },
}

DRIVE_COMMAND: dict[str, Any] = {
    "title": "floornav.DriveCommand",
    "description": "A drive command as floornav sent it to the Uno",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "When the command was sent"},
        "source": {
            "type": "string",
            "description": "Who commanded it: autonomy, teleop, estop, watchdog, timeout, ...",
        },
        "linear_m_s": {"type": "number", "description": "Forward speed commanded"},
        "angular_rad_s": {"type": "number", "description": "Turn rate, counter-clockwise +"},
        "left_wheel_m_s": {"type": "number", "description": "Left wheel speed it means"},
        "right_wheel_m_s": {"type": "number", "description": "Right wheel speed it means"},
        "left_pwm": {"type": "integer", "description": "PWM sent to the left motor"},
        "right_pwm": {"type": "integer", "description": "PWM sent to the right motor"},
        "heading_rad": {
            "type": ["number", "null"],
            "description": "Steering's chosen heading (robot frame), autonomy only",
        },
        "origin_age_ms": {
            "type": "number",
            "description": "Age of the camera frame the command derives from, when sent",
        },
    },
    "required": ["timestamp", "source", "left_pwm", "right_pwm"],
}

STOP_EVENT: dict[str, Any] = {
    "title": "floornav.StopEvent",
    "description": "A stop: its cause (app.runtime.stops.STOP_RULES), why, and whether it "
    "latched a fault",
    "type": "object",
    "properties": {
        "timestamp": {**TIME, "description": "When the stop started"},
        "cause": {
            "type": "string",
            "description": "link, camera, stale, clearance, not_floor, calibration",
        },
        "reason": {"type": "string", "description": "The reason, in a sentence"},
        "latched": {"type": "boolean", "description": "A fault that needs a reset"},
        "zeroes_motors": {
            "type": "boolean",
            "description": "Holds the motors at zero (else only forward motion is taken)",
        },
        "missed": {
            "type": "integer",
            "minimum": 0,
            "description": "Stops that happened since the previous message and are not "
            "recorded (they came faster than the recorder looks)",
        },
    },
    "required": ["timestamp", "cause", "reason", "latched"],
}

SCHEMAS: dict[str, dict[str, Any]] = {
    schema["title"]: schema
    for schema in (COMPRESSED_IMAGE, POSE_IN_FRAME, LOG, GRID, DRIVE_COMMAND, STOP_EVENT)
}
"""Every schema by its name (the MCAP schema record's ``name``)."""
