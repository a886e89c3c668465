"""What one web app's routes share: the service, the token check, metrics, the encoder."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from prometheus_client import CollectorRegistry

from app.web.auth import BearerAuth
from app.web.metrics import WebMetrics
from app.web.service import RobotService
from app.web.video import FrameEncoder


@dataclass
class WebContext:
    service: RobotService
    token: str
    auth: BearerAuth
    registry: CollectorRegistry
    metrics: WebMetrics
    encoder: FrameEncoder

    @property
    def protect_reads(self) -> bool:
        return self.auth.protect_reads


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf turned into None and numpy scalars into Python ones, so
    strict JSON (browsers' JSON.parse, Starlette's allow_nan=False) accepts it."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
