"""Acceptance figures for the paper's two-step calibration, and cv2.calibrateCamera beside it.

    PYTHONPATH=. python benchmarks/bench_calibration.py [--trials N] [--noise PX]

Synthetic control points on the three visible faces of the 400 mm calibration box (a 7x7 grid
per face by default), a 1600x1200 camera (fx 2400, barrel k1 = +0.08 in the paper's inverse model, ≈ −0.08
in OpenCV's) and a 1024x768 projector (fx 1700, k1 = +0.02), Gaussian pixel noise. The truth is
in the paper's model, so a perfect estimator leaves exactly the noise.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anklescan.core.calibration.model import paper_model as pm
from anklescan.core.calibration.model.device_model import Device, look_at  # noqa: E402
from anklescan.core.calibration.procedures.box import face_grid_points  # noqa: E402
from anklescan.core.calibration.procedures.calibrate import calibrate_device  # noqa: E402

CAMERA_SIZE, PROJECTOR_SIZE = (1600, 1200), (1024, 768)


def truth_vectors() -> tuple[np.ndarray, np.ndarray]:
    """Paper vectors of a realistic rig looking at the box from the front right, above."""
    R, t = look_at([650.0, 1050.0, 750.0], [0.0, 0.0, 140.0])
    cam = Device(*CAMERA_SIZE, [[2400.0, 0, 806.0], [0, 2398.0, 590.0], [0, 0, 1]], [], R, t)
    Cn = pm.device_to_camera(cam)
    Cn[10] = 0.08
    R, t = look_at([250.0, 1150.0, 820.0], [0.0, 0.0, 150.0])
    proj = Device(*PROJECTOR_SIZE, [[1700.0, 0, 520.0], [0, 1700.0, 700.0], [0, 0, 1]], [], R, t, "column")
    Pn = pm.device_to_projector(proj)
    Pn[8] = 0.02
    return Cn, Pn


def synthetic(seed: int = 0, noise: float = 0.1, per_side: int = 7, size: float = 400.0):
    """(X, uv_noisy, u_noisy, Cn, Pn) for one trial."""
    rng = np.random.default_rng(seed)
    Cn, Pn = truth_vectors()
    X = face_grid_points(per_side, size=size)
    uv = pm.project_camera(Cn, X) + rng.normal(0, noise, (len(X), 2))
    u = pm.project_projector(Pn, X) + rng.normal(0, noise, len(X))
    return X, uv, u, Cn, Pn


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def gauge_fixed(Pn: np.ndarray, X: np.ndarray) -> np.ndarray:
    """The truth moved to the estimator's gauge (see anklescan.core.calibration.procedures.calibrate)."""
    P = Pn.copy()
    P[4] = -pm.rotation_from_rpy(*P[:3])[1] @ X.mean(axis=0)
    return P


def camera_errors(est: np.ndarray, true: np.ndarray) -> dict:
    return {"fx_rel": abs(est[8] / true[8] - 1), "fy_rel": abs(est[9] / true[9] - 1),
            "pp_px": float(np.hypot(est[6] - true[6], est[7] - true[7])),
            "rot_deg": rotation_error_deg(pm.rotation_from_rpy(*est[:3]), pm.rotation_from_rpy(*true[:3])),
            "t_mm": float(np.linalg.norm(est[3:6] - true[3:6])), "k1": est[10] - true[10]}


def projector_errors(est: np.ndarray, true: np.ndarray) -> dict:
    return {"fx_rel": abs(est[7] / true[7] - 1), "pp_px": abs(est[6] - true[6]),
            "rot_deg": rotation_error_deg(pm.rotation_from_rpy(*est[:3]), pm.rotation_from_rpy(*true[:3])),
            "t_mm": float(np.linalg.norm(est[3:6] - true[3:6])), "k1": est[8] - true[8]}


def opencv_camera(X: np.ndarray, uv: np.ndarray, Cn0: np.ndarray) -> tuple[np.ndarray, float]:
    """cv2.calibrateCamera on the same points; a non-planar rig needs an intrinsic guess.

    The guess is our own DLT (step 1), so both start equal. k1, k2, k3 free, tangential fixed
    to zero like the paper. Returns the estimated paper vector (radial refit) and OpenCV's RMS.
    """
    K0 = np.array([[Cn0[8], 0, Cn0[6]], [0, Cn0[9], Cn0[7]], [0, 0, 1]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera([X.astype(np.float32)], [uv.astype(np.float32)], CAMERA_SIZE,
                                                     K0, np.zeros(5), flags=flags, criteria=crit)
    R = cv2.Rodrigues(rvecs[0])[0]
    dev = Device(*CAMERA_SIZE, K, dist.ravel(), R, tvecs[0].ravel())
    return dev, float(rms)


def opencv_vs_truth(dev: Device, Cn: np.ndarray) -> dict:
    true = pm.camera_to_device(Cn, *CAMERA_SIZE)
    return {"fx_rel": abs(dev.fx / true.fx - 1), "fy_rel": abs(dev.fy / true.fy - 1),
            "pp_px": float(np.hypot(dev.cx - true.cx, dev.cy - true.cy)),
            "rot_deg": rotation_error_deg(dev.R, true.R), "t_mm": float(np.linalg.norm(dev.t - true.t))}


def image_error_px(dev: Device, Cn: np.ndarray) -> float:
    """RMS pixel distance between a Device and the true paper model over the box volume."""
    X = volume_points()
    d = dev.project(X) - pm.project_camera(Cn, X)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def volume_points() -> np.ndarray:
    """The working volume: foot to knee above the box's footprint."""
    g = np.linspace(-180, 180, 7)
    return np.stack(np.meshgrid(g, g, np.linspace(20, 560, 7)), -1).reshape(-1, 3)


def reconstruction_error_mm(camera: Device, projector: Device, Cn: np.ndarray, Pn: np.ndarray) -> float:
    """RMS 3-D error of ray/column-plane triangulation with estimated devices and exact observations."""
    X = volume_points()
    uv, u = pm.project_camera(Cn, X), pm.project_projector(Pn, X)
    d = camera.rays(uv)
    plane = projector.column_plane(u)
    n, dd = plane[:, :3], plane[:, 3]
    s = -(n @ camera.center + dd) / np.sum(n * d, axis=1)
    err = camera.center + s[:, None] * d - X
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def trial(seed: int, noise: float, per_side: int = 7, size: float = 400.0) -> dict:
    from anklescan.core.calibration.procedures.calibrate import initial_camera_vector
    X, uv, u, Cn, Pn = synthetic(seed, noise, per_side, size)
    t0 = time.perf_counter()
    cam, cq = calibrate_device(X, uv, "camera", CAMERA_SIZE)
    t_cam = time.perf_counter() - t0
    proj, pq = calibrate_device(X, u, "projector", PROJECTOR_SIZE)
    ours_dev = pm.camera_to_device(cam, *CAMERA_SIZE)
    proj_dev = pm.projector_to_device(proj, *PROJECTOR_SIZE)
    cv_dev, cv_rms = opencv_camera(X, uv, initial_camera_vector(X, uv, 1))
    return {
        "ours_3d": reconstruction_error_mm(ours_dev, proj_dev, Cn, Pn),
        "cv_3d": reconstruction_error_mm(cv_dev, proj_dev, Cn, Pn),
        "se_cam": cq.std_errors,
        "se_proj": pq.std_errors,
        "cam": camera_errors(cam, Cn),
        "proj": projector_errors(proj, gauge_fixed(Pn, X)),
        "cam_sigma": cq.sigma_px,
        "proj_sigma": pq.sigma_px,
        "cam_rms": cq.rms_px,
        "proj_rms": pq.rms_px,
        "cv": opencv_vs_truth(cv_dev, Cn),
        "cv_rms": cv_rms,
        "t_cam": t_cam,
        "ours_img": image_error_px(ours_dev, Cn),
        "cv_img": image_error_px(cv_dev, Cn),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--noise", type=float, default=0.1)
    ap.add_argument("--per-side", type=int, default=7, help="grid points per face side")
    ap.add_argument("--size", type=float, default=400.0, help="box edge, mm")
    args = ap.parse_args(argv)
    runs = [trial(s, args.noise, args.per_side, args.size) for s in range(args.trials)]

    def worst(path):
        return max(r[path[0]][path[1]] if len(path) == 2 else r[path[0]] for r in runs)

    def mean(path):
        return float(np.mean([r[path[0]][path[1]] if len(path) == 2 else r[path[0]] for r in runs]))

    n = len(face_grid_points(args.per_side))
    print(f"{args.trials} trials, {args.size:g} mm box, {n} points (3 faces x {args.per_side}x{args.per_side}), "
          f"noise {args.noise} px per coordinate")
    print(f"noise estimate sigma: camera mean {mean(['cam_sigma']):.4f} worst-dev "
          f"{max(abs(r['cam_sigma'] / args.noise - 1) for r in runs) * 100:.1f} %, projector mean {mean(['proj_sigma']):.4f} "
          f"worst-dev {max(abs(r['proj_sigma'] / args.noise - 1) for r in runs) * 100:.1f} %")
    print(f"{'':24}{'ours camera':>14}{'cv2 camera':>14}{'ours projector':>16}")
    rows = [("focal rel. error (max)", "fx_rel", "{:.2e}"), ("principal pt px (max)", "pp_px", "{:.3f}"),
            ("rotation deg (max)", "rot_deg", "{:.4f}"), ("translation mm (max)", "t_mm", "{:.3f}")]

    def rms(path):
        return float(np.sqrt(np.mean([r[path[0]][path[1]] ** 2 for r in runs])))

    for label, key, fmt in rows:
        print(f"{label:24}{fmt.format(worst(['cam', key])):>14}{fmt.format(worst(['cv', key])):>14}"
              f"{fmt.format(worst(['proj', key])):>16}")
    for label, key, fmt in rows:  # the typical error: RMS over the trials
        label = label.replace("(max)", "(RMS)")
        print(f"{label:24}{fmt.format(rms(['cam', key])):>14}{fmt.format(rms(['cv', key])):>14}"
              f"{fmt.format(rms(['proj', key])):>16}")
    se = runs[0]["se_cam"], runs[0]["se_proj"]
    print(f"predicted 1-sigma (trial 0): camera ku/ku {se[0]['ku'] / 2400:.1e}, u0 {se[0]['u0']:.2f} px, "
          f"v0 {se[0]['v0']:.2f} px, "
          f"tz {se[0]['tz']:.2f} mm; projector ku/ku {se[1]['ku'] / 1700:.1e}, u0 {se[1]['u0']:.2f} px, tz {se[1]['tz']:.2f} mm")
    print(f"{'camera image error vs truth, px RMS over the volume (mean)':60}{mean(['ours_img']):.4f} ours, "
          f"{mean(['cv_img']):.4f} cv2")
    print(f"{'3-D error of triangulation, mm RMS over the volume (mean)':60}{mean(['ours_3d']):.4f} ours, "
          f"{mean(['cv_3d']):.4f} cv2 camera")
    print(f"{'3-D error (worst trial)':60}{worst(['ours_3d']):.4f} ours, {worst(['cv_3d']):.4f} cv2 camera")
    print(f"camera solve time {mean(['t_cam']) * 1000:.0f} ms mean")


if __name__ == "__main__":
    main()
