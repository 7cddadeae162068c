"""The sticker's image fit's cost (docs/marks.md, "Speed"): ``find_marks`` on captures of the
case table (tests/data/mark_cases.csv), CPU seconds (min of 3), with the image fit and with the
rim fit alone (the image fit disabled), and the marks found by each.

    python benchmarks/bench_image_fit.py [NAME ...]
"""

from __future__ import annotations

import sys
import time

from anklescan.core.measure import mark_fit
from anklescan.core.measure import pipeline as P
from anklescan.core.measure.marks import find_marks
from anklescan.core.scan.lit_image import clipped_white
from anklescan.hardware.sim_mark_cases import captured, load_cases

DEFAULT = ("sticker 15 0/0", "sticker 25 20/-20", "default 0/0 full")


def main() -> None:
    cases = {c.name: c for c in load_cases()}
    with_image = mark_fit._sticker_by_image
    for name in sys.argv[1:] or DEFAULT:
        case = cases[name]
        rig = case.rig()
        cap = captured(rig)
        cal = rig.true_calibration()
        decoded = P.decode(cap)
        cloud = P.cloud_from_decoded(cap, cal, decoded)
        lit = P.averaged_lit(cap, decoded.thresholds.get("camera_gamma"))
        clip = clipped_white(cap)
        row = {}
        for label, fit in (("image fit", with_image), ("rim only", lambda cand, edge_fit: None)):
            mark_fit._sticker_by_image = fit
            times = []
            for _ in range(3):
                t0 = time.process_time()
                marks = find_marks(lit, cloud, cal, clipped=clip)
                times.append(time.process_time() - t0)
            row[label] = f"{min(times):.2f} s CPU, {len(marks.marks)} marks"
        mark_fit._sticker_by_image = with_image
        print(f"{name}: " + "; ".join(f"{k} {v}" for k, v in row.items()))


if __name__ == "__main__":
    main()
