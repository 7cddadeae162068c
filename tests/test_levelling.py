"""`calibrate level`: a calibration in a tilted, turned frame brought into the clinic's frame (SPEC §1)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from anklescan.core.measure.angles import compute_angles
from anklescan.core.calibration.file import Calibration, load_calibration, save_calibration
from anklescan.core.scan.capture import save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.hardware.sim_scene import Box, ObjectId, Plane, Scene, leg_scene
from anklescan.hardware.simrig import SimRig

ROOT = Path(__file__).resolve().parents[1]
TABLE_TOP_Z = 120.0


def run(*args):
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def reference_table_scene(centre=(0.0, 0.0), turn_deg=0.0) -> Scene:
    """The level reference table alone (220 x 320 mm top, long side along y) on its post, over the floor."""
    c = np.cos(np.radians(turn_deg))
    s = np.sin(np.radians(turn_deg))
    axes = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    table = Box(kind=ObjectId.TABLE, centre=(*centre, TABLE_TOP_Z - 12.5), axes=axes, half=(110.0, 160.0, 12.5))
    stand = Box(kind=ObjectId.STAND, centre=(*centre, (TABLE_TOP_Z - 25) / 2), half=(30.0, 30.0, (TABLE_TOP_Z - 25) / 2),
                albedo=0.25)
    return Scene([Plane(kind=ObjectId.FLOOR, albedo=0.5), table, stand])


def moved(cal: Calibration, Q: np.ndarray, q: np.ndarray) -> Calibration:
    """The same rig in the frame X' = Q X + q."""
    def dev(d):
        return d.with_pose(d.R @ Q.T, d.t - d.R @ Q.T @ q)
    return Calibration(dev(cal.camera), dev(cal.projector), {"source": "test: tilted, turned frame"})


@pytest.fixture(scope="module")
def table_scan(tmp_path_factory):
    work = tmp_path_factory.mktemp("level")
    rig = SimRig(reference_table_scene(), scale=0.25, seed=5)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    save_capture(work / "table", pset, rig.capture_many(render_all(pset)))
    return work, rig


def test_level_brings_a_tilted_turned_calibration_back_to_the_clinic_frame(table_scan):
    work, rig = table_scan
    true = rig.true_calibration()
    Q = Rotation.from_euler("zyx", [37.0, 8.0, -11.0], degrees=True).as_matrix()
    q = np.array([150.0, -80.0, 40.0])
    save_calibration(moved(true, Q, q), work / "tilted.json")
    done = run("calibrate", "level", work / "tilted.json", work / "table", "--out", work / "level.json")
    assert done.returncode == 0, done.stderr
    lev = load_calibration(work / "level.json")
    # clinic frame = the true world shifted up to the table top's centre
    M = lev.camera.R.T @ true.camera.R  # true world -> levelled frame
    m = lev.camera.R.T @ (true.camera.t - lev.camera.t)
    assert np.allclose(lev.projector.R.T @ true.projector.R, M, atol=1e-9)
    origin = np.linalg.solve(M, -m)
    # the origin matters to no angle; the top's edges each lose a pixel or two to the depth-edge
    # filter (~5 mm along y at this quarter scale, more at the far edge): 4.9 mm measured
    assert np.linalg.norm(origin - [0, 0, TABLE_TOP_Z]) < 8.0
    assert abs(origin[2] - TABLE_TOP_Z) < 0.2
    for inv, pf in ((0, 0), (20, 0), (0, 20), (-15, 10), (10, -20)):
        marks = {k: mk.centre for k, mk in leg_scene(inv, pf).marks.items()}
        want = compute_angles(marks)
        got = compute_angles({k: M @ v + m for k, v in marks.items()})
        for name in ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion"):
            assert abs(got[name]["value"] - want[name]["value"]) < 0.05, (inv, pf, name)
    meta = json.loads((work / "level.json").read_text())["levelled"]
    assert meta["capture"] == "table" and 300 < meta["table_top_mm"][0] < 325


def test_level_refuses_an_output_naming_an_input_and_a_scan_without_a_table(table_scan, tmp_path):
    work, rig = table_scan
    save_calibration(rig.true_calibration(), tmp_path / "cal.json")
    before = (tmp_path / "cal.json").read_bytes()
    done = run("calibrate", "level", tmp_path / "cal.json", work / "table", "--out", tmp_path / "cal.json")
    assert done.returncode == 2 and "is the input" in done.stderr
    assert (tmp_path / "cal.json").read_bytes() == before
    flat = SimRig(Scene([Plane(kind=ObjectId.FLOOR, albedo=0.5)]), scale=0.25, seed=2)
    pset = make_pattern_set("default", flat.projector.width, flat.projector.height)
    save_capture(tmp_path / "floor", pset, flat.capture_many(render_all(pset)))
    done = run("calibrate", "level", tmp_path / "cal.json", tmp_path / "floor", "--out", tmp_path / "out.json")
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    assert not (tmp_path / "out.json").exists()
