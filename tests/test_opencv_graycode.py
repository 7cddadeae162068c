"""`anklescan import opencv-graycode` on the simulated rig: OpenCV's GrayCodePattern order and bit
convention written out here independently of anklescan.core.scan.patterns, photographed, imported, decoded."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.core.errors import CaptureError
from anklescan.core.scan.capture import load_capture
from anklescan.core.scan.decode import decode
from anklescan.core.scan.opencv_graycode import import_opencv_graycode
from anklescan.hardware.simrig import SimRig

ROOT = Path(__file__).resolve().parents[1]


def opencv_frames(width: int, height: int, step: int) -> list[np.ndarray]:
    """What procam-calibration's gen_graycode_imgs.py projects: OpenCV's GrayCodePattern.generate()
    at (width/step, height/step), each code pixel blown up to step x step projector pixels."""
    cw, ch = -(-width // step), -(-height // step)
    out = []
    for n, size, axis in ((math.ceil(math.log2(cw)), width, 1), (math.ceil(math.log2(ch)), height, 0)):
        code = np.arange(size) // step
        gray = code ^ (code >> 1)
        for b in range(n):
            bit = ((gray >> (n - 1 - b)) & 1).astype(np.uint8) * 255  # MSB first, white where 1
            for img in (bit, 255 - bit):
                out.append(np.broadcast_to(img[None, :] if axis else img[:, None], (height, width)).copy())
    out += [np.full((height, width), 255, np.uint8), np.zeros((height, width), np.uint8)]
    return out


@pytest.mark.parametrize("step", [1, 2])
def test_imported_opencv_capture_decodes_to_the_true_projector_pixels(tmp_path, step):
    rig = SimRig(scale=0.25, seed=7)
    W, H = rig.projector.width, rig.projector.height
    src = tmp_path / "opencv"
    src.mkdir()
    for i, img in enumerate(opencv_frames(W, H, step)):
        cv2.imwrite(str(src / f"graycode_{i:02d}.png"), rig.capture(img))
    done = subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", "import", "opencv-graycode", src, "--projector",
                           f"{W}x{H}", "--step", str(step), "--out", tmp_path / "cap"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    d = decode(load_capture(tmp_path / "cap"))
    truth = rig.truth()
    ok = d.valid & truth.lit & np.isfinite(d.row)
    assert ok.mean() > 0.3
    # a code is the centre of its step x step block: within step/2 of the truth, plus a little blur
    for got, want in ((d.column, truth.proj_uv[..., 0]), (d.row, truth.proj_uv[..., 1])):
        err = np.abs(got[ok] - want[ok])
        assert np.median(err) < 0.5 * step + 0.3 and np.mean(err > step + 1.5) < 0.01


def test_import_refuses_an_unreadable_frame_and_writes_nothing(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    frames = opencv_frames(8, 4, 1)  # 3 column bits, 2 row bits: 12 frames
    for i, img in enumerate(frames):
        cv2.imwrite(str(src / f"f{i}.png"), img)
    (src / "f11.png").write_bytes(b"not a png")
    with pytest.raises(CaptureError, match="unreadable"):
        import_opencv_graycode(src, tmp_path / "out", 8, 4, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no output, no temporary
    (src / "f11.png").unlink()
    with pytest.raises(CaptureError, match="11 images"):
        import_opencv_graycode(src, tmp_path / "out", 8, 4, 1)


def test_cli_import_names_the_users_damaged_frame_not_a_temporary(tmp_path):
    """The line named our hidden copy (".out.zg8gjrdz.tmp/f11.png"), a file the user cannot find."""
    src = tmp_path / "src"
    src.mkdir()
    for i, img in enumerate(opencv_frames(8, 4, 1)):
        cv2.imwrite(str(src / f"f{i:02d}.png"), img)
    (src / "f11.png").write_bytes((src / "f11.png").read_bytes()[:60])  # truncated
    done = subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", "import", "opencv-graycode", str(src),
                           "--projector", "8x4", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert str(src / "f11.png") in done.stderr and ".tmp" not in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_cli_import_into_a_link_to_an_empty_folder_is_one_clear_line(tmp_path):
    """--out naming a symbolic link to an empty folder failed after copying every frame, with
    "Not a directory (out)"; now refused first, as every folder output refuses a link."""
    src = tmp_path / "src"
    src.mkdir()
    for i, img in enumerate(opencv_frames(8, 4, 1)):
        cv2.imwrite(str(src / f"f{i:02d}.png"), img)
    (tmp_path / "empty").mkdir()
    (tmp_path / "out").symlink_to("empty")
    done = subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", "import", "opencv-graycode", str(src),
                           "--projector", "8x4", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and "symbolic link" in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "out", "src"] and not any((tmp_path / "empty").iterdir())
