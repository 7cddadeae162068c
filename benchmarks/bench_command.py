"""The whole ``anklescan reconstruct`` command against a bare process that only reads the same
PNGs, both timed as fresh subprocesses (interpreter start, imports, everything), on a simulated
full-resolution capture (camera 1600x1200, projector 1024x768).

    python benchmarks/bench_command.py [--runs 7] [--layout side|above|diagonal] [--axes column,row]
                                       [--scale 1.0] [--keep DIR] [--profile]

The bare process is ``python -c`` with ``cv2.imread`` of every frame, on two threads as
``load_capture`` reads them (``--bare-serial``: one thread). Runs alternate between the two so
that a busy machine slows both alike; medians and minima are printed. ``--profile`` also runs the
command once under cProfile and prints where its time goes. ``--keep DIR`` keeps (and reuses) the
capture and calibration.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

BARE = """
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import cv2
folder = Path(sys.argv[1])
files = sorted(p for p in folder.iterdir() if p.suffix == ".png")
workers = int(sys.argv[2])
with ThreadPoolExecutor(max_workers=workers) as pool:
    images = list(pool.map(lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED), files))
assert all(im is not None for im in images)
"""


def make_capture(work: Path, layout: str, axes: tuple[str, ...] | None, scale: float) -> tuple[Path, Path]:
    tag = layout + ("" if axes is None else "_" + "_".join(axes))
    folder, cal_path = work / f"capture_{tag}", work / f"calibration_{layout}.json"
    if (folder / "manifest.json").exists() and cal_path.exists():
        return folder, cal_path
    from anklescan.core.calibration.model.file import save_calibration
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.core.scan.triangulate import scan_axes
    from anklescan.hardware.simrig import RigLayout, SimRig

    rig = SimRig(scale=scale, layout=RigLayout(layout))
    cal = rig.true_calibration()
    axes = axes or scan_axes(cal)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=axes)
    t0 = time.perf_counter()
    save_capture(folder, pset, [rig.capture(img) for img in render_all(pset)])
    save_calibration(cal, cal_path)
    print(f"simulated {len(pset.frames)} frames ({layout} rig, axes {','.join(axes)}) in {time.perf_counter() - t0:.0f} s")
    return folder, cal_path


def timed(cmd: list[str]) -> tuple[float, float]:
    """Wall time and CPU time (user + system, all threads) of a subprocess."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--layout", default="side")
    ap.add_argument("--axes", help="stripe axes of the capture (default: what the rig needs)")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--keep", type=Path)
    ap.add_argument("--bare-serial", action="store_true", help="the bare process reads on one thread")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="anklescan-bench-command-"))
    work.mkdir(parents=True, exist_ok=True)
    axes = tuple(args.axes.split(",")) if args.axes else None
    folder, cal_path = make_capture(work, args.layout, axes, args.scale)
    out = work / "cloud.ply"
    n_frames = sum(1 for p in folder.iterdir() if p.suffix == ".png")
    command = [sys.executable, "-m", "anklescan.app.cli", "-q", "reconstruct", str(folder), "--calibration", str(cal_path),
               "--out", str(out)]
    bare = [sys.executable, "-c", BARE, str(folder), "1" if args.bare_serial else "2"]
    timed(bare), timed(command)  # warm the page cache and the interpreter's bytecode
    t_cmd, t_bare = [], []
    for _ in range(args.runs):
        t_bare.append(timed(bare))
        t_cmd.append(timed(command))
    wb, wc = [t[0] for t in t_bare], [t[0] for t in t_cmd]
    cb, cc = [t[1] for t in t_bare], [t[1] for t in t_cmd]
    mb, mc = statistics.median(wb), statistics.median(wc)
    print(f"capture: {n_frames} PNG frames, {folder}")
    print(f"bare PNG read ({'1 thread' if args.bare_serial else '2 threads'}): wall median {mb:.2f} s, min {min(wb):.2f} s; "
          f"CPU median {statistics.median(cb):.2f} s")
    print(f"anklescan reconstruct:        wall median {mc:.2f} s, min {min(wc):.2f} s; CPU median {statistics.median(cc):.2f} s")
    print(f"ratio: wall medians {mc / mb:.2f}, wall minima {min(wc) / min(wb):.2f}, CPU medians "
          f"{statistics.median(cc) / statistics.median(cb):.2f} (target <= 2)   [{args.runs} alternating runs each]")
    if args.profile:
        prof = work / "reconstruct.prof"
        subprocess.run([sys.executable, "-m", "cProfile", "-o", str(prof), "-m", "anklescan.app.cli", "-q", "reconstruct",
                        str(folder), "--calibration", str(cal_path), "--out", str(out)], check=True, cwd=ROOT)
        import pstats

        pstats.Stats(str(prof)).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
