"""The SPEC §4 calibration file: round trip and a clear error for every malformed case."""

import copy
import json

import numpy as np
import pytest

from anklescan.core.calibration.model.file import calibration_from_dict, calibration_to_dict, load_calibration, save_calibration
from anklescan.core.errors import CalibrationError
from anklescan.hardware.simrig import SimRig


@pytest.fixture(scope="module")
def good():
    return calibration_to_dict(SimRig(scale=0.25).true_calibration())


def test_round_trip_is_exact(tmp_path, good):
    path = tmp_path / "cal.json"
    save_calibration(calibration_from_dict(good), path)
    again = load_calibration(path)
    for dev in ("camera", "projector"):
        for key in ("K", "dist", "R", "t"):
            assert np.array_equal(np.asarray(getattr(getattr(again, dev), key)), np.asarray(good[dev][key]))
    assert json.loads(path.read_text())["units"] == "mm"
    assert not list(tmp_path.glob(".*tmp"))


def _broken(good, edit):
    obj = copy.deepcopy(good)
    edit(obj)
    return obj


@pytest.mark.parametrize("edit, message", [
    (lambda o: o.pop("projector"), "missing 'projector'"),
    (lambda o: o["camera"].pop("K"), "camera is missing 'K'"),
    (lambda o: o["camera"].__setitem__("K", [[1, 0, 0], [0, 1, 0]]), r"camera.K has shape \[2, 3\]"),
    (lambda o: o["projector"].__setitem__("R", [[1, 0, 0], [0, 2, 0], [0, 0, 1]]), "projector.R is not a rotation"),
    (lambda o: o["camera"].__setitem__("R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "camera.R is not a rotation"),
    (lambda o: o["camera"].__setitem__("t", [1, 2]), r"camera.t has shape \[2\]"),
    (lambda o: o["camera"].__setitem__("t", ["a", 2, 3]), "camera.t is not numeric"),
    (lambda o: o["camera"].__setitem__("width", -5), "camera.width must be a positive integer"),
    (lambda o: o["camera"].__setitem__("dist", [0, 0, 0, 0, 0, 0, 0]), "camera.dist must be up to 5"),
    (lambda o: o.__setitem__("units", "inch"), "units must be 'mm'"),
    (lambda o: o["projector"].__setitem__("axis", "row"), "projector.axis must be one of"),
])
def test_malformed_calibration_is_one_clear_line(good, edit, message):
    with pytest.raises(CalibrationError, match=message) as err:
        calibration_from_dict(_broken(good, edit))
    assert "\n" not in str(err.value)


def test_column_axis_with_unknown_row_intrinsics(good):
    obj = _broken(good, lambda o: o["projector"].update(axis="column", K=[o["projector"]["K"][0], None, [0, 0, 1]]))
    cal = calibration_from_dict(obj)
    assert cal.projector.axis == "column" and cal.projector.fy == cal.projector.fx


def test_unreadable_files(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(bad)
