"""One set of teleop bounds for every way of driving by hand."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, ValidationError

from app.bridges.mqtt import TeleopCommand
from app.control.teleop_limits import TELEOP_MAX_ANGULAR_RAD_S, TELEOP_MAX_LINEAR_M_S
from app.web.schemas import TeleopRequest
from app.web.ws import TeleopMessage

ENTRY_POINTS: list[tuple[type[BaseModel], dict[str, object]]] = [
    (TeleopRequest, {}),
    (TeleopMessage, {"type": "teleop"}),
    (TeleopCommand, {"cmd": "teleop"}),
]


@pytest.mark.parametrize(("model", "extra"), ENTRY_POINTS)
def test_every_entry_point_takes_the_bounds_and_refuses_past_them(
    model: type[BaseModel], extra: dict[str, object]
) -> None:
    edge = {"v_m_s": -TELEOP_MAX_LINEAR_M_S, "omega_rad_s": TELEOP_MAX_ANGULAR_RAD_S}
    model.model_validate({**extra, **edge})
    for field, value in [
        ("v_m_s", TELEOP_MAX_LINEAR_M_S + 0.01),
        ("omega_rad_s", -TELEOP_MAX_ANGULAR_RAD_S - 0.01),
        ("v_m_s", float("nan")),
        ("omega_rad_s", float("inf")),
    ]:
        with pytest.raises(ValidationError, match=field):
            model.model_validate({**extra, **edge, field: value})
