"""Manual placement where the automatic search missed a mark: does a click beside it snap to it?

    .venv/bin/python benchmarks/bench_snap.py --trials 155/0/20,177/0/-20 [--scale 1.0] [--offset 3]
        [--jobs 2] [--size unknown|given]

Each trial is ``variant/inversion/plantar flexion`` (a drawn set-up of ``hardware/sim_variety.py``;
the seed is the posture's index in ``bench_marks.py``'s five-posture sweep unless a fourth
field gives it). The capture is measured as ``anklescan measure`` does; for every true mark
the search did not find, two clicks ``--offset`` mm beside its true centre (either way across
the leg, in the mark's plane) are snapped as the 3-D view snaps them
(``anklescan.core.measure.marks.snap_to_disk``). Prints each click's outcome: the snapped
centre's error and error/SD, or 'kept' (no disk found: the click stays where it is), then the
count of missed marks whose clicks both snapped within 0.35 mm and 3.37 SD.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_marks import captured  # noqa: E402

from anklescan.core.measure.mark_candidates import points_image  # noqa: E402
from anklescan.core.measure.marks import LABELS, snap_to_disk  # noqa: E402
from anklescan.core.measure.pipeline import measure_capture  # noqa: E402
from anklescan.core.scan.lit_image import averaged_lit, clipped_white  # noqa: E402
from anklescan.hardware.sim_variety import draw_variant, variant_rig  # noqa: E402

POSTURE_SEEDS = {(0, -20): 0, (0, 20): 1, (10, 0): 2, (20, -20): 3, (20, 20): 4}  # bench_marks' sweep
GOOD_MM, GOOD_Z = 0.35, 3.37


def _parse(spec: str):
    fields = [int(f) for f in spec.split("/")]
    v, inv, pf = fields[:3]
    seed = fields[3] if len(fields) > 3 else POSTURE_SEEDS.get((inv, pf), 0)
    return v, inv, pf, seed


def _clicks(centre, normal, offset):
    across = np.cross(normal, [0.0, 0.0, 1.0])
    across = across / np.linalg.norm(across) if np.linalg.norm(across) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return [centre + s * offset * across for s in (1.0, -1.0)]


def _trial(job):
    (v, inv, pf, seed), scale, offset, given = job
    variant = draw_variant(v)
    rig = variant_rig(variant, inv, pf, scale=scale, seed=seed)
    cap = captured(rig)
    cal = rig.true_calibration()
    res = measure_capture(cap, cal, variant.diameter if given else None)
    truth = rig.mark_truth()
    found = {min(truth.marks, key=lambda k: np.linalg.norm(truth.marks[k] - m.centre)) for m in res.marks.marks}
    lit = averaged_lit(cap)
    pts, clipped = points_image(res.cloud, lit.shape), clipped_white(cap)
    size = variant.diameter if given else (res.marks.diameter[0] if res.marks.diameter else None)
    rows = []
    for k in sorted(set(LABELS) - found):
        outcomes = []
        for click in _clicks(truth.marks[k], truth.mark_normals[k], offset):
            m = snap_to_disk(click, lit, pts, cal, mark_diameter_mm=size, clipped=clipped)
            if m is None:
                outcomes.append(None)
                continue
            e = m.centre - truth.marks[k]
            outcomes.append((float(np.linalg.norm(e)), float(np.sqrt(e @ np.linalg.solve(m.covariance, e)))))
        rows.append((k, outcomes))
    return variant.describe(), (v, inv, pf, seed), rows


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", required=True, help="variant/inv/pf[/seed],... e.g. 155/0/20,177/0/-20")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--offset", type=float, default=3.0, help="mm between the click and the true centre")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--size", default="unknown", choices=("unknown", "given"))
    a = ap.parse_args(argv)
    jobs = [(_parse(t), a.scale, a.offset, a.size == "given") for t in a.trials.split(",")]
    missed = good = 0
    with multiprocessing.Pool(a.jobs) if a.jobs > 1 else contextlib.nullcontext() as pool:
        for describe, (_v, inv, pf, seed), rows in (pool.imap(_trial, jobs) if pool else map(_trial, jobs)):
            print(describe, flush=True)
            print(f"  inv {inv:3d} pf {pf:4d} seed {seed}: " + ("every mark found" if not rows else
                                                               f"{len(rows)} mark(s) missed"), flush=True)
            for k, outcomes in rows:
                missed += 1
                text = ", ".join("kept" if o is None else f"{o[0]:.2f} mm ({o[1]:.1f} SD)" for o in outcomes)
                good += all(o is not None and o[0] < GOOD_MM and o[1] < GOOD_Z for o in outcomes)
                print(f"    mark {k}: clicks {a.offset:g} mm beside it -> {text}", flush=True)
    print(f"missed marks whose clicks both snapped within {GOOD_MM} mm and {GOOD_Z} SD: {good} of {missed}")


if __name__ == "__main__":
    main()
