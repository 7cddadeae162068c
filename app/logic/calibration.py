"""The calibration's logic, without Qt: the current calibration (kept in the app's settings,
passed in as ``settings``: get/set/sync), accepting and verifying, the cameras that photograph the box and the chessboard,
and the work done on a capture folder (run in background jobs by app.calibration_wizard).

The dialog is app.calibration_wizard (its pages: app.calibration_pages, the paper's manual
method: app.calibration_manual).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

from anklescan.app.logic.settings import AppSettings, CalibrationVerdict

if TYPE_CHECKING:
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.calibration.procedures.board import BoardCalibration
    from anklescan.core.calibration.procedures.calibrate import CalibrationReport
    from anklescan.core.calibration.procedures.levelling import TableTop
    from anklescan.core.calibration.procedures.verification import VerificationResult
    from anklescan.core.records.store import Store
    from anklescan.core.scan.capture import Image
    from anklescan.core.scan.decode import DecodeResult
    from anklescan.core.vocabulary import CalibrationRecord
    from anklescan.hardware.camera import Camera
    from anklescan.hardware.sim_scene import Scene
    from anklescan.hardware.simrig import SimulatedCamera

CORNER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")
Folder = str | os.PathLike[str]  # a capture folder


class RigView(Protocol):
    """What the cameras here need of the app's rig (app.rig.Rig: not imported, it reaches for Qt)."""

    simulated: bool
    camera: Camera


# ==== the current calibration =============================================================
@dataclass(frozen=True)
class CurrentCalibration:
    """The current calibration as the settings keep it."""

    path: str  # its file; "" when there is none
    id: int | None  # its row in the data folder's database; None when not in one
    created: str  # ISO 8601
    verified: CalibrationVerdict
    verified_at: str  # ISO 8601; "" when not verified


def current_calibration_info(settings: AppSettings) -> CurrentCalibration:
    s = settings
    return CurrentCalibration(s.calibration_path, s.calibration_id, s.calibration_created, s.calibration_verified,
                              s.calibration_verified_at)


def load_current_calibration(settings: AppSettings) -> tuple[Calibration, int | None] | tuple[None, None]:
    """(Calibration, database id) of the current calibration, or (None, None)."""
    from anklescan.core.calibration.model.file import load_calibration
    info = current_calibration_info(settings)
    if not info.path or not Path(info.path).exists():
        return None, None
    return load_calibration(info.path), info.id


def calibration_warning(settings: AppSettings, now: _dt.datetime | None = None) -> str:
    """The main window's banner text: "" when the current calibration is fine.

    Warns when there is none, when it is older than the ``calibration_max_age_days`` setting
    (default 30), or when its last verification failed.
    """
    s = settings
    info = current_calibration_info(s)
    if not info.path:
        return "No calibration yet: run Calibration… (Scan menu) before measuring patients."
    max_age = s.calibration_max_age_days
    now = now or _dt.datetime.now(_dt.UTC)
    problems = []
    if info.verified is CalibrationVerdict.FAIL:
        problems.append(f"its last verification failed ({info.verified_at[:10]})")
    try:
        age = (now - _dt.datetime.fromisoformat(info.created)).total_seconds() / 86400
    except ValueError:
        age = None
    if age is not None and age > max_age:
        problems.append(f"it is {age:.0f} days old (limit {max_age:g})")
    if not problems:
        return ""
    return "The calibration should be renewed: " + " and ".join(problems) + ". Use Calibration… (Scan menu)."


def _now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def accept_calibration(cal: Calibration, report: CalibrationReport | None, data_folder: Path, store: Store | None,
                       settings: AppSettings, source: str = "box") -> tuple[Path, int | None]:
    """Save atomically, add to the database (versioned: a new row each time), make current."""
    from anklescan.core.calibration.model.file import calibration_to_dict, save_calibration
    created = _now_iso()
    cal.extra["created"] = created
    cal.extra.setdefault("source", source)
    folder = Path(data_folder) / "calibrations"
    path = folder / f"calibration_{created.replace(':', '').replace('+0000', 'Z')[:17]}.json"
    n = 1
    while path.exists():  # two accepted within a second keep both versions
        path = folder / f"calibration_{created.replace(':', '')[:17]}_{n}.json"
        n += 1
    save_calibration(cal, path)
    cid = None
    if store is not None:
        rms = float(report.camera.rms_px) if report is not None else None
        cid = store.calibrations.add(calibration_to_dict(cal), rms=rms, source=f"{source}: {path.name}").id
    _make_current(settings, path, cid, created, CalibrationVerdict.NONE)
    return path, cid


def use_stored_calibration(record: CalibrationRecord, data_folder: Path, settings: AppSettings) -> Path:
    """Make a calibration kept in the database (a CalibrationRecord) the current one: its own file
    when it is still in the data folder and the same, else the database's copy written next to
    the others. Its verification in the database is kept as the current verdict."""
    from anklescan.core.atomic import write_text_atomic
    from anklescan.core.calibration.model.file import calibration_from_dict
    calibration_from_dict(record.data)  # a calibration that cannot be read is refused before anything changes
    folder = Path(data_folder) / "calibrations"
    name = record.source.split(": ", 1)[-1] if ": " in record.source else ""
    path = folder / name if name.endswith(".json") else None
    if path is None or not path.is_file() or _json_or_none(path) != record.data:
        path = folder / f"calibration_db{record.id}.json"
        write_text_atomic(path, json.dumps(record.data, indent=1) + "\n")
    created = str(record.data.get("created", "") or record.created)
    _make_current(settings, path, record.id, created,
                  CalibrationVerdict.PASS if record.verified else CalibrationVerdict.NONE)
    return path


def _make_current(settings: AppSettings, path: Path, cid: int | None, created: str, verified: CalibrationVerdict) -> None:
    s = settings
    s.calibration_path, s.calibration_id, s.calibration_created = str(path), cid, created
    s.calibration_verified, s.calibration_verified_at = verified, ""
    s.sync()


def _json_or_none(path: Path) -> object:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def record_verification(result: VerificationResult, settings: AppSettings, calibration_path: str | None = None) -> None:
    """Remember the verdict (the banner reads it) and keep the report next to the file."""
    from anklescan.core.atomic import write_text_atomic
    s = settings
    s.calibration_verified = CalibrationVerdict.PASS if result.passed else CalibrationVerdict.FAIL
    s.calibration_verified_at = _now_iso()
    s.sync()
    path = calibration_path or s.calibration_path
    if path:
        write_text_atomic(Path(path).with_suffix(".verification.json"),
                          json.dumps({"verified_at": _now_iso(), **result.to_dict()}, indent=1) + "\n")


# ==== what is in front of the camera ========================================================
def _scene_camera(rig: RigView, scene: Scene, name: str) -> SimulatedCamera:
    from anklescan.hardware.simrig import SimulatedCamera
    cam = rig.camera
    # the callers check hasattr(rig.camera, "rig"): of the cameras only a simulated one has its rig
    assert isinstance(cam, SimulatedCamera), "a scene camera is made for the simulated rig only"
    sim = SimulatedCamera(cam.rig.with_scene(scene), cam.projector, name)
    for control, c in cam.controls().items():
        sim.set_control(control, c.value)
    sim.open()
    return sim


# where a person stands the box for its 1st, 2nd, 3rd scan on the simulated rig: on the floor at
# the table (its documented place), on a stand at the knee, half-way (docs/calibration_app.md)
SIM_BOX_LIFTS_MM = (0.0, 300.0, 150.0)


def box_camera(rig: RigView, position: int = 0) -> Camera:
    """The camera that photographs the box: on the simulated rig a simulated camera on the box
    scene (same devices, same projector image) with the box at ``position`` (``SIM_BOX_LIFTS_MM``);
    on real hardware the rig's own camera."""
    if not rig.simulated or not hasattr(rig.camera, "rig"):
        return rig.camera
    from anklescan.core.calibration.procedures.box import BoxPose
    from anklescan.hardware.sim_scene import box_scene_objects, quad_scene
    lift = SIM_BOX_LIFTS_MM[position % len(SIM_BOX_LIFTS_MM)]
    return _scene_camera(rig, quad_scene(box_scene_objects(4.0, BoxPose.placed(lift_mm=lift))),
                         "Simulated camera (box)")


def board_camera(rig: RigView, view: int, cols: int, rows: int, square: float) -> Camera:
    """The camera that photographs the chessboard: on the simulated rig a simulated camera on board
    pose ``view`` (hardware.sim_board: the first flat on the table, then tilted; a person moves the
    board between scans); on real hardware the rig's own camera."""
    if not rig.simulated or not hasattr(rig.camera, "rig"):
        return rig.camera
    from anklescan.hardware.sim_board import board_views
    views = board_views(cols, rows, square)
    return _scene_camera(rig, views[view % len(views)][0], "Simulated camera (board)")


def camera_size(camera: Camera) -> tuple[int, int]:
    info = camera.info
    return int(info.width), int(info.height)


# ==== control points ========================================================================
@dataclass
class BoxPoints:
    """Control points of one box scan, with the camera pixel of every projector point (for arrows)."""

    white: np.ndarray
    cam_xyz: np.ndarray
    cam_uv: np.ndarray
    proj_xyz: np.ndarray
    proj_uv: np.ndarray  # (N, 2) column, row
    proj_cam_uv: np.ndarray  # (N, 2) camera pixel where each projector point was read
    found: dict[int, np.ndarray] = field(default_factory=dict)  # marker id -> (4, 2) camera corners


def observe(white: np.ndarray, column: np.ndarray, row: np.ndarray | None) -> BoxPoints:
    from anklescan.core.calibration.procedures.box import observe_box
    obs = observe_box(white, column, row)
    return BoxPoints(np.asarray(white, np.float32), obs.cam_xyz, obs.cam_uv, obs.proj_xyz, obs.proj_uv,
                     obs.proj_cam_uv, obs.found)


def calibrate_box(points: BoxPoints, camera_size: tuple[int, int], projector_size: tuple[int, int],
                  exclude_flagged: bool = True) -> tuple[Calibration, CalibrationReport]:
    from anklescan.core.calibration.procedures.calibrate import calibrate_points
    # radial_terms=2: real lenses (and the simulator's) need k2 beyond the paper's k1.
    return calibrate_points(points.cam_xyz, points.cam_uv, points.proj_xyz, points.proj_uv, camera_size=camera_size,
                            projector_size=projector_size, radial_terms=2, exclude_flagged=exclude_flagged)


def kept(n: int, excluded: Iterable[int]) -> np.ndarray:
    out: np.ndarray = np.setdiff1d(np.arange(n), np.asarray(list(excluded), int))
    return out


def refine_click(image: np.ndarray, x: float, y: float, half_window: int) -> tuple[float, float]:
    """The marker corner nearest a click, to sub-pixel (cv2.cornerSubPix on the stretched image)."""
    import cv2

    from anklescan.core.calibration.procedures.box import stretch_to_8bit
    g = stretch_to_8bit(image)
    h, w = g.shape
    if not (half_window <= x < w - half_window and half_window <= y < h - half_window):
        return x, y
    p = np.array([[[x, y]]], np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    r = cv2.cornerSubPix(g, p, (half_window, half_window), (-1, -1), crit).reshape(2)
    # a click on a flat area converges nowhere useful: keep the click itself
    return (float(r[0]), float(r[1])) if np.hypot(*(r - [x, y])) <= half_window else (x, y)


def manual_points() -> list[tuple[str, np.ndarray]]:
    """(label, world mm) of every marker corner, in the order the operator is asked for them."""
    from anklescan.core.calibration.procedures.box import marker_corners_world, marker_layout
    layout = marker_layout()
    return [(f"marker {mid} ({layout[mid][0].name} face), {CORNER_NAMES[k]} corner", X[k])
            for mid, X in sorted(marker_corners_world().items()) for k in range(4)]


def cam_pixels_of(proj_xyz: np.ndarray, cam_xyz: np.ndarray, cam_uv: np.ndarray) -> np.ndarray:
    """Where to draw each projector residual: its point's camera click, else nowhere (NaN)."""
    out: list[np.ndarray | tuple[float, float]] = []
    for X in proj_xyz:
        hit = np.flatnonzero(np.all(np.isclose(cam_xyz, X), axis=1))
        out.append(cam_uv[hit[0]] if hit.size else (np.nan, np.nan))
    return np.array(out).reshape(-1, 2)


# ==== work on a capture folder (background jobs) =================================================
def decode_folder(folder: Folder) -> DecodeResult:
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.decode import decode
    return decode(load_capture(folder))


def white_frame(folder: Folder) -> Image:
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.patterns import FrameKind
    cap = load_capture(folder)
    return cap.frame(cap.pattern_set.files[cap.pattern_set.index(FrameKind.WHITE)])


class BoxFit(NamedTuple):
    """A box calibration from its scans (a tuple: ``points, cal, report = calibrate_folders(...)``)."""

    points: BoxPoints
    calibration: Calibration
    report: CalibrationReport


def calibrate_folder(folder: Folder, camera_size: tuple[int, int], projector_size: tuple[int, int]) -> BoxFit:
    """(BoxPoints, Calibration, report) from a box scan; BoxCalibrationRefused (its one line says what
    to do) when the residuals are far beyond the corners' noise."""
    from anklescan.core.calibration.procedures.box import BoxCapture, BoxPose, check_residuals, observe_box
    from anklescan.core.calibration.procedures.frame import FRAME_KEY, FrameSource
    decoded = decode_folder(folder)
    obs = observe_box(decoded.white, decoded.require_column(), decoded.row)
    pts = BoxPoints(np.asarray(decoded.white, np.float32), obs.cam_xyz, obs.cam_uv, obs.proj_xyz, obs.proj_uv,
                    obs.proj_cam_uv, obs.found)
    cal, report = calibrate_box(pts, camera_size, projector_size)
    check_residuals(report, [BoxCapture(Path(folder).name, BoxPose(), obs)], cal)
    cal.extra[FRAME_KEY] = FrameSource.BOX.value
    cal.extra["source"] = f"calibration box scan {Path(folder).name}"
    cal.extra["box"] = {"markers_found": sorted(pts.found), "camera_points": len(pts.cam_xyz),
                        "projector_points": len(pts.proj_xyz), "capture": str(folder)}
    return BoxFit(pts, cal, report)


def calibrate_folders(folders: Sequence[Folder], camera_size: tuple[int, int],
                      projector_size: tuple[int, int]) -> BoxFit:
    """(BoxPoints of all positions, drawn on the last scan's white frame, Calibration, report) from
    box scans at several positions in one fit (core.calibration.procedures.box.calibrate_from_box_captures;
    refused like one scan)."""
    from anklescan.core.calibration.procedures.box import calibrate_from_box_captures
    if len(folders) == 1:
        return calibrate_folder(folders[0], camera_size, projector_size)
    cal, report, caps = calibrate_from_box_captures(folders)
    obs = [c.observations for c in caps]
    pts = BoxPoints(np.asarray(decode_folder(folders[-1]).white, np.float32),
                    np.concatenate([c.pose.apply(o.cam_xyz) for c, o in zip(caps, obs, strict=True)]),
                    np.concatenate([o.cam_uv for o in obs]),
                    np.concatenate([c.pose.apply(o.proj_xyz) for c, o in zip(caps, obs, strict=True)]),
                    np.concatenate([o.proj_uv for o in obs]), np.concatenate([o.proj_cam_uv for o in obs]),
                    obs[-1].found)
    return BoxFit(pts, cal, report)


def calibrate_board_folders(folders: Sequence[Folder], cols: int, rows: int,
                            square: float) -> tuple[BoardCalibration, Image]:
    """(board calibration result, the first view's white frame)."""
    from anklescan.core.calibration.procedures.board import calibrate_from_board_captures
    return calibrate_from_board_captures(folders, cols, rows, square), white_frame(folders[0])


def check_board_folder(folder: Folder, cols: int, rows: int) -> Path:
    """The folder, once the chessboard's corners are found in its white frame (raises otherwise)."""
    from anklescan.core.calibration.procedures.board import find_corners
    find_corners(white_frame(folder), cols, rows)
    return Path(folder)


def level_folder(folder: Folder, cal: Calibration, table_size: str = "") -> tuple[Calibration, TableTop]:
    """(levelled calibration, TableTop) from a scan of the level reference table of ``table_size`` ("LxW" mm)."""
    from anklescan.core.calibration.procedures.levelling import DEFAULT_TABLE, level_calibration, parse_table_size
    from anklescan.core.scan.capture import load_capture
    table = parse_table_size(table_size) if table_size else DEFAULT_TABLE
    return level_calibration(cal, load_capture(folder), table)


def verify_folder(folder: Folder, cal: Calibration) -> tuple[np.ndarray, VerificationResult]:
    """(white frame, VerificationResult) of a verification scan of the box."""
    from anklescan.core.calibration.procedures.verification import compare_distances, measure_centres
    decoded = decode_folder(folder)
    return decoded.white, compare_distances(measure_centres(cal, decoded.white, decoded.require_column(), decoded.row))
