"""Real photographs from another lab (tests/data/procam-calibration, MIT licence; see its README).

A printed 9x7-corner chessboard of 75 mm squares at 2.9-3.7 m, under OpenCV Gray codes from a
projector ~630 mm above the camera.  The board calibration uses two captures; the third is
measured: the pitch of its corners from 3-D (corner rays met with the board's fitted plane) and
the board's flatness.  docs/real-data.md has the figures and how they were made.
"""

from __future__ import annotations

import filecmp
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.core.calibration.procedures.board import calibrate_board_views, observe_board, observe_board_maps
from anklescan.core.calibration.procedures.board_metrics import measure_board, triangulate_both
from anklescan.core.scan.capture import load_capture
from anklescan.core.scan.decode import decode
from anklescan.core.scan.opencv_graycode import import_opencv_graycode

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "procam-calibration"
sys.path.insert(0, str(DATA))
from make_test_data import decode_map  # noqa: E402

COLS, ROWS, SQUARE = 9, 7, 75.0
PROJECTOR = (2048, 1536)  # covers every code at graycode_step 2 (the README)


def run(*args):
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def capture_1(tmp_path_factory):
    out = tmp_path_factory.mktemp("real") / "capture_1"
    import_opencv_graycode(DATA / "capture_1", out, *PROJECTOR, step=2)
    cap = load_capture(out)
    return cap, decode(cap)


def _map_view(k: int):
    read = lambda what: cv2.imread(str(DATA / "decoded" / f"capture_{k}_{what}.png"), cv2.IMREAD_UNCHANGED)  # noqa: E731
    return observe_board_maps(read("white"), decode_map(read("column")), decode_map(read("row")),
                              COLS, ROWS, 2.0, f"capture_{k}")


def _measure(cal, cap, d):
    corners = observe_board(cap, COLS, ROWS, decoded=d).corners
    ok = d.valid & np.isfinite(d.row)
    v, u = np.nonzero(ok)
    pix = np.stack([u, v], axis=1)
    X, noise = triangulate_both(cal, pix.astype(float), np.stack([d.column[ok], d.row[ok]], 1).astype(float),
                                2 / np.sqrt(12))  # Gray code only: a code spans 2 projector px
    return measure_board(cal, X, pix, noise, corners, cap.shape, COLS, ROWS, SQUARE)


def test_cli_import_copies_the_frames_and_decodes_the_board(tmp_path):
    out = tmp_path / "képek capture"  # non-ASCII, spaces
    before = sorted(p.name for p in (DATA / "capture_1").iterdir())
    done = run("import", "opencv-graycode", DATA / "capture_1", "--projector", "2048x1536", "--step", "2",
               "--out", out)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (DATA / "capture_1").iterdir()) == before  # the source is untouched
    m = json.loads((out / "manifest.json").read_text())
    assert m["axes"] == ["column", "row"] and len(m["frames"]) == 42
    assert m["frames"][0] == {"file": "graycode_00.png", "kind": "gray", "axis": "column", "bit": 0, "bits": 10,
                              "stripe": 2, "inverse": False}
    assert m["frames"][21]["axis"] == "row" and m["frames"][21]["inverse"]
    assert m["frames"][40]["kind"] == "white" and m["frames"][41]["kind"] == "black"
    assert all(filecmp.cmp(DATA / "capture_1" / f, out / f, shallow=False) for f in before)
    d = decode(load_capture(out))
    corners = observe_board(load_capture(out), COLS, ROWS, decoded=d).corners
    inside = np.zeros(d.valid.shape, np.uint8)
    cv2.fillConvexPoly(inside, corners[[0, COLS - 1, -1, -COLS]].astype(np.int32), 1)
    # on the board (black squares included) nearly every pixel decodes both axes
    both = d.valid & np.isfinite(d.row)
    assert both[inside > 0].mean() > 0.45  # the black squares reflect too little to decode (~half of them)
    # the row code runs down the image, the column code across (OpenCV's order, MSB first)
    c = corners.reshape(ROWS, COLS, 2)
    p = observe_board(load_capture(out), COLS, ROWS, decoded=d).proj.reshape(ROWS, COLS, 2)
    assert (np.sign(np.diff(p[..., 0], axis=1)) == np.sign(np.diff(c[..., 0], axis=1))).all()
    assert (np.sign(np.diff(p[..., 1], axis=0)) == np.sign(np.diff(c[..., 1], axis=0))).all()


def test_cli_import_refuses_a_wrong_projector_size_and_writes_nothing(tmp_path):
    out = tmp_path / "cap"
    done = run("import", "opencv-graycode", DATA / "capture_1", "--projector", "1024x768", "--step", "2", "--out", out)
    assert done.returncode == 2 and "38 frames" in done.stderr and "check --projector" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []
    done = run("import", "opencv-graycode", DATA / "capture_1", "--projector", "2048x1536", "--step", "2",
               "--out", DATA / "capture_1" / "inside")
    assert done.returncode == 2 and "input" in done.stderr
    assert not (DATA / "capture_1" / "inside").exists()


def test_board_calibration_from_two_captures_measures_the_third(capture_1):
    cap, d = capture_1
    result = calibrate_board_views([_map_view(0), _map_view(2)], COLS, ROWS, SQUARE, PROJECTOR)
    rep = result.report
    assert rep.camera.rms_px < 0.3 and rep.projector.rms_px < 0.5
    assert all(se is not None and np.isfinite(se) for se in rep.projector.std_errors.values())
    # the projector sits ~630 mm from the camera, along the image's vertical (the README)
    base = result.calibration.projector.center - result.calibration.camera.center
    assert 600 < np.linalg.norm(base) < 680
    m = _measure(result.calibration, cap, d)
    assert abs(m.pitch_error_pct) < 0.5, m
    assert m.flatness_rms_mm <= 3.5, m
    assert m.flatness_rms_mm < 1.5 * m.predicted_rms_mm, m  # no bending beyond the cloud's own noise


def test_author_calibration_imported_measures_the_board(capture_1, tmp_path):
    cap, d = capture_1
    done = run("calibrate", "import", DATA / "calibration_result.xml", "--projector", "2048x1536",
               "--out", tmp_path / "author.json")
    assert done.returncode == 0, done.stderr
    from anklescan.core.calibration.model.file import load_calibration

    cal = load_calibration(tmp_path / "author.json")
    assert np.allclose(cal.camera.R, np.eye(3)) and np.allclose(cal.camera.t, 0)  # world = camera
    m = _measure(cal, cap, d)
    assert abs(m.pitch_error_pct) < 1.5, m
    assert m.flatness_rms_mm <= 3.5, m


def test_measure_on_a_real_capture_without_marks_refuses_in_one_line(capture_1, tmp_path):
    """The command a user runs on another lab's photographs (a chessboard, no marks): exit 2, one
    line saying what the search saw, no RESULT.json."""
    cap, _ = capture_1
    assert run("calibrate", "import", DATA / "calibration_result.xml", "--projector", "2048x1536",
               "--out", tmp_path / "author.json").returncode == 0
    out = tmp_path / "RESULT.json"
    done = run("measure", cap.folder, "--calibration", tmp_path / "author.json", "--out", out)
    assert done.returncode == 2, done.stderr
    line = done.stderr.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line, line
    assert "marks not found" in line and "found 0 marks" in line and "candidate blob" in line, line
    assert not out.exists() and not list(tmp_path.glob("RESULT*"))


@pytest.mark.slow
def test_board_command_needs_two_views_and_a_findable_board(tmp_path, capture_1):
    cap, _ = capture_1
    done = run("calibrate", "board", cap.folder, "--board", "9x7", "--square", "75", "--out", tmp_path / "c.json")
    assert done.returncode == 2 and "two or more captures" in done.stderr, done.stderr
    done = run("calibrate", "board", cap.folder, cap.folder, "--board", "9x7", "--square", "75",
               "--out", tmp_path / "c.json")
    assert done.returncode == 2 and "twice" in done.stderr, done.stderr
    # OpenCV finds an 8x7 grid inside this 9x7 board: the wrong size is caught, not calibrated
    done = run("calibrate", "board", cap.folder, "--board", "8x7", "--square", "75", "--out", tmp_path / "c.json")
    assert done.returncode == 2 and "more inner corners than --board 8x7" in done.stderr, done.stderr
    assert not (tmp_path / "c.json").exists()


def test_board_command_refuses_a_copy_of_a_view(tmp_path, capture_1):
    """A copied capture is the same view: it calibrated (exit 0, fx 3022 ± 185 from one pose)."""
    cap, _ = capture_1
    copy = tmp_path / "copy of capture_1"
    shutil.copytree(cap.folder, copy)
    done = run("calibrate", "board", cap.folder, copy, "--board", "9x7", "--square", "75", "--out", tmp_path / "c.json")
    assert done.returncode == 2 and "copy of" in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    assert not (tmp_path / "c.json").exists()
