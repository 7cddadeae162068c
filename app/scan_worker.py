"""The scan: project every pattern, capture each frame in step, then decode and reconstruct.

Threading model
---------------
The worker runs in its own QThread and owns the camera for the scan; the projector window is a
widget and lives on the UI thread. For each frame the worker

1. emits ``showRequested(index, pattern)``; the UI thread shows it on the projector window;
2. waits until the UI thread calls ``confirm_shown(index)``, which it does only after the window
   has painted that frame *and* one event-loop round trip has passed (the backing store has
   been flushed to the window system), so the camera can never see the previous pattern;
3. waits the settle time (projector LCD response, camera exposure start): the camera's
   latency self-test result when one was run (hardware.sync), else ``ScanJob.settle_s``;
4. captures, and hands the image to ``CaptureWriter`` at once, so a crash loses nothing
   already captured. The manifest's "capture" key records the device, its settings, the
   settle time and, per frame, when it was shown and captured.

Every wait is sliced into short steps that check the cancel flag, so cancel takes effect within
one slice (50 ms) plus, at worst, one camera exposure. Decode and reconstruct are single calls
that cannot be interrupted; cancel during them only drops the result.

All communication with the UI is by queued signals, except the two thread-safe entry points
``confirm_shown`` and ``cancel`` (threading.Event), which the UI calls directly: the worker's
own event loop is busy running the scan, so a queued slot would never be delivered to it.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from PySide6.QtCore import QObject, QThread, Signal, Slot

from anklescan.core.errors import AnkleScanError
from anklescan.hardware.camera import CameraDisconnected


SLICE_S = 0.05
SHOW_TIMEOUT_S = 5.0


class Cancelled(Exception):
    pass


class ScanError(AnkleScanError):
    """A scan that stopped for a reason the clinician must be told about."""


@dataclass
class ScanJob:
    pattern_set: object                 # anklescan.core.scan.patterns.PatternSet
    camera: object                      # hardware.camera.Camera
    folder: Path                        # the capture folder (created; must not hold a capture)
    settle_s: float = 0.03
    calibration: object = None          # anklescan.core.calibration.file.Calibration or None: capture only
    metadata: dict = field(default_factory=dict)
    render: Callable | None = None      # (pattern_set, frame) -> uint8 array; anklescan.core.scan.patterns.render_frame
    reconstruct: Callable | None = None  # (folder, calibration) -> PointCloud, or a anklescan.core.measure.pipeline result
    cloud_path: Path | None = None      # where to write the cloud (PLY), in the worker thread


@dataclass
class ScanResult:
    folder: Path
    frames: int
    capture_s: float
    process_s: float = 0.0
    cloud: object = None                # core PointCloud, or None when not reconstructed
    note: str = ""                      # why there is no cloud, when there is none
    preview: object = None              # (H, W, 3) uint8 RGB: depth image, or the white frame
    depth_range: tuple = (0.0, 0.0)     # mm from the camera, near and far ends of the colours
    marks: dict = field(default_factory=dict)  # automatically found marks, label -> xyz mm
    marks_note: str = ""                # what the detector could not find, when it missed some
    cloud_path: Path | None = None      # the saved cloud, when ScanJob.cloud_path was given
    capture_sha256: str = ""            # content hashes, made in the worker: the UI thread only records them
    cloud_sha256: str = ""
    save_error: str = ""                # why the cloud could not be saved, when it could not
    # how far the subject moved during the capture (core/scan/motion.py), computed in the worker thread
    motion_mm: float | None = None      # None: not measured (no motion references, or no measurement)
    motion_sd_mm: float | None = None
    motion_flagged: bool = False        # moved more than the threshold: "scan again?"
    motion_note: str = ""               # why there is no motion figure, when there is none
    duration_s: float = 0.0             # the scan's duration: first frame shown to last frame captured


class ScanWorker(QObject):
    showRequested = Signal(int, object)      # frame index, uint8 pattern array
    progress = Signal(int, int, str)         # done, total, what is happening
    frameCaptured = Signal(int, object)      # frame index, camera image (for a live thumbnail)
    finished = Signal(object)                # ScanResult
    failed = Signal(str, str)                # one-line message, capture folder (frames kept)
    cancelled = Signal(str)                  # capture folder

    def __init__(self, job: ScanJob):
        super().__init__()
        self.job = job
        self._cancel = threading.Event()
        self._shown = threading.Event()
        self._shown_index = -1
        self._lock = threading.Lock()
        self._abort_message = ""

    # ---- called from the UI thread ------------------------------------------------------
    def cancel(self) -> None:
        self._cancel.set()

    def abort(self, message: str) -> None:
        """Stop because something outside the worker went wrong (e.g. the projector screen left)."""
        self._abort_message = message
        self._cancel.set()

    def confirm_shown(self, index: int) -> None:
        with self._lock:
            self._shown_index = index
        self._shown.set()

    # ---- the worker thread --------------------------------------------------------------
    @Slot()
    def run(self) -> None:
        folder = str(self.job.folder)
        try:
            result = self._scan()
        except Cancelled:
            self.cancelled.emit(folder)
        except AnkleScanError as exc:
            self.failed.emit(str(exc), folder)
        except Exception as exc:  # a bug or a device error: still a message, never a crash
            traceback.print_exc()
            self.failed.emit(f"{type(exc).__name__}: {exc}", folder)
        else:
            self.finished.emit(result)

    def _scan(self) -> ScanResult:
        t0 = time.perf_counter()
        self._capture_all()
        capture_s = time.perf_counter() - t0
        result = ScanResult(Path(self.job.folder), len(self.job.pattern_set.frames), capture_s, duration_s=capture_s)
        if self.job.calibration is None or self.job.reconstruct is None:
            result.note = ("No calibration: the frames are saved but not reconstructed."
                           if self.job.calibration is None else "Capture only: the frames are saved.")
            result.preview = white_preview(self.job.folder, self.job.pattern_set)
            return result
        self._check_cancel()
        n = len(self.job.pattern_set.frames)
        self.progress.emit(n, n, "Decoding and reconstructing…")
        t1 = time.perf_counter()
        out = self._reconstruct()
        if hasattr(out, "marks"):  # a measurement: the cloud plus the marks found on it
            result.cloud = out.cloud
            result.marks = {int(k): tuple(float(v) for v in m.centre) for k, m in out.marks.labelled.items()}
            result.marks_note = "" if out.complete else out.marks.message()
            motion = getattr(out, "motion", None)
            if motion is not None:
                result.motion_mm, result.motion_sd_mm = motion.value_mm, motion.sd_mm
                result.motion_flagged = bool(out.motion_flagged)
                result.motion_note = "" if motion.measured else motion.reason
        else:
            result.cloud = out
        result.process_s = time.perf_counter() - t1
        self._check_cancel()
        if result.cloud is not None and len(result.cloud) > 0:
            # Made here, not on the UI thread: it touches every point.
            result.preview, result.depth_range = depth_preview(result.cloud, self.job.calibration)
        else:
            result.note = "The reconstruction found no points: check focus, exposure and that the foot is lit."
            result.preview = white_preview(self.job.folder, self.job.pattern_set)
        self._save(result)
        return result

    def _save(self, result: ScanResult) -> None:
        """Write the cloud and hash the files here: both touch every byte of the trial."""
        from anklescan.core.records.store import sha256_path
        if self.job.cloud_path is not None and result.cloud is not None and len(result.cloud) > 0:
            from anklescan.core.scan.pointcloud import write_ply
            try:
                write_ply(self.job.cloud_path, result.cloud)
                result.cloud_path = Path(self.job.cloud_path)
                result.cloud_sha256 = sha256_path(result.cloud_path)
            except Exception as exc:  # the capture is still kept; the clinician is told
                result.save_error = f"The point cloud could not be saved: {exc}"
        result.capture_sha256 = sha256_path(self.job.folder)

    def _capture_all(self) -> None:
        from anklescan.core.scan.capture import CaptureWriter  # imported here: the worker module loads fast

        from anklescan.hardware.sync import settle_for

        pset = self.job.pattern_set
        render = self.job.render or _default_render()
        settle = settle_for(self.job.camera, self.job.settle_s)
        writer = CaptureWriter(self.job.folder, pset, {**_device_metadata(self.job.camera, settle), **self.job.metadata})
        timing = writer.metadata.setdefault("frames", {})
        t0 = time.monotonic()
        total = len(pset.frames)
        for i, frame in enumerate(pset.frames):
            self._check_cancel()
            self.progress.emit(i, total, f"Frame {i + 1} of {total}")
            self._show_and_wait(i, render(pset, frame))
            shown = time.monotonic()
            self._sleep(settle.seconds)
            start = time.monotonic()
            image = self._capture()
            timing[frame.file] = _frame_timing(self.job.camera, t0, shown, start)
            writer.add(frame.file, image)
            self.frameCaptured.emit(i, image)
        writer.finish()
        self.progress.emit(total, total, "Capture complete")

    def _show_and_wait(self, index: int, pattern: np.ndarray) -> None:
        self._shown.clear()
        self.showRequested.emit(index, pattern)
        deadline = time.monotonic() + SHOW_TIMEOUT_S
        while True:
            self._check_cancel()
            if self._shown.wait(SLICE_S):
                with self._lock:
                    if self._shown_index == index:
                        return
                self._shown.clear()
            if time.monotonic() > deadline:
                raise ScanError("The projector window did not show the pattern; is the projector screen still connected?")

    def _capture(self) -> np.ndarray:
        try:
            return self.job.camera.capture()
        except CameraDisconnected as exc:
            raise ScanError(f"The camera was disconnected during the scan ({exc}).") from None

    def _reconstruct(self):
        return self.job.reconstruct(self.job.folder, self.job.calibration)

    def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            if self._cancel.wait(min(left, SLICE_S)):
                self._check_cancel()

    def _check_cancel(self) -> None:
        if self._cancel.is_set():
            if self._abort_message:
                raise ScanError(self._abort_message)
            raise Cancelled


def _device_metadata(camera, settle) -> dict:
    """Device, backend, exposure, gain ... as the camera reports them; duck-typed cameras
    without ``metadata()`` still get their name recorded."""
    try:
        meta = dict(camera.metadata())
    except Exception:
        from anklescan.app.rig import camera_name
        meta = {"device": camera_name(camera)}
    meta["settle_ms"] = round(settle.seconds * 1000, 1)
    meta["settle_source"] = settle.source
    if settle.result is not None:
        meta["latency_test"] = settle.result.as_dict()
    return meta


def _frame_timing(camera, t0: float, shown: float, start: float) -> dict:
    """Seconds since the first frame's start; "started" is the wall-clock start of the scan."""
    out = {"shown_s": round(shown - t0, 4), "capture_start_s": round(start - t0, 4),
           "capture_end_s": round(time.monotonic() - t0, 4)}
    info = getattr(camera, "frame_info", None)
    if callable(info):
        out.update({k: v for k, v in info().items() if k not in ("requested", "returned")})
    return out


def _default_render():
    from anklescan.core.scan.patterns import render_frame
    return render_frame


def depth_preview(cloud, calibration) -> tuple[np.ndarray, tuple[float, float]]:
    """Camera-view image of the cloud coloured by distance from the camera (near = warm).

    Stands in for the 3-D viewer of the next issue; the camera's own viewpoint needs no
    projection maths and shows holes in the reconstruction where the clinician expects them.
    """
    import cv2

    cam = calibration.camera
    depth = cam.to_device(cloud.points)[:, 2]
    lo, hi = np.percentile(depth, [1, 99]) if depth.size > 1 else (depth.min(), depth.max() + 1)
    hi = max(hi, lo + 1e-6)
    level = np.clip(255 * (hi - depth) / (hi - lo), 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(level[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]  # BGR → RGB
    image = np.full((cam.height, cam.width, 3), 24, np.uint8)
    uv = np.rint(np.asarray(cloud.pixels, dtype=np.float64)).astype(int) if cloud.pixels is not None \
        else np.rint(_project(cam, cloud.points)).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    image[uv[ok, 1], uv[ok, 0]] = colours[ok]
    return image, (float(lo), float(hi))


def _project(cam, points):
    x = cam.to_device(points)
    uv = x[:, :2] / x[:, 2:3]
    return uv * [cam.fx, cam.fy] + [cam.cx, cam.cy]


def white_preview(folder, pattern_set) -> np.ndarray | None:
    """The white frame as RGB: what the camera saw, when there is no cloud to show."""
    white = [f.file for f in pattern_set.frames if f.kind == "white"]
    if not white:
        return None
    from anklescan.core.scan.capture import read_image  # any path, even one that is not valid UTF-8
    from anklescan.core.errors import CaptureError

    try:
        img = read_image(Path(folder) / white[0])
    except CaptureError:
        return None
    if img is None:
        return None
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else np.ascontiguousarray(img[..., ::-1])


def measure_folder(folder, calibration, mark_diameter_mm: float | None = None,
                   motion_threshold_mm: float | None = None):
    """Reconstruct the saved frames, find the seven marks on them and how far the subject moved
    (``anklescan measure``); the marks' size is the session's setting, or measured when None."""
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.motion import DEFAULT_THRESHOLD_MM
    return measure_capture(load_capture(folder), calibration, mark_diameter_mm,
                           motion_threshold_mm=DEFAULT_THRESHOLD_MM if motion_threshold_mm is None else motion_threshold_mm)


def reconstruct_folder(folder, calibration):
    """What ``anklescan reconstruct`` does: load the saved frames, decode, triangulate."""
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.reconstruct import reconstruct
    return reconstruct(load_capture(folder), calibration)


class ScanController(QObject):
    """Lives on the UI thread: runs one ScanWorker in a QThread and feeds it the projector.

    The projector is any object with ``show_frame(array) -> token`` and a ``painted(token)``
    signal (app.projector_window.ProjectorWindow).
    """

    progress = Signal(int, int, str)
    frameCaptured = Signal(int, object)
    finished = Signal(object)
    failed = Signal(str, str)
    cancelled = Signal(str)
    busyChanged = Signal(bool)

    def __init__(self, projector, parent=None):
        super().__init__(parent)
        self.projector = projector
        self.projector.painted.connect(self._painted)
        self._thread = None
        self._worker = None
        self._pending = None  # (token, frame index) waiting to be painted

    @property
    def busy(self) -> bool:
        return self._worker is not None

    def start(self, job: ScanJob) -> None:
        if self.busy:
            raise ScanError("A scan is already running.")
        thread = QThread()
        thread.setObjectName("scan")
        worker = ScanWorker(job)
        worker.moveToThread(thread)
        thread.started.connect(worker.run)
        worker.showRequested.connect(self._show)  # queued: runs on the UI thread
        # Bound slots of this UI-thread object, so every delivery is queued onto the UI thread.
        worker.progress.connect(self._progress)
        worker.frameCaptured.connect(self._frame_captured)
        worker.finished.connect(self._finished)
        worker.failed.connect(self._failed)
        worker.cancelled.connect(self._cancelled)
        self._thread, self._worker = thread, worker
        self.busyChanged.emit(True)
        thread.start()

    def cancel(self) -> None:
        if self._worker is not None:
            self._worker.cancel()

    def abort(self, message: str) -> None:
        if self._worker is not None:
            self._worker.abort(message)

    def wait(self, timeout_ms: int = 5000) -> bool:
        return self._thread.wait(timeout_ms) if self._thread is not None else True

    def stop(self, timeout_ms: int = 10_000) -> bool:
        """Cancel and wait for the worker to return (for quitting). The thread's event loop is
        told to exit once run() returns, so this does not wait on the UI thread's own queue."""
        if self._thread is None:
            return True
        self.cancel()
        self._thread.quit()
        stopped = self._thread.wait(timeout_ms)
        if stopped:  # the worker's own 'cancelled' is still queued: it finds nothing left to finish
            self._thread, self._worker, self._pending = None, None, None
            self.busyChanged.emit(False)
        return stopped

    @Slot(int, object)
    def _show(self, index: int, pattern) -> None:
        if self._worker is None:
            return
        try:
            token = self.projector.show_frame(pattern)
        except Exception as exc:
            self._worker.abort(f"The projector window cannot show the pattern: {exc}")
            return
        self._pending = (token, index)

    @Slot(int)
    def _painted(self, token: int) -> None:
        if self._pending and self._pending[0] == token and self._worker is not None:
            self._worker.confirm_shown(self._pending[1])
            self._pending = None

    @Slot(int, int, str)
    def _progress(self, done, total, text):
        self.progress.emit(done, total, text)

    @Slot(int, object)
    def _frame_captured(self, index, image):
        self.frameCaptured.emit(index, image)

    @Slot(object)
    def _finished(self, result):
        self._done(self.finished, result)

    @Slot(str, str)
    def _failed(self, message, folder):
        self._done(self.failed, message, folder)

    @Slot(str)
    def _cancelled(self, folder):
        self._done(self.cancelled, folder)

    def _done(self, signal, *args) -> None:
        if self._thread is None:  # already stopped (quitting): nothing more to report
            return
        thread, self._thread, self._worker, self._pending = self._thread, None, None, None
        thread.quit()
        thread.wait()  # the worker has returned from run(); this is immediate
        self.busyChanged.emit(False)
        signal.emit(*args)
