"""OpenCV FileStorage calibrations in and out (`calibrate import`, `calibrate export`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.core.calibration.model.file import load_calibration, save_calibration
from anklescan.core.calibration.procedures.opencv_calibration import (
    export_opencv_calibration,
    import_opencv_calibration,
    relative_pose,
)
from anklescan.core.errors import CalibrationError
from anklescan.hardware.simrig import SimRig

ROOT = Path(__file__).resolve().parents[1]


def run(*args):
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


@pytest.fixture(scope="module")
def cal():
    return SimRig(scale=0.25).true_calibration()


def _write_stereo(path: Path, cal, rvec: bool = False, size: bool = True) -> None:
    R, T = relative_pose(cal)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if size:
        fs.write("image_size", np.array([cal.camera.width, cal.camera.height], np.float64))
    fs.write("K1", cal.camera.K)
    fs.write("D1", cal.camera.dist.reshape(1, 5))
    fs.write("K2", cal.projector.K)
    fs.write("D2", np.r_[cal.projector.dist, 0.0, 0.0, 0.0].reshape(1, 8))  # 8 terms, the rational ones zero
    fs.write("R", cv2.Rodrigues(R)[0] if rvec else R)
    fs.write("T", T.reshape(3, 1) / 1000.0)
    fs.release()


@pytest.mark.parametrize("rvec", [False, True])
def test_stereo_names_give_the_rig_in_the_camera_frame(tmp_path, cal, rvec):
    _write_stereo(tmp_path / "stereo.yml", cal, rvec)
    got = import_opencv_calibration(tmp_path / "stereo.yml", (cal.projector.width, cal.projector.height), unit="m")
    assert np.allclose(got.camera.R, np.eye(3)) and np.allclose(got.camera.t, 0)
    R, T = relative_pose(cal)
    assert np.allclose(got.projector.R, R, atol=1e-9) and np.allclose(got.projector.t, T, atol=1e-6)
    assert np.allclose(got.projector.dist, cal.projector.dist)
    assert (got.camera.width, got.camera.height) == (cal.camera.width, cal.camera.height)
    # distances between the devices survive the change of frame
    assert np.isclose(np.linalg.norm(got.projector.center), np.linalg.norm(cal.projector.center - cal.camera.center))


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_export_then_import_keeps_our_world_frame(tmp_path, cal, suffix):
    out = export_opencv_calibration(cal, tmp_path / f"ours{suffix}")
    back = import_opencv_calibration(out, (cal.projector.width, cal.projector.height))
    for a, b in ((back.camera, cal.camera), (back.projector, cal.projector)):
        assert np.allclose(a.R, b.R, atol=1e-12) and np.allclose(a.t, b.t, atol=1e-9)
        assert np.allclose(a.K, b.K) and np.allclose(a.dist, b.dist)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)  # what another tool reads
    R, T = relative_pose(cal)
    assert np.allclose(fs.getNode("R").mat(), R) and np.allclose(fs.getNode("T").mat().ravel(), T)
    assert np.allclose(fs.getNode("K1").mat(), cal.camera.K)


def test_bad_files_are_one_line_errors(tmp_path, cal):
    (tmp_path / "junk.yml").write_text("this is not: [a calibration\n")
    with pytest.raises(CalibrationError):
        import_opencv_calibration(tmp_path / "junk.yml", (1024, 768))
    _write_stereo(tmp_path / "nosize.yml", cal, size=False)
    with pytest.raises(CalibrationError, match="--camera WxH"):
        import_opencv_calibration(tmp_path / "nosize.yml", (1024, 768))
    assert import_opencv_calibration(tmp_path / "nosize.yml", (1024, 768), camera_size=(400, 300),
                                     unit="m").camera.width == 400
    fs = cv2.FileStorage(str(tmp_path / "half.xml"), cv2.FILE_STORAGE_WRITE)
    fs.write("K1", cal.camera.K)
    fs.release()
    done = run("calibrate", "import", tmp_path / "half.xml", "--projector", "1024x768", "--camera", "400x300",
               "--out", tmp_path / "out.json")
    assert done.returncode == 2 and "K2" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out.json").exists()


def test_cli_export_and_its_guards(tmp_path, cal):
    save_calibration(cal, tmp_path / "cal.json")
    done = run("calibrate", "export", tmp_path / "cal.json", "--out", tmp_path / "cal.txt")
    assert done.returncode == 2 and "suffix" in done.stderr
    done = run("calibrate", "export", tmp_path / "cal.json", "--out", tmp_path / "cal.json")
    assert done.returncode == 2 and "is the input" in done.stderr
    done = run("calibrate", "export", tmp_path / "cal.json", "--out", tmp_path / "cal.yml")
    assert done.returncode == 0, done.stderr
    done = run("calibrate", "import", tmp_path / "cal.yml", "--projector", "256x192", "--out", tmp_path / "back.json")
    assert done.returncode == 0, done.stderr
    back = load_calibration(tmp_path / "back.json")
    assert np.allclose(back.projector.t, cal.projector.t, atol=1e-9)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["back.json", "cal.json", "cal.yml"]  # no temporaries


def test_cli_import_refuses_a_camera_size_the_file_contradicts(tmp_path, cal):
    """--camera 640x480 for a file saying 256x192 wrote a calibration of no camera (the file's
    intrinsics on another sensor), exit 0; now one line naming both sizes, nothing written."""
    save_calibration(cal, tmp_path / "cal.json")
    assert run("calibrate", "export", tmp_path / "cal.json", "--out", tmp_path / "cal.yml").returncode == 0
    w, h = cal.camera.width, cal.camera.height
    done = run("calibrate", "import", tmp_path / "cal.yml", "--projector", "256x192", "--camera", f"{2 * w}x{2 * h}",
               "--out", tmp_path / "back.json")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"{w}x{h}" in done.stderr and f"{2 * w}x{2 * h}" in done.stderr, done.stderr
    assert not (tmp_path / "back.json").exists()
    done = run("calibrate", "import", tmp_path / "cal.yml", "--projector", "256x192", "--camera", f"{w}x{h}",
               "--out", tmp_path / "back.json")
    assert done.returncode == 0, done.stderr  # the same size said twice is fine


def test_cli_import_of_a_folder_says_it_is_a_folder(tmp_path):
    """A folder given as FILE was "not found", though the user can see it."""
    (tmp_path / "stereo").mkdir()
    done = run("calibrate", "import", tmp_path / "stereo", "--projector", "1024x768", "--out", tmp_path / "c.json")
    assert done.returncode == 2 and "is a folder" in done.stderr and "not found" not in done.stderr, done.stderr


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_a_column_only_projector_stays_column_only_through_export_and_import(tmp_path, cal, suffix):
    """SPEC §4: a projector calibrated from vertical stripes only has no row intrinsics ("axis":
    "column"). Exported and imported back it came out as a 2-D projector whose nominal K2 row was
    taken for calibrated: row stripes would have been triangulated with made-up geometry."""
    import json

    from anklescan.core.calibration.model.file import calibration_to_dict

    obj = calibration_to_dict(cal)
    obj["projector"]["axis"] = "column"
    obj["projector"]["K"][1] = None
    (tmp_path / "ours.json").write_text(json.dumps(obj))
    assert run("calibrate", "export", tmp_path / "ours.json", "--out", tmp_path / f"col{suffix}").returncode == 0
    done = run("calibrate", "import", tmp_path / f"col{suffix}", "--projector",
               f"{cal.projector.width}x{cal.projector.height}", "--out", tmp_path / "back.json")
    assert done.returncode == 0, done.stderr
    back = load_calibration(tmp_path / "back.json")
    assert back.projector.axis == "column"
    assert np.allclose(back.projector.K[0], cal.projector.K[0]) and np.allclose(back.projector.t, cal.projector.t)
