"""A Qt-free signal: the logic layer says what changed; the windows connect to it."""

from __future__ import annotations

from collections.abc import Callable


class Event:
    """Callbacks run in the emitting thread; the logic is only driven from the UI thread, so
    that is where they run (background work reports back through app.background first)."""

    def __init__(self) -> None:
        self._slots: list[Callable] = []

    def connect(self, slot: Callable) -> None:
        self._slots.append(slot)

    def emit(self, *args) -> None:
        for slot in list(self._slots):
            slot(*args)
