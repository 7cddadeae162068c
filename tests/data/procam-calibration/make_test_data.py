"""Rebuild this folder's test data from the procam-calibration sample captures (see README.md).

    PYTHONPATH=. python tests/data/procam-calibration/make_test_data.py ../shared/realdata/procam-calibration

* ``capture_1/``: all 42 frames of capture_1, with every pixel farther than ``GROW`` squares
  outside the board's outer inner corners set to 0 (the board and its margin are bit-exact;
  zeros compress to almost nothing, the rest of the room does not).
* ``decoded/capture_{0,2}_{white,column,row}.png``: the white frame (masked the same way) and
  the decoded projector maps of the two other captures, as 16-bit PNGs of ``2 * coordinate``
  (exact: Gray-code-only decoding gives half-integers), 65535 where the pixel did not decode.
  They are what the board calibration reads from a capture, at a fraction of the size.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))

from anklescan.core.calibration.procedures.board import find_corners  # noqa: E402
from anklescan.core.scan.capture import load_capture  # noqa: E402
from anklescan.core.scan.decode import decode  # noqa: E402
from anklescan.core.scan.opencv_graycode import import_opencv_graycode  # noqa: E402

GROW = 1.6  # squares beyond the outer inner corners: the whole printed board and a margin
COLS, ROWS = 9, 7
INVALID = 65535


def board_mask(white: np.ndarray) -> np.ndarray:
    c, _ = find_corners(white, COLS, ROWS)
    g = c.reshape(ROWS, COLS, 2)
    ex, ey = (g[0, -1] - g[0, 0]) / (COLS - 1), (g[-1, 0] - g[0, 0]) / (ROWS - 1)
    q = np.array([g[0, 0] - GROW * (ex + ey), g[0, -1] + GROW * (ex - ey),
                  g[-1, -1] + GROW * (ex + ey), g[-1, 0] + GROW * (ey - ex)])
    m = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(q).astype(np.int32), 1)
    return m


def encode_map(a: np.ndarray) -> np.ndarray:
    out = np.full(a.shape, INVALID, np.uint16)
    ok = np.isfinite(a)
    out[ok] = np.round(2 * a[ok]).astype(np.uint16)
    return out


def decode_map(img: np.ndarray) -> np.ndarray:
    out = img.astype(np.float32) / 2
    out[img == INVALID] = np.nan
    return out


def main(src: Path) -> None:
    png = [cv2.IMWRITE_PNG_COMPRESSION, 9]
    (HERE / "decoded").mkdir(exist_ok=True)
    for k in range(3):
        d = src / f"capture_{k}"
        white = cv2.imread(str(d / "graycode_40.png"), cv2.IMREAD_UNCHANGED)
        m = board_mask(white)
        if k == 1:
            out = HERE / "capture_1"
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            for f in sorted(d.glob("*.png")):
                cv2.imwrite(str(out / f.name), cv2.imread(str(f), cv2.IMREAD_UNCHANGED) * m, png)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            cap = Path(tmp) / "cap"
            import_opencv_graycode(d, cap, 2048, 1536, 2)
            res = decode(load_capture(cap))
        cv2.imwrite(str(HERE / "decoded" / f"capture_{k}_white.png"), white * m, png)
        for axis, a in (("column", res.column), ("row", res.row)):
            cv2.imwrite(str(HERE / "decoded" / f"capture_{k}_{axis}.png"), encode_map(np.where(m > 0, a, np.nan)), png)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
