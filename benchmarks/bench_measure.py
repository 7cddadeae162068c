"""``anklescan measure`` side by side with ``anklescan reconstruct`` and a bare process that only
reads the same PNGs, each timed as a fresh subprocess (interpreter start, imports, everything),
on a simulated full-resolution capture with the default scene's seven marks.

    python benchmarks/bench_measure.py [--runs 5] [--layout side] [--axes column,row] [--keep DIR] [--profile]
                                       [--stages] [--before DIR]

The capture and its calibration are made as ``bench_command.py`` makes them (``--keep DIR``
keeps and reuses them). Runs alternate bare / reconstruct / measure so that a busy machine slows
all three alike; medians and minima are printed, and the measure / bare ratio (issue 41's
target: at most 2). ``--profile`` also runs ``measure`` once under cProfile and prints where
its time goes. ``--stages`` also runs ``measure``'s stages one after another in a fresh process
and prints each one's CPU and wall time (the command overlaps some of them on threads).
``--before DIR``: also time ``measure`` of another version of AnkleScan, alternating with the
rest, where DIR holds its ``anklescan`` package (e.g. a link tree like build/mypy's of an older
checkout); its RESULT.json is compared with this version's (byte for byte, else the largest
differences of the marks' centres and the angles, and which other values differ).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import BARE, ROOT, make_capture, timed  # noqa: E402

STAGES = """
import sys, time
clock = [time.perf_counter(), time.process_time()]
def lap(name):
    t, c = time.perf_counter(), time.process_time()
    print(f"  {name:34s} CPU {c - clock[1]:5.2f} s   wall {t - clock[0]:5.2f} s")
    clock[:] = [t, c]
import numpy, cv2
lap("interpreter, numpy, cv2")
from anklescan.core.measure import pipeline as P
lap("import the measure stage")
from anklescan.core.calibration.model.file import load_calibration
from anklescan.core.scan.capture import load_capture
cal = load_calibration(sys.argv[2])
capture = load_capture(sys.argv[1])
lap("calibration, frames read (2 threads)")
P.check_compatible(capture, cal)
decoded = P.decode(capture)
lap("decode")
cloud = P.cloud_from_decoded(capture, cal, decoded)
lap("grids, triangulate (cloud)")
lit = P.averaged_lit(capture, decoded.thresholds.get("camera_gamma"))
lap("lit image")
marks = P.find_marks(lit, cloud, cal, mark_diameter_mm=None, clipped=P.clipped_white(capture))
lap("find_marks")
motion = P.estimate_motion(capture, cal, decoded, cloud)
P.honest_angles(marks, cal, motion)
P.measure_warnings(P.WarningContext(marks.centres(), cal, marks.overexposed_message()))
lap("motion, angles, warnings")
P.frame_warnings(cal.extra, cloud.points, cal.camera.center)
lap("frame check")
"""


def compare_results(ours: Path, theirs: Path) -> str:
    """One line: RESULT.json byte-identical to the other version's, or how far its marks' centres
    (mm) and angles (degrees) are from it (issue 38: within 0.005 mm and 0.001°), and whether any
    other value differs beyond 1e-9 relative."""
    if ours.read_bytes() == theirs.read_bytes():
        return "RESULT.json byte-identical to the --before version's"
    a, b = (json.loads(p.read_text(encoding="utf-8")) for p in (ours, theirs))
    if sorted(a["marks"]) != sorted(b["marks"]):
        return f"RESULT.json DIFFERS: marks {sorted(a['marks'])} against {sorted(b['marks'])}"
    centre = max(abs(x - y) for k in a["marks"] for x, y in zip(a["marks"][k], b["marks"][k], strict=True))
    angle = max((abs(a["angles"][k]["value"] - b["angles"][k]["value"]) for k in a["angles"]), default=0.0)
    other: list[str] = []

    def walk(x: object, y: object, path: str) -> None:
        if isinstance(x, dict) and isinstance(y, dict):
            if set(x) != set(y):
                other.append(path)
            for k in set(x) & set(y):
                walk(x[k], y[k], f"{path}/{k}")
        elif isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y):
                other.append(path)
            for i, (u, v) in enumerate(zip(x, y, strict=False)):
                walk(u, v, f"{path}[{i}]")
        elif isinstance(x, float) and isinstance(y, float):
            if not math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12):
                other.append(path)
        elif x != y:
            other.append(path)

    walk(a, b, "")
    ok = centre <= 0.005 and angle <= 0.001
    return (f"RESULT.json vs the --before version's: centres within {centre:.1e} mm, angles within {angle:.1e}° "
            f"({'within' if ok else 'BEYOND'} 0.005 mm / 0.001°); "
            + (f"{len(other)} other values differ beyond 1e-9: {', '.join(sorted(other)[:5])}" if other
               else "every other value within 1e-9"))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--layout", default="side")
    ap.add_argument("--axes", help="stripe axes of the capture (default: what the rig needs)")
    ap.add_argument("--keep", type=Path)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--stages", action="store_true", help="CPU and wall time of each stage of measure")
    ap.add_argument("--before", type=Path, help="a folder holding another version's anklescan package")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="anklescan-bench-measure-"))
    work.mkdir(parents=True, exist_ok=True)
    axes = tuple(args.axes.split(",")) if args.axes else None
    folder, cal_path = make_capture(work, args.layout, axes, 1.0)
    n_frames = sum(1 for p in folder.iterdir() if p.suffix == ".png")
    cli = [sys.executable, "-m", "anklescan.app.cli", "-q"]
    commands = {
        "bare PNG read (2 threads)": [sys.executable, "-c", BARE, str(folder), "2"],
        "anklescan reconstruct": cli + ["reconstruct", str(folder), "--calibration", str(cal_path),
                                        "--out", str(work / "cloud.ply")],
        "anklescan measure": cli + ["measure", str(folder), "--calibration", str(cal_path),
                                    "--out", str(work / "result.json")],
    }
    if args.before is not None:
        commands["anklescan measure (--before)"] = [
            "env", f"PYTHONPATH={args.before.resolve()}", *cli, "measure", str(folder), "--calibration",
            str(cal_path), "--out", str(work / "result_before.json")]
    for cmd in commands.values():
        timed(cmd)  # warm the page cache and the interpreter's bytecode
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in commands}
    for _ in range(args.runs):
        for name, cmd in commands.items():
            times[name].append(timed(cmd))
    print(f"capture: {n_frames} PNG frames (1600x1200), {folder}; {args.runs} alternating runs each")
    for name, t in times.items():
        wall, cpu = [x[0] for x in t], [x[1] for x in t]
        print(f"{name:28s} wall median {statistics.median(wall):.2f} s, min {min(wall):.2f} s; "
              f"CPU median {statistics.median(cpu):.2f} s")
    keys = ("bare PNG read (2 threads)", "anklescan measure")
    wall_b, wall_m = (statistics.median(x[0] for x in times[k]) for k in keys)
    cpu_b, cpu_m = (statistics.median(x[1] for x in times[k]) for k in keys)
    print(f"measure / bare read: wall medians {wall_m / wall_b:.2f}, CPU medians {cpu_m / cpu_b:.2f} (target <= 2)")
    if args.before is not None:
        print(compare_results(work / "result.json", work / "result_before.json"))
    if args.stages:
        print("measure's stages one after another, in a fresh process:")
        subprocess.run([sys.executable, "-c", STAGES, str(folder), str(cal_path)], check=True, cwd=ROOT)
    if args.profile:
        prof = work / "measure.prof"
        subprocess.run([sys.executable, "-m", "cProfile", "-o", str(prof)] + commands["anklescan measure"][1:],
                       check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        import pstats

        pstats.Stats(str(prof)).sort_stats("cumulative").print_stats(30)


if __name__ == "__main__":
    main()
