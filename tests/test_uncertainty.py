"""The calibrated volume, the parameters' covariance and the honest ± (SPEC §3, §4, §6)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_uncertainty as bench  # noqa: E402

from anklescan.core.calibration.model.file import (  # noqa: E402
    Calibration,
    calibrated_volume,
    load_calibration,
    parameter_covariance,
    save_calibration,
)
from anklescan.core.calibration.procedures.levelling import apply_level  # noqa: E402
from anklescan.core.errors import CalibrationError  # noqa: E402
from anklescan.core.measure.angles import compute_angles  # noqa: E402
from anklescan.core.measure.measure_warnings import WarningContext, measure_warnings  # noqa: E402
from anklescan.core.measure.uncertainty import calibration_jacobian, position_uncertainty  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def truth() -> Calibration:
    return bench.true_rig()


@pytest.fixture(scope="module")
def table_box(truth: Calibration) -> Calibration:
    return bench.noisy_calibration(truth, bench.box_points((0.0,)), 0.2, np.random.default_rng(11))


@pytest.fixture(scope="module")
def two_boxes(truth: Calibration) -> Calibration:
    return bench.noisy_calibration(truth, bench.box_points((0.0, 300.0)), 0.2, np.random.default_rng(12))


def test_volume_is_the_span_of_the_control_points(table_box: Calibration, two_boxes: Calibration) -> None:
    X = bench.box_points((0.0,))
    vol = calibrated_volume(table_box)
    np.testing.assert_allclose(vol.min, X.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(vol.max, X.max(axis=0), atol=1e-3)
    assert calibrated_volume(two_boxes).max[2] > vol.max[2] + 150  # the raised box's points that the rig sees


def test_covariance_predicts_the_spread_of_calibrations(truth: Calibration) -> None:
    """The recorded covariance, propagated to a point, matches the spread over repeated calibrations."""
    P = np.array([[0.0, 0.0, 250.0], [100.0, -80.0, 150.0]])
    uv, u = truth.camera.project(P), truth.projector.project(P)[:, 0]
    from anklescan.core.scan.triangulate import triangulate_points

    errs, preds = [], []
    for seed in range(12):
        cal = bench.noisy_calibration(truth, bench.box_points((0.0,)), 0.3, np.random.default_rng(seed))
        Y = triangulate_points(cal, uv, u)
        cov = parameter_covariance(cal)
        J = calibration_jacobian(cal, cov, Y)
        preds.append(np.sqrt(np.diag(J @ cov.matrix @ J.T)))
        errs.append((Y - P).ravel())
    spread = np.std(np.array(errs) - np.mean(errs, axis=0), axis=0)
    ratio = spread / np.mean(preds, axis=0)
    assert 0.5 < np.median(ratio) < 1.5, ratio


def test_round_trip_and_old_files_load(tmp_path: Path, table_box: Calibration, truth: Calibration) -> None:
    save_calibration(table_box, tmp_path / "new.json")
    back = load_calibration(tmp_path / "new.json")
    assert parameter_covariance(back).parameters == parameter_covariance(table_box).parameters
    save_calibration(truth, tmp_path / "old.json")  # no volume, no covariance: as before this change
    old = load_calibration(tmp_path / "old.json")
    assert calibrated_volume(old) is None and parameter_covariance(old) is None
    marks = bench.true_marks((0.0, 0.0))
    joint, shares = position_uncertainty(old, marks, {k: np.eye(3) * 0.01 for k in marks})
    np.testing.assert_allclose(joint.matrix, np.kron(np.eye(7), np.eye(3) * 0.01))
    assert measure_warnings(WarningContext(marks, old)) == []


@pytest.mark.parametrize("bad", [{"min": [0, 0], "max": [1, 1, 1]}, {"min": [0, 0, 5], "max": [1, 1, 1]}, "box"])
def test_malformed_volume_is_refused(tmp_path: Path, truth: Calibration, bad: object) -> None:
    obj = json.loads(json.dumps({"units": "mm"}))
    save_calibration(truth, tmp_path / "c.json")
    obj = json.loads((tmp_path / "c.json").read_text())
    obj["volume"] = bad
    (tmp_path / "c.json").write_text(json.dumps(obj))
    with pytest.raises(CalibrationError, match="volume"):
        load_calibration(tmp_path / "c.json")


def test_level_moves_volume_and_keeps_the_covariance_meaning(table_box: Calibration) -> None:
    a = math.radians(20.0)
    A = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    o = np.array([30.0, -50.0, 120.0])
    new = apply_level(table_box, A, o, {})
    P = np.array([[10.0, -30.0, 520.0], [80.0, -100.0, 121.0]])
    P_new = (P - o) @ A  # old = A @ new + o
    vol_old, vol_new = calibrated_volume(table_box), calibrated_volume(new)
    for p, q in zip(P, P_new, strict=True):
        assert vol_new.outside(q).distance_mm <= vol_old.outside(p).distance_mm + 1e-6  # the new box holds the old
    C_old = calibration_jacobian(table_box, parameter_covariance(table_box), P)
    C_old = C_old @ parameter_covariance(table_box).matrix @ C_old.T
    J_new = calibration_jacobian(new, parameter_covariance(new), P_new)
    C_new = J_new @ parameter_covariance(new).matrix @ J_new.T
    R = np.kron(np.eye(2), A.T)
    np.testing.assert_allclose(C_new, R @ C_old @ R.T, rtol=2e-3, atol=1e-6)


def test_warnings_name_the_knee_marks_with_the_table_box_only(table_box: Calibration, two_boxes: Calibration) -> None:
    for posture in ((0.0, 0.0), (15.0, -10.0)):
        marks = bench.true_marks(posture)
        lines = measure_warnings(WarningContext(marks, table_box))
        assert [int(line.split()[1]) for line in lines] == [1, 3], lines
        assert all("outside the calibrated volume (above it)" in w and "knee's height" in w for w in lines)
        assert measure_warnings(WarningContext(marks, two_boxes)) == []


def test_motion_enters_the_sd_as_a_position_uncertainty(truth: Calibration) -> None:
    """Without a covariance or volume, leg inversion's SD is the motion's alone: σ √2 / |P1 - P2| in x-z."""
    marks = bench.true_marks((5.0, 5.0))
    joint, _ = position_uncertainty(truth, marks, None, motion_value_mm=0.6, motion_sd_mm_=0.1)
    sd = compute_angles(marks, 0.0, joint=joint)["leg_inversion"].sd
    sigma = math.sqrt(0.6**2 / 3 + 0.1**2)
    d = marks[1] - marks[2]
    assert sd == pytest.approx(math.degrees(sigma * math.sqrt(2) / math.hypot(d[0], d[2])), rel=1e-4)


def test_coverage_on_a_small_seeded_sweep() -> None:
    """Calibrations with 0.1 and 0.3 px noise, box on the table and at two heights, six postures."""
    rows = bench.sweep(2, (0.1, 0.3), 300.0, 0.05)
    z = np.array([abs(r["err"]) / r["sd"] for r in rows])
    assert len(rows) == 2 * 2 * 2 * len(bench.POSTURES) * 4
    assert 0.90 <= np.mean(z <= 2.0) <= 0.98, np.mean(z <= 2.0)


def test_coverage_with_board_calibrations() -> None:
    """The same with chessboard calibrations (another model: no model term, its covariance alone)."""
    rows = bench.sweep(1, (0.1, 0.3), 300.0, 0.05, board=True, boxes_too=False)
    z = np.array([abs(r["err"]) / r["sd"] for r in rows])
    assert len(rows) == 2 * len(bench.POSTURES) * 4
    assert np.mean(z <= 2.0) >= 0.90 and z.max() < 3.0, (np.mean(z <= 2.0), z.max())


def _csv(path: Path, header: str, rows: np.ndarray) -> None:
    path.write_text(header + "\n" + "\n".join(",".join(f"{v:.6f}" for v in r) for r in rows) + "\n")


def test_cli_calibrate_points_takes_several_files(tmp_path: Path, truth: Calibration) -> None:
    rng = np.random.default_rng(3)
    parts = []
    for k, h in enumerate((0.0, 300.0)):
        X = bench.box_points((h,))
        uv, col = truth.camera.project(X), truth.projector.project(X)
        ok = ((uv >= 0) & (uv <= [truth.camera.width - 1, truth.camera.height - 1])).all(1) \
            & (col[:, 0] >= 0) & (col[:, 0] <= truth.projector.width - 1)
        X, uv, u = X[ok], uv[ok] + rng.normal(0, 0.1, (ok.sum(), 2)), col[ok, 0] + rng.normal(0, 0.1, ok.sum())
        _csv(tmp_path / f"cam{k}.csv", "X,Y,Z,u,v", np.column_stack([X, uv]))
        _csv(tmp_path / f"proj{k}.csv", "X,Y,Z,u", np.column_stack([X, u]))
        parts.append(X)

    def cli(*args: object) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)

    d = tmp_path
    both = cli("calibrate", "points", "--camera", d / "cam0.csv", d / "cam1.csv", "--projector", d / "proj0.csv",
               "--projector", d / "proj1.csv", "--out", d / "both.json")
    assert both.returncode == 0, both.stderr
    vol = calibrated_volume(load_calibration(d / "both.json"))
    np.testing.assert_allclose(vol.max, np.vstack(parts).max(axis=0), atol=1e-3)
    one = cli("calibrate", "points", "--camera", d / "cam0.csv", "--projector", d / "proj0.csv",
              "--out", d / "one.json")
    assert one.returncode == 0, one.stderr
    np.testing.assert_allclose(calibrated_volume(load_calibration(d / "one.json")).max, parts[0].max(axis=0), atol=1e-3)
    same = cli("calibrate", "points", "--camera", d / "cam0.csv", d / "cam0.csv", "--projector", d / "proj0.csv",
               "--out", d / "same.json")
    assert same.returncode == 2 and len(same.stderr.strip().splitlines()) == 1 and "Traceback" not in same.stderr
    assert not (d / "same.json").exists()


@pytest.mark.slow
def test_measure_writes_the_warnings_and_an_honest_sd(tmp_path: Path) -> None:
    """A rendered capture of the leg (0.5 scale) measured with the table box's calibration, then
    with the box at two heights: RESULT.json names marks 1 and 3, then nothing; every angle within
    2.5 SD of the truth."""
    from anklescan.core.measure.pipeline import run_measure
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.sim_scene import angles_from_marks, leg_scene
    from anklescan.hardware.simrig import SimRig

    scene = leg_scene(6.0, 8.0, leg_offset_deg=(-2.5, 1.0))
    rig = SimRig(scene, scale=0.5, seed=8)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column",))
    save_capture(tmp_path / "cap", pset, rig.capture_many(render_all(pset)))
    truth = angles_from_marks({k: m.centre for k, m in scene.marks.items()})
    for name, raises, named in (("table", (0.0,), [1, 3]), ("both", (0.0, 300.0), [])):
        cal = bench.noisy_calibration(rig.true_calibration(), bench.box_points(raises), 0.1, np.random.default_rng(5))
        save_calibration(cal, tmp_path / f"{name}.json")
        run_measure(tmp_path / "cap", tmp_path / f"{name}.json", tmp_path / f"{name}-result.json")
        result = json.loads((tmp_path / f"{name}-result.json").read_text(encoding="utf-8"))
        volume = [w for w in result["warnings"] if "outside the calibrated volume" in w]
        assert [int(w.split()[1]) for w in volume] == named, result["warnings"]
        for angle, v in result["angles"].items():
            assert abs(v["value"] - truth[angle]) <= 2.5 * v["sd"], (name, angle, v, truth[angle])
        outside = result["mark_uncertainty"]["1"]["outside_volume_mm"]
        assert (outside > 50) if named else (outside == 0), outside


def test_the_store_keeps_the_honest_sd(tmp_path: Path, table_box: Calibration) -> None:
    """store.results.update_marks with the measurement's joint covariance: the trial's *_sd columns (the
    CSV's) hold the SD computed from it, not the per-mark default."""
    from anklescan.core.records.store import Store

    marks = bench.true_marks((4.0, -6.0))
    joint, _ = position_uncertainty(table_box, marks, {k: np.eye(3) * 0.01 for k in marks})
    want = compute_angles(marks, 0.0, joint=joint)
    with Store.open(tmp_path / "s.sqlite") as s:
        s.patients.add("P-001", sprain_count=0)
        ses = s.sessions.start("P-001", condition="barefoot")
        t = s.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0)
        s.results.update_marks(t.id, {k: list(v) for k, v in marks.items()}, "auto", "test", sigma_mm=0.0, joint=joint)
        got = s.trials.get(t.id)
    for name in ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion"):
        assert getattr(got, f"{name}_sd") == pytest.approx(want[name].sd, rel=1e-9)
    assert got.leg_inversion_sd != pytest.approx(compute_angles(marks)["leg_inversion"].sd, rel=0.05)


def test_warnings_are_one_line_each_and_extendable(two_boxes: Calibration) -> None:
    from anklescan.core.measure.measure_warnings import CHECKS, warnings_by_mark

    marks = bench.true_marks((0.0, 0.0))
    ctx = WarningContext(marks, two_boxes, "overexposed: mark 5 saturates the camera")
    assert measure_warnings(ctx) == ["overexposed: mark 5 saturates the camera"]
    extra = measure_warnings(ctx, [*CHECKS, lambda c: [f"{len(c.marks)} marks"]])
    assert extra[-1] == "7 marks" and all("\n" not in w for w in extra)
    far = {**marks, 2: marks[2] + [0.0, 0.0, -400.0]}
    lines = measure_warnings(WarningContext(far, two_boxes))
    assert warnings_by_mark(lines) == {2: lines} and "(below it)" in lines[0] and "this mark's height" in lines[0]
