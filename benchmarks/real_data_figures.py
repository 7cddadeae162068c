"""The figures of docs/real-data.md, from the full procam-calibration captures.

    PYTHONPATH=. python benchmarks/real_data_figures.py ../shared/realdata/procam-calibration

For every pair of captures: a chessboard calibration from the pair
(anklescan.core.calibration.procedures.board), then the third capture measured
(anklescan.core.calibration.procedures.board_metrics): the pitch of its corners in 3-D and the flatness of its board
against the cloud's predicted noise.  Then the author's calibration_result.xml, imported,
on each capture.  The clouds triangulate the camera ray against the projector ray of both decoded
codes (anklescan.core.calibration.procedures.board_metrics.triangulate_both).
"""

from __future__ import annotations

import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

from anklescan.core.calibration.procedures.board import DEFAULT_DIST, calibrate_board_views, observe_board
from anklescan.core.calibration.procedures.board_metrics import measure_board, triangulate_both
from anklescan.core.calibration.procedures.opencv_calibration import import_opencv_calibration
from anklescan.core.scan.capture import load_capture
from anklescan.core.scan.decode import decode
from anklescan.core.scan.opencv_graycode import import_opencv_graycode
from anklescan.core.scan.reconstruct import cloud_from_decoded

COLS, ROWS, SQUARE, STEP = 9, 7, 75.0, 2
PROJECTOR = (2048, 1536)


def main(src: Path, model: str = DEFAULT_DIST) -> None:
    data = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(3):
            out = Path(tmp) / f"capture_{k}"
            import_opencv_graycode(src / f"capture_{k}", out, *PROJECTOR, STEP)
            cap = load_capture(out)
            d = decode(cap)
            data[k] = (cap, d, observe_board(cap, COLS, ROWS, decoded=d))

    def measure_reconstructed(cal, k):
        """Through anklescan.core.scan.reconstruct, the path of 'anklescan reconstruct': each pixel on the axis (or
        both) the rig supports, with the cloud's own predicted noise (along the camera ray)."""
        cap, d, view = data[k]
        cloud = cloud_from_decoded(cap, cal, d)
        return measure_board(cal, cloud.points.astype(float), cloud.pixels.astype(float), cloud.sigma,
                             view.corners, cap.shape, COLS, ROWS, SQUARE)

    def measure(cal, k):
        if VIA_RECONSTRUCT:
            return measure_reconstructed(cal, k)
        cap, d, view = data[k]
        ok = d.valid & np.isfinite(d.row)
        v, u = np.nonzero(ok)
        pix = np.stack([u, v], axis=1)
        X, noise = triangulate_both(cal, pix.astype(float), np.stack([d.column[ok], d.row[ok]], 1).astype(float),
                                    STEP / np.sqrt(12))
        return measure_board(cal, X, pix, noise, view.corners, cap.shape, COLS, ROWS, SQUARE)

    print(f"distortion model {model}")
    print(
        "| calibration | measured | distance m | pitch mm | pitch error % | pitch SD mm | flatness RMS mm "
        "| predicted mm | RMS cam / proj px |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for pair in itertools.combinations(range(3), 2):
        (k,) = set(range(3)) - set(pair)
        res = calibrate_board_views([data[i][2] for i in pair], COLS, ROWS, SQUARE, PROJECTOR, model)
        m = measure(res.calibration, k)
        print(f"| board, captures {pair[0]}+{pair[1]} | {k} | {m.distance_mm / 1000:.2f} | {m.pitch_mm:.2f} | "
              f"{m.pitch_error_pct:+.2f} | {m.pitch_sd_mm:.2f} | {m.flatness_rms_mm:.2f} | {m.predicted_rms_mm:.2f} | "
              f"{res.report.camera.rms_px:.3f} / {res.report.projector.rms_px:.3f} |")
    author = import_opencv_calibration(src / "calibration_result.xml", PROJECTOR)
    for k in range(3):
        m = measure(author, k)
        print(f"| author's XML (5 captures) | {k} | {m.distance_mm / 1000:.2f} | {m.pitch_mm:.2f} | "
              f"{m.pitch_error_pct:+.2f} | {m.pitch_sd_mm:.2f} | {m.flatness_rms_mm:.2f} | {m.predicted_rms_mm:.2f} | |")


VIA_RECONSTRUCT = False

if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--reconstruct"]
    VIA_RECONSTRUCT = len(args) < len(sys.argv) - 1  # measure the clouds 'anklescan reconstruct' writes
    main(Path(args[0]), *args[1:])
