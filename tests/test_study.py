"""The clinic's own study (issue 39, SPEC §7): `anklescan report` and `anklescan export` from a database
alone. Every figure is recomputed here independently from the files (trials.csv with pandas, ICC with
pingouin and by the Shrout–Fleiss formula), the XLSX is read back with openpyxl, the C3D with the `c3d`
package (written with ezc3d), the FHIR Bundle validated with fhir.resources."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from anklescan.app.cli import main
from anklescan.core.records.store import Store
from anklescan.core.vocabulary import StudyRow

PF_SETTINGS = (-20.0, 0.0, 20.0)


def table_marks(inv: float, pf: float) -> dict[int, tuple[float, float, float]]:
    """Seven marks: a leg and a table plane whose inversion and plantar flexion are exactly ``inv``, ``pf``."""
    a, b = -math.tan(math.radians(inv)), -math.tan(math.radians(pf))
    leg = {1: (0.0, 0.0, 450.0), 2: (0.0, 0.0, 80.0), 3: (40.0, 0.0, 440.0), 4: (40.0, 0.0, 70.0)}
    table = {lab: (x, y, a * x + b * y) for lab, (x, y) in zip((5, 6, 7), ((-60, -40), (60, -40), (0, 80)),
                                                                strict=True)}
    return {**leg, **table}


# patient → (condition → [visit date → per-trial mismatch of inversion, plantar flexion])
def _cohort(rng) -> dict:
    out = {}
    for k in range(5):
        bias = rng.normal(0, 1.5, 2)
        out[f"P{k + 1}"] = {c: {d: [tuple(bias * (0.6 if c == "shoes" else 1) + rng.normal(0, 0.8, 2))
                                    for _ in PF_SETTINGS] for d in ("2026-01-10", "2026-02-14")}
                            for c in ("barefoot", "shoes")}
    return out


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("clinic data")
    rng = np.random.default_rng(39)
    with Store.open(data_dir=folder) as store:
        cal = store.calibrations.add({"units": "mm"}, rms=0.2, source="test").id
        for code, conds in _cohort(rng).items():
            store.patients.add(code, sprain_count=2 if code in ("P1", "P2") else 0,
                              affected_side="left" if code == "P1" else None)
            for cond, visits in conds.items():
                for date, mms in visits.items():
                    s = store.sessions.start(code, condition=cond, date=date, calibration_id=cal)
                    for pf, (mi, mp) in zip(PF_SETTINGS, mms, strict=True):
                        t = store.trials.add(s.id, ref_inversion=10.0, ref_plantar_flexion=pf)
                        store.results.update_marks(t.id, table_marks(10.0 + mi, pf + mp), "manual", "test")
        # trials that must not count: excluded, failed, moved
        s = store.sessions.all("P1")[0]
        t = store.trials.add(s.id, ref_inversion=10.0, ref_plantar_flexion=0.0)
        store.results.update_marks(t.id, table_marks(19.0, 5.0), "manual", "test")
        store.trials.exclude(t.id, "=patient sneezed")
        t = store.trials.add(s.id, ref_inversion=10.0, ref_plantar_flexion=0.0)
        store.trials.set_status(t.id, "failed", "no marks")
        t = store.trials.add(s.id, ref_inversion=10.0, ref_plantar_flexion=0.0)
        store.results.update_marks(t.id, table_marks(25.0, 0.0), "manual", "test")
        store.trials.set_motion(t.id, 2.0, 0.1, scan_duration_s=3.0)
        # a one-visit, one-trial patient
        store.patients.add("P9")
        s = store.sessions.start("P9", condition="barefoot", date="2026-03-01", calibration_id=cal)
        t = store.trials.add(s.id, ref_inversion=0.0, ref_plantar_flexion=0.0)
        store.results.update_marks(t.id, table_marks(0.5, -0.2), "auto", "detector")
    return folder


def run(capfd, *args) -> tuple[int, str, list[str]]:
    code = main(["-q", *map(str, args)])
    out, err = capfd.readouterr()
    return code, out, [ln for ln in err.splitlines() if ln.strip()]


@pytest.fixture(scope="module")
def report(data, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("study") / "report ü"
    assert main(["-q", "report", "--data", str(data), "--out", str(out)]) == 0
    return out


def trials_frame(report: Path) -> pd.DataFrame:
    raw = (report / "trials.csv").read_bytes()
    assert raw.startswith(b"\xef\xbb\xbf")   # UTF-8 with BOM
    return pd.read_csv(report / "trials.csv", encoding="utf-8-sig")


def test_report_writes_every_file_with_spec_columns(report):
    names = {p.name for p in report.iterdir()}
    assert {"report.pdf", "trials.csv", "trials.xlsx", "data_dictionary.csv", "position_sense.csv",
            "reliability.csv"} <= names
    df = trials_frame(report)
    for col in ("patient", "session", "visit_date", "condition", "trial", "status", "excluded",
                "reference_inversion", "reference_plantar_flexion", "mismatch_inversion", "mismatch_plantar_flexion",
                "leg_inversion", "leg_inversion_sd", "leg_plantar_flexion", "leg_plantar_flexion_sd",
                "table_inversion", "table_inversion_sd", "table_plantar_flexion", "table_plantar_flexion_sd",
                "motion_mm", "calibration"):
        assert col in df.columns, col
    assert len(df) == 5 * 2 * 2 * 3 + 3 + 1   # every trial, with its state
    assert set(df.status) == {"complete", "failed"}
    assert df.excluded.sum() == 2   # the excluded and the moved one
    dictionary = pd.read_csv(report / "data_dictionary.csv", encoding="utf-8-sig")
    described = set(dictionary[dictionary.file == "trials.csv"].column)
    assert described == set(df.columns)
    assert (report / "report.pdf").read_bytes()[:5] == b"%PDF-"


def test_position_sense_recomputed_from_trials_csv(report):
    df = trials_frame(report)
    use = df[(df.status == "complete") & (~df.excluded)]
    ps = pd.read_csv(report / "position_sense.csv", encoding="utf-8-sig")
    assert list(ps.columns) == ["patient", "session", "visit_date", "condition", "axis", "n", "AE", "CE", "VE", "E"]
    assert len(ps) == (5 * 4 + 1) * 2
    for _, r in ps.iterrows():
        m = use[(use.session == r.session)][f"mismatch_{r.axis}"].dropna().to_numpy()
        assert r.n == m.size
        assert abs(r.AE - np.abs(m).mean()) < 0.01 and abs(r.CE - m.mean()) < 0.01
        if m.size > 1:
            assert abs(r.VE - m.std(ddof=1)) < 0.01
            assert abs(r.E - math.hypot(m.mean(), m.std(ddof=1))) < 0.01
        else:
            assert math.isnan(r.VE) and math.isnan(r.E)
    # the known geometry: the mismatch is what the simulated patient set, to a hair
    p1 = use[use.patient == "P1"]
    assert np.allclose(p1.table_inversion - p1.reference_inversion, p1.mismatch_inversion, atol=1e-6)


def _icc21(x: np.ndarray) -> float:
    """Shrout & Fleiss ICC(2,1) from the two-way ANOVA mean squares (n subjects × k sessions)."""
    n, k = x.shape
    grand = x.mean()
    msr = k * ((x.mean(axis=1) - grand) ** 2).sum() / (n - 1)
    msc = n * ((x.mean(axis=0) - grand) ** 2).sum() / (k - 1)
    sse = ((x - x.mean(axis=1, keepdims=True) - x.mean(axis=0, keepdims=True) + grand) ** 2).sum()
    mse = sse / ((n - 1) * (k - 1))
    return (msr - mse) / (msr + (k - 1) * mse + k * (msc - mse) / n)


def test_reliability_recomputed_independently(report):
    df = trials_frame(report)
    use = df[(df.status == "complete") & (~df.excluded)]
    rel = pd.read_csv(report / "reliability.csv", encoding="utf-8-sig")
    assert list(rel.columns) == ["condition", "axis", "icc", "ci_low", "ci_high", "sem", "mdc95", "n_patients"]
    assert len(rel) == 4
    for _, r in rel.iterrows():
        sub = use[use.condition == r.condition]
        ae = (sub.assign(a=sub[f"mismatch_{r.axis}"].abs()).groupby(["patient", "visit_date", "session"]).a.mean()
              .reset_index().sort_values(["patient", "visit_date", "session"]))
        first_two = ae.groupby("patient").head(2)
        counts = first_two.groupby("patient").size()
        keep = first_two[first_two.patient.isin(counts[counts == 2].index)]
        x = keep.a.to_numpy().reshape(-1, 2)
        assert r.n_patients == len(x) == 5
        assert abs(r.icc - _icc21(x)) < 0.02
        assert r.ci_low <= r.icc <= r.ci_high
        sd = keep.a.std(ddof=1)
        assert abs(r["sem"] - sd * math.sqrt(1 - r.icc)) < 1e-6
        assert abs(r.mdc95 - 1.96 * math.sqrt(2) * r["sem"]) < 1e-9


def test_xlsx_has_the_csv_rows(report):
    from openpyxl import load_workbook

    with open(report / "trials.csv", encoding="utf-8-sig", newline="") as fh:
        rows = list(csv.reader(fh))
    ws = load_workbook(report / "trials.xlsx", read_only=True)["trials"]
    xrows = [["" if v is None else v for v in row] for row in ws.iter_rows(values_only=True)]
    assert xrows[0] == rows[0] and len(xrows) == len(rows)
    for a, b in zip(rows[1:], xrows[1:], strict=True):
        for u, v in zip(a, b, strict=True):
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                assert abs(float(u) - v) < 1e-9
            else:
                assert u == str(v)
    # a free-text cell that starts like a formula is not one
    assert any(r[rows[0].index("excluded_reason")] == "'=patient sneezed" for r in rows)


def test_site_mdc_kept_in_data_folder(report, data):
    kept = json.loads((data / "site_mdc.json").read_text())
    rel = pd.read_csv(report / "reliability.csv", encoding="utf-8-sig")
    assert {(r["condition"], r["axis"]): r["mdc95"] for r in kept["rows"]} == pytest.approx(
        {(r.condition, r.axis): r.mdc95 for r in rel.itertuples()})


@pytest.mark.slow
def test_report_refuses_foreign_folder_and_replaces_its_own(data, report, tmp_path, capfd):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.docx").write_text("keep me")
    code, _, err = run(capfd, "report", "--data", data, "--out", foreign)
    assert code == 2 and len(err) == 1 and "did not write" in err[0]
    assert [p.name for p in foreign.iterdir()] == ["thesis.docx"]
    # an earlier report folder is replaced (a copy: the module's report stays whole for the other tests)
    earlier = tmp_path / "earlier"
    shutil.copytree(report, earlier)
    code, out, err = run(capfd, "report", "--data", data, "--out", earlier, "--patient", "P2")
    assert code == 0, err
    df = trials_frame(earlier)
    assert set(df.patient) == {"P2"}
    # visits from a date on
    code, out, err = run(capfd, "report", "--data", data, "--out", tmp_path / "later", "--from", "2026-02-01")
    assert code == 0, err
    assert set(trials_frame(tmp_path / "later").visit_date) == {"2026-02-14", "2026-03-01"}
    code, _, err = run(capfd, "report", "--data", data, "--out", tmp_path / "x", "--patient", "NOPE")
    assert code == 2 and len(err) == 1 and "NOPE" in err[0]
    code, _, err = run(capfd, "report", "--data", tmp_path / "empty", "--out", tmp_path / "y")
    assert code == 2 and len(err) == 1
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


@pytest.mark.slow
def test_report_keeps_an_earlier_reports_file_the_user_edited(data, report, tmp_path, capfd):
    """A table of an earlier report that the user has since changed (notes added in a spreadsheet)
    is theirs: the folder is refused untouched. It was replaced, the notes lost, exit 0."""
    earlier = tmp_path / "earlier"
    shutil.copytree(report, earlier)
    with open(earlier / "trials.csv", "a", encoding="utf-8") as fh:
        fh.write("my notes on P2,,,\n")
    before = (earlier / "trials.csv").read_bytes()
    code, _, err = run(capfd, "report", "--data", data, "--out", earlier)
    assert code == 2 and len(err) == 1 and "did not write" in err[0], err
    assert (earlier / "trials.csv").read_bytes() == before
    (earlier / "trials.csv").unlink()  # a file of the report removed by the user: the rest is still the report's
    code, _, err = run(capfd, "report", "--data", data, "--out", earlier)
    assert code == 0 and (earlier / "trials.csv").is_file(), err


def test_export_c3d_reads_back_with_seven_labelled_marks(data, tmp_path, capfd):
    import c3d

    with Store.open(data_dir=data, read_only=True) as store:
        trial = store.trials.all(store.sessions.all("P3")[0].id)[1]
        marks = {m.label: (m.x, m.y, m.z) for m in store.marks.all(trial.id)}
    out = tmp_path / "trial.c3d"
    code, _, err = run(capfd, "export", "--data", data, "--trial", trial.id, "--format", "c3d", "--out", out)
    assert code == 0, err
    with open(out, "rb") as fh:
        reader = c3d.Reader(fh)
        labels = [s.strip() for s in reader.point_labels]
        frames = list(reader.read_frames())
    assert labels == ["1", "2", "3", "4", "5", "6", "7"] and len(frames) == 1
    pts = frames[0][1]
    for i, lab in enumerate(range(1, 8)):
        assert np.allclose(pts[i, :3], marks[lab], atol=1e-3)
    code, _, err = run(capfd, "export", "--data", data, "--session", 1, "--format", "c3d",
                       "--out", out.with_suffix(".x"))
    assert code == 2 and len(err) == 1
    code, said, _ = run(capfd, "export", "--data", data, "--trial", trial.id, "--format", "c3d", "--out", out)
    assert code == 0 and "C3D" in said and "not counted" not in said


def test_export_c3d_of_an_excluded_trial_says_so(data, tmp_path, capfd):
    """An excluded trial's marks are exported as they are, but the line said nothing of its
    state: a C3D of the sneeze trial read like any other."""
    with Store.open(data_dir=data, read_only=True) as store:
        trial = next(t for t in store.trials.all(store.sessions.all("P1")[0].id) if t.excluded_reason)
    code, said, err = run(capfd, "export", "--data", data, "--trial", trial.id, "--format", "c3d",
                          "--out", tmp_path / "sneeze.c3d")
    assert code == 0, err
    assert said.strip().endswith("; the trial is not counted in the statistics (excluded: =patient sneezed)"), said


def test_export_fhir_bundle_is_valid(data, tmp_path, capfd):
    from fhir.resources.R4B.bundle import Bundle

    out = tmp_path / "session.json"
    code, _, err = run(capfd, "export", "--data", data, "--session", 1, "--format", "fhir", "--out", out)
    assert code == 0, err
    obj = json.loads(out.read_text())
    b = Bundle.model_validate(obj) if hasattr(Bundle, "model_validate") else Bundle.parse_obj(obj)
    obs = [e.resource for e in b.entry if e.resource.__resource_type__ == "Observation"]
    # one per complete trial of session 1 (P1's first): 3, the excluded one and the moved one; not the failed one
    assert len(obs) == 5
    assert sum("excluded" in o.note[0].text for o in obs) == 2
    for o in obs:
        units = {c.valueQuantity.code for c in o.component}
        assert units == {"deg"}
        codes = {c.code.coding[0].code for c in o.component}
        assert {"leg_inversion", "table_plantar_flexion", "mismatch_inversion"} <= codes
        assert o.bodySite.coding[0].code == "70258002" and o.effectiveDateTime is not None
    code, _, err = run(capfd, "export", "--data", data, "--session", 999, "--format", "fhir", "--out",
                       tmp_path / "n.json")
    assert code == 2 and len(err) == 1 and not (tmp_path / "n.json").exists()
    # the same export again replaces its own bundle; a C3D export onto it, or a FHIR export onto
    # another JSON (a measurement result), is refused and leaves that file as it was
    assert run(capfd, "export", "--data", data, "--session", 1, "--format", "fhir", "--out", out)[0] == 0
    before = out.read_bytes()
    trial = tmp_path / "trial.json"
    trial.write_text('{"marks": {}, "angles": {}}')
    for fmt, target in (("c3d", out), ("fhir", trial)):
        code, _, err = run(capfd, "export", "--data", data, "--session", 1, "--format", fmt, "--out", target)
        assert code == 2 and len(err) == 1 and "did not write" in err[0], err
    assert out.read_bytes() == before and trial.read_text() == '{"marks": {}, "angles": {}}'


def test_export_fhir_of_one_failed_trial_says_so(data, tmp_path, capfd):
    """`export --trial N --format fhir` of a failed trial said "the session has no complete trial",
    naming neither the trial asked for nor why."""
    with Store.open(data_dir=data, read_only=True) as store:
        failed = next(t for t in store.trials.all(store.sessions.all("P1")[0].id) if t.status == "failed")
    out = tmp_path / "t.json"
    code, _, err = run(capfd, "export", "--data", data, "--trial", failed.id, "--format", "fhir", "--out", out)
    assert code == 2 and len(err) == 1 and f"trial {failed.id} failed" in err[0], err
    assert not out.exists()


def test_report_pages_follow_the_drawing_rules(report):
    """No "-0.00" anywhere; a page whose settings all have one trial says so and asks for repeats;
    one trial is one point; legends sit above the axes, off the data."""
    import subprocess

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from anklescan.core.records import report as rp

    assert rp.signed(-0.001) == "+0.00" and rp.signed(-0.006) == "-0.01"
    if shutil.which("pdftotext"):   # the module's report: every patient of `data`
        text = subprocess.run(["pdftotext", str(report / "report.pdf"), "-"], capture_output=True, text=True).stdout
        assert "-0.00" not in text and "\u22120.00" not in text
        assert "one trial (n=1)" in text and "Repeat every setting" in text   # patient P9
    one = [StudyRow(id=1, session_id=1, created="", ref_inversion=0.0, ref_plantar_flexion=0.0, patient_code="P9",
                    condition="barefoot", mismatch_inversion=0.4, mismatch_plantar_flexion=-0.3, marks_confirmed=False)]
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.1, 0.1, 0.8, 0.6))
    rp._plot_error_range(ax, {0.0: one}, "inversion")
    points = [ln for ln in ax.lines if ln.get_marker() == "o" and len(ln.get_xdata())]
    assert len(points) == 1 and points[0].get_markerfacecolor() == "none" and points[0].get_zorder() > 4
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    assert ax.get_legend().get_window_extent(r).y0 >= ax.get_window_extent(r).y1 - 1


def test_a_change_is_real_only_beyond_the_kept_mdc(tmp_path):
    """The site's MDC kept in the data folder judges a patient's visits when the database alone cannot
    give one (here: a single patient), and only a change larger than MDC95 is called real."""
    from anklescan.core.records import reliability as rel
    from anklescan.core.records.study import patient_visits, study_tables

    kept = [rel.Reliability("barefoot", axis, 6, 0.8, 0.4, 0.95, 0.25, 1.96 * math.sqrt(2) * 0.25)
            for axis in ("inversion", "plantar_flexion")]
    assert rel.save_site_mdc(tmp_path, kept, "2026-12-04T10:00:00") == tmp_path / "site_mdc.json"
    assert rel.load_site_mdc(tmp_path)[("barefoot", "inversion")] == kept[0]
    with Store.open(data_dir=tmp_path) as store:
        store.patients.add("Q1")
        for date, err in (("2026-01-05", 2.0), ("2026-02-05", 1.5), ("2026-03-05", 0.2)):
            s = store.sessions.start("Q1", condition="barefoot", date=date)
            t = store.trials.add(s.id, ref_inversion=5.0, ref_plantar_flexion=0.0)
            store.results.update_marks(t.id, table_marks(5.0 + err, 0.0), "manual", "test")
        data = store.reports.report_input()
    visits = [v for v in patient_visits(study_tables(data, data_dir=tmp_path), "Q1") if v.axis == "inversion"]
    mdc = kept[0].mdc95   # 0.69°
    assert [v.real for v in visits] == [None, False, True]   # -0.5° is within it, -1.3° is real
    assert visits[2].change == pytest.approx(-1.3, abs=1e-6) and abs(visits[2].change) > mdc


def test_c3d_keeps_seven_labels_when_marks_are_missing(tmp_path):
    """A trial with marks 3 and 4 not found: still seven labelled points, those two invalid (residual −1)."""
    import warnings

    import c3d

    from anklescan.core.records.c3d import write_c3d

    marks = {k: v for k, v in table_marks(5.0, 0.0).items() if k not in (3, 4)}
    assert write_c3d(marks, tmp_path / "t.c3d") == 5
    with open(tmp_path / "t.c3d", "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")   # "no analog data": a still scan has none
        reader = c3d.Reader(fh)
        assert [s.strip() for s in reader.point_labels] == [str(k) for k in range(1, 8)]
        (_, pts, _), = list(reader.read_frames())
    assert (pts[[2, 3], 3] == -1).all() and (pts[[0, 1, 4, 5, 6], 3] >= 0).all()
    assert np.allclose(pts[4, :3], marks[5], atol=1e-3)


def test_report_on_an_empty_database_file_says_it_is_empty(tmp_path, capfd):
    """A 0-byte anklescan.sqlite (a failed copy) was said not to exist."""
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "anklescan.sqlite").write_bytes(b"")
    code, _, err = run(capfd, "report", "--data", folder, "--out", tmp_path / "out")
    assert code == 2 and len(err) == 1 and "is empty" in err[0] and "not exist" not in err[0], err
    assert not (tmp_path / "out").exists() and (folder / "anklescan.sqlite").read_bytes() == b""
