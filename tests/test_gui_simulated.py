"""The simulated rig a newcomer can trust (issue 42): a simulated patient stands on the tables,
sets the adjustable one to the references the clinician types, and everything says "simulated"."""

import csv
import json
import subprocess

import numpy as np
import pytest
from gui_actions import button, calibrated_window, click, menu_action, press_accept, save_as, with_dialog
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QLineEdit

from anklescan.app.main_parts import PAGE_MARKS, PAGE_SCAN, PAGE_SESSION
from anklescan.hardware.sim_patient import PatientProfile, SimulatedPatient

pytestmark = pytest.mark.gui


def _type(field: QLineEdit, text: str) -> None:
    click(field)
    field.selectAll()
    QTest.keyClicks(field, text)
    QTest.keyClick(field, Qt.Key.Key_Return)


def test_a_simulated_patient_sets_the_table_near_the_reference():
    """The model alone: a sprain history sets the table further from the reference than none."""
    refs = [(inv, pf) for inv in (0.0, 10.0, 20.0) for pf in (-20.0, 0.0, 20.0)] * 10
    spread = {}
    for profile in PatientProfile:
        patient = SimulatedPatient(profile, seed=3)
        errors = np.array([patient.stance(r, "barefoot").mismatch for r in refs])
        spread[profile] = float(np.sqrt(np.mean(errors ** 2)))
        assert 0.2 < spread[profile] < 5.0
    assert spread[PatientProfile.SPRAIN_HISTORY] > 1.5 * spread[PatientProfile.NO_SPRAIN]
    # seeded: the same patient answers the same way
    a, b = SimulatedPatient(PatientProfile.NO_SPRAIN, seed=1), SimulatedPatient(PatientProfile.NO_SPRAIN, seed=1)
    assert a.stance((10.0, 0.0), "shoes") == b.stance((10.0, 0.0), "shoes")


@pytest.mark.slow
def test_three_trials_on_the_simulated_rig_follow_the_references(qtbot, tmp_path, monkeypatch):
    """New patient, session, three trials at different references on the app's default rig
    scale: each measured mismatch is the simulated patient's table setting error (small), not
    minus the reference; the window, the trial list, the report's every page and the CSV say
    simulated."""
    (tmp_path / "scale.ini").write_text("[scan]\nsim_scale=0.75\n")
    monkeypatch.setenv("ANKLESCAN_SETTINGS", str(tmp_path / "scale.ini"))
    win = calibrated_window(qtbot)
    win.resize(1280, 800)
    panel = win.camera_panel
    assert panel.patient_box.isVisibleTo(panel)
    panel.profile.setCurrentIndex(panel.profile.findData(PatientProfile.SPRAIN_HISTORY.value))
    assert win.settings.sim_patient is PatientProfile.SPRAIN_HISTORY
    assert "SIMULATED" in win.rig_label.text() and "sprain history" in win.rig_label.text()

    def fill(dialog):
        QTest.keyClicks(dialog.code, "SIM-P1")
        dialog.sprains.lineEdit().selectAll()
        QTest.keyClicks(dialog.sprains.lineEdit(), "3")
        dialog.side.setCurrentIndex(dialog.side.findData("right"))
        QTest.keyClicks(dialog.last_sprain, "14.8.2026")
        press_accept(dialog)  # not a date: the dialog stays open and says how to write it
        assert dialog.isVisible() and "YYYY-MM-DD" in dialog.message.text()
        dialog.last_sprain.clear()
        QTest.keyClicks(dialog.last_sprain, "2026-08-14")
        press_accept(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), fill)
    patient = win.store.patients.get("SIM-P1")
    assert patient.last_sprain == "2026-08-14" and patient.affected_side == "right"
    assert win.records.patients.currentItem().text() == "SIM-P1   ·  3 sprain(s), right side"
    click(button(win, "New session"))
    sid = win.records.current_session_id()

    refs = [(0.0, -20.0), (10.0, 0.0), (20.0, 20.0)]
    for inv, pf in refs:
        form = win.scan_page.form
        win.tabs.setCurrentIndex(PAGE_SCAN)
        _type(form.inversion.edit, f"{inv:g}")
        _type(form.plantar_flexion.edit, f"{pf:g}")
        with qtbot.waitSignal(win.controller.busyChanged, timeout=240_000, check_params_cb=lambda b: b is False):
            click(win.scan_page.scan_button)
        qtbot.wait(200)
    trials = win.store.trials.all(sid)
    assert len(trials) == 3 and all(t.simulated and t.status == "complete" for t in trials)
    print()
    for t, ref in zip(trials, refs, strict=True):
        assert (t.ref_inversion, t.ref_plantar_flexion) == ref
        meta = json.loads((win.store.files.resolve(t.capture_path) / "manifest.json").read_text())["capture"]
        truth = meta["simulated_patient"]
        true_mismatch = np.subtract(truth["table_deg"], truth["reference_deg"])
        measured = np.array([t.mismatch_inversion, t.mismatch_plantar_flexion])
        print(f"reference {ref}: true mismatch {true_mismatch.round(2)}, measured {measured.round(2)}")
        assert np.all(np.abs(true_mismatch) < 8.0)                 # a patient's error, not minus the reference
        assert np.all(np.abs(measured - true_mismatch) < 1.0)      # the scanner measures what the patient set
    # after the scan the projector is back to black (no stripe pattern left on the patient), and the
    # Result tab shows the last trial's angles, without "-0.00"
    assert win.projector.mode == "black"
    result_text = win.result_page.angles.text()
    last = trials[-1]
    assert "Mismatch" in result_text and f"{last.mismatch_inversion:+.2f}°" in result_text
    assert "SIMULATED" in result_text and "-0.00" not in result_text
    # the screens say simulated: the trial list (numbered per session) and the 3-D view's title
    texts = [win.records.trials.item(i).text() for i in range(win.records.trials.count())]
    assert [s.split()[1] for s in texts] == ["1", "2", "3"] and all("simulated" in s for s in texts)

    win.tabs.setCurrentIndex(PAGE_SESSION)  # the session plots say it in their title
    assert "SIMULATED" in win.session_view.title

    pdf = tmp_path / "out" / "report.pdf"
    pdf.parent.mkdir()
    with qtbot.waitSignal(win.reportWritten, timeout=120_000):
        with_dialog(qtbot, menu_action(win, "File/Session report (PDF + CSV)…").trigger, save_as(pdf))
    pages = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True,
                           check=True).stdout.split("\f")
    pages = [p for p in pages if p.strip()]
    assert pages and all("SIMULATED" in p for p in pages)
    with open(pdf.with_suffix(".csv"), encoding="utf-8-sig") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3 and {r["simulated"] for r in rows} == {"1"}
    win.close()


@pytest.mark.slow
def test_an_uncertain_mark_is_shown_where_it_is_and_only_where_it_holds(qtbot, tmp_path, monkeypatch):
    """The lateral knee plate clips at plantar flexion +20 and not at -20 (the table now follows
    the reference): after the +20 scan mark 3's SD and 'overexposed' are in the marks table, beside
    its label in the 3-D view, in the database and in the report; the -20 scan warns of nothing."""
    (tmp_path / "scale.ini").write_text("[scan]\nsim_scale=0.5\n")
    monkeypatch.setenv("ANKLESCAN_SETTINGS", str(tmp_path / "scale.ini"))
    win = calibrated_window(qtbot)
    win.resize(1280, 800)
    win.records.add_patient("P-OVER", 0, None)
    win.records.start_session("barefoot")
    sid = win.records.current_session_id()

    def scan(inv: str, pf: str) -> int:
        win.tabs.setCurrentIndex(PAGE_SCAN)
        _type(win.scan_page.form.inversion.edit, inv)
        _type(win.scan_page.form.plantar_flexion.edit, pf)
        with qtbot.waitSignal(win.controller.busyChanged, timeout=240_000, check_params_cb=lambda b: b is False):
            click(win.scan_page.scan_button)
        qtbot.wait(200)
        return win.store.trials.all(sid)[-1].id

    # the patient already has a real trial (from a real rig): mixing is said, on screen and in the report
    real = win.store.trials.add(sid, ref_inversion=5.0, ref_plantar_flexion=5.0, status="failed")
    assert not real.simulated
    low = scan("0", "-20")
    assert "overexposed" not in win.banner.text and "keep simulated patients apart" in win.banner.text
    print("\n-20:", {m.label: (round(m.sd_mm, 3), m.warning) for m in win.store.marks.all(low)})
    assert all("overexposed" not in m.warning for m in win.store.marks.all(low))
    high = scan("0", "20")
    assert "Mark 3 is overexposed" in win.banner.text
    marks = {m.label: m for m in win.store.marks.all(high)}
    assert marks[3].warning == "overexposed" and marks[3].sd_mm > 0
    win.tabs.setCurrentIndex(PAGE_MARKS)
    qtbot.wait(100)
    table = win.marks_page.editor.list
    header = [table.horizontalHeaderItem(c).text() for c in range(table.columnCount())]
    assert "SD" in header
    row3 = [table.item(2, c).text() for c in range(table.columnCount())]
    assert row3[header.index("SD")] == f"{marks[3].sd_mm:.2f}" and "overexposed" in row3[-1]
    status = table.item(2, table.columnCount() - 1)  # read whole, not cut to "automatic, to ..."
    rect = table.visualItemRect(status)
    needed = table.fontMetrics().boundingRect(0, 0, rect.width() - 8, 1000, Qt.TextFlag.TextWordWrap, status.text())
    assert needed.height() <= rect.height() and needed.width() <= rect.width()
    # every row of the table is on screen, none scrolled away
    assert table.viewport().height() >= sum(table.rowHeight(r) for r in range(table.rowCount()))
    assert "overexposed" in win.marks_page.viewer.mark_notes[3]
    # confirming keeps the warning; the next banner does not take it away
    click(win.marks_page.editor.confirm_button)
    win.banner.show_message("info", "something else")
    assert {m.label: m for m in win.store.marks.all(high)}[3].warning == "overexposed"
    pdf = tmp_path / "out" / "report.pdf"
    pdf.parent.mkdir()
    with qtbot.waitSignal(win.reportWritten, timeout=120_000):
        with_dialog(qtbot, menu_action(win, "File/Session report (PDF + CSV)…").trigger, save_as(pdf))
    text = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True,
                          check=True).stdout
    assert "mark 3 overexposed" in " ".join(text.split())
    pages = [p for p in text.split("\f") if p.strip()]
    assert all("SIMULATED and real trials mixed" in " ".join(p.split()) for p in pages)
    win.close()


def test_the_simulated_patient_sways_as_set_in_camera_setup(qtbot):
    win = calibrated_window(qtbot)
    panel = win.camera_panel
    assert panel.sway.specialValueText() == "stands still" and win.rig.camera.rig.motion is None
    panel.sway.setValue(2.0)
    assert win.settings.sim_sway_mm == 2.0
    assert win.rig.camera.rig.motion is not None and win.rig.camera.rig.motion.sway.amplitude_mm == 2.0
    # the next trial's stance keeps the sway
    win.rig.stand_patient((0.0, 0.0), "barefoot")
    assert win.rig.camera.rig.motion is not None
    panel.sway.setValue(0.0)
    assert win.rig.camera.rig.motion is None
    win.close()
