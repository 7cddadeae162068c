"""Box calibration at one, two or three heights, raised or turned (issue 37's targets).

    python benchmarks/bench_box_positions.py [--scale 0.5] [--seed 1] [--out DIR]

Renders the calibration box (column and row patterns) at its documented place, raised 100 and
300 mm (towards the knee) and turned 30° on the floor, then calibrates from each position alone
and from table + knee together (``calibrate_from_box_captures``). For each calibration: accepted or
refused, its RMS, the worst SPEC §3 angle error over five postures of the leg scene (the marks seen
through the true rig, triangulated with the calibration, in its own frame) and the knee marks'
position error (mm; meaningful where the first capture's box is at its documented place).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from anklescan.core.calibration.model.file import Calibration  # noqa: E402
from anklescan.core.calibration.procedures import box as cb  # noqa: E402
from anklescan.core.errors import AnkleScanError  # noqa: E402
from anklescan.core.scan.capture import save_capture  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.hardware.sim_scene import angles_from_marks, box_scene_objects, leg_scene, quad_scene  # noqa: E402
from anklescan.hardware.simrig import SimRig  # noqa: E402

POSTURES = ((0, 0), (20, 0), (0, 20), (-15, 10), (10, -20))
POSITIONS = {"documented": cb.BoxPose(), "raised 100": cb.BoxPose.placed(lift_mm=100.0),
             "raised 300": cb.BoxPose.placed(lift_mm=300.0), "turned 30": cb.BoxPose.placed(turn_deg=30.0)}


def render_box(pose: cb.BoxPose, scale: float, seed: int, folder: Path) -> Path:
    rig = SimRig(quad_scene(box_scene_objects(4.0, pose)), scale=scale, seed=seed)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column", "row"))
    return save_capture(folder, pset, rig.capture_many(render_all(pset)))


def triangulate(cal: Calibration, uv: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """Camera rays through ``uv`` cut by the projector planes of ``proj`` (N, 2) columns and rows."""
    d = cal.camera.rays(uv)
    c = cal.camera.center
    planes = cal.projector.column_plane(proj[:, 0], proj[:, 1])
    s = -(planes[:, :3] @ c + planes[:, 3]) / np.einsum("ij,ij->i", planes[:, :3], d)
    return c + s[:, None] * d


def errors(cal: Calibration, true: Calibration) -> tuple[float, float]:
    """(worst angle error, deg; worst knee mark error, mm) over POSTURES."""
    worst_deg, worst_mm = 0.0, 0.0
    for inv, pf in POSTURES:
        marks = {k: np.asarray(m.centre) for k, m in leg_scene(inv, pf).marks.items()}
        keys = sorted(marks)
        P = np.array([marks[k] for k in keys])
        Q = triangulate(cal, true.camera.project(P), true.projector.project(P))
        got, want = angles_from_marks(dict(zip(keys, Q, strict=True))), angles_from_marks(marks)
        worst_deg = max(worst_deg, max(abs(got[k] - want[k]) for k in want))
        knee = [keys.index("1"), keys.index("3")]
        worst_mm = max(worst_mm, float(np.linalg.norm(Q[knee] - P[knee], axis=1).max()))
    return worst_deg, worst_mm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="box_positions_"))
    out.mkdir(parents=True, exist_ok=True)
    true = SimRig(quad_scene([]), scale=args.scale).true_calibration()
    folders = {}
    for name, pose in POSITIONS.items():
        folder = out / name.replace(" ", "_")
        folders[name] = folder if folder.exists() else render_box(pose, args.scale, args.seed, folder)
    runs = [[n] for n in POSITIONS] + [["documented", "raised 300"], ["documented", "raised 100", "raised 300"]]
    print(f"scale {args.scale}, seed {args.seed}")
    print("| positions | result | camera RMS / max px | projector RMS / max px | worst angle error | knee marks |")
    print("| --- | --- | --- | --- | --- | --- |")
    for names in runs:
        label = " + ".join(names)
        try:
            cal, report, caps = cb.calibrate_from_box_captures([folders[n] for n in names], check=False)
        except AnkleScanError as e:
            print(f"| {label} | failed: {e} | | | | |")
            continue
        c, p = report.camera, report.projector
        try:
            cb.check_residuals(report, caps, cal)
            verdict = "accepted"
        except cb.BoxCalibrationRefused as e:
            verdict = "refused (" + str(e).split("worst: ")[1].split(". ")[0] + ")"
        deg, mm = errors(cal, true)
        print(f"| {label} | {verdict} | {c.rms_px:.3f} / {c.point_errors_px.max():.2f} | "
              f"{p.rms_px:.3f} / {p.point_errors_px.max():.2f} | {deg:.3f}° | {mm:.2f} mm |")


if __name__ == "__main__":
    main()
