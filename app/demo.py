"""``anklescan demo``: a whole clinical study on the built-in simulated rig, no hardware.

Calibrate from a scan of the calibration box, check the scanner against the simulator's ground
truth, then scan two simulated patients — one with a history of ankle sprains whose sense of
the joint angle is off, one without — barefoot and in shoes, over the paper's grid of table
settings; find the marks, compute the angles, keep everything in a real sessions database and
write the study report (PDF + CSV).

The simulated patient sets the adjustable table to what feels like the reference angle; the
error of that setting is the patient model below. Everything else — images, decoding,
calibration, marks, angles — is the product's own pipeline working on simulated photographs.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from anklescan.core.atomic import copy_private, filling_output_dir, make_tree_private, seal_output_dir, write_text_atomic
from anklescan.core.vocabulary import (
    CONDITIONS,
    LABEL_KEYS,
    Axis,
    JsonObject,
    MarkKind,
    MarkLabel,
    MarkSource,
    Trial,
    parse_label,
)
from anklescan.hardware.sim_patient import PATIENTS, SimPatient, table_setting  # noqa: F401  (the patient model)

if TYPE_CHECKING:
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.measure.pipeline import MarkDiameter
    from anklescan.core.records.store import Store

# The output folder's marker names every file the demo wrote (core.atomic.claim_output_dir):
# the next demo run replaces exactly those, and refuses a folder holding anything else.
OUTPUT_COMMAND = "demo"


INVERSIONS = (0.0, 10.0, 20.0)
# the whole range in three steps (the benchmark has all five: docs/marks.md)
PLANTAR_FLEXIONS = (-20.0, 0.0, 20.0)
# (patient, condition): the sprain patient both ways (barefoot vs shoes), the other barefoot
# (sprain history vs none) — the study's two comparisons in three sessions, under two minutes
SESSIONS = (("SIM-01", "barefoot"), ("SIM-01", "shoes"), ("SIM-02", "barefoot"))
DEMO_SCALE = 0.75  # marks are found reliably from 0.75 up; 0.75 keeps the demo under two minutes

Progress = Callable[[str], object]  # where the lines go: print, the command's quiet-aware printer, a test's list


@dataclass(frozen=True)
class Drift:
    """A trial's sway: the patient drifts ``mm`` in all along ``direction`` (a horizontal unit vector)."""

    mm: float
    direction: tuple[float, float, float]


@dataclass(frozen=True)
class TrialJob:
    """One trial for a scanning worker (pickled to it): what to simulate, where to save it, how to measure it."""

    label: str
    table: tuple[float, float]  # the table as the simulated patient set it: (inversion, plantar flexion)
    scale: float
    seed: int
    capture: str  # the capture folder to write
    cloud: str  # the PLY to write
    calibration: JsonObject
    accuracy: bool  # also compare the cloud with the simulator's truth
    marks: tuple[MarkKind, float, bool]  # the patient's marks: kind, diameter (mm), diameter given by the clinic
    mark_diameter: float | None  # the session's mark diameter, None: measured
    sway: Drift | None = None  # None: the patient stands still
    camera: str = "webcam"  # a key of hardware.sim_sway.FRAME_S


class MotionCheck(TypedDict):
    """A trial's measured motion beside the simulator's truth."""

    mm: float | None
    sd: float | None
    flagged: bool
    duration_s: float | None
    true_mm: float


class JointMatrix(TypedDict):
    """``JointCovariance`` as plain lists, to come back from a worker."""

    labels: list[MarkLabel]
    matrix: list[list[float]]


class TrialResult(TypedDict):
    """What a scanning worker sends back for one trial (plain data: it crosses processes)."""

    motion: MotionCheck
    label: str
    complete: bool
    message: str
    missing: list[str]
    marks: dict[str, list[float]]  # label key -> centre (mm)
    covariances: dict[str, list[list[float]]]  # label key -> 3x3 (mm²)
    joint: JointMatrix | None
    warnings: list[str]
    angles: dict[str, dict[str, float]]
    mark_type: MarkKind
    mark_diameter: MarkDiameter | None
    mark_errors_mm: dict[str, float]
    angle_errors_deg: dict[str, float]
    accuracy: dict[str, JsonObject] | None  # hardware.sim_accuracy.as_dict, on the trial chosen for it
    seconds: float


@dataclass(frozen=True)
class BoxCalibration:
    """The simulated scanner's calibration from the box scan, and its worse RMS (px) of camera and projector."""

    calibration: JsonObject
    rms: float


class PlannedTrial(TypedDict):
    """One trial of ``study_plan()``."""

    patient: SimPatient
    condition: str
    ref: tuple[float, float]  # the reference setting: (inversion, plantar flexion)
    visit: int  # days after the first visit
    table: tuple[float, float]  # the table as the simulated patient set it
    seed: int


# ---------------------------------------------------------------------------- workers
def _worker_init(scale: float | None = None) -> None:
    # two processes share two cores: no nested thread pools
    import cv2

    cv2.setNumThreads(1)
    if scale is not None:
        # started while the main process calibrates: the imports and the camera's rays are
        # ready for the first trial instead of after the calibration
        from anklescan.core.measure import pipeline  # noqa: F401
        from anklescan.hardware.sim_scene import leg_scene
        from anklescan.hardware.simrig import SimRig

        SimRig(leg_scene(0.0, 0.0), scale=scale).warm_camera_rays()


_CALIBRATIONS: dict[str, Calibration] = {}


def _calibration(obj: JsonObject) -> Calibration:
    """One Calibration object per worker, so its triangulation cache is built once, not per trial."""
    from anklescan.core.calibration.model.file import calibration_from_dict

    key = json.dumps(obj, sort_keys=True)
    if key not in _CALIBRATIONS:
        _CALIBRATIONS[key] = calibration_from_dict(obj)
    return _CALIBRATIONS[key]


def _scan_trial(job: TrialJob) -> TrialResult:
    """Simulate one trial's scan, save it, measure it; compare with the truth (demo only)."""
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.capture import load_capture, save_capture
    from anklescan.core.scan.motion import default_motion_refs
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.core.scan.pointcloud import write_ply
    from anklescan.core.scan.triangulate import scan_axes
    from anklescan.hardware.sim_accuracy import as_dict, evaluate
    from anklescan.hardware.sim_scene import angles_from_marks, leg_scene
    from anklescan.hardware.sim_sway import FRAME_S, Sway, swaying_capture, true_largest_displacement
    from anklescan.hardware.simrig import SimRig

    t0 = time.perf_counter()
    mark_type, diameter, _ = job.marks
    scene = leg_scene(*job.table, mark_type=mark_type, mark_radius=diameter / 2)
    rig = SimRig(scene, scale=job.scale, seed=job.seed)
    cal = _calibration(job.calibration)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=scan_axes(cal),
                            motion_refs=default_motion_refs("default"))
    frame_s = FRAME_S[job.camera]
    drift = job.sway or Drift(0.0, (1.0, 0.0, 0.0))
    sway = Sway.drift(drift.mm, len(pset.frames) * frame_s, drift.direction)
    frames, times = swaying_capture(rig, render_all(pset), sway, frame_s)
    save_capture(job.capture, pset, frames,
                 metadata={"device": "simulated rig", "trial": job.label, "duration_s": len(frames) * frame_s})
    capture = load_capture(job.capture)
    result = measure_capture(capture, cal, job.mark_diameter)
    # measure_capture always sets the cloud and the motion (None only in results built elsewhere)
    assert result.cloud is not None and result.motion is not None
    write_ply(job.cloud, result.cloud)
    true_marks = {k: np.asarray(m.centre) for k, m in scene.marks.items()}
    true_angles = angles_from_marks(true_marks)
    found = result.marks.labelled
    motion = result.motion
    return {
        "motion": {"mm": motion.value_mm, "sd": motion.sd_mm, "flagged": result.motion_flagged,
                   "duration_s": result.duration_s, "true_mm": true_largest_displacement(rig, sway, times)},
        "label": job.label,
        "complete": result.complete,
        "message": "" if result.complete else result.marks.message(),
        "missing": [k for k in LABEL_KEYS if k not in result.marks.labelled],
        "marks": {k: [float(x) for x in m.centre] for k, m in found.items()},
        "covariances": {k: np.asarray(c).tolist() for k, c in result.marks.covariances().items()},
        "joint": None if result.position_covariance is None else
        {"labels": list(result.position_covariance.labels), "matrix": result.position_covariance.matrix.tolist()},
        "warnings": list(result.warnings),
        "angles": result.angles.to_json(),
        "mark_type": mark_type,
        "mark_diameter": result.mark_diameter(),
        "mark_errors_mm": {k: float(np.linalg.norm(np.asarray(m.centre) - true_marks[k])) for k, m in found.items()},
        "angle_errors_deg": {k: float(v.value - true_angles[k]) for k, v in result.angles.items()},
        "accuracy": as_dict(evaluate(result.cloud, rig.truth())) if job.accuracy else None,
        "seconds": time.perf_counter() - t0,
    }


def _warm_pool(scale: float) -> ProcessPoolExecutor:
    """Two scanning workers, started now so that they warm up while the main process calibrates."""
    workers = max(1, min(2, os.cpu_count() or 1))
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_init, initargs=(scale,))
    for _ in range(workers):
        pool.submit(int)  # a spawn pool starts a worker per submitted job
    return pool


def _calibrate(out: Path, scale: float, progress: Progress) -> BoxCalibration:
    from anklescan.core.calibration.model.file import calibration_to_dict, save_calibration
    from anklescan.core.calibration.procedures.box import calibrate_from_box_capture
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.sim_scene import box_scene_objects, quad_scene
    from anklescan.hardware.simrig import SimRig

    rig = SimRig(quad_scene(box_scene_objects()), scale=scale, seed=1)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=(Axis.COLUMN, Axis.ROW))
    folder = save_capture(out / "calibration_box_capture", pset, rig.capture_many(render_all(pset)),
                          metadata={"device": "simulated rig", "scene": "calibration box"})
    cal, report = calibrate_from_box_capture(folder)
    save_calibration(cal, out / "calibration.json")
    cam, proj = report.camera, report.projector
    progress(f"calibrated from the box: camera {cam.n_points} points RMS {cam.rms_px:.3f} px, "
             f"projector {proj.n_points} points RMS {proj.rms_px:.3f} px -> {out / 'calibration.json'}")
    return BoxCalibration(calibration_to_dict(cal), max(cam.rms_px, proj.rms_px))


# ---------------------------------------------------------------------------- the study
def _filling_out(out: Path) -> AbstractContextManager[Path]:
    """An empty or new folder, or an earlier demo's own output (its files only are removed);
    anything else is refused before any work. Yields the folder's real path, which the run writes
    into; a run that fails or is interrupted leaves nothing of its own there
    (core.atomic.filling_output_dir)."""
    return filling_output_dir(out, OUTPUT_COMMAND)


def _finish_out(out: Path) -> None:
    make_tree_private(out)  # a clinic's layout, so patient-data rules: files 0600, folders 0700
    seal_output_dir(out, OUTPUT_COMMAND)


def _sway(rng: np.random.Generator, sway_mm: float) -> Drift | None:
    """One trial in three drifts, by a random amount up to ``sway_mm`` in a random horizontal direction."""
    amount, angle, moves = rng.uniform(0.0, sway_mm), rng.uniform(0, 2 * np.pi), rng.uniform() < 1 / 3
    return Drift(float(amount), (float(np.cos(angle)), float(np.sin(angle)), 0.0)) if (sway_mm > 0 and moves) else None


def _plan(store: Store, cal_id: int, quick: bool, scale: float, cal_dict: JsonObject, sway_mm: float = 0.0,
          camera: str = "webcam") -> list[tuple[TrialJob, int]]:
    sway_rng = np.random.default_rng(18)
    rng = np.random.default_rng(2026)
    sessions = [s for s in SESSIONS if s[1] == "barefoot"] if quick else SESSIONS
    inversions = (0.0, 20.0) if quick else INVERSIONS
    pfs = (-20.0, 20.0) if quick else PLANTAR_FLEXIONS
    jobs: list[tuple[TrialJob, int]] = []
    for p in PATIENTS:
        store.patients.add(p.code, sprain_count=p.sprain_count, last_sprain=p.last_sprain,
                          affected_side="right" if p.sprain_count else None, notes=p.notes)
        for condition in (c for code, c in sessions if code == p.code):
            session = store.sessions.start(p.code, condition=condition, operator="demo",
                                          calibration_id=cal_id, notes=f"simulated rig, {p.marks[0]}s {p.marks[1]:g} mm")
            if p.marks[2]:
                session = store.sessions.set_mark_diameter(session.id, p.marks[1])
            for inv in inversions:
                for pf in pfs:
                    trial = store.trials.add(session.id, ref_inversion=inv, ref_plantar_flexion=pf)
                    table = table_setting(p, condition, inv, pf, rng)
                    folder = store.files.trial_dir(trial.id, create=True)
                    jobs.append((TrialJob(label=f"{p.code} {condition:8s} ref inv {inv:+5.1f} pf {pf:+5.1f}",
                                          table=table, scale=scale, seed=int(rng.integers(2**31)),
                                          capture=str(folder / "capture"), cloud=str(folder / "cloud.ply"),
                                          calibration=cal_dict, accuracy=False, marks=p.marks,
                                          mark_diameter=session.mark_diameter_mm,
                                          sway=_sway(sway_rng, sway_mm), camera=camera), trial.id))
    # the scanner's accuracy against the truth: on the first trial whose patient stood still
    still = [i for i, (j, _) in enumerate(jobs) if j.sway is None]
    if still:
        job, trial_id = jobs[still[0]]
        jobs[still[0]] = (replace(job, accuracy=True), trial_id)
    return jobs


def _record(store: Store, trial_id: int, job: TrialJob, res: TrialResult) -> None:
    store.trials.set_simulated(trial_id)  # a simulated patient: every report and CSV says so
    store.trials.set_files(trial_id, capture=Path(job.capture), cloud=Path(job.cloud))
    m = res["motion"]
    store.trials.set_motion(trial_id, m["mm"], m["sd"], scan_duration_s=m["duration_s"])
    if res["marks"]:
        # store the measured marks; the store recomputes the angles and mismatch from them
        # the marks' joint covariance (calibration, model, mark centres, motion: SPEC §3) gives the SD
        # a copy typed as update_marks takes the marks (a Mapping's key type is invariant)
        marks: dict[MarkLabel | str, list[float]] = {k: c for k, c in res["marks"].items()}
        joint = res.get("joint")
        if joint is not None:
            from anklescan.core.measure.angles import JointCovariance
            store.results.update_marks(trial_id, marks, MarkSource.AUTO, "anklescan demo", sigma_mm=0.0,
                               joint=JointCovariance(tuple(joint["labels"]), np.asarray(joint["matrix"])))
        else:
            store.results.update_marks(trial_id, marks, MarkSource.AUTO, "anklescan demo",
                               sigma_mm={parse_label(k): np.asarray(c) for k, c in res["covariances"].items()})


def run_demo(out: Path, quick: bool = False, progress: Progress = print, scale: float = DEMO_SCALE,
             sway_mm: float = 0.0,
             camera: str = "webcam") -> int:
    with _filling_out(out) as real:
        return _run_demo(real, quick, progress, scale, sway_mm, camera)


def _run_demo(out: Path, quick: bool, progress: Progress, scale: float, sway_mm: float, camera: str) -> int:
    from anklescan.core.records.report import write_session_report, write_study_report
    from anklescan.core.records.store import Store

    t_start = time.perf_counter()
    progress(f"simulated rig at scale {scale} (camera {round(1600 * scale)}x{round(1200 * scale)}, projector "
             f"{round(1024 * scale)}x{round(768 * scale)}); output in {out}")
    with _warm_pool(scale) as pool, Store.open(out / "anklescan.db", data_dir=out / "data") as store:
        progress("calibrating the simulated scanner from a scan of the calibration box (about 20 s)…")
        cal = _calibrate(out, scale, progress)
        cal_id = store.calibrations.add(cal.calibration, rms=cal.rms, source="demo: simulated box scan").id
        jobs = _plan(store, cal_id, quick, scale, cal.calibration, sway_mm, camera)
        progress(f"scanning {len(jobs)} trials of {len(PATIENTS)} simulated patients on {os.cpu_count()} cores")
        results: list[TrialResult] = []
        for k, ((job, trial_id), res) in enumerate(zip(jobs, pool.map(_scan_trial, [j for j, _ in jobs]),
                                                       strict=True), start=1):
            _record(store, trial_id, job, res)
            results.append(res)
            progress(f"[{k}/{len(jobs)}] {_clinical_line(res, store.trials.get(trial_id))}")
            if res["accuracy"]:
                acc = res["accuracy"]["subject"]
                copy_private(job.cloud, out / "scan.ply")
                progress(f"scanner accuracy vs ground truth (leg, foot, table, marks), box calibration: "
                         f"RMS {acc['rms_mm']:.3f} mm, outliers {100 * acc['outlier_fraction']:.3f} %, "
                         f"coverage {100 * acc['coverage']:.1f} % -> {out / 'scan.ply'}")
        report = write_study_report(store.reports.report_input(), out / "report.pdf", out / "trials.csv")
        for session in store.sessions.all():
            patient = store.patients.get(session.patient_id).code
            write_session_report(store.reports.report_input([session.id]), out / f"session_{patient}_{session.condition}.pdf")
    _summarise(results, out, progress)
    _finish_out(out)
    progress(f"database {out / 'anklescan.db'}, study report {report.pdf_path} ({report.pages} pages), "
             f"{report.csv_path}, one session report per session; {time.perf_counter() - t_start:.0f} s")
    return 0  # plates left for manual placement are a normal outcome, not a failure of the run


def _clinical_line(res: TrialResult, trial: Trial) -> str:
    """One trial as a clinician reads it: who, the reference, the mismatch, and what to do (the
    comparison with the simulator's truth goes to summary.json, not here)."""
    def deg(v: float | None) -> str:
        if v is None:
            return "—"
        text = f"{v:+.1f}"
        return f"{text[1:] if float(text) == 0 else text}°"  # 0.0, never -0.0
    text = (f"{res['label']}: mismatch inversion {deg(trial.mismatch_inversion)}, "
            f"plantar flexion {deg(trial.mismatch_plantar_flexion)}")
    text += " · all 7 marks found" if res["complete"] else (
        f" · marks {', '.join(res['missing'])} not found: place them in the 3-D view")
    m = res["motion"]
    if m["flagged"]:
        text += f" · moved {m['mm']:.1f} mm during the scan: left out of the statistics"
    return text


def _summarise(results: list[TrialResult], out: Path, progress: Progress) -> None:
    mark_err = [e for r in results for e in r["mark_errors_mm"].values()]
    ang_err = [abs(e) for r in results for e in r["angle_errors_deg"].values()]
    complete = sum(r["complete"] for r in results)
    summary = {"trials": len(results), "complete": complete,
               "max_mark_error_mm": max(mark_err, default=None), "max_angle_error_deg": max(ang_err, default=None),
               "scan_accuracy": next((r["accuracy"] for r in results if r["accuracy"]), None),
               "marks": {t: {"trials": sum(r["mark_type"] == t for r in results),
                             "max_mark_error_mm": max((e for r in results if r["mark_type"] == t
                                                       for e in r["mark_errors_mm"].values()), default=None),
                             "diameters_mm": sorted({round(r["mark_diameter"]["value"], 2) for r in results
                                                     if r["mark_type"] == t and r["mark_diameter"]})}
                         for t in sorted({r["mark_type"] for r in results})}}
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2) + "\n")  # atomic and private
    progress(f"{complete}/{len(results)} trials with all seven marks found automatically (the others keep their "
             f"table angles and mismatch); self-check against the simulator's truth (summary.json): "
             f"worst mark centre {summary['max_mark_error_mm'] or float('nan'):.2f} mm, "
             f"worst angle {summary['max_angle_error_deg'] or float('nan'):.2f}°")


# ---------------------------------------------------------------------------- --study
# ``anklescan demo --study``: the paper's cohort (§5.1: four patients with a sprain history, four
# without), each barefoot and in shoes, so the report's group page carries real tests. The
# patient model is the one above (table_setting): a sprain history gives a larger bias, gain and
# scatter in setting the table; shoes scale the error down (shoes_factor). The simulated scene
# has no shoe geometry: in shoes only the patient's sense of angle changes, not what is scanned.
STUDY_PATIENTS = PATIENTS + (
    SimPatient("SIM-03", 2, "2026-06-30", "simulated: two sprains, left ankle", (-1.2, 1.4), (0.10, 0.02),
               (0.0, 0.06), 1.4, 0.6),
    SimPatient("SIM-04", 4, "2026-10-02", "simulated: recurrent sprains, right ankle", (2.0, -0.6), (0.08, 0.0),
               (0.06, -0.05), 1.8, 0.5),
    SimPatient("SIM-05", 2, "2026-04-11", "simulated: two sprains, right ankle", (1.0, 1.6), (0.14, 0.0),
               (-0.04, 0.07), 1.3, 0.65),
    SimPatient("SIM-06", 0, None, "simulated: no sprain history", (-0.3, 0.2), (0.01, 0.0), (0.0, 0.02), 0.6, 0.85),
    SimPatient("SIM-07", 0, None, "simulated: no sprain history", (0.1, -0.3), (0.0, 0.01), (0.01, 0.0), 0.8, 0.8),
    SimPatient("SIM-08", 0, None, "simulated: no sprain history", (0.3, 0.0), (-0.02, 0.0), (0.0, -0.02), 0.5, 0.9),
)
# Per session one inversion setting and three plantar flexions (the range): 8 patients ×
# 2 conditions × 3 trials = 48 scans. The paper's whole grid (3 × 3 per session, 144 scans) would
# take three times as long; three trials per patient and condition already give each patient's
# mean |mismatch|, which is what the tests compare (core/records/study_stats.py).
STUDY_INVERSIONS = (0.0,)
STUDY_PLANTAR_FLEXIONS = (-20.0, 0.0, 20.0)
# Every patient comes back for a retest four weeks after the first visit (same settings, both
# conditions), so the study's reliability (ICC, SEM, MDC95: core/records/reliability.py) and each
# patient's visits over time carry numbers: 8 patients × 2 conditions × 2 visits × 3 trials = 96 scans.
STUDY_VISITS = (0, 28)   # days after the first visit


def study_plan(patients: Sequence[SimPatient] = STUDY_PATIENTS, inversions: Sequence[float] = STUDY_INVERSIONS,
               pfs: Sequence[float] = STUDY_PLANTAR_FLEXIONS, seed: int = 2027,
               visits: Sequence[int] = STUDY_VISITS) -> list[PlannedTrial]:
    """Every trial of the simulated study, in scanning order: patient, visit (days after the first),
    condition, reference setting, the table setting the simulated patient chose, and the simulator's seed."""
    rng = np.random.default_rng(seed)
    plan: list[PlannedTrial] = []
    for visit in visits:
        for p in patients:
            for condition in CONDITIONS:
                for inv in inversions:
                    for pf in pfs:
                        plan.append({"patient": p, "condition": condition, "ref": (inv, pf), "visit": visit,
                                     "table": table_setting(p, condition, inv, pf, rng),
                                     "seed": int(rng.integers(2**31))})
    return plan


def run_study_demo(out: Path, progress: Progress = print, scale: float = DEMO_SCALE,
                   plan: list[PlannedTrial] | None = None) -> int:
    """The whole simulated study: box calibration, every trial of ``study_plan()`` scanned and
    measured by the product's pipeline, the study report (with the group page's tests), the CSV and
    one session report per patient (barefoot and shoes)."""
    with _filling_out(out) as real:
        return _run_study_demo(real, progress, scale, study_plan() if plan is None else plan)


def _run_study_demo(out: Path, progress: Progress, scale: float, plan: list[PlannedTrial]) -> int:
    from anklescan.core.records.report import write_session_report, write_study_report
    from anklescan.core.records.store import Store

    t_start = time.perf_counter()
    first_day = _dt.date.today() - _dt.timedelta(days=max(t.get("visit", 0) for t in plan))
    progress(f"simulated study at scale {scale}: {len({t['patient'].code for t in plan})} patients, "
             f"{len(plan)} trials; output in {out}")
    results: list[TrialResult] = []
    with _warm_pool(scale) as pool, Store.open(out / "anklescan.db", data_dir=out / "data") as store:
        cal = _calibrate(out, scale, progress)
        cal_id = store.calibrations.add(cal.calibration, rms=cal.rms, source="demo: simulated box scan").id
        sessions: dict[tuple[str, str, int], int] = {}  # (patient, condition, visit) -> session id
        jobs: list[tuple[TrialJob, int]] = []
        for t in plan:
            p = t["patient"]
            if p.code not in {q.code for q in store.patients.all()}:
                store.patients.add(p.code, sprain_count=p.sprain_count, last_sprain=p.last_sprain,
                                  affected_side="right" if p.sprain_count else None, notes=p.notes)
            key = (p.code, t["condition"], t.get("visit", 0))
            if key not in sessions:
                day = first_day + _dt.timedelta(days=key[2])
                sessions[key] = store.sessions.start(p.code, condition=t["condition"], operator="demo", date=day,
                                                    calibration_id=cal_id,
                                                    notes="simulated rig, --study" + (", retest" if key[2] else "")).id
                if p.marks[2]:  # the clinic gave the marks' size for this patient's sessions
                    store.sessions.set_mark_diameter(sessions[key], p.marks[1])
            mark_diameter = store.sessions.get(sessions[key]).mark_diameter_mm
            inv, pf = t["ref"]
            trial = store.trials.add(sessions[key], ref_inversion=inv, ref_plantar_flexion=pf, calibration_id=cal_id)
            folder = store.files.trial_dir(trial.id, create=True)
            jobs.append((TrialJob(label=f"{p.code} {t['condition']:8s} ref inv {inv:+5.1f} pf {pf:+5.1f}",
                                  table=t["table"], scale=scale, seed=t["seed"], capture=str(folder / "capture"),
                                  cloud=str(folder / "cloud.ply"), calibration=cal.calibration,
                                  accuracy=False, marks=p.marks, mark_diameter=mark_diameter), trial.id))
        for k, ((job, trial_id), res) in enumerate(zip(jobs, pool.map(_scan_trial, [j for j, _ in jobs]), strict=False), 1):
            _record(store, trial_id, job, res)
            results.append(res)
            m = store.trials.get(trial_id)
            mm = ("mismatch –" if m.mismatch_inversion is None else
                  f"mismatch inv {m.mismatch_inversion:+5.2f}° pf {m.mismatch_plantar_flexion:+5.2f}°")
            progress(f"[{k}/{len(jobs)}] {res['label']}: {mm}"
                     + ("" if res["complete"] else f"  marks {', '.join(res['missing'])} not found"))
        report = write_study_report(store.reports.report_input(), out / "report.pdf", out / "trials.csv")
        for code in dict.fromkeys(c for c, _, _ in sessions):
            write_session_report(store.reports.report_input([sid for (c, _, _), sid in sessions.items() if c == code]),
                                 out / f"session_{code}.pdf")
        _study_summary(store, progress)
        from anklescan.core.records.study import write_study_folder

        study = write_study_folder(store.reports.report_input(), out / "study", data_dir=out, keep_site_mdc=True)
        progress(f"the clinic's study (as `anklescan report --data {out}`): {study.folder} ({study.pages} pages, "
                 "position_sense.csv, reliability.csv, trials.xlsx)")
        _reliability_summary(study.folder, progress)
    _summarise(results, out, progress)
    _finish_out(out)
    progress(f"database {out / 'anklescan.db'}, study report {report.pdf_path} ({report.pages} pages), "
             f"{report.csv_path}, one session report per patient; {time.perf_counter() - t_start:.0f} s")
    return 0


def _reliability_summary(folder: Path, progress: Progress) -> None:
    """The reliability rows, one line each (the PDF's last page has them with Bland–Altman plots)."""
    import csv

    with open(folder / "reliability.csv", encoding="utf-8-sig", newline="") as fh:
        for r in csv.DictReader(fh):
            progress(f"retest reliability, {r['condition']}, AE of {r['axis'].replace('_', ' ')}: "
                     f"n={r['n_patients']} patients, ICC(2,1) {r['icc'][:5] or '–'}, "
                     f"MDC95 {r['mdc95'][:5] + '°' if r['mdc95'] else '–'}")


def _study_summary(store: Store, progress: Progress) -> None:
    """The group page's two questions, one line each (the PDF has every test)."""
    from anklescan.core.records import study_stats as st

    s = st.study_stats(store.reports.study_rows())
    for c in CONDITIONS:
        progress(f"sprain history vs none, {c}, |mismatch of inversion|: "
                 + st.format_group_test(s.history_tests[(c, "inversion")]))
    progress("barefoot vs shoes, all patients, |mismatch of inversion|: "
             + st.format_paired_test(s.condition_tests[("all", "inversion")]))
