"""The bounds every hand-driving entry point puts on a teleop command: the REST API
(`app.web.schemas.TeleopRequest`), the control socket (`app.web.ws.TeleopMessage`) and
MQTT (`app.bridges.mqtt.TeleopCommand`). One definition, so the three cannot drift.

They are a sanity bound on what a client may ask for, not the robot's limits: the
drive stage clamps every command to ``drive.max_linear_speed_m_s`` and the wheels'
reach. NaN and infinity are refused.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

TELEOP_MAX_LINEAR_M_S = 2.0
TELEOP_MAX_ANGULAR_RAD_S = 10.0

TeleopLinearSpeed = Annotated[
    float, Field(ge=-TELEOP_MAX_LINEAR_M_S, le=TELEOP_MAX_LINEAR_M_S, allow_inf_nan=False)
]
TeleopAngularSpeed = Annotated[
    float, Field(ge=-TELEOP_MAX_ANGULAR_RAD_S, le=TELEOP_MAX_ANGULAR_RAD_S, allow_inf_nan=False)
]
