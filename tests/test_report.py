"""PDF/CSV reports and the study statistics behind the group page."""

import csv
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from anklescan.core.errors import AnkleScanError
from anklescan.core.records import report
from anklescan.core.records import study_stats as st
from anklescan.core.records.report import CSV_COLUMNS, UNCONFIRMED_LABEL, write_session_report, write_study_report
from anklescan.core.records.store import Store
from anklescan.core.vocabulary import Angle, StudyRow

INV_SETTINGS = (0.0, 20.0)
PF_SETTINGS = (0.0, 10.0, 20.0, 30.0)


def synthetic_study(store: Store, n_per_group=3, repeats=2, seed=0):
    """Sprain-history patients mis-sense more, shoes help: the paper's qualitative result."""
    rng = np.random.default_rng(seed)
    cal = store.calibrations.add({"units": "mm"}, rms=0.21, source="simulated rig", verified=True)
    sessions = []
    for g, sprains in (("S", 3), ("C", 0)):
        for i in range(n_per_group):
            code = f"{g}-{i + 1:02d}"
            store.patients.add(code, sprain_count=sprains, affected_side="right" if sprains else None,
                              last_sprain="2024-01-15" if sprains else None)
            for cond in ("barefoot", "shoes"):
                s = store.sessions.start(code, condition=cond, date="2024-06-03",
                                        operator="Dr. Test", calibration_id=cal.id)
                sessions.append(s.id)
                spread = (4.0 if sprains else 1.5) * (0.6 if cond == "shoes" else 1.0)
                for inv in INV_SETTINGS:
                    for pf in PF_SETTINGS:
                        for _ in range(repeats):
                            t = store.trials.add(s.id, ref_inversion=inv, ref_plantar_flexion=pf)
                            ti, tp = inv + rng.normal(0, spread), pf + rng.normal(0.05 * pf, spread)
                            store.results.update_angles(t.id, {
                                "leg_inversion": Angle(rng.normal(2, 1), 0.1),
                                "leg_plantar_flexion": Angle(pf * 0.4, 0.1),
                                "table_inversion": Angle(ti, 0.15),
                                "table_plantar_flexion": Angle(tp, 0.15)})
    return sessions


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    path = tmp_path_factory.mktemp("study") / "db.sqlite"
    with Store.open(path) as s:
        sessions = synthetic_study(s)
    s = Store.open(path)
    yield s, sessions
    s.close()


def pdf_pages(path: Path) -> int:
    """Page count from the PDF page tree (matplotlib writes one /Count)."""
    import re
    counts = re.findall(rb"/Type /Pages[^>]*?/Count (\d+)|/Count (\d+)[^>]*?/Type /Pages",
                        path.read_bytes())
    return max(int(a or b) for a, b in counts)


# ----------------------------------------------------------------- reports

def test_session_report_pdf_and_csv(study, tmp_path):
    store, sessions = study
    pdf, out_csv = tmp_path / "r.pdf", tmp_path / "r.csv"
    res = write_session_report(store.reports.report_input(sessions[:1]), pdf, out_csv)
    # header/table page (16 trials fit) + Fig. 10 + one error-range page per inversion
    # setting + the group page
    assert res.pages == 1 + 1 + len(INV_SETTINGS) + 1
    assert pdf.read_bytes()[:5] == b"%PDF-" and pdf_pages(pdf) == res.pages
    rows = list(csv.DictReader(out_csv.open()))
    trials = store.trials.all(sessions[0])
    assert len(rows) == len(trials) and tuple(rows[0]) == CSV_COLUMNS
    for r, t in zip(rows, trials, strict=False):
        assert int(r["trial_id"]) == t.id and r["patient_code"] == "S-01"
        assert r["condition"] == "barefoot" and float(r["calibration_rms"]) == 0.21
        for k in ("ref_inversion", "table_inversion", "mismatch_plantar_flexion",
                  "mismatch_inversion_sd"):
            assert float(r[k]) == getattr(t, k)
        assert r["capture_path"] == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv", "r.pdf"]
    if shutil.which("pdftoppm"):   # the page must also rasterise (what a viewer does)
        subprocess.run(["pdftoppm", "-r", "30", "-png", "-f", "1", "-l", "1", str(pdf),
                        str(tmp_path / "p")], check=True, timeout=60)
        png = next(tmp_path.glob("p*.png"))
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_multi_session_report_pages(study, tmp_path):
    store, sessions = study
    res = write_session_report(store.reports.report_input(sessions[:2]), tmp_path / "r.pdf")
    assert res.pages == 2 * (2 + len(INV_SETTINGS)) + 1 and res.csv_path is None


def test_long_session_table_continues(tmp_path):
    with Store.open(tmp_path / "db.sqlite") as s:
        s.patients.add("L-1")
        ses = s.sessions.start("L-1", condition="shoes")
        for i in range(30):
            s.trials.add(ses.id, ref_inversion=0, ref_plantar_flexion=i)   # none measured
        res = write_session_report(s.reports.report_input([ses.id]), tmp_path / "l.pdf", tmp_path / "l.csv")
    # 24 rows + continuation page, Fig. 10 page ("no measured trials"); no group page: one
    # patient has nothing to compare
    assert res.pages == 2 + 1
    rows = list(csv.DictReader((tmp_path / "l.csv").open()))
    assert len(rows) == 30 and rows[0]["mismatch_inversion"] == ""


def test_study_report(study, tmp_path):
    store, _ = study
    res = write_study_report(store.reports.report_input(), tmp_path / "s.pdf", tmp_path / "s.csv")
    assert res.pages == 1 + 2 + 1 and pdf_pages(tmp_path / "s.pdf") == 4
    rows = list(csv.DictReader((tmp_path / "s.csv").open()))
    assert len(rows) == 12 * len(INV_SETTINGS) * len(PF_SETTINGS) * 2


def test_report_errors_leave_nothing(study, tmp_path):
    store, sessions = study
    with pytest.raises(AnkleScanError, match="does not exist"):
        write_session_report(store.reports.report_input(sessions[:1]), tmp_path / "nope" / "r.pdf")
    with pytest.raises(AnkleScanError, match="no session"):
        write_session_report(store.reports.report_input([99999]), tmp_path / "r.pdf", tmp_path / "r.csv")
    (tmp_path / "r.pdf").write_bytes(b"old")
    with pytest.raises(AnkleScanError, match="no sessions"):
        write_session_report(store.reports.report_input([]), tmp_path / "r.pdf")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.pdf"]
    assert (tmp_path / "r.pdf").read_bytes() == b"old"


def test_csv_neutralises_formulas(tmp_path):
    with Store.open(tmp_path / "db.sqlite") as s:
        s.patients.add("F-1")
        ses = s.sessions.start("F-1", condition="shoes", operator="=HYPERLINK(1)")
        s.trials.add(ses.id, ref_inversion=0, ref_plantar_flexion=0, notes="-2 felt odd")
        write_study_report(s.reports.report_input(), tmp_path / "f.pdf", tmp_path / "f.csv")
    r = next(csv.DictReader((tmp_path / "f.csv").open()))
    assert r["operator"] == "'=HYPERLINK(1)" and r["notes"] == "'-2 felt odd"


# ------------------------------------------------------------------- stats

def rows_for(values: dict[tuple[str, str], list[float]], sprains: dict[str, int]):
    return [StudyRow(id=i, session_id=1, created="", ref_inversion=None, ref_plantar_flexion=None,
                     patient_code=p, condition=c, sprain_count=sprains[p],
                     mismatch_inversion=v, mismatch_plantar_flexion=-v)
            for i, ((p, c), v) in enumerate(((pc, v) for pc, vs in values.items() for v in vs))]


def test_per_patient_aggregation_and_groups():
    vals = {("A", "barefoot"): [2, -4], ("B", "barefoot"): [5, 7], ("C", "barefoot"): [1, -1],
            ("D", "barefoot"): [0.5, 1.5]}
    s = st.study_stats(rows_for(vals, {"A": 2, "B": 1, "C": 0, "D": 0}))
    assert s.patient_means[("A", "barefoot", "inversion")] == 3.0
    ps = s.patient_summary[("sprain history", "barefoot", "inversion")]
    assert (ps.n, ps.mean_abs, ps.min, ps.max) == (2, 4.5, 3.0, 6.0)
    assert ps.sd == pytest.approx(math.sqrt(4.5))
    ts = s.trial_summary[("sprain history", "barefoot", "inversion")]
    assert ts.n == 4 and ts.mean_abs == 4.5 and ts.mean_signed == 2.5
    t = s.history_tests[("barefoot", "inversion")]
    assert (t.n_a, t.n_b) == (2, 2) and t.mean_diff == pytest.approx(3.5)
    assert t.rank_biserial == 1.0 and "indicative" in t.note
    assert s.history_tests[("shoes", "inversion")].note == st.TOO_SMALL
    assert s.condition_tests[("all", "inversion")].note == st.TOO_SMALL


def test_group_test_matches_scipy():
    from scipy import stats
    a, b = [3.1, 4.2, 5.0, 6.3, 4.4], [1.2, 2.0, 1.7, 2.9]
    t = st.compare_groups(a, b)
    assert t.welch_p == pytest.approx(stats.ttest_ind(a, b, equal_var=False).pvalue)
    assert t.mwu_p == pytest.approx(stats.mannwhitneyu(a, b).pvalue)
    assert t.hedges_g > 1


def test_paired_condition_comparison():
    a, b = [4.0, 5.0, 3.5, 6.0, 4.5], [2.0, 3.9, 2.5, 4.0, 2.2]
    t = st.compare_paired(a, b)
    assert t.n == 5 and t.mean_diff == pytest.approx(np.mean(np.subtract(a, b)))
    assert t.wilcoxon_p == pytest.approx(0.0625) and "0.0625" in t.note
    assert "n too small" in st.format_paired_test(st.compare_paired([1.0], [2.0]))
    assert st.compare_paired([1, 2], [0, 1]).note == "differences are all equal"


def test_report_stats_reflect_synthetic_effect(study):
    store, _ = study
    s = st.study_stats(store.reports.study_rows())
    for c in st.CONDITIONS:
        t = s.history_tests[(c, "inversion")]
        assert t.n_a == t.n_b == 3 and t.mean_diff > 0
    assert s.condition_tests[("all", "inversion")].n == 6
    assert s.condition_tests[("all", "inversion")].mean_diff > 0


# ------------------------------------------------- trial states, calibrations, plots

MARKS = {1: (10.0, 60.0, 520.0), 2: (0.0, 55.0, 200.0), 3: (55.0, 10.0, 520.0), 4: (45.0, 0.0, 200.0),
         5: (80.0, -100.0, 120.0), 6: (80.0, 95.0, 135.0), 7: (-48.0, 135.0, 128.0)}
LONG_SOURCE = ("imported from /home/clinic/anklescan/calibrations/2026-11-20_morning_box_scan_"
               "after_the_projector_was_refocused_and_levelled/calibration.json")


def _angles(ti, tp):
    return {"table_inversion": Angle(ti, 0.001), "table_plantar_flexion": Angle(tp, 0.001)}


@pytest.fixture
def states_session(tmp_path):
    """One patient: three counted trials with a mismatch of thousandths of a degree (one of
    them with unconfirmed automatic marks), and a cancelled, a failed and an excluded trial
    whose large mismatch must not reach any plot or statistic; two calibrations."""
    s = Store.open(tmp_path / "db.sqlite", data_dir=tmp_path)
    c1 = s.calibrations.add({"units": "mm"}, rms=0.21, source=LONG_SOURCE, verified=True)
    c2 = s.calibrations.add({"units": "mm"}, rms=0.3, source="simulated box scan")
    s.patients.add("P-1", sprain_count=2)
    ses = s.sessions.start("P-1", condition="barefoot", calibration_id=c1.id)   # no operator
    ids = {}
    for name, pf, d, cal in (("a", -20.0, 0.0015, None), ("b", 0.0, -0.0010, None), ("auto", 20.0, 0.0005, c2.id),
                             ("cancel", 0.0, 30.0, None), ("fail", 0.0, 30.0, None), ("excl", 20.0, -30.0, None)):
        t = s.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=pf, calibration_id=cal)
        s.results.update_angles(t.id, _angles(d, pf - d))
        ids[name] = t.id
    s.results.update_marks(ids["auto"], {5: MARKS[5]}, "auto", "", recompute=False)
    s.results.update_marks(ids["a"], {5: MARKS[5]}, "auto", "confirmed by dr.k", recompute=False)
    s.trials.set_status(ids["cancel"], "cancelled", "operator stopped the scan")
    s.trials.set_status(ids["fail"], "failed", "projector disconnected")
    s.trials.exclude(ids["excl"], "patient moved")
    yield s, ses.id, ids, (c1.id, c2.id)
    s.close()


def _capture_figures(monkeypatch) -> list:
    figs = []
    save = report._Pages.save

    def keep(self, fig):
        figs.append(fig)
        save(self, fig)
    monkeypatch.setattr(report._Pages, "save", keep)
    return figs


def test_study_rows_carry_state_and_mark_confirmation(states_session):
    store, sid, ids, (c1, c2) = states_session
    rows = {r.trial_id: r for r in store.reports.study_rows()}
    assert [rows[ids[k]].counted for k in ("a", "auto", "cancel", "fail", "excl")] == [1, 1, 0, 0, 0]
    assert rows[ids["a"]].marks_confirmed == 1 and rows[ids["auto"]].marks_confirmed == 0
    assert rows[ids["b"]].marks_confirmed == 1          # no marks: nothing left to confirm
    assert rows[ids["a"]].calibration_id == c1 and rows[ids["auto"]].calibration_id == c2


def test_states_shown_in_table_but_only_counted_trials_plotted(states_session, tmp_path, monkeypatch):
    store, sid, ids, (c1, c2) = states_session
    figs = _capture_figures(monkeypatch)
    res = write_session_report(store.reports.report_input([sid]), tmp_path / "r.pdf", tmp_path / "r.csv")
    # header + Fig. 10 + one error-range page; no group page (one patient: nothing to compare)
    assert res.pages == 3 == len(figs)
    texts = [t.get_text() for t in figs[0].texts]
    cells = [c.get_text().get_text() for ax in figs[0].axes for tab in ax.tables
             for c in tab.get_celld().values()]
    body = " ".join(texts + cells).replace("\n", " ")   # wrapped lines read as one
    for want in ("cancelled", "failed", "excluded", "complete*", "operator stopped the scan",
                 "patient moved", "projector disconnected", "not recorded", f"#{c1}", f"#{c2}",
                 "3 counted", "Group comparison"):
        assert want in body, want
    # only counted trials are "to do": the cancelled, failed and excluded ones have no leg marks either
    assert "3 with a leg angle missing" in body and "6 with" not in body
    # every header line stays on the page (the long calibration source wraps)
    r = figs[0].canvas.get_renderer()
    page = figs[0].bbox
    for t in figs[0].texts:
        box = t.get_window_extent(r)
        assert box.x0 >= page.x0 and box.x1 <= page.x1, t.get_text()[:40]
    # plots: only the three counted trials, all within ±0.002°, on an axis of at least ±1°
    fig10, err = figs[1], figs[2]
    points = [y for ax in fig10.axes for ln in ax.lines if ln.get_marker() == "o" for y in ln.get_ydata()]
    assert points and max(abs(float(y)) for y in points) < 0.01
    for ax in fig10.axes + err.axes:
        lo, hi = ax.get_ylim()
        assert lo <= -report.MIN_HALF_SPAN_DEG and hi >= report.MIN_HALF_SPAN_DEG
        ax.figure.canvas.draw()
        assert ax.yaxis.get_offset_text().get_text() == ""          # no "1e-3" / "+1.2e1"
    # the trial with unconfirmed automatic marks is hollow, with its legend entry
    hollow = [ln for ax in err.axes for ln in ax.lines if ln.get_markerfacecolor() == "none" and len(ln.get_xdata())]
    assert len(hollow) == 2                          # one point per axis panel
    assert all(UNCONFIRMED_LABEL in [t.get_text() for t in ax.get_legend().get_texts()] for ax in err.axes)
    assert any(UNCONFIRMED_LABEL in [t.get_text() for t in leg.get_texts()] for leg in fig10.legends)
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert {r["status"] for r in rows} == {"complete", "cancelled", "failed"}
    assert [r["excluded_reason"] for r in rows if r["counted"] == "0"][-1] == "patient moved"
    if shutil.which("pdftotext"):
        text = subprocess.run(["pdftotext", "-layout", str(tmp_path / "r.pdf"), "-"], capture_output=True,
                              text=True, check=True).stdout
        assert "operator stopped the scan" in text and "Group comparison — " not in text


def test_stats_use_counted_trials_only(states_session):
    store, *_ = states_session
    rows = store.reports.study_rows()
    s = st.study_stats(rows)
    assert s.patient_means[("P-1", "barefoot", "inversion")] == pytest.approx((0.0015 + 0.0010 + 0.0005) / 3)
    assert s.trial_summary[("sprain history", "barefoot", "inversion")].n == 3
    assert not st.has_tests(s)
    assert sum(len(v) for per in report._by_setting(rows, "inversion").values() for v in per.values()) == 3


def test_group_page_only_with_something_to_compare(study, tmp_path, monkeypatch):
    store, sessions = study
    figs = _capture_figures(monkeypatch)
    write_session_report(store.reports.report_input(sessions[:1]), tmp_path / "r.pdf")
    assert figs[-1]._suptitle.get_text().startswith("Group comparison")
    assert st.has_tests(st.study_stats(store.reports.study_rows()))


def test_study_report_of_one_patient_has_no_empty_pages(states_session, tmp_path, monkeypatch):
    store, *_ = states_session
    figs = _capture_figures(monkeypatch)
    res = write_study_report(store.reports.report_input(), tmp_path / "s.pdf")
    # the overview (saying why there is no group comparison) and the one group that has a patient
    assert res.pages == 2
    assert "Group comparison" in [t.get_text() for t in figs[0].texts]
    assert figs[1]._suptitle.get_text().endswith("sprain history") and any(
        t.get_text().startswith("1 patient;") for t in figs[1].texts
    )


def test_session_report_states_the_mark_diameter_setting():
    from types import SimpleNamespace

    from anklescan.core.records.report import _mark_diameter_text

    assert _mark_diameter_text(SimpleNamespace(mark_diameter_mm=None)) == "measured from each capture (auto)"
    assert _mark_diameter_text(SimpleNamespace(mark_diameter_mm=12.5)) == "12.5 mm (given)"
