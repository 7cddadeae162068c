"""Cost of the input checks (issue 15) and how fast bad input is refused.

    python benchmarks/bench_input_checks.py [--runs 5]

Prints: ``load_capture`` of a full-resolution simulated capture (1600x1200, 30 frames), which
now reads every frame header first, decodes through bytes, and checks that the capture is lit;
and the time to refuse a capture whose headers claim 20000x20000 frames and a pattern set of
30000x30000 (both refused before anything is allocated).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from anklescan.core.calibration.model.file import save_calibration  # noqa: E402
from anklescan.core.scan.capture import load_capture, save_capture  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.hardware.simrig import SimRig  # noqa: E402
from tests.test_reliability import _png_header_only  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rig = SimRig(scale=1.0)
        pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
        save_capture(work / "capture", pset, [rig.capture(img) for img in render_all(pset)])
        save_calibration(rig.true_calibration(), work / "cal.json")
        times = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            cap = load_capture(work / "capture")
            times.append(time.perf_counter() - t0)
        print(f"load_capture {cap.frames.shape[2]}x{cap.frames.shape[1]} x {cap.frames.shape[0]} frames: "
              f"median {statistics.median(times):.3f} s, min {min(times):.3f} s over {args.runs} runs")
        for f in pset.files:
            (work / "capture" / f).write_bytes(_png_header_only(20000, 20000))
        cli = [sys.executable, "-m", "anklescan.app.cli", "-q"]
        for label, argv in (("reconstruct, 20000x20000 frames", ["reconstruct", str(work / "capture"),
                                                                 "--calibration", str(work / "cal.json"),
                                                                 "--out", str(work / "x.ply")]),
                            ("patterns --projector 30000x30000", ["patterns", "--out", str(work / "p"),
                                                                  "--projector", "30000x30000"])):
            t0 = time.perf_counter()
            done = subprocess.run(cli + argv, capture_output=True, text=True, cwd=ROOT)
            print(f"{label}: exit {done.returncode} in {time.perf_counter() - t0:.2f} s "
                  f"(process start included): {done.stderr.strip()}")


if __name__ == "__main__":
    main()
