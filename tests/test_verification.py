import numpy as np
import pytest

from anklescan.core.calibration.procedures import box as cb
from anklescan.core.calibration.procedures import verification as ver
from anklescan.core.errors import CalibrationError
from anklescan.core.scan.triangulate import triangulate_points


def _true_cal(scale=0.25):
    sim = pytest.importorskip("anklescan.hardware.simrig")
    return sim.SimRig(scale=scale).true_calibration()


def test_exact_projections_triangulate_to_the_points():
    cal = _true_cal()
    X = np.concatenate(list(cb.marker_corners_world().values()))
    got = triangulate_points(cal, cal.camera.project(X), cal.projector.project(X))
    assert np.abs(got - X).max() < 1e-6


def test_perfect_centres_pass_and_a_scale_error_fails():
    truth = ver.true_centres()
    ok = ver.compare_distances(dict(truth))
    assert ok.passed and ok.rms_mm < 1e-9 and len(ok.pairs) == 27 * 26 // 2
    scaled = {k: 1.002 * v for k, v in truth.items()}  # 0.2 % too large: ~0.5 mm over 250 mm
    bad = ver.compare_distances(scaled)
    assert not bad.passed and bad.mean_mm > 0.3
    assert "FAIL" in bad.format_text() and bad.to_dict()["n_pairs"] == len(bad.pairs)


def test_too_few_markers_is_one_line_error():
    truth = ver.true_centres()
    with pytest.raises(CalibrationError, match="at least"):
        ver.compare_distances({k: truth[k] for k in range(3)})


def test_verification_scan_of_simulated_box_with_true_calibration(tmp_path):
    """The floor of the method at scale 0.5: the true calibration, a simulated scan of the box."""
    sim = pytest.importorskip("anklescan.hardware.simrig")
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.sim_scene import box_scene_objects, quad_scene

    rig = sim.SimRig(quad_scene(box_scene_objects()), scale=0.5)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column", "row"))
    save_capture(tmp_path / "box", pset, rig.capture_many(render_all(pset)))
    res = ver.verify_box_capture(tmp_path / "box", rig.true_calibration())
    assert len(res.centres) >= 18
    # docs/calibration_app.md: 0.023 mm RMS, 0.075 mm worst at scale 0.5 (0.20 / 0.76 mm with
    # cornerSubPix corners and windows crossing onto the next face)
    assert res.rms_mm <= 0.06 and res.max_abs_mm <= 0.2 and res.passed
