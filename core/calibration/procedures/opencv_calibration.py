"""Projector-camera calibrations in OpenCV FileStorage (XML / YAML / JSON), both ways.

Import (SPEC §6 ``calibrate import``): camera and projector intrinsics and distortion plus the
rotation and translation from the camera's frame to the projector's (``x_p = R x_c + T``, what
``cv2.stereoCalibrate`` returns with the camera first).  Two naming schemes are read:

* procam-calibration (kamino410): ``cam_int cam_dist proj_int proj_dist roration|rotation
  translation`` (+ ``img_shape`` = camera (rows, cols));
* the usual stereo names: ``K1 D1 K2 D2 R T`` (+ ``image_size``/``imageSize`` = camera (w, h)).

The world frame of the result is the camera's (camera R = I, t = 0), which is not the clinic's
frame (SPEC §1): ``anklescan calibrate level`` brings it there.  Lengths are taken as mm unless
told otherwise (``unit``).

Export writes the stereo names (``K1 D1 K2 D2 R T`` relative to the camera, as other tools expect)
and also procam-calibration's, plus ``R_world_camera``/``t_world_camera`` so that our world frame
is not lost: ``x_cam = R_world_camera x_world + t_world_camera``.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from anklescan.core.atomic import write_text_atomic
from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration, calibration_from_dict, calibration_to_dict
from anklescan.core.errors import CalibrationError
from anklescan.core.limits import MIN_BASELINE_MM
from anklescan.core.vocabulary import Axis

UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
NAMES = {  # role -> accepted keys, first found wins
    "cam_K": ("cam_int", "K1", "camera_matrix", "cameraMatrix1", "M1"),
    "cam_dist": ("cam_dist", "D1", "dist_coeffs", "distCoeffs1"),
    "proj_K": ("proj_int", "K2", "projector_matrix", "cameraMatrix2", "M2"),
    "proj_dist": ("proj_dist", "D2", "distCoeffs2"),
    "R": ("roration", "rotation", "R"),
    "T": ("translation", "T"),
}
SUFFIXES = (".xml", ".yml", ".yaml", ".json")
PROJECTOR_AXIS_KEY = "projector_axis"  # written by our export for a column-only projector (SPEC §4 "axis")


def _read_storage(path: Path) -> cv2.FileStorage:
    if path.is_dir():  # as load_json says it: "not found" for a folder the user can see misleads
        raise CalibrationError(f"calibration file {path} is a folder, not a file")
    if not path.is_file():
        raise CalibrationError(f"calibration file not found: {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_AUTO)
    except (cv2.error, SystemError):  # a parse error surfaces as either, depending on the build
        fs = None
    if fs is None or not fs.isOpened():
        raise CalibrationError(f"{path}: not an OpenCV FileStorage file (XML/YAML)")
    if not fs.root().isMap():  # a JSON list or a bare number: OpenCV asserts on any key lookup
        fs.release()
        raise CalibrationError(f"{path}: a FileStorage calibration must hold named entries (a map), "
                               "not a list or a single value")
    return fs


def _node(fs: cv2.FileStorage, keys: tuple[str, ...]) -> tuple[str, cv2.FileNode] | None:
    for k in keys:
        n = fs.getNode(k)
        if not n.empty() and not n.isNone():
            return k, n
    return None


def _array(node: cv2.FileNode, key: str, path: Path) -> np.ndarray:
    a: np.ndarray | None
    try:
        if node.isSeq():
            a = np.array([node.at(i).real() for i in range(node.size())], np.float64)
        elif node.isReal() or node.isInt():
            a = np.array([node.real()], np.float64)
        else:
            a = node.mat()
    except cv2.error:
        a = None
    if a is None:
        raise CalibrationError(f"{path}: '{key}' is not a matrix")
    a = np.asarray(a, np.float64)
    if not np.isfinite(a).all():
        raise CalibrationError(f"{path}: '{key}' has non-finite entries")
    return a


def _get(fs: cv2.FileStorage, role: str, path: Path) -> tuple[str, np.ndarray]:
    """The ``role`` entry's key and value; CalibrationError when the file has none."""
    key, value = _get_optional(fs, role, path)
    if key is None or value is None:
        raise CalibrationError(f"{path}: no {' / '.join(NAMES[role])} entry")
    return key, value


def _get_optional(fs: cv2.FileStorage, role: str, path: Path) -> tuple[str | None, np.ndarray | None]:
    """The ``role`` entry's key and value; (None, None) when the file has none."""
    found = _node(fs, NAMES[role])
    if found is None:
        return None, None
    key, node = found
    return key, _array(node, key, path)


def _K(a: np.ndarray, key: str, path: Path) -> np.ndarray:
    if a.size != 9:
        raise CalibrationError(f"{path}: '{key}' must be a 3x3 camera matrix, has {a.size} entries")
    return a.reshape(3, 3)


def _dist(a: np.ndarray | None, key: str | None, path: Path) -> np.ndarray:
    if a is None:
        return np.zeros(5)
    d = a.ravel()
    if d.size > 5 and np.any(d[5:] != 0):
        raise CalibrationError(f"{path}: '{key}' has {d.size} distortion coefficients; only k1,k2,p1,p2,k3 "
                               f"(OpenCV's 5-term model) are supported")
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return out


def _rotation(a: np.ndarray, key: str, path: Path) -> np.ndarray:
    if a.size == 3:
        R, _ = cv2.Rodrigues(a.reshape(3, 1))
    elif a.size == 9:
        R = a.reshape(3, 3)
    else:
        raise CalibrationError(f"{path}: '{key}' must be a 3x3 rotation or a 3-vector, has {a.size} entries")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise CalibrationError(f"{path}: '{key}' is not a rotation matrix (not orthonormal with det +1)")
    u, _, vt = np.linalg.svd(R)  # the file's ~16 digits: make it exactly orthonormal
    orthonormal: np.ndarray = u @ vt
    return orthonormal


def _camera_size(fs: cv2.FileStorage, path: Path, given: tuple[int, int] | None) -> tuple[int, int]:
    """The camera's size: the file's, else ``given`` (--camera). Both, and different, is refused:
    the intrinsics are the file's camera's, so another size would make a calibration of no camera."""
    for key, order in (("img_shape", "hw"), ("image_size", "wh"), ("imageSize", "wh"), ("camera_size", "wh")):
        n = fs.getNode(key)
        if n.empty() or n.isNone():
            continue
        a = _array(n, key, path).ravel()
        if a.size >= 2 and np.all(a[:2] > 0) and np.all(a[:2] == np.round(a[:2])):
            w, h = (int(a[1]), int(a[0])) if order == "hw" else (int(a[0]), int(a[1]))
            if given is not None and (int(given[0]), int(given[1])) != (w, h):
                raise CalibrationError(f"{path}: its '{key}' says the camera is {w}x{h}, --camera says "
                                       f"{given[0]}x{given[1]}; leave --camera out, or check the file")
            return w, h
        if given is None:
            raise CalibrationError(f"{path}: '{key}' is not an image size")
        break
    if given is not None:
        return int(given[0]), int(given[1])
    raise CalibrationError(f"{path}: the camera's image size is not in the file (img_shape / image_size); "
                           f"give it with --camera WxH")


def import_opencv_calibration(path: str | os.PathLike[str], projector_size: tuple[int, int],
                              camera_size: tuple[int, int] | None = None,
                              unit: str = "mm") -> Calibration:
    """A FileStorage projector-camera calibration as our Calibration, world frame = camera frame."""
    path = Path(path)
    if unit not in UNITS_MM:
        raise CalibrationError(f"unknown unit {unit!r} (one of {', '.join(UNITS_MM)})")
    fs = _read_storage(path)
    try:
        kc, cam_K = _get(fs, "cam_K", path)
        kcd, cam_d = _get_optional(fs, "cam_dist", path)
        kp, proj_K = _get(fs, "proj_K", path)
        kpd, proj_d = _get_optional(fs, "proj_dist", path)
        kr, R = _get(fs, "R", path)
        kt, T = _get(fs, "T", path)
        cw, ch = _camera_size(fs, path, camera_size)
        rms_node = fs.getNode("rms")
        rms = float(rms_node.real()) if not rms_node.empty() and (rms_node.isReal() or rms_node.isInt()) else None
        # our own export keeps its world frame; anything else is in the camera's
        # our own export of a column-only projector (SPEC §4 "axis": "column"): its K2 row is nominal
        axis_node = fs.getNode(PROJECTOR_AXIS_KEY)
        axis = Axis.COLUMN if axis_node.isString() and axis_node.string() == Axis.COLUMN else Axis.BOTH
        Rw = fs.getNode("R_world_camera")
        world = None
        if not Rw.empty() and not fs.getNode("t_world_camera").empty():
            world = (_rotation(_array(Rw, "R_world_camera", path), "R_world_camera", path),
                     _array(fs.getNode("t_world_camera"), "t_world_camera", path).ravel())
    finally:
        fs.release()
    if T.size != 3:
        raise CalibrationError(f"{path}: '{kt}' must be a 3-vector, has {T.size} entries")
    pw, ph = projector_size
    Rc, tc = (np.eye(3), np.zeros(3)) if world is None else world
    if tc.size != 3:
        raise CalibrationError(f"{path}: 't_world_camera' must be a 3-vector")
    s = UNITS_MM[unit]
    baseline = float(np.linalg.norm(T)) * s
    if not baseline >= MIN_BASELINE_MM:
        raise CalibrationError(f"{path}: '{kt}' puts the projector {baseline:.3g} mm from the camera: no depth "
                               f"can be triangulated (at least {MIN_BASELINE_MM:g} mm; is the file in another "
                               "unit? give --unit m, cm or in)")
    R = _rotation(R, kr, path)
    camera = Device(cw, ch, _K(cam_K, kc, path), _dist(cam_d, kcd, path), Rc, tc * s)
    projector = Device(pw, ph, _K(proj_K, kp, path), _dist(proj_d, kpd, path), R @ Rc,
                       R @ (tc * s) + T.ravel() * s, axis)
    extra = {"source": f"imported from OpenCV FileStorage {path.name}",
             "frame": ("camera (not levelled: run 'anklescan calibrate level' before measuring angles)"
                       if world is None else "the exporting tool's world frame (R_world_camera, t_world_camera)"),
             "frame_source": "camera" if world is None else "unknown",  # core.calibration.procedures.frame.FrameSource
             "imported": {"keys": [kc, kcd, kp, kpd, kr, kt], "unit": unit, "rms_px": rms}}
    # through the JSON form once: the same validation as a loaded calibration file
    return calibration_from_dict(calibration_to_dict(Calibration(camera, projector, extra)))


def relative_pose(cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation from the camera's frame to the projector's."""
    Rc, tc, Rp, tp = cal.camera.R, cal.camera.t, cal.projector.R, cal.projector.t
    R = Rp @ Rc.T
    return R, tp - R @ tc


def export_opencv_calibration(cal: Calibration, out: str | os.PathLike[str]) -> Path:
    """Write ``cal`` as an OpenCV FileStorage (format from the suffix), atomically."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in SUFFIXES:
        raise CalibrationError(f"output {out}: the suffix must be one of {', '.join(SUFFIXES)} "
                               f"(it chooses the FileStorage format)")
    if not out.parent.is_dir():
        raise CalibrationError(f"output folder {out.parent} does not exist")
    R, T = relative_pose(cal)
    c, p = cal.camera, cal.projector
    # written in memory, then through the project's atomic, private writer
    fmt = {".xml": cv2.FILE_STORAGE_FORMAT_XML, ".json": cv2.FILE_STORAGE_FORMAT_JSON}.get(
        suffix, cv2.FILE_STORAGE_FORMAT_YAML)
    fs = cv2.FileStorage(suffix, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | fmt)
    if not fs.isOpened():
        raise CalibrationError(f"cannot write {out}")
    fs.writeComment("AnkleScan calibration: K1/D1 camera, K2/D2 projector, x_proj = R x_cam + T (mm)")
    if p.axis == Axis.COLUMN:
        # FileStorage has no "unknown" for K2's second row (nominal here): say so, or a re-import
        # would take the projector's rows for calibrated and triangulate row stripes with them
        fs.writeComment("the projector's rows are not calibrated: K2's second row is nominal, use columns only")
        fs.write(PROJECTOR_AXIS_KEY, str(Axis.COLUMN))
    fs.write("image_size", np.array([c.width, c.height], np.float64))
    fs.write("projector_size", np.array([p.width, p.height], np.float64))
    for k, v in (("K1", c.K), ("D1", c.dist.reshape(1, 5)), ("K2", p.K), ("D2", p.dist.reshape(1, 5)),
                 ("R", R), ("T", T.reshape(3, 1))):
        fs.write(k, np.ascontiguousarray(v, np.float64))
    fs.write("img_shape", np.array([[c.height], [c.width]], np.float64))
    for k, v in (("cam_int", c.K), ("cam_dist", c.dist.reshape(1, 5)), ("proj_int", p.K),
                 ("proj_dist", p.dist.reshape(1, 5)), ("rotation", R), ("translation", T.reshape(3, 1)),
                 ("R_world_camera", c.R), ("t_world_camera", c.t.reshape(3, 1))):
        fs.write(k, np.ascontiguousarray(v, np.float64))
    write_text_atomic(out, fs.releaseAndGetString())
    return out
