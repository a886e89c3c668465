"""The HTTP/WebSocket API and dashboard server (`create_app`)."""

from app.web.app import create_app
from app.web.auth import resolve_token
from app.web.service import RobotService

__all__ = ["RobotService", "create_app", "resolve_token"]
