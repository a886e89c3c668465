"""Request and response bodies of the REST API (they make the OpenAPI schema)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.messages import State

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PixelPair = tuple[
    Annotated[float, Field(allow_inf_nan=False, ge=-1e5, le=1e5)],
    Annotated[float, Field(allow_inf_nan=False, ge=-1e5, le=1e5)],
]
GroundPair = tuple[
    Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)],
    Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)],
]


def check_board_pattern(pattern: str) -> tuple[int, int]:
    """(cols, rows) of a ``COLSxROWS`` pattern OpenCV can detect: at least 3x3 inner
    corners (its detector raises on fewer; `parse_pattern` allows 2). Raises ValueError."""
    cols, _, rows = pattern.lower().partition("x")
    if not (cols.isdigit() and rows.isdigit()) or min(int(cols), int(rows)) < 3:
        raise ValueError(f"pattern must be COLSxROWS inner corners, each >= 3, got {pattern!r}")
    return int(cols), int(rows)


class Body(BaseModel):
    """Request bodies reject unknown fields (a typo must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid")


class TeleopRequest(Body):
    """One hand-driving command; repeat it at >= 10 Hz (the mux lets go after
    ``safety.teleop_timeout_s``, 0.5 s by default)."""

    v_m_s: Annotated[float, Field(ge=-2.0, le=2.0, allow_inf_nan=False)]
    omega_rad_s: Annotated[float, Field(ge=-10.0, le=10.0, allow_inf_nan=False)]
    driver: Annotated[str, Field(min_length=1, max_length=64)] = "api"
    take_over: bool = False


class TeleopReleaseRequest(Body):
    driver: Annotated[str | None, Field(min_length=1, max_length=64)] = None
    """Release only this driver's teleop; None releases whoever drives."""


class EstopRequest(Body):
    source: Annotated[str, Field(min_length=1, max_length=64)] = "api"


class ChessboardCalibrationRequest(Body):
    """A chessboard lying flat on the floor, seen in the current frame."""

    pattern: Annotated[str, Field(pattern=r"^[0-9]{1,2}x[0-9]{1,2}$", examples=["9x6"])]
    """Inner corners, COLSxROWS."""
    square_m: Annotated[float, Field(gt=0.0, le=1.0, allow_inf_nan=False)]
    board_x_m: Annotated[float, Field(ge=-10.0, le=10.0, allow_inf_nan=False)] = 0.0
    board_y_m: Annotated[float, Field(ge=-10.0, le=10.0, allow_inf_nan=False)] = 0.0
    board_yaw_rad: Annotated[float, Field(ge=-0.8, le=0.8, allow_inf_nan=False)] = 0.0
    """The board frame in the robot frame (`app.mapping.calibration.BoardPlacement`)."""
    save: bool = True

    @field_validator("pattern")
    @classmethod
    def _opencv_pattern(cls, pattern: str) -> str:
        check_board_pattern(pattern)
        return pattern


class PointPairCalibrationRequest(Body):
    """Four or more pixels of the current frame with their floor positions."""

    image_points_px: Annotated[list[PixelPair], Field(min_length=4, max_length=500)]
    ground_points_m: Annotated[list[GroundPair], Field(min_length=4, max_length=500)]
    """Robot frame: x forward, y left, metres."""
    save: bool = True

    @model_validator(mode="after")
    def _same_length(self) -> PointPairCalibrationRequest:
        if len(self.image_points_px) != len(self.ground_points_m):
            raise ValueError(
                f"image_points_px has {len(self.image_points_px)} points but "
                f"ground_points_m {len(self.ground_points_m)}"
            )
        return self


CalibrationRequest = ChessboardCalibrationRequest | PointPairCalibrationRequest


class CalibrationResponse(BaseModel):
    reprojection_rms_px: float
    ground_rms_m: float
    points: int
    inliers: int
    image_size: tuple[int, int]
    board_origin_px: tuple[float, float] | None
    corners_px: list[tuple[float, float]] | None
    """The detected chessboard corners (chessboard requests), for the wizard to draw."""
    saved_to: str | None


class CommandResponse(BaseModel):
    ok: bool = True
    state: State
    detail: str = ""


class EstopResetResponse(CommandResponse):
    was_estopped: bool


class FaultResetResponse(CommandResponse):
    cleared: str | None
    """The latched fault's reason that was cleared, or null when none was latched."""


class ErrorResponse(BaseModel):
    detail: str
    errors: list[dict[str, Any]] | None = None


ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "missing or wrong bearer token"},
    422: {"model": ErrorResponse, "description": "malformed body or rejected value"},
}
REFUSED_RESPONSE: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorResponse, "description": "refused in the current state"}
}
