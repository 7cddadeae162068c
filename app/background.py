"""Work off the UI thread: one small helper for everything slow that is not the scan itself
(report rendering, file hashing, detection previews).

``run_in_background(fn, on_done, on_error)`` runs ``fn()`` in a Python thread and delivers its
result, or its exception's message, to the callbacks on the UI thread through a queued Qt
signal. Numpy, OpenCV and matplotlib release the GIL for their heavy parts, so the UI keeps
painting while the job runs.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable

from PySide6.QtCore import QObject, Signal, Slot

_running: set["BackgroundJob"] = set()  # keeps each job (and its signal) alive until delivered


class BackgroundJob(QObject):
    """Created on the UI thread, so its slot runs there: ``done`` emitted from the worker
    thread is queued to the UI thread (a bare function would be called in the worker)."""

    done = Signal(object, str)  # result, error message ("" when it worked)

    def __init__(self, fn: Callable[[], object], on_done: Callable[[object], None],
                 on_error: Callable[[str], None]):
        super().__init__()
        self._fn, self._on_done, self._on_error = fn, on_done, on_error
        self.thread = threading.Thread(target=self._run, name="anklescan-job", daemon=True)
        self.done.connect(self._deliver)

    def _run(self) -> None:
        try:
            result, error = self._fn(), ""
        except Exception as exc:  # delivered as a message: a job never takes the app down
            traceback.print_exc()
            result, error = None, str(exc) or type(exc).__name__
        self.done.emit(result, error)

    @Slot(object, str)
    def _deliver(self, result, error: str) -> None:
        _running.discard(self)
        if error:
            self._on_error(error)
        else:
            self._on_done(result)

    def wait(self, timeout_s: float | None = None) -> bool:
        self.thread.join(timeout_s)
        return not self.thread.is_alive()


def run_in_background(fn: Callable[[], object], on_done: Callable[[object], None],
                      on_error: Callable[[str], None]) -> BackgroundJob:
    job = BackgroundJob(fn, on_done, on_error)
    _running.add(job)
    job.thread.start()
    return job


def pending_jobs() -> int:
    return len(_running)
