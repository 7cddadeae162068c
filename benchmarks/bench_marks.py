"""Mark centres and angles against the simulated rig's truth over the table settings.

    /work/venv/bin/python benchmarks/bench_marks.py [--scale 1.0] [--quick]

Prints, per trial, each mark's centre error (mm), fitted radius, the four angle errors (deg)
and whether all seven were found and labelled; then the worst cases.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.capture import capture_from_images  # noqa: E402
from core.measure import measure_capture  # noqa: E402
from core.patterns import make_pattern_set, render_all  # noqa: E402
from hardware.sim_scene import leg_scene  # noqa: E402
from hardware.simrig import SimRig  # noqa: E402

SETTINGS = [(inv, pf) for inv in (0, 10, 20) for pf in (-20, -10, 0, 10, 20)]
QUICK = [(0, 0), (20, 20), (10, -20), (20, -20)]


def trial(inv, pf, scale, seed):
    rig = SimRig(leg_scene(inv, pf), scale=scale, seed=seed)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    cap = capture_from_images(pset, rig.capture_many(render_all(pset)))
    t = time.perf_counter()
    res = measure_capture(cap, rig.true_calibration())
    dt = time.perf_counter() - t
    tr = rig.truth()
    mark_err = {k: float(np.linalg.norm(m.centre - tr.marks[k])) for k, m in res.marks.labelled.items()}
    ang_err = {k: float(v["value"] - tr.angles[k]) for k, v in res.angles.items()}
    return res, mark_err, ang_err, dt


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)
    worst_mark, worst_angle, failures = 0.0, 0.0, 0
    for i, (inv, pf) in enumerate(QUICK if a.quick else SETTINGS):
        res, me, ae, dt = trial(inv, pf, a.scale, seed=i)
        ok = res.complete
        failures += not ok
        worst_mark = max([worst_mark, *me.values()])
        worst_angle = max([worst_angle, *map(abs, ae.values())])
        marks = " ".join(f"{k}:{v:.2f}" for k, v in sorted(me.items()))
        angles = " ".join(f"{k.replace('_', ' ')[:10]}:{v:+.3f}" for k, v in ae.items())
        print(f"inv {inv:3d} pf {pf:4d}  {'7/7' if ok else 'INCOMPLETE'}  marks(mm) {marks}  angles(deg) {angles}  "
              f"[{dt:.1f} s]", flush=True)
        if not ok:
            print("    " + res.marks.message(), flush=True)
    print(f"worst mark error {worst_mark:.3f} mm, worst angle error {worst_angle:.3f} deg, incomplete trials {failures}")


if __name__ == "__main__":
    main()
