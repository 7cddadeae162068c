"""Acquisition: the one place where a pattern is shown and a frame captured.

Everything that photographs what the projector shows — the patient scan (app.scan_worker), the
camera panel's latency self-test and test shot (app.camera_panel) and the calibration dialog's
box, board and spot-refinement captures (app.calibration_wizard) — goes through ``Acquisition``:

    show the frame → wait until it is presented → settle → capture

for a list of frames, giving a list of images, with progress, cancel and a per-frame callback.
The sequence blocks, so it runs off the UI thread: ``Acquisition.start`` runs it in a background
job (app.background) and delivers the results on the UI thread; ``Acquisition.acquire`` is the
sequence itself, for code that already runs in a worker (the scan).

The projector is a ``ProjectorOutput`` (hardware.camera): ``size`` and ``show(image)``, which
returns once the image is on screen. The simulated projector (hardware.simrig) is one; the real
window (app.projector_window, a widget living on the UI thread) is one through ``WindowOutput``,
which asks the UI thread to paint the frame and waits for the window's ``painted`` signal — sent
one event-loop round trip after the paint, once the backing store has been flushed to the window
system — so the camera never sees the previous pattern.

Settle time: the camera's latency self-test result when one was run (hardware.sync), else the
settings' value. Every wait is sliced (``SLICE_S``) and checks cancel. One lock per camera keeps
two users (a preview and a scan) from grabbing at once.
"""

from __future__ import annotations

import contextlib
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from PySide6.QtCore import QObject, QThread, Signal, Slot

from anklescan.app.background import BackgroundJob, Cancelled, run_in_background
from anklescan.core.errors import AnkleScanError
from anklescan.hardware.camera import Camera, ProjectorOutput

if TYPE_CHECKING:
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.hardware.sync import Settle

T = TypeVar("T")
Timing = dict[str, object]  # one frame's times (and the camera's frame_info), as the capture manifest records them

SLICE_S = 0.05
SHOW_TIMEOUT_S = 5.0  # a frame not painted by then: the window is closed, hidden or on a lost screen


class AcquisitionError(AnkleScanError):
    """The projector could not show a frame (the camera's own errors pass through)."""


# ---- the real projector window as a ProjectorOutput ---------------------------------------------
class _WindowBridge(QObject):
    """Lives on the UI thread: paints what the worker asks for and reports the painted token."""

    request = Signal(object, object, str)  # _Pending, image, mode

    def __init__(self, window: ProjectorWindow):
        super().__init__()
        self.window: ProjectorWindow | None = window
        self._waiting: list[_Pending] = []
        self._lock = threading.Lock()
        self.request.connect(self._show)  # queued when emitted from a worker thread
        window.painted.connect(self._painted)

    @Slot(object, object, str)
    def _show(self, pending: _Pending, image: np.ndarray, mode: str) -> None:
        if pending.abandoned:
            return
        if self.window is None:
            pending.error = "The projector output was closed."
            pending.event.set()
            return
        try:
            pending.token = self.window.show_frame(image, mode)
        except Exception as exc:  # e.g. a frame of the wrong size: the worker says why
            pending.error = f"The projector window cannot show the pattern: {exc}"
            pending.event.set()
            return
        with self._lock:
            self._waiting.append(pending)

    @Slot(int)
    def _painted(self, token: int) -> None:
        now = time.monotonic()
        with self._lock:
            done = [p for p in self._waiting if p.token is not None and token >= p.token]
            self._waiting = [p for p in self._waiting if p not in done]
        for p in done:
            p.presented = now
            p.event.set()

    def detach(self) -> None:
        if self.window is None:
            return
        with contextlib.suppress(RuntimeError, TypeError):
            self.window.painted.disconnect(self._painted)
        self.window = None


class _Pending:
    def __init__(self) -> None:
        self.event = threading.Event()
        self.token: int | None = None
        self.presented = 0.0
        self.error = ""
        self.abandoned = False


class WindowOutput(ProjectorOutput):
    """app.projector_window.ProjectorWindow behind the ProjectorOutput interface.

    Create it on the UI thread. ``show`` must be called from a worker thread (it waits for the UI
    thread to paint); ``mirror`` (the simulated projector) is fed every frame the window paints,
    so the simulated camera photographs exactly what is on screen, when it is on screen."""

    def __init__(self, window: ProjectorWindow, mirror: ProjectorOutput | None = None):
        self.window = window
        self._bridge = _WindowBridge(window)
        self._mirror: Callable[[np.ndarray], None] | None = None
        if mirror is not None:
            self._mirror = mirror.show
            window.frameShown.connect(self._mirror)

    @property
    def size(self) -> tuple[int, int]:
        return self.window.projector_size

    def show(self, image: np.ndarray, *, mode: str = "pattern", cancelled: threading.Event | None = None) -> None:
        """Returns when the frame is presented (``present`` also says when)."""
        self.present(image, mode=mode, cancelled=cancelled)

    def present(self, image: np.ndarray, *, mode: str = "pattern", cancelled: threading.Event | None = None) -> float:
        """Returns when the frame is presented, with that time (time.monotonic)."""
        if QThread.currentThread() is self._bridge.thread():
            raise RuntimeError("WindowOutput.show waits for the UI thread: call it from a worker")
        pending = _Pending()
        self._bridge.request.emit(pending, image, mode)
        deadline = time.monotonic() + SHOW_TIMEOUT_S
        try:
            while not pending.event.wait(SLICE_S):
                if cancelled is not None and cancelled.is_set():
                    raise Cancelled
                if time.monotonic() > deadline:
                    raise AcquisitionError("The projector window did not show the pattern; is the projector "
                                           "screen still connected?")
        finally:
            pending.abandoned = True
        if pending.error:
            raise AcquisitionError(pending.error)
        return pending.presented

    def close(self) -> None:
        self._bridge.detach()
        if self._mirror is not None:
            with contextlib.suppress(RuntimeError, TypeError):
                self.window.frameShown.disconnect(self._mirror)
            self._mirror = None


def as_output(projector: ProjectorOutput | ProjectorWindow) -> ProjectorOutput:
    """A ProjectorOutput for a ProjectorWindow, or the output itself."""
    return projector if isinstance(projector, ProjectorOutput) else WindowOutput(projector)


# ---- one lock per camera ------------------------------------------------------------------------
_LOCKS: weakref.WeakKeyDictionary[object, threading.RLock] = weakref.WeakKeyDictionary()
_LOCKS_GUARD = threading.Lock()
_FALLBACK_LOCK = threading.RLock()


def camera_lock(camera: object) -> threading.RLock:
    with _LOCKS_GUARD:
        try:
            return _LOCKS.setdefault(camera, threading.RLock())
        except TypeError:  # not weak-referenceable
            return _FALLBACK_LOCK


# ---- the sequence -------------------------------------------------------------------------------
class Acquisition:
    """A camera and a projector output, and the show → presented → settle → capture sequence."""

    def __init__(self, camera: Camera, output: ProjectorOutput, settle_s: float = 0.03):
        self.camera, self.output, self.settle_s = camera, output, float(settle_s)

    def settle(self) -> Settle:
        """hardware.sync.Settle: the self-test's (or typed) settle time, else ``settle_s``."""
        from anklescan.hardware.sync import settle_for
        return settle_for(self.camera, self.settle_s)

    def present(self, image: np.ndarray, *, mode: str = "pattern", cancelled: threading.Event | None = None) -> float:
        """Show ``image`` and return once it is presented, with that time (time.monotonic)."""
        if isinstance(self.output, WindowOutput):
            return self.output.present(image, mode=mode, cancelled=cancelled)
        self.output.show(image)
        return time.monotonic()

    def capture(self) -> np.ndarray:
        with camera_lock(self.camera):
            return self.camera.capture()

    def preview(self) -> np.ndarray:
        with camera_lock(self.camera):
            return self.camera.preview()

    def acquire(self, frames: Sequence[Any], *, render: Callable[[Any], np.ndarray] | None = None,
                settle_s: float | None = None, mode: str = "pattern",
                on_frame: Callable[[int, np.ndarray, Timing], None] | None = None,
                progress: Callable[[int, int, str], None] | None = None,
                cancelled: threading.Event | None = None, keep: bool = True) -> list[np.ndarray]:
        """Show each frame (``render(frame)`` when given, for frames made on demand), wait until it
        is presented, wait the settle time, capture. ``on_frame(index, image, timing)`` is called
        in this thread after each capture (timing: seconds since the first frame was asked for,
        as the capture manifest records them). Raises background.Cancelled on cancel. Returns the
        images (none when ``keep`` is False: the caller stores them from ``on_frame``).

        ``frames`` are the images to show, or, with ``render``, what it makes each image from."""
        settle = self.settle().seconds if settle_s is None else float(settle_s)
        images: list[np.ndarray] = []
        total, t0 = len(frames), time.monotonic()
        for i, frame in enumerate(frames):
            _check(cancelled)
            if progress is not None:
                progress(i, total, f"Frame {i + 1} of {total}")
            shown = self.present(render(frame) if render is not None else frame, mode=mode, cancelled=cancelled)
            shown = min(shown, time.monotonic())
            _sleep(settle - (time.monotonic() - shown), cancelled)
            start = time.monotonic()
            image = self.capture()
            if on_frame is not None:
                on_frame(i, image, self._timing(t0, shown, start))
            if keep:
                images.append(image)
        if progress is not None:
            progress(total, total, "Capture complete")
        return images

    def _timing(self, t0: float, shown: float, start: float) -> Timing:
        out: Timing = {"shown_s": round(shown - t0, 4), "capture_start_s": round(start - t0, 4),
               "capture_end_s": round(time.monotonic() - t0, 4)}
        info = getattr(self.camera, "frame_info", None)
        if callable(info):
            out.update({k: v for k, v in info().items() if k not in ("requested", "returned")})
        return out

    def start(self, frames: Sequence[Any], on_done: Callable[[list[np.ndarray]], None],
              on_error: Callable[[str], None], *,
              on_progress: Callable[[int, int, str], None] | None = None,
              on_frame: Callable[[int, np.ndarray], None] | None = None,
              on_cancelled: Callable[[], None] | None = None, **acquire_kw: Any) -> BackgroundJob:
        """From the UI thread: ``acquire`` in a background job; every callback runs on the UI
        thread (``on_frame(index, image)`` for a live thumbnail). Returns the job (``cancel()``)."""
        def run(job: BackgroundJob) -> list[np.ndarray]:
            post: Callable[[int, np.ndarray, Timing], None] | None
            post = (lambda i, image, _t: job.post(on_frame, i, image)) if on_frame is not None else None
            return self.acquire(frames, on_frame=post, progress=job.progress, cancelled=job.cancelled, **acquire_kw)
        return run_in_background(run, on_done, on_error, on_progress=on_progress, on_cancelled=on_cancelled,
                                 pass_job=True, name="acquisition")

    def run(self, fn: Callable[[Acquisition], T], on_done: Callable[[T], None], on_error: Callable[[str], None],
            **kw: Any) -> BackgroundJob:
        """From the UI thread: ``fn(self)`` in a background job (a test shot, the latency self-test)."""
        return run_in_background(lambda: fn(self), on_done, on_error, name="acquisition", **kw)


def _check(cancelled: threading.Event | None) -> None:
    if cancelled is not None and cancelled.is_set():
        raise Cancelled


def _sleep(seconds: float, cancelled: threading.Event | None) -> None:
    """Wait ``seconds`` in this (worker) thread, returning early only to raise Cancelled."""
    end = time.monotonic() + max(0.0, seconds)
    while (left := end - time.monotonic()) > 0:
        if cancelled is not None:
            if cancelled.wait(min(left, SLICE_S)):
                raise Cancelled
        else:
            threading.Event().wait(min(left, SLICE_S))
