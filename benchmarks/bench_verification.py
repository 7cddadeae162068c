"""Box calibration and verification figures on the simulated rig (issue #8's targets).

    python benchmarks/bench_verification.py [--scale 1.0] [--seed 11]

One simulated scan of the calibration box (column and row patterns) is calibrated as the app's
guided flow does (``anklescan.core.calibration.procedures.box.calibrate_from_box_capture``: the same corners, the
same windows); a second scan of the box, with fresh noise, is verified with that calibration
and with the rig's true one. Prints the focal-length errors, the corner error against the
simulator's truth, and the verification's RMS and worst distance error (target ≤ 0.2 mm).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from anklescan.core.calibration.procedures import box as cb
from anklescan.core.calibration.procedures.verification import verify_box_capture  # noqa: E402
from anklescan.core.scan.capture import save_capture  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.hardware.sim_scene import box_scene_objects, quad_scene  # noqa: E402
from anklescan.hardware.simrig import SimRig  # noqa: E402


def box_capture(rig: SimRig, folder: Path) -> Path:
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column", "row"))
    return save_capture(folder, pset, rig.capture_many(render_all(pset)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args()
    rig = SimRig(quad_scene(box_scene_objects()), scale=args.scale, seed=args.seed)
    true = rig.true_calibration()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cal_scan = box_capture(rig, Path(tmp) / "calibrate")
        ver_scan = box_capture(rig, Path(tmp) / "verify")
        print(f"two box scans simulated: {time.perf_counter() - t0:.1f} s "
              f"(camera {true.camera.width}x{true.camera.height})")

        from anklescan.core.scan.capture import load_capture
        from anklescan.core.scan.decode import decode
        white = decode(load_capture(cal_scan)).white
        found = cb.detect_markers(white)
        world = cb.marker_corners_world()
        for refine in (False, True):
            got = cb.detect_markers(white, refine_edges=refine) if not refine else found
            err = np.concatenate([got[i] - true.camera.project(world[i]) for i in got])
            print(f"corners ({'outline edges' if refine else 'cornerSubPix only'}): {len(got)} markers, "
                  f"error RMS {np.sqrt(np.mean(np.sum(err**2, axis=1))):.3f} px, "
                  f"worst {np.abs(err).max():.3f} px")

        t0 = time.perf_counter()
        cal, report = cb.calibrate_from_box_capture(cal_scan)
        print(f"calibration: {time.perf_counter() - t0:.1f} s; camera RMS {report.camera.rms_px:.3f} px, "
              f"projector RMS {report.projector.rms_px:.3f} px")
        print(f"focal error: camera {100 * abs(cal.camera.fx / true.camera.fx - 1):.3f} %, "
              f"projector {100 * abs(cal.projector.fx / true.projector.fx - 1):.3f} %")
        for name, c in (("box calibration", cal), ("true calibration", true)):
            res = verify_box_capture(ver_scan, c)
            print(f"verification with the {name}: {len(res.centres)} centres, {len(res.pairs)} distances, "
                  f"RMS {res.rms_mm:.3f} mm, worst {res.max_abs_mm:.3f} mm, mean {res.mean_mm:+.3f} mm "
                  f"-> {'PASS' if res.passed else 'FAIL'}")


if __name__ == "__main__":
    main()
