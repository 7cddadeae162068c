"""The scan: project every pattern, capture each frame in step, then decode and reconstruct.

Threading model
---------------
``ScanController`` lives on the UI thread and runs one scan as a background job
(app.background). The job acquires the frames through app.acquisition — the one show →
presented → settle → capture sequence, whose docstring says how a frame is known to be on
screen before the camera fires — and hands each image to ``CaptureWriter`` at once, so a crash
loses nothing already captured. The manifest's "capture" key records the device, its settings,
the settle time and, per frame, when it was shown and captured. Then it decodes, reconstructs,
makes the preview, writes the cloud and hashes the files, all in the job.

Cancel takes effect within one wait slice (50 ms) plus, at worst, one camera exposure. Decode
and reconstruct are single calls that cannot be interrupted; cancel during them only drops the
result. Everything reaches the UI by queued delivery on the UI thread.
"""

from __future__ import annotations

import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from PySide6.QtCore import QObject, Signal, SignalInstance

from anklescan.app.acquisition import Acquisition, as_output
from anklescan.app.background import BackgroundJob, Cancelled, run_in_background
from anklescan.core.errors import AnkleScanError
from anklescan.hardware.camera import CameraDisconnected

# the core types are imported where used (the module loads fast); here only for the annotations
if TYPE_CHECKING:
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.core.calibration.model.device_model import Device
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.measure.angles import JointCovariance
    from anklescan.core.measure.mark_types import Mark
    from anklescan.core.measure.pipeline import MeasureResult
    from anklescan.core.scan.patterns import Frame, PatternSet
    from anklescan.core.scan.pointcloud import PointCloud
    from anklescan.hardware.camera import Camera, ProjectorOutput
    from anklescan.hardware.sync import Settle

__all__ = ["Cancelled", "ScanController", "ScanError", "ScanJob", "ScanResult", "run_scan"]


class ScanError(AnkleScanError):
    """A scan that stopped for a reason the clinician must be told about."""


# (pattern_set, frame) -> the projector image (uint8, height x width)
RenderFrame = Callable[["PatternSet", "Frame"], npt.NDArray[np.uint8]]
# (capture folder, calibration) -> the cloud and the marks on it
Reconstruct = Callable[[Path, "Calibration"], "MeasureResult"]


@dataclass
class ScanJob:
    pattern_set: PatternSet
    camera: Camera
    folder: Path                        # the capture folder (created; must not hold a capture)
    settle_s: float = 0.03
    calibration: Calibration | None = None  # None: capture only
    metadata: dict[str, object] = field(default_factory=dict)  # written beside the capture (JSON)
    render: RenderFrame | None = None   # None: anklescan.core.scan.patterns.render_frame
    reconstruct: Reconstruct | None = None  # e.g. measure_folder
    cloud_path: Path | None = None      # where to write the cloud (PLY), in the worker thread


@dataclass
class ScanResult:
    folder: Path
    frames: int
    capture_s: float
    process_s: float = 0.0
    cloud: PointCloud | None = None     # None when not reconstructed
    note: str = ""                      # why there is no cloud, when there is none
    preview: np.ndarray | None = None   # (H, W, 3) uint8 RGB: depth image, or the white frame
    depth_range: tuple[float, float] = (0.0, 0.0)  # mm from the camera, near and far ends of the colours
    marks: dict[int, tuple[float, ...]] = field(default_factory=dict)  # automatically found marks, label -> xyz mm
    marks_note: str = ""                # what the detector could not find, when it missed some (its own words)
    marks_missing: list[int] = field(default_factory=list)  # the labels it did not find
    overexposed: list[str] = field(default_factory=list)  # labels of the marks whose face saturates the camera
    warnings: list[str] = field(default_factory=list)  # the measurement's one-line warnings (SPEC §6)
    position_covariance: JointCovariance | None = None  # the marks' joint covariance: the angles' honest ± (SPEC §3)
    quality: dict[int, MarkQuality] = field(default_factory=dict)  # label -> MarkQuality of the automatic marks
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


OBLIQUE_VIEW_DEG = 70.0  # a plate seen more obliquely than this has a less accurate centre (docs/marks.md)


@dataclass(frozen=True)
class MarkQuality:
    """How certain an automatic mark's position is: its SD (mm, the isotropic equivalent of its
    covariance) and why it is less certain than usual ("" when nothing is wrong)."""

    sd_mm: float
    warning: str = ""


def mark_quality(mark: Mark) -> MarkQuality:
    """A measured mark's (core.measure.marks.Mark) SD and warnings, for the marks table and the 3-D view."""
    notes: list[str] = []
    if mark.clipped:
        notes.append("overexposed")
    if mark.view_deg is not None and mark.view_deg > OBLIQUE_VIEW_DEG:
        notes.append(f"seen at {mark.view_deg:.0f}°")
    return MarkQuality(float(mark.sd), ", ".join(notes))


# (index, image): a captured frame, on the UI thread
OnFrame = Callable[[int, np.ndarray], None]


def run_scan(job: ScanJob, acquisition: Acquisition, bg: BackgroundJob, on_frame: OnFrame | None = None) -> ScanResult:
    """The whole scan, in a background job ``bg`` (app.background.BackgroundJob): acquire and
    store every frame, then reconstruct, preview, save and hash. ``bg.post`` carries each
    captured frame to ``on_frame(index, image)`` on the UI thread."""
    work = _Scan(job, acquisition, bg)
    work.on_frame = on_frame
    try:
        return work.run()
    except (Cancelled, AnkleScanError):
        raise
    except Exception as exc:  # a bug or a device error: still a message, never a crash
        traceback.print_exc()
        raise ScanError(f"{type(exc).__name__}: {exc}") from exc


class _Scan:
    def __init__(self, job: ScanJob, acquisition: Acquisition, bg: BackgroundJob) -> None:
        self.job, self.acquisition, self.bg = job, acquisition, bg
        self.on_frame: OnFrame | None = None

    def run(self) -> ScanResult:
        t0 = time.perf_counter()
        self._capture_all()
        capture_s = time.perf_counter() - t0
        result = ScanResult(Path(self.job.folder), len(self.job.pattern_set.frames), capture_s, duration_s=capture_s)
        if self.job.calibration is None or self.job.reconstruct is None:
            result.note = ("No calibration: the frames are saved but not reconstructed."
                           if self.job.calibration is None else "Capture only: the frames are saved.")
            result.preview = white_preview(self.job.folder, self.job.pattern_set)
            return result
        self.bg.check_cancel()
        n = len(self.job.pattern_set.frames)
        self.bg.progress(n, n, "Decoding and reconstructing…")
        t1 = time.perf_counter()
        out = self.job.reconstruct(self.job.folder, self.job.calibration)  # the cloud and the marks on it
        result.cloud = out.cloud
        result.marks = {int(k): tuple(float(v) for v in m.centre) for k, m in out.marks.labelled.items()}
        result.marks_note = "" if out.complete else out.marks.message()
        result.marks_missing = [int(label) for label in out.marks.missing]
        result.overexposed = out.marks.overexposed()
        result.warnings = list(out.warnings)
        result.position_covariance = out.position_covariance
        result.quality = {int(k): mark_quality(m) for k, m in out.marks.labelled.items()}
        if out.motion is not None:
            result.motion_mm, result.motion_sd_mm = out.motion.value_mm, out.motion.sd_mm
            result.motion_flagged = bool(out.motion_flagged)
            result.motion_note = "" if out.motion.measured else out.motion.reason
        result.process_s = time.perf_counter() - t1
        self.bg.check_cancel()
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
        from anklescan.core.scan.capture import CaptureWriter  # imported here: the module loads fast

        pset = self.job.pattern_set
        render = self.job.render or _default_render()
        settle = self.acquisition.settle()
        writer = CaptureWriter(self.job.folder, pset, {**_device_metadata(self.job.camera, settle), **self.job.metadata})
        timing = writer.metadata.setdefault("frames", {})

        def store(i: int, image: np.ndarray, frame_timing: dict[str, object]) -> None:
            timing[pset.frames[i].file] = frame_timing
            writer.add(pset.frames[i].file, image)
            if self.on_frame is not None:
                self.bg.post(self.on_frame, i, image)

        try:
            self.acquisition.acquire(pset.frames, render=lambda frame: render(pset, frame), settle_s=settle.seconds,
                                     on_frame=store, progress=self.bg.progress, cancelled=self.bg.cancelled,
                                     keep=False)
        except CameraDisconnected as exc:
            raise ScanError(f"The camera was disconnected during the scan ({exc}).") from None
        writer.finish()


def _device_metadata(camera: Camera, settle: Settle) -> dict[str, object]:
    """Device, backend, exposure, gain ... as the camera reports them; duck-typed cameras
    without ``metadata()`` still get their name recorded."""
    try:
        meta: dict[str, object] = dict(camera.metadata())
    except Exception:
        from anklescan.app.rig import camera_name
        meta = {"device": camera_name(camera)}
    meta["settle_ms"] = round(settle.seconds * 1000, 1)
    meta["settle_source"] = settle.source
    if settle.result is not None:
        meta["latency_test"] = settle.result.as_dict()
    return meta


def _default_render() -> RenderFrame:
    from anklescan.core.scan.patterns import render_frame
    return render_frame


def depth_preview(cloud: PointCloud, calibration: Calibration) -> tuple[np.ndarray, tuple[float, float]]:
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


def _project(cam: Device, points: np.ndarray) -> np.ndarray:
    x = cam.to_device(points)
    uv = x[:, :2] / x[:, 2:3]
    out: np.ndarray = uv * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    return out


def white_preview(folder: str | os.PathLike[str], pattern_set: PatternSet) -> np.ndarray | None:
    """The white frame as RGB: what the camera saw, when there is no cloud to show."""
    white = [f.file for f in pattern_set.frames if f.kind == "white"]
    if not white:
        return None
    from anklescan.core.errors import CaptureError
    from anklescan.core.scan.capture import read_image  # any path, even one that is not valid UTF-8

    try:
        img = read_image(Path(folder) / white[0])
    except CaptureError:
        return None
    if img is None:
        return None
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else np.ascontiguousarray(img[..., ::-1])


def measure_folder(folder: str | os.PathLike[str], calibration: Calibration, mark_diameter_mm: float | None = None,
                   motion_threshold_mm: float | None = None) -> MeasureResult:
    """Reconstruct the saved frames, find the seven marks on them and how far the subject moved
    (``anklescan measure``); the marks' size is the session's setting, or measured when None."""
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.motion import DEFAULT_THRESHOLD_MM
    return measure_capture(load_capture(folder), calibration, mark_diameter_mm,
                           motion_threshold_mm=DEFAULT_THRESHOLD_MM if motion_threshold_mm is None else motion_threshold_mm)


def reconstruct_folder(folder: str | os.PathLike[str], calibration: Calibration) -> PointCloud:
    """What ``anklescan reconstruct`` does: load the saved frames, decode, triangulate."""
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.reconstruct import reconstruct
    return reconstruct(load_capture(folder), calibration)


class ScanController(QObject):
    """Lives on the UI thread: runs one scan at a time as a background job, through the
    projector's acquisition (app.acquisition).

    ``projector`` is a ProjectorOutput (hardware.camera), or the ProjectorWindow, which is then
    put behind one (app.acquisition.WindowOutput).
    """

    progress = Signal(int, int, str)
    frameCaptured = Signal(int, object)
    finished = Signal(object)
    failed = Signal(str, str)
    cancelled = Signal(str)
    busyChanged = Signal(bool)

    def __init__(self, projector: ProjectorOutput | ProjectorWindow, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.projector = projector
        self.output = as_output(projector)
        self._job: BackgroundJob | None = None  # the running background job
        self._scan: ScanJob | None = None       # its ScanJob
        self._abort_message = ""

    @property
    def busy(self) -> bool:
        return self._job is not None

    def start(self, job: ScanJob) -> None:
        if self.busy:
            raise ScanError("A scan is already running.")
        acquisition = Acquisition(job.camera, self.output, job.settle_s)
        self._abort_message = ""
        self._scan = job
        self._job = run_in_background(
            lambda bg: run_scan(job, acquisition, bg, lambda i, image: self._frame_captured(bg, i, image)),
            lambda result: self._done(bg_job, self.finished, result),
            lambda message: self._done(bg_job, self.failed, message, str(job.folder)),
            on_progress=lambda done, total, text: self._progress(bg_job, done, total, text),
            on_cancelled=lambda: self._ended_by_cancel(bg_job), pass_job=True, name="scan")
        bg_job = self._job
        self.busyChanged.emit(True)

    def cancel(self) -> None:
        if self._job is not None:
            self._job.cancel()

    def abort(self, message: str) -> None:
        """Stop because something outside the scan went wrong (e.g. the projector screen left)."""
        if self._job is not None:
            self._abort_message = message
            self._job.cancel()

    def wait(self, timeout_ms: int = 5000) -> bool:
        return self._job.wait(timeout_ms / 1000) if self._job is not None else True

    def stop(self, timeout_ms: int = 10_000) -> bool:
        """Cancel and wait for the job to return (for quitting); its own report, still queued,
        then finds nothing left to finish."""
        if self._job is None:
            return True
        self.cancel()
        stopped = self._job.wait(timeout_ms / 1000)
        if stopped:
            self._job = self._scan = None
            self.busyChanged.emit(False)
        return stopped

    def _progress(self, bg: BackgroundJob, done: int, total: int, text: str) -> None:
        if bg is self._job:
            self.progress.emit(done, total, text)

    def _frame_captured(self, bg: BackgroundJob, index: int, image: np.ndarray) -> None:
        if bg is self._job:
            self.frameCaptured.emit(index, image)

    def _ended_by_cancel(self, bg: BackgroundJob) -> None:
        folder = str(self._scan.folder) if self._scan is not None else ""
        if self._abort_message:
            self._done(bg, self.failed, self._abort_message, folder)
        else:
            self._done(bg, self.cancelled, folder)

    def _done(self, bg: BackgroundJob, signal: SignalInstance, *args: object) -> None:
        if bg is not self._job:  # already stopped (quitting): nothing more to report
            return
        self._job = self._scan = None
        self.busyChanged.emit(False)
        signal.emit(*args)
