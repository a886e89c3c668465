"""What one web app's routes share: the service, the token check, metrics, the encoder."""

from __future__ import annotations

from dataclasses import dataclass

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
