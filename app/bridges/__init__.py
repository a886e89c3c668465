"""The daemon's links to the robotics and home-automation ecosystem, each off unless
configured: an MQTT bridge (`app.bridges.mqtt`), a Foxglove live view
(`app.bridges.foxglove_view`). Each is a `app.runtime.core.Service` that runs beside the
web server and reads the runtime the way the web does (immutable snapshots and the
runtime's verbs), so a bridge that fails or stalls never touches driving."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from app.runtime import Runtime
    from app.runtime.core import Service


def bridge_services(runtime: Runtime, token: str) -> list[Service]:
    """The configured bridges for ``runtime``; ``token`` is the daemon's API token (the
    same rules as the REST API: stopping needs none, moving the robot needs it)."""
    services: list[Service] = []
    if runtime.config.mqtt.url is not None:
        from app.bridges.mqtt import MqttBridge

        services.append(MqttBridge(runtime, token))
    if runtime.config.foxglove.port is not None:
        from app.bridges.foxglove_view import foxglove_view

        view = foxglove_view(runtime)  # read-only: needs no token
        if view is not None:
            services.append(view)
    return services
