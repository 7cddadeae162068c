"""The daily check's figures on the simulated rig: the true rig, a frame turned 2° (a wrong levelling)
and a projector nudged 0.5° about the vertical, for the wedge block and the reference table on its own.

    .venv/bin/python benchmarks/bench_daily_check.py [--scales 0.25,0.5]

Each line: the object, its set angles, the true rig's error (inversion / plantar flexion, degrees),
the block-jackknife SD, the top's sag (mm), the check's time; then each wrong rig's error and verdict.
About 20 s a scale on two cores.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.calibration.procedures.daily_check import run_check
from anklescan.core.scan.capture import load_capture, save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.hardware.sim_check import CheckObject, MarkStyle, check_scene, nudged_device, rotated_frame
from anklescan.hardware.simrig import SimRig

CASES = ((CheckObject.WEDGE, MarkStyle.NONE, (0, 0)), (CheckObject.WEDGE, MarkStyle.NONE, (20, 0)),
         (CheckObject.WEDGE, MarkStyle.NONE, (-10, 15)), (CheckObject.TABLE, MarkStyle.PLATE, (10, -20)),
         (CheckObject.TABLE, MarkStyle.STICKER, (-15, 10)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scales", default="0.25,0.5")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_check_"))
    for scale in (float(s) for s in args.scales.split(",")):
        for obj, marks, (inv, pf) in CASES:
            rig = SimRig(check_scene(inv, pf, obj, marks=marks), scale=scale, seed=7)
            pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
            folder = tmp / f"{scale}_{obj.value}_{marks.value}_{inv}_{pf}"
            save_capture(folder, pset, rig.capture_many(render_all(pset)))
            cap, true = load_capture(folder), rig.true_calibration()
            t0 = time.perf_counter()
            r = run_check(cap, true, inv, pf)
            dt = time.perf_counter() - t0
            out = [f"{scale:.2f} {obj.value:5s} {marks.value:7s} ({inv:+3d},{pf:+3d}) true "
                   f"{r.inversion_off:+.3f}/{r.plantar_flexion_off:+.3f} sd {r.top.inversion.sd:.3f}/"
                   f"{r.top.plantar_flexion.sd:.3f} sag {r.top.sag_mm:.2f} {dt:.1f} s"]
            for name, cal in (("frame x 2°", rotated_frame(true, 2, "x")), ("frame y 2°", rotated_frame(true, 2, "y")),
                              ("projector z 0.5°", Calibration(true.camera, nudged_device(true.projector, 0.5, "z"),
                                                               {}))):
                w = run_check(cap, cal, inv, pf)
                out.append(f"{name} {w.inversion_off:+.2f}/{w.plantar_flexion_off:+.2f} "
                           f"{'pass' if w.passed else 'FAIL'}")
            print(" | ".join(out), flush=True)


if __name__ == "__main__":
    main()
