"""A Qt-free signal: the logic layer says what changed; the windows connect to it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, ParamSpec

P = ParamSpec("P")  # what an event carries: ``Event[[Severity, str]]`` emits (kind, text)


class Event(Generic[P]):
    """Callbacks run in the emitting thread; the logic is only driven from the UI thread, so
    that is where they run (background work reports back through app.background first)."""

    def __init__(self) -> None:
        self._slots: list[Callable[P, object]] = []

    def connect(self, slot: Callable[P, object]) -> None:
        self._slots.append(slot)

    def emit(self, *args: P.args, **kwargs: P.kwargs) -> None:
        for slot in list(self._slots):
            slot(*args, **kwargs)
