"""Work off the UI thread: the one helper for everything slow — scans and other acquisitions,
report rendering, file hashing, detection previews.

``run_in_background(fn, on_done, on_error)`` runs ``fn()`` in a Python thread and delivers its
result, or its exception's message, to the callbacks on the UI thread through a queued Qt
signal. Numpy, OpenCV and matplotlib release the GIL for their heavy parts, so the UI keeps
painting while the job runs.

Long work takes the job itself (``pass_job=True``: ``fn(job)``) and then has

- ``job.progress(done, total, text)``: delivered to ``on_progress`` on the UI thread;
- ``job.post(callback, *args)``: any other call delivered on the UI thread (a live thumbnail);
- cancel: the UI calls ``job.cancel()``; the work checks ``job.cancelled`` (a threading.Event,
  so it can also wait on it) or calls ``job.check_cancel()``, which raises ``Cancelled``; a job
  that ends with ``Cancelled`` reports to ``on_cancelled`` instead of ``on_error``.

``owner``: the widget the callbacks act on. A window closed while its job ran is deleted by
Qt before the result comes; then nothing is delivered (a callback on it would raise
"Internal C++ object already deleted" in the event loop).
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

from PySide6.QtCore import QObject, Signal, Slot
from shiboken6 import isValid

_running: set[BackgroundJob] = set()  # keeps each job (and its signal) alive until delivered

T = TypeVar("T")


class Cancelled(Exception):
    """Raised inside a job whose ``cancel()`` was called."""


class BackgroundJob(QObject):
    """Created on the UI thread, so its slots run there: signals emitted from the worker
    thread are queued to the UI thread (a bare function would be called in the worker)."""

    done = Signal(object, str, bool)  # result, error message ("" when it worked), cancelled
    _posted = Signal(object, object)  # callback, args

    # ``fn`` is called as ``fn(job)`` or ``fn()`` (``pass_job``); its result reaches ``on_done`` through the
    # ``done`` signal, which carries any object: run_in_background matches the two, so here they are Any
    def __init__(self, fn: Callable[..., Any], on_done: Callable[[Any], None], on_error: Callable[[str], None], *,
                 on_progress: Callable[[int, int, str], None] | None = None,
                 on_cancelled: Callable[[], None] | None = None, pass_job: bool = False, name: str = "anklescan-job",
                 owner: QObject | None = None) -> None:
        super().__init__()
        self._fn, self._on_done, self._on_error, self._owner = fn, on_done, on_error, owner
        self._on_progress, self._on_cancelled, self._pass_job = on_progress, on_cancelled, pass_job
        self.cancelled = threading.Event()
        self.finished = False  # set on the UI thread once the callbacks have been called
        # not ``thread``: that would hide QObject.thread() (the Qt thread the job's slots run in)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.done.connect(self._deliver)
        self._posted.connect(self._call)

    # ---- in the worker thread -----------------------------------------------------------
    def _run(self) -> None:
        cancelled = False
        try:
            result, error = (self._fn(self) if self._pass_job else self._fn()), ""
        except Cancelled:
            result, error, cancelled = None, "", True
        except Exception as exc:  # delivered as a message: a job never takes the app down
            traceback.print_exc()
            result, error = None, str(exc) or type(exc).__name__
        self.done.emit(result, error, cancelled)

    def progress(self, done: int, total: int, text: str = "") -> None:
        if self._on_progress is not None:
            self._posted.emit(self._on_progress, (done, total, text))

    def post(self, callback: Callable[..., object], *args: object) -> None:
        """Call ``callback(*args)`` on the UI thread (queued, in order with progress and done)."""
        self._posted.emit(callback, args)

    def check_cancel(self) -> None:
        if self.cancelled.is_set():
            raise Cancelled

    # ---- on the UI thread ---------------------------------------------------------------
    def cancel(self) -> None:
        self.cancelled.set()

    def _owner_alive(self) -> bool:
        return self._owner is None or isValid(self._owner)

    @Slot(object, object)
    def _call(self, callback: Callable[..., object], args: tuple[object, ...]) -> None:
        if not self.finished and self._owner_alive():
            callback(*args)

    @Slot(object, str, bool)
    def _deliver(self, result: object, error: str, cancelled: bool) -> None:
        _running.discard(self)
        self.finished = True
        if not self._owner_alive():
            return  # its window was closed: nothing is left to tell
        if cancelled:
            if self._on_cancelled is not None:
                self._on_cancelled()
        elif error:
            self._on_error(error)
        else:
            self._on_done(result)

    def wait(self, timeout_s: float | None = None) -> bool:
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()


def run_in_background(fn: Callable[..., T], on_done: Callable[[T], None], on_error: Callable[[str], None], *,
                      on_progress: Callable[[int, int, str], None] | None = None,
                      on_cancelled: Callable[[], None] | None = None, pass_job: bool = False,
                      name: str = "anklescan-job", owner: QObject | None = None) -> BackgroundJob:
    job = BackgroundJob(fn, on_done, on_error, on_progress=on_progress, on_cancelled=on_cancelled,
                        pass_job=pass_job, name=name, owner=owner)
    _running.add(job)
    job._thread.start()
    return job


def pending_jobs() -> int:
    return len(_running)
