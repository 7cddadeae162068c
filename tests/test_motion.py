"""Motion during a scan (issue 18): the swaying simulator, the motion references in the pattern
set, the estimate against the simulator's truth, and the flag in the result, the database and
the report. Small resolution (scale 0.25): the figures at scale 0.5 are in docs/performance.md."""

import json
import math

import numpy as np
import pytest

from anklescan.core.calibration.model.file import save_calibration
from anklescan.core.errors import AnkleScanError, CaptureError
from anklescan.core.measure.pipeline import measure_capture, run_measure
from anklescan.core.records.store import Store
from anklescan.core.scan.capture import load_capture, save_capture
from anklescan.core.scan.decode import decode
from anklescan.core.scan.motion import default_motion_refs, estimate_motion, motion_looks, scan_duration_s
from anklescan.core.scan.patterns import PatternSet, make_pattern_set, render_all
from anklescan.core.scan.reconstruct import cloud_from_decoded
from anklescan.hardware.sim_scene import ObjectId, leg_scene
from anklescan.hardware.sim_sway import (
    FRAME_S,
    CombinedSway,
    Sway,
    SwayClock,
    SwayShape,
    ankle_of,
    swaying_capture,
    true_largest_displacement,
)
from anklescan.hardware.simrig import SimRig

SCALE = 0.25


def _scan(tmp_path, name, sway_mm, axis="forward", posture=(0.0, 0.0), seed=5):
    rig = SimRig(leg_scene(*posture), scale=SCALE, seed=seed)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height,
                            motion_refs=default_motion_refs("default"))
    sway = Sway.drift(sway_mm, len(pset.frames) * FRAME_S["webcam"], axis)
    frames, times = swaying_capture(rig, render_all(pset), sway, FRAME_S["webcam"])
    capture = load_capture(save_capture(tmp_path / name, pset, frames, metadata={"duration_s": times[-1]}))
    return rig, capture, true_largest_displacement(rig, sway, times)


@pytest.fixture(scope="module")
def still(tmp_path_factory):
    return _scan(tmp_path_factory.mktemp("still"), "c", 0.0, posture=(20.0, -20.0))


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    return _scan(tmp_path_factory.mktemp("moved"), "c", 2.0, "forward")


def test_pattern_set_repeats_phase_pairs_and_the_manifest_says_so():
    pset = make_pattern_set("default", 1024, 768, motion_refs=3)
    repeats = [f for f in pset.frames if f.kind == "repeat"]
    assert len(pset.frames) == 36 and len(repeats) == 6
    assert pset.frames[0].kind == pset.frames[1].kind == pset.frames[-1].kind == "repeat"
    back = PatternSet.from_manifest(json.loads(json.dumps(pset.to_manifest())))
    assert back.files == pset.files and [f.of for f in back.frames] == [f.of for f in pset.frames]
    assert [len(look) for look in motion_looks(back)] == [2, 2, 2]
    # a repeat shows exactly the frame it names; the axis code (what the decoder reads) ignores it
    images = render_all(pset)
    for i, f in enumerate(pset.frames):
        if f.kind == "repeat":
            assert np.array_equal(images[i], images[pset.files.index(f.of)])
    assert pset.axis_code("column").phase == tuple(i for i, f in enumerate(pset.frames) if f.kind == "phase")
    bad = pset.to_manifest()
    bad["frames"][0]["of"] = "nothing.png"
    with pytest.raises(CaptureError, match="repeat frame"):
        PatternSet.from_manifest(bad)
    with pytest.raises(CaptureError, match="motion references"):
        make_pattern_set("paper", 1024, 768, motion_refs=2)


def test_short_preset_has_fewer_frames():
    short = make_pattern_set("short", 1024, 768)
    assert len(short.frames) == 24 and short.axis_code("column").steps == 4
    assert len(make_pattern_set("short", 1024, 768, motion_refs=2).frames) == 28


def test_sway_moves_only_the_subject_and_tilts_about_the_ankle():
    rig = SimRig(leg_scene(), scale=SCALE)
    sway = Sway.drift(3.0, 1.0, "sideways")
    clock = SwayClock(sway)
    moved_scene = clock.scene_at(rig.scene, 1.0)
    before, after = rig.scene.marks, moved_scene.marks
    for k in "567":  # table marks stay
        assert np.allclose(before[k].centre, after[k].centre)
    ankle_shift = after["4"].centre - before["4"].centre
    knee_shift = after["3"].centre - before["3"].centre
    assert ankle_shift[0] > 2.9 and knee_shift[0] > ankle_shift[0]  # the knee moves further
    assert abs(ankle_shift[1]) < 1e-6
    assert math.isclose(Sway(amplitude_mm=2.0, speed_mm_s=4.0).offset(math.pi), 0.0, abs_tol=1e-9)


def test_still_scan_is_not_flagged(still):
    rig, capture, true = still
    cal = rig.true_calibration()
    decoded = decode(capture)
    m = estimate_motion(capture, cal, decoded, cloud_from_decoded(capture, cal, decoded))
    assert true == 0.0 and m.measured and m.looks == default_motion_refs("default")
    assert m.value_mm <= 0.2 and not m.flagged(0.5)
    assert 0.0 <= m.sd_mm < 0.5


def test_drift_is_measured_and_flagged(moved):
    rig, capture, true = moved
    cal = rig.true_calibration()
    result = measure_capture(capture, cal)
    m = result.motion
    print(f"true {true:.2f} mm, estimate {m.value_mm:.2f} ± {m.sd_mm:.2f} mm")
    assert 2.0 < true < 3.0
    assert abs(m.value_mm - true) <= max(0.3 * true, 0.2)
    assert result.motion_flagged and m.sd_mm > 0
    out = result.to_dict()
    assert out["motion_mm"]["value"] == pytest.approx(m.value_mm, abs=1e-3)
    assert out["motion"]["flagged"] is True and out["motion"]["scan_duration_s"] > 0.5
    assert "MOVED" in result.format_text()
    assert [w for w in out["warnings"] if "during the scan" in w] == [
        f"the subject moved {m.value_mm:.1f} mm during the scan (more than the 0.5 mm threshold: scan again)"]
    json.dumps(out)  # RESULT.json stays serialisable


def test_capture_without_references_says_why(still, tmp_path):
    rig, capture, _ = still
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    plain = load_capture(save_capture(tmp_path / "plain", pset, rig.capture_many(render_all(pset))))
    cal = rig.true_calibration()
    decoded = decode(plain)
    m = estimate_motion(plain, cal, decoded, cloud_from_decoded(plain, cal, decoded))
    assert not m.measured and "no motion reference" in m.reason
    assert m.to_dict() == {"value": None, "sd": None} and not m.flagged()
    assert scan_duration_s(plain) is None


def test_store_flags_excludes_and_keeps(tmp_path):
    with Store.open(tmp_path / "db.sqlite") as s:
        s.patients.add("P1")
        ses = s.sessions.start("P1", condition="barefoot")
        trials = [s.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0) for _ in range(3)]
        marks = {1: [0, 40, 480], 2: [0, 40, 80], 3: [35, 0, 485], 4: [35, 0, 85],
                 5: [-40, -60, 50], 6: [45, -50, 50], 7: [5, 90, 50]}
        for t in trials:
            s.results.update_marks(t.id, marks, "auto")
        # make the moved trial's mismatch stand out, so its exclusion shows in the mean
        s.results.update_marks(trials[2].id, {5: [-40, -60, 60]}, "manual")
        s.trials.set_motion(trials[0].id, 0.1, 0.05, scan_duration_s=1.1)
        s.trials.set_motion(trials[1].id, None, None, scan_duration_s=60.0)
        t2 = s.trials.set_motion(trials[2].id, 1.8, 0.2, scan_duration_s=1.1)
        assert t2.motion_flagged and t2.excluded_for_motion and t2.motion_mm == 1.8
        assert not s.trials.get(trials[0].id).motion_flagged and not s.trials.get(trials[1].id).motion_flagged
        summ = s.reports.session_summary(ses.id)
        assert summ.moved_trials == [trials[2].id] and summ.inversion.n == 2
        rows = {r.trial_id: r for r in s.reports.study_rows()}
        assert rows[trials[2].id].excluded_for_motion == 1 and rows[trials[0].id].excluded_for_motion == 0
        s.trials.keep(trials[2].id)
        summ = s.reports.session_summary(ses.id)
        assert summ.moved_trials == [] and summ.inversion.n == 3
        assert s.trials.get(trials[2].id).motion_keep
        # a stricter threshold flags the small one too
        assert s.trials.set_motion(trials[0].id, 0.1, 0.05, threshold_mm=0.05).motion_flagged
        from anklescan.core.errors import AnkleScanError
        with pytest.raises(AnkleScanError):
            s.trials.set_motion(trials[0].id, float("nan"))
        with pytest.raises(AnkleScanError):
            s.trials.set_motion(trials[0].id, 1.0, threshold_mm=0)


def test_report_shows_motion(tmp_path):
    from anklescan.core.records.report import write_csv, write_session_report
    with Store.open(tmp_path / "db.sqlite") as s:
        s.patients.add("P1")
        ses = s.sessions.start("P1", condition="barefoot")
        t = s.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0)
        s.trials.set_motion(t.id, 1.8, 0.2, scan_duration_s=1.1)
        rep = write_session_report(s.reports.report_input([ses.id]), tmp_path / "r.pdf")
        assert rep.pages >= 1 and (tmp_path / "r.pdf").stat().st_size > 0
        from anklescan.core.records.report import _motion_cell
        row = s.reports.study_rows()[0]
        assert _motion_cell(row) == "1.80 out / 1.1"
        write_csv(s.reports.study_rows(), tmp_path / "t.csv")
        text = (tmp_path / "t.csv").read_text()
        assert "motion_mm" in text.splitlines()[0] and "1.8" in text


# ---------------------------------------------------------------- motion of any shape (issue 37)
def _shape_scan(tmp_path, name, make_sway, camera="webcam", seed=3):
    """A scan of the default set (its default looks) with the sway ``make_sway(pset, rig, frame_s)``."""
    rig = SimRig(leg_scene(), scale=SCALE, seed=seed)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height,
                            motion_refs=default_motion_refs("default"))
    frame_s = FRAME_S[camera]
    sway = make_sway(pset, rig, frame_s)
    frames, times = swaying_capture(rig, render_all(pset), sway, frame_s)
    capture = load_capture(save_capture(tmp_path / name, pset, frames, metadata={"duration_s": times[-1]}))
    cal = rig.true_calibration()
    decoded = decode(capture)
    m = estimate_motion(capture, cal, decoded, cloud_from_decoded(capture, cal, decoded))
    return rig, capture, m, true_largest_displacement(rig, sway, times)


def _leg_length(rig) -> float:
    return next(o for o in rig.scene.objects if o.kind == ObjectId.LEG).length


def _twitch_in_gray(pset, frame_s, height_mm=1.0, axis="sideways") -> Sway:
    """A twitch out and back within the Gray-code frames, held as long as the widest gap between two looks."""
    gray = [i for i, f in enumerate(pset.frames) if f.kind == "gray"]
    starts = [lk[0] for lk in motion_looks(pset)]
    gap = max(b - a for a, b in zip(starts, starts[1:], strict=False))
    start = gray[len(gray) // 4]
    return Sway.twitch_of(height_mm, start * frame_s, gap * frame_s, frame_s, axis, tilt_deg_per_mm=0.0)


SHAPES = {
    # 1 mm peak to peak, back and forth once over the scan, no tilt: the tester's sway
    "sway back and forth": (lambda p, r, fs: Sway.back_and_forth(1.0, len(p.frames) * fs, "sideways",
                                                                 tilt_deg_per_mm=0.0), "webcam"),
    "twitch during the Gray code": (lambda p, r, fs: _twitch_in_gray(p, fs), "webcam"),
    # about the ankle only: the top of the leg moves 3 mm, the ankle stays
    "rotation about the ankle": (lambda p, r, fs: Sway.rotation(_leg_length(r), Sway.drift(3.0, len(p.frames) * fs,
                                                                                          "forward")), "webcam"),
    # a sway forward twice over the scan and a sideways twitch on top, with a DSLR's timing
    "sway and twitch, DSLR": (lambda p, r, fs: CombinedSway((
        Sway.back_and_forth(0.8, len(p.frames) * fs / 2, "forward", phase_rad=0.5),
        _twitch_in_gray(p, fs, 0.8))), "dslr"),
}


def test_sway_shapes_move_as_described():
    twitch = Sway.twitch_of(1.0, 1.0, 0.5, 0.1)
    assert twitch.shape is SwayShape.TWITCH and twitch.offset(0.9) == 0.0
    assert twitch.offset(1.3) == pytest.approx(1.0) and twitch.offset(1.75) == pytest.approx(0.0, abs=1e-12)
    sway = Sway.back_and_forth(1.0, 2.0, phase_rad=0.3)
    offs = [sway.offset(t) for t in np.linspace(0, 2, 401)]
    assert sway.shape is SwayShape.OSCILLATION and max(offs) - min(offs) == pytest.approx(1.0, abs=1e-3)
    rig = SimRig(leg_scene(), scale=SCALE)
    length = _leg_length(rig)
    rot = Sway.rotation(length, Sway.drift(3.0, 1.0, "sideways"))
    R, T = rot.pose(1.0)
    ankle = ankle_of(rig.scene)
    leg = next(o for o in rig.scene.objects if o.kind == ObjectId.LEG)
    top = ankle + np.asarray(leg.axes)[:, 2] * length
    assert np.allclose(T, 0.0)  # the ankle stays
    assert np.linalg.norm(R @ (top - ankle) - (top - ankle)) == pytest.approx(3.0, rel=0.01)
    both = CombinedSway((rot, Sway.drift(1.0, 1.0, "forward", tilt_deg_per_mm=0.0)))
    R2, T2 = both.pose(1.0)
    assert np.allclose(R2, R) and np.allclose(T2, [0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def shape_scan(tmp_path_factory):
    """Each shape's scan, made once for the module (the rotation serves two tests)."""
    done = {}

    def get(shape):
        if shape not in done:
            make, camera = SHAPES[shape]
            done[shape] = _shape_scan(tmp_path_factory.mktemp("shape"), "c", make, camera)
        return done[shape]

    return get


@pytest.mark.parametrize("shape", list(SHAPES))
def test_motion_of_any_shape_is_measured(shape_scan, shape):
    _, _, m, true = shape_scan(shape)
    print(f"{shape}: true {true:.2f} mm, estimate {m.value_mm:.2f} ± {m.sd_mm:.2f} mm")
    assert true > 0.7
    assert abs(m.value_mm - true) <= 0.3 * true
    assert m.flagged(0.5)


def test_marks_lost_to_motion_say_how_far_it_moved(shape_scan, tmp_path):
    """A rotation about the ankle that moves the top of the leg 3 mm: the marks are lost, and the
    one-line error says the subject moved, by the motion measured without them."""
    rig, capture, m, true = shape_scan("rotation about the ankle")
    save_calibration(rig.true_calibration(), tmp_path / "cal.json")
    try:
        result = run_measure(capture.folder, tmp_path / "cal.json", tmp_path / "RESULT.json")
    except AnkleScanError as e:
        msg = str(e)
        print(msg[:160])
        assert "\n" not in msg and "nothing written" in msg and not (tmp_path / "RESULT.json").exists()
        moved = float(msg.split("moved ")[1].split(" mm during the scan")[0])
        assert moved == pytest.approx(m.value_mm, abs=0.05)
    else:  # the marks survived: RESULT.json says it moved
        out = json.loads((tmp_path / "RESULT.json").read_text())
        assert result.motion_flagged and any("during the scan" in w for w in out["warnings"])
