"""How services beside the stages (the bridges of `app.bridges`) show their state in
`app.runtime.reports.status` and the metrics, without the runtime knowing them: a
service registers a function returning a small JSON-ready dict under a name, per
runtime (or any object standing for one, such as a test's fake)."""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any

StatusSource = Callable[[], dict[str, Any]]

_sources: weakref.WeakKeyDictionary[object, dict[str, StatusSource]] = weakref.WeakKeyDictionary()


def register_status(owner: object, name: str, source: StatusSource) -> None:
    """Report ``source()`` as ``name`` in ``owner``'s status (replaces an earlier one)."""
    _sources.setdefault(owner, {})[name] = source


def service_status(owner: object, name: str) -> dict[str, Any] | None:
    """What the service ``name`` of ``owner`` reports now, or None when none registered."""
    try:
        sources = _sources.get(owner)
    except TypeError:  # not weak-referenceable or not hashable: nothing registered
        return None
    source = sources.get(name) if sources is not None else None
    return source() if source is not None else None
