"""Is the ± honest? Coverage of the angles' SD over calibrations and postures (SPEC §3).

    PYTHONPATH=. python benchmarks/bench_uncertainty.py [--seeds N] [--growth]

The cheap sweep the docs' table comes from (docs/performance.md, "Honest ±"): the simulator's
true rig (hardware/simrig.py: OpenCV distortion with k1, k2 and tangential terms, which the
paper's model lacks) projects the calibration box's control points (core/calibration/procedures/box.py's
face grid), with Gaussian pixel noise, and `calibrate_points` fits the paper's model, once with
the box where it stands and once with a second copy raised by --raise mm (the box at the knee's
height too). The simulated leg's seven true mark centres (hardware/sim_scene.py, several
postures) get Gaussian position noise (--mark-sd), are projected through the true rig to their
camera pixel and projector column, triangulated with the fitted calibration, and their angles
compared with the true ones. The SD is core/measure/uncertainty.py's, with the mark SD given.

``--growth`` measures EXTRAPOLATION_GROWTH instead: points on a grid round the volume, triangulated
from exact observations with the single-box calibrations; the per-axis error's excess variance
over the covariance's prediction, fitted as (g · distance outside)².
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anklescan.core.calibration.model.file import (  # noqa: E402
    Calibration,
    calibrated_volume,
    parameter_covariance,  # noqa: E402
)
from anklescan.core.calibration.procedures.box import face_grid_points  # noqa: E402
from anklescan.core.calibration.procedures.calibrate import calibrate_points  # noqa: E402
from anklescan.core.measure.angles import compute_angles  # noqa: E402
from anklescan.core.measure.uncertainty import calibration_jacobian, position_uncertainty  # noqa: E402
from anklescan.core.scan.triangulate import triangulate_points  # noqa: E402
from anklescan.hardware.sim_scene import angles_from_marks, leg_scene  # noqa: E402
from anklescan.hardware.simrig import default_camera, default_projector  # noqa: E402

ANGLES = ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion")
TERMS = 1  # radial terms of the paper's model (--terms)
POSTURES = ((0.0, 0.0), (10.0, -10.0), (-10.0, 15.0), (15.0, 5.0), (-5.0, -15.0), (20.0, 20.0))


def true_rig() -> Calibration:
    return Calibration(default_camera(), default_projector())


def box_points(raises: tuple[float, ...]) -> np.ndarray:
    X = face_grid_points()
    return np.vstack([X + [0.0, 0.0, h] for h in raises])


def noisy_calibration(truth: Calibration, X: np.ndarray, noise_px: float, rng: np.random.Generator,
                      terms: int = 1) -> Calibration:
    uv = truth.camera.project(X)
    col = truth.projector.project(X)
    seen = (np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] <= truth.camera.width - 1) & (uv[:, 1] >= 0)
            & (uv[:, 1] <= truth.camera.height - 1) & np.isfinite(col).all(1) & (col[:, 0] >= 0)
            & (col[:, 0] <= truth.projector.width - 1) & (col[:, 1] >= 0) & (col[:, 1] <= truth.projector.height - 1))
    X = X[seen]
    uv = uv[seen] + rng.normal(0.0, noise_px, (len(X), 2))
    u = col[seen, 0] + rng.normal(0.0, noise_px, len(X))
    cal, _ = calibrate_points(X, uv, X, u, radial_terms=terms, camera_size=(truth.camera.width, truth.camera.height),
                              projector_size=(truth.projector.width, truth.projector.height))
    return cal


def true_marks(posture: tuple[float, float]) -> dict[int, np.ndarray]:
    scene = leg_scene(*posture)
    return {int(k): np.asarray(m.centre, float) for k, m in scene.marks.items()}


def measured(truth: Calibration, cal: Calibration, marks: dict[int, np.ndarray], mark_sd: float,
             rng: np.random.Generator) -> dict[int, np.ndarray]:
    labels = sorted(marks)
    X = np.array([marks[k] for k in labels]) + rng.normal(0.0, mark_sd, (len(labels), 3))
    uv, proj = truth.camera.project(X), truth.projector.project(X)
    proj = proj if cal.projector.axis == "both" else proj[:, 0]  # a 2-D projector model reads rows too
    Y = triangulate_points(cal, uv, proj)
    return dict(zip(labels, Y, strict=True))


BOARD = (9, 7, 40.0)  # inner corners and square (mm) of the simulated chessboard (hardware/sim_board.py)


def board_calibration(truth: Calibration, noise_px: float, rng: np.random.Generator
                      ) -> tuple[Calibration, np.ndarray, np.ndarray]:
    """A chessboard calibration (core/calibration/procedures/board.py) from the simulator's four board poses,
    corners and projector points projected through the true rig with noise; and (B, b): the
    board calibration's world = B @ (true world) + b (its frame is the first board's)."""
    import cv2

    from anklescan.core.calibration.procedures.board import BoardView, board_points, board_world_frame, calibrate_board_views
    from anklescan.hardware.sim_board import board_views

    cols, rows, square = BOARD
    c_off = np.array([(cols - 1) * square / 2, (rows - 1) * square / 2, 0.0])
    Xb = board_points(cols, rows, square)
    views, first = [], None
    for k, (_scene, centre, Rv) in enumerate(board_views(cols, rows, square)):
        Xw = centre + (Xb - c_off) @ Rv.T
        uv = truth.camera.project(Xw) + rng.normal(0.0, noise_px, (len(Xw), 2))
        pp = truth.projector.project(Xw) + rng.normal(0.0, noise_px, (len(Xw), 2))
        spacing = float(np.median(np.linalg.norm(np.diff(uv, axis=0), axis=1)))
        views.append(BoardView(f"view{k}", (truth.camera.width, truth.camera.height), uv, pp,
                               np.full(len(Xw), noise_px), spacing))
        if first is None:
            Rcb = truth.camera.R @ Rv
            first = (cv2.Rodrigues(Rcb)[0].ravel(), truth.camera.R @ (centre - Rv @ c_off) + truth.camera.t, centre, Rv)
    cal = calibrate_board_views(views, cols, rows, square, (truth.projector.width, truth.projector.height)).calibration
    rvec, tvec, centre, Rv = first
    A, o = board_world_frame(rvec, tvec, cols, rows, square)
    # board coords X_b = Rvᵀ (X_w - centre) + c_off = A @ world_b + o
    B = A.T @ Rv.T
    return cal, B, A.T @ (c_off - Rv.T @ centre - o)


def sweep(seeds: int, noises: tuple[float, ...], raise_mm: float, mark_sd: float, board: bool = False,
          boxes_too: bool = True) -> list[dict]:
    truth = true_rig()
    rows = []
    paths = [("table box", (0.0,)), ("table + knee box", (0.0, raise_mm))] if boxes_too else []
    paths += [("board, 4 views", None)] if board else []
    for boxes, raises in paths:
        for noise in noises:
            for seed in range(seeds):
                rng = np.random.default_rng(1000 * seed + int(noise * 100))
                if raises is None:
                    cal, B, b = board_calibration(truth, noise, rng)
                else:
                    cal, B, b = noisy_calibration(truth, box_points(raises), noise, rng, TERMS), np.eye(3), np.zeros(3)
                for posture in POSTURES:
                    world = true_marks(posture)
                    marks = {k: B @ v + b for k, v in world.items()}  # in the calibration's frame
                    ref = angles_from_marks({str(k): v for k, v in marks.items()})
                    got = measured(truth, cal, world, mark_sd, rng)  # triangulated: in the calibration's frame
                    joint, shares = position_uncertainty(cal, got, {k: np.eye(3) * mark_sd**2 for k in got})
                    ang = compute_angles(got, 0.0, joint=joint)
                    knee = max(float(np.linalg.norm(got[k] - marks[k])) for k in (1, 3))
                    for name in ANGLES:
                        rows.append({"boxes": boxes, "noise": noise, "seed": seed, "posture": posture, "angle": name,
                                     "err": ang[name].value - ref[name], "sd": ang[name].sd, "knee_mm": knee,
                                     "outside": max(s.outside_mm for s in shares.values())})
    return rows


def rendered(postures: tuple[tuple[float, float], ...], scale: float, raise_mm: float) -> list[dict]:
    """Full captures of the leg (rendered, decoded, marks found by the pipeline): the independent check."""
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.capture import capture_from_images
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.simrig import SimRig

    rows = []
    for i, posture in enumerate(postures):
        scene = leg_scene(*posture, leg_offset_deg=(-2.0, 3.0))
        rig = SimRig(scene, scale=scale, seed=50 + i)
        pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column",))
        cap = capture_from_images(pset, rig.capture_many(render_all(pset)))
        truth = rig.true_calibration()
        ref = angles_from_marks({k: m.centre for k, m in scene.marks.items()})
        for boxes, raises in (("table box", (0.0,)), ("table + knee box", (0.0, raise_mm))):
            # pixel noise in full-resolution pixels, scaled with the rig
            cal = noisy_calibration(truth, box_points(raises), 0.2 * scale, np.random.default_rng(90 + i))
            res = measure_capture(cap, cal)
            knee = max(float(np.linalg.norm(res.marks.labelled[k].centre - scene.marks[k].centre)) for k in ("1", "3"))
            for name in ANGLES:
                if name in res.angles:
                    rows.append({"boxes": boxes, "noise": 0.2, "seed": i, "posture": posture, "angle": name,
                                 "err": res.angles[name].value - ref[name], "sd": res.angles[name].sd,
                                 "knee_mm": knee, "warnings": res.warnings})
    return rows


def table(rows: list[dict]) -> str:
    out = ["| calibration | noise px | angles | within 2 SD | max abs err / SD | max abs err ° | median SD ° "
           "| knee marks max err mm |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    order = {"table box": 0, "table + knee box": 1}
    keys = sorted({(r["boxes"], r["noise"]) for r in rows}, key=lambda k: (order.get(k[0], 2), k[1]))
    for key in [*keys, ("all", None)]:
        sel = [r for r in rows if key[0] == "all" or (r["boxes"], r["noise"]) == key]
        z = np.array([abs(r["err"]) / r["sd"] for r in sel])
        err = np.array([abs(r["err"]) for r in sel])
        out.append(f"| {key[0]} | {'all' if key[1] is None else key[1]} | {len(sel)} | {100 * np.mean(z <= 2):.1f} % | "
                   f"{z.max():.2f} | {err.max():.3f} | {np.median([r['sd'] for r in sel]):.3f} | "
                   f"{max(r['knee_mm'] for r in sel):.2f} |")
    return "\n".join(out)


def growth(seeds: int, noise: float) -> tuple[float, float]:
    """Fit (a, g): per-axis excess variance over the covariance's prediction = (a + g d)²."""
    truth = true_rig()
    g = np.mgrid[-400:401:100, -400:401:100, -100:701:100].reshape(3, -1).T.astype(float)
    ds, excess = [], []
    for seed in range(seeds):
        rng = np.random.default_rng(seed + 77)
        cal, B, b = noisy_calibration(truth, box_points((0.0,)), noise, rng, TERMS), np.eye(3), np.zeros(3)
        vol = calibrated_volume(cal)
        uv = truth.camera.project(g)
        col = truth.projector.project(g)
        ok = (np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < truth.camera.width) & (uv[:, 1] >= 0)
              & (uv[:, 1] < truth.camera.height) & (col[:, 0] >= 0) & (col[:, 0] < truth.projector.width))
        P, uv, u = g[ok] @ B.T + b, uv[ok], (col[ok] if cal.projector.axis == "both" else col[ok, 0])
        Y = triangulate_points(cal, uv, u)
        J = calibration_jacobian(cal, parameter_covariance(cal), Y)
        C = J @ parameter_covariance(cal).matrix @ J.T
        for i in range(len(P)):
            d = vol.outside(P[i]).distance_mm
            var_pred = np.trace(C[3 * i:3 * i + 3, 3 * i:3 * i + 3]) / 3.0
            ds.append(d)
            excess.append(float(np.sum((Y[i] - P[i]) ** 2)) / 3.0 - var_pred)
    d, e = np.array(ds), np.array(excess)
    for lo, hi in ((0, 1), (1, 100), (100, 200), (200, 300), (300, 500)):
        s = (d >= lo) & (d < hi)
        if s.any():
            print(f"outside {lo:3d}-{hi:3d} mm: {s.sum():4d} points, RMS excess per axis "
                  f"{np.sqrt(max(np.mean(e[s]), 0)):.3f} mm")
    a = float(np.sqrt(max(np.mean(e[d == 0]), 0.0)))  # inside: the model's own error
    out = d > 0
    fit = least_squares(lambda p: (a + p[0] * d[out]) ** 2 - e[out], [0.003], bounds=([0.0], [np.inf]))
    return a, float(fit.x[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.1, 0.2, 0.3])
    ap.add_argument("--raise", dest="raise_mm", type=float, default=300.0, help="the second box's height, mm")
    ap.add_argument("--mark-sd", type=float, default=0.05, help="mark centre SD per axis, mm")
    ap.add_argument("--growth", action="store_true")
    ap.add_argument("--board", action="store_true", help="add chessboard calibrations (4 simulated poses)")
    ap.add_argument("--rendered", action="store_true", help="full rendered captures instead (the independent check)")
    ap.add_argument("--scale", type=float, default=0.5, help="--rendered: the simulated rig's scale")
    ap.add_argument("--terms", type=int, default=1, choices=(1, 2), help="radial terms of the paper's model")
    args = ap.parse_args()
    global TERMS
    TERMS = args.terms
    t0 = time.time()
    if args.growth:
        a, g = growth(args.seeds, 0.2)
        print(f"MODEL_ERROR_MM fit: {a:.4f} mm, EXTRAPOLATION_GROWTH fit: {g:.4f} mm/mm")
    elif args.rendered:
        rows = rendered(((-8.0, 12.0), (12.0, -4.0), (3.0, 18.0)), args.scale, args.raise_mm)
        print(table(rows))
        for r in rows[::4]:
            print(r["boxes"], r["posture"], "; ".join(r["warnings"]) or "no warnings")
    else:
        print(table(sweep(args.seeds, tuple(args.noise), args.raise_mm, args.mark_sd, args.board)))
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
