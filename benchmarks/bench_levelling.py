"""`calibrate level` after realistic calibrations (issue 37): right within 0.2° or refused.

    python benchmarks/bench_levelling.py [--scale 1.0] [--seeds 5] [--noise 0.1 0.3] [--table 320x220]

The paper's path: 75 control points of a 200 mm box seen through the simulated rig with Gaussian
pixel noise, ``calibrate_points``, then ``level_calibration`` from a scan of the level reference
table (``--table``: its top, mm, long side first; its 25 mm board on a post over the floor). For
each calibration: the top found (or the refusal), the frame's errors against the one the table
defines under that calibration (the true top's points seen by the true devices and triangulated
with the levelled calibration: their plane's normal against z, the long centre line against y),
and the worst SPEC §3 angle error of five leg postures (the calibration's own error included).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from anklescan.core.calibration.model.file import Calibration  # noqa: E402
from anklescan.core.calibration.procedures.box import face_grid_points  # noqa: E402
from anklescan.core.calibration.procedures.calibrate import calibrate_points  # noqa: E402
from anklescan.core.calibration.procedures.levelling import level_calibration, parse_table_size  # noqa: E402
from anklescan.core.errors import AnkleScanError  # noqa: E402
from anklescan.core.scan.capture import load_capture, save_capture  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.hardware.sim_scene import Box, ObjectId, Plane, Scene, angles_from_marks, leg_scene  # noqa: E402
from anklescan.hardware.simrig import SimRig  # noqa: E402

TOP_Z = 120.0


def table_scene(length: float, width: float) -> Scene:
    table = Box(kind=ObjectId.TABLE, centre=(0.0, 0.0, TOP_Z - 12.5), half=(width / 2, length / 2, 12.5))
    post = (TOP_Z - 25) / 2
    stand = Box(kind=ObjectId.STAND, centre=(0.0, 0.0, post), half=(30.0, 30.0, post), albedo=0.25)
    return Scene([Plane(kind=ObjectId.FLOOR, albedo=0.5), table, stand])


def triangulate(cal: Calibration, uv: np.ndarray, columns: np.ndarray) -> np.ndarray:
    d = cal.camera.rays(uv)
    c = cal.camera.center
    planes = cal.projector.column_plane(columns)
    s = -(planes[:, :3] @ c + planes[:, 3]) / np.einsum("ij,ij->i", planes[:, :3], d)
    return c + s[:, None] * d


def frame_errors(cal: Calibration, true: Calibration, length: float, width: float) -> tuple[float, float]:
    a, b = np.meshgrid(np.linspace(-0.4 * width, 0.4 * width, 7), np.linspace(-0.44 * length, 0.44 * length, 9))
    top = np.stack([a.ravel(), b.ravel(), np.full(a.size, TOP_Z)], axis=1)
    Q = triangulate(cal, true.camera.project(top), true.projector.project(top)[:, 0])
    n = np.linalg.svd(Q - Q.mean(axis=0))[2][2]
    line = np.array([[0.0, -0.44 * length, TOP_Z], [0.0, 0.44 * length, TOP_Z]])
    L = triangulate(cal, true.camera.project(line), true.projector.project(line)[:, 0])
    v = (L[1] - L[0]) / np.linalg.norm(L[1] - L[0])
    return float(np.degrees(np.arccos(abs(n[2])))), float(np.degrees(np.arctan2(abs(v[0]), v[1])))


def angle_error(cal: Calibration, true: Calibration) -> float:
    worst = 0.0
    for inv, pf in ((0, 0), (20, 0), (0, 20), (-15, 10), (10, -20)):
        marks = {k: np.asarray(m.centre) for k, m in leg_scene(inv, pf).marks.items()}
        keys = sorted(marks)
        P = np.array([marks[k] for k in keys])
        Q = triangulate(cal, true.camera.project(P), true.projector.project(P)[:, 0])
        got, want = angles_from_marks(dict(zip(keys, Q, strict=True))), angles_from_marks(marks)
        worst = max(worst, max(abs(got[k] - want[k]) for k in want))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.1, 0.3])
    ap.add_argument("--table", default="320x220")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    spec = parse_table_size(args.table)
    out = args.out or Path(tempfile.mkdtemp(prefix="levelling_"))
    out.mkdir(parents=True, exist_ok=True)
    rig = SimRig(table_scene(spec.length_mm, spec.width_mm), scale=args.scale, seed=5)
    folder = out / f"table_{args.table}_{args.scale}"
    if not folder.exists():
        pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
        save_capture(folder, pset, rig.capture_many(render_all(pset)))
    capture = load_capture(folder)
    true = rig.true_calibration()
    X = face_grid_points(5, margin_mm=20.0, size=200.0)
    print(f"scale {args.scale}, table {spec.describe()}, 75 control points of a 200 mm box")
    print("| noise px | seed | top found | frame z / y error | worst angle error (calibration's own included) |")
    print("| --- | --- | --- | --- | --- |")
    for noise in args.noise:
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            uv = true.camera.project(X) + rng.normal(0, noise, (len(X), 2))
            u = true.projector.project(X)[:, 0] + rng.normal(0, noise, len(X))
            cal, _ = calibrate_points(X, uv, X, u, camera_size=(true.camera.width, true.camera.height),
                                      projector_size=(true.projector.width, true.projector.height))
            try:
                levelled, top = level_calibration(cal, capture, spec)
            except AnkleScanError as e:
                print(f"| {noise} | {seed} | refused: {e} | | |")
                continue
            z, y = frame_errors(levelled, true, spec.length_mm, spec.width_mm)
            print(f"| {noise} | {seed} | {top.describe()} | {z:.3f}° / {y:.3f}° | {angle_error(levelled, true):.3f}° |")


if __name__ == "__main__":
    main()
