"""Where a simulated trial's time goes: the simulator's light transport, its frames, its truth.

    python benchmarks/bench_simulator.py [--scale 0.75] [--runs 3]

One leg scene (plates, inversion 10°, plantar flexion 0°) on the default rig, one process, one
thread for OpenCV (as in the demo's workers). Prints the median of ``--runs`` for: building the
light transport (the ray cast, per scene), the default pattern set's frames taken one by one and
in batches (``SimRig.capture_many``), and building the ground truth (the demo skips it for a still
scan). The camera's ray cache is warm, as from a demo worker's second trial on.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.hardware.sim_scene import leg_scene  # noqa: E402
from anklescan.hardware.simrig import SimRig  # noqa: E402


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench(scale: float, runs: int) -> dict:
    def rig() -> SimRig:
        return SimRig(leg_scene(10.0, 0.0, mark_type="plate", mark_radius=7.5), scale=scale, seed=3)

    warm = rig()
    warm.warm_camera_rays()
    images = render_all(make_pattern_set("default", warm.projector.width, warm.projector.height))
    out = {"transport": [], "one_by_one": [], "batched": [], "truth": []}
    for _ in range(runs):
        r = rig()
        out["transport"].append(_timed(r.prepare))
        out["one_by_one"].append(_timed(lambda r=r: _one_by_one(r, images)))
        out["batched"].append(_timed(lambda r=r: r.capture_many(images)))
        out["truth"].append(_timed(r.truth))
    same = all(np.array_equal(a, b) for a, b in zip(rig().capture_many(images), _one_by_one(rig(), images), strict=False))
    return {"camera": f"{warm.camera.width}x{warm.camera.height}", "frames": len(images), "identical": same,
            **{k: statistics.median(v) for k, v in out.items()}}


def _one_by_one(r: SimRig, images) -> list:
    return [r.capture(im) for im in images]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.75)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    r = bench(args.scale, args.runs)
    n = r["frames"]
    print(f"camera {r['camera']} (scale {args.scale}), {n} frames, median of {args.runs} runs")
    print(f"light transport        {r['transport']:6.2f} s")
    print(f"frames one by one      {r['one_by_one']:6.2f} s  ({1e3 * r['one_by_one'] / n:.1f} ms a frame)")
    print(f"frames batched         {r['batched']:6.2f} s  ({1e3 * r['batched'] / n:.1f} ms a frame)"
          f"  identical frames: {r['identical']}")
    print(f"ground truth           {r['truth']:6.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
