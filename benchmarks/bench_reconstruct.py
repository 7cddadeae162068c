"""Scan pipeline figures on the simulated rig at full resolution (camera 1600x1200, projector
1024x768, noise 2/255): accuracy of the default and paper presets against ground truth, time of
decode + triangulate, and peak memory of the whole ``anklescan reconstruct`` command.

    python benchmarks/bench_reconstruct.py [--runs 7] [--scale 1.0] [--keep DIR] [--calibration true|box]
                                           [--layout side|above|diagonal] [--axes column,row] [--presets default,paper]

``--calibration box`` first calibrates from a simulated scan of the calibration box (column and
row patterns) and reconstructs with that instead of the rig's true calibration: the whole
calibrate-then-scan path. ``--layout`` places the projector beside the camera (default), above it
or diagonal to it; the scan projects the stripe axes that rig needs (``scan_axes``) unless
``--axes`` says otherwise.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from anklescan.core.calibration.model.file import save_calibration  # noqa: E402
from anklescan.core.scan.capture import load_capture, save_capture  # noqa: E402
from anklescan.core.scan.decode import decode  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.core.scan.reconstruct import cloud_from_decoded  # noqa: E402
from anklescan.core.scan.triangulate import cache_for, scan_axes  # noqa: E402
from anklescan.hardware.sim_accuracy import evaluate  # noqa: E402
from anklescan.hardware.simrig import RigLayout, SimRig  # noqa: E402


def simulate(rig: SimRig, preset: str, folder: Path, axes=("column",)) -> Path:
    pset = make_pattern_set(preset, rig.projector.width, rig.projector.height, axes=axes)
    return save_capture(folder, pset, [rig.capture(img) for img in render_all(pset)])


def box_calibration(rig: SimRig, work: Path):
    from anklescan.core.calibration.procedures.box import calibrate_from_box_capture
    from anklescan.hardware.sim_scene import box_scene_objects, quad_scene

    box = rig.with_scene(quad_scene(box_scene_objects()))
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column", "row"))
    folder = save_capture(work / "capture_box", pset, [box.capture(img) for img in render_all(pset)])
    cal, report = calibrate_from_box_capture(folder)
    print("box calibration:\n  " + "\n  ".join(report.format_text().splitlines()[:1] + [
        line for line in report.format_text().splitlines() if line.startswith("projector")]))
    return cal


def time_reconstruct(capture, cal, runs: int) -> tuple[float, float, object]:
    cloud = cloud_from_decoded(capture, cal, decode(capture))  # warm-up: builds the calibration cache
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        cloud = cloud_from_decoded(capture, cal, decode(capture))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3, float(np.min(times)) * 1e3, cloud


def command_peak_mb(capture_dir: Path, cal_path: Path, out: Path) -> tuple[float, float]:
    """Peak RSS of the command by GNU time: the rusage of a child forked from this (large)
    process would count pages it inherited before exec."""
    cmd = [sys.executable, "-m", "anklescan.app.cli", "-q", "reconstruct", str(capture_dir), "--calibration", str(cal_path),
           "--out", str(out)]
    gnu_time = shutil.which("time") or ("/usr/bin/time" if Path("/usr/bin/time").exists() else None)
    t0 = time.perf_counter()
    if gnu_time is None:
        subprocess.run(cmd, check=True, cwd=ROOT)
        return float("nan"), time.perf_counter() - t0
    done = subprocess.run([gnu_time, "-f", "%M", *cmd], check=True, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    return int(done.stderr.strip().splitlines()[-1]) / 1024.0, wall


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, help="keep the simulated captures here")
    ap.add_argument("--calibration", choices=("true", "box"), default="true")
    ap.add_argument("--layout", default="side", help="side, above, diagonal (or an angle in degrees)")
    ap.add_argument("--axes", help="stripe axes to project (default: what the rig needs)")
    ap.add_argument("--presets", default="default,paper")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="anklescan-bench-"))
    layout = RigLayout(args.layout) if args.layout in set(RigLayout) else float(args.layout)
    rig = SimRig(scale=args.scale, layout=layout)
    cal = rig.true_calibration() if args.calibration == "true" else box_calibration(rig, work)
    cal_path = work / "calibration.json"
    save_calibration(cal, cal_path)
    axes = tuple(args.axes.split(",")) if args.axes else scan_axes(cal)
    print(f"rig: camera {rig.camera.width}x{rig.camera.height}, projector {rig.projector.width}x{rig.projector.height}, "
          f"layout {args.layout}, stripes {'+'.join(axes)}")
    t0 = time.perf_counter()
    cache_for(cal)
    print(f"calibration cache build: {time.perf_counter() - t0:.3f} s (once per calibration; the rest is built at "
          f"the first scan)")
    truth = rig.truth()
    for preset in args.presets.split(","):
        folder = simulate(rig, preset, work / f"capture_{preset}", axes)
        capture = load_capture(folder)
        med, best, cloud = time_reconstruct(capture, cal, args.runs)
        acc = evaluate(cloud, truth)
        print(f"\n[{preset}] {len(capture.pattern_set.frames)} frames")
        print(f"  decode + triangulate: median {med:.1f} ms, min {best:.1f} ms ({args.runs} runs)")
        print(f"  subject (leg, foot, table, marks): {acc['subject'].format()}")
        print(f"  whole frame (incl. floor):         {acc['frame'].format()}")
        print(f"  rejected pixels: {cloud.meta['rejected']}; points by axes: {cloud.meta['points_by_axes']}")
        if preset == "default":
            peak, wall = command_peak_mb(folder, cal_path, work / "cloud.ply")
            print(f"  `anklescan reconstruct` command: peak RSS {peak:.0f} MB, wall {wall:.1f} s")


if __name__ == "__main__":
    main()
