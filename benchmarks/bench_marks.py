"""Mark centres and angles against the simulated rig's truth over the table settings.

    /work/venv/bin/python benchmarks/bench_marks.py [--scale 1.0] [--quick]
        [--postures 20/20,10/20] [--seed N] [--camera-blur PX] [--projector-blur PX] [--noise SIGMA]

Prints, per trial, each labelled mark's centre error (mm), the four angle errors (deg),
whether all seven were found and labelled, and which true marks were not found (each plate
found is matched to the nearest true centre); then the worst cases and the counts.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.capture import capture_from_images  # noqa: E402
from core.marks import LABELS  # noqa: E402
from core.measure import measure_capture  # noqa: E402
from core.patterns import make_pattern_set, render_all  # noqa: E402
from hardware.sim_scene import leg_scene  # noqa: E402
from hardware.simrig import Optics, SimRig  # noqa: E402

SETTINGS = [(inv, pf) for inv in (0, 10, 20) for pf in (-20, -10, 0, 10, 20)]
QUICK = [(0, 0), (20, 20), (10, -20), (20, -20)]


def trial(inv, pf, scale, seed, optics=None):
    rig = SimRig(leg_scene(inv, pf), scale=scale, seed=seed, optics=optics)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    cap = capture_from_images(pset, rig.capture_many(render_all(pset)))
    t = time.perf_counter()
    res = measure_capture(cap, rig.true_calibration())
    dt = time.perf_counter() - t
    tr = rig.truth()
    mark_err = {k: float(np.linalg.norm(m.centre - tr.marks[k])) for k, m in res.marks.labelled.items()}
    ang_err = {k: float(v["value"] - tr.angles[k]) for k, v in res.angles.items()}
    nearest = {}
    for m in res.marks.marks:
        k = min(tr.marks, key=lambda k: np.linalg.norm(tr.marks[k] - m.centre))
        nearest[k] = m.label
    res.found_truth = nearest  # true label -> label given (None: found, not labelled)
    return res, mark_err, ang_err, dt


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--postures", help="inversion/plantar flexion pairs, e.g. 20/20,0/-20 (default: all 15)")
    ap.add_argument("--seed", type=int, help="one seed for every trial (default: the trial's index)")
    ap.add_argument("--camera-blur", type=float, help="px (rig default 0.6)")
    ap.add_argument("--projector-blur", type=float, help="projector px (rig default 0.8)")
    ap.add_argument("--noise", type=float, help="read noise, fraction of full scale (rig default 2/255)")
    a = ap.parse_args(argv)
    overrides = {k: v for k, v in (("camera_blur_px", a.camera_blur), ("projector_blur_px", a.projector_blur),
                                   ("noise_sigma", a.noise)) if v is not None}
    optics = Optics(**overrides) if overrides else None
    settings = QUICK if a.quick else SETTINGS
    if a.postures:
        settings = [tuple(int(v) for v in p.split("/")) for p in a.postures.split(",")]
    worst_mark, worst_angle, failures = 0.0, 0.0, 0
    n_found = n_right = n_total = 0
    for i, (inv, pf) in enumerate(settings):
        res, me, ae, dt = trial(inv, pf, a.scale, seed=i if a.seed is None else a.seed, optics=optics)
        ok = res.complete
        failures += not ok
        n_total += 7
        n_found += len(res.found_truth)
        n_right += sum(k == lab for k, lab in res.found_truth.items())
        worst_mark = max([worst_mark, *me.values()])
        worst_angle = max([worst_angle, *map(abs, ae.values())])
        marks = " ".join(f"{k}:{v:.2f}" for k, v in sorted(me.items()))
        angles = " ".join(f"{k.replace('_', ' ')[:10]}:{v:+.3f}" for k, v in ae.items())
        print(f"inv {inv:3d} pf {pf:4d}  {'7/7' if ok else 'INCOMPLETE'}  marks(mm) {marks}  angles(deg) {angles}  "
              f"[{dt:.1f} s]", flush=True)
        if not ok:
            print("    " + res.marks.message(), flush=True)
            print(f"    true marks not found: {', '.join(sorted(set(LABELS) - set(res.found_truth))) or 'none'}", flush=True)
    print(f"worst mark error {worst_mark:.3f} mm, worst angle error {worst_angle:.3f} deg, incomplete trials {failures}; "
          f"plates found {n_found}/{n_total}, correctly labelled {n_right}/{n_total}")


if __name__ == "__main__":
    main()
