"""The clinic's study in the app (issue 39), driven as a person drives it: File > Study report… (its
dialog filled through its own widgets, the report written in the background) and File > Patient
history… for the patient clicked in the sidebar."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
import pytest
from gui_actions import click, menu_action, press_accept, with_dialog
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QDialogButtonBox
from test_study import PF_SETTINGS, table_marks

from anklescan.app.main_window import MainWindow
from anklescan.core.records.store import Store

pytestmark = pytest.mark.gui
SHOTS = Path(os.environ.get("ANKLESCAN_SHOTS", "/tmp/anklescan-study-shots"))


def _fill_clinic(folder: Path) -> None:
    """Three patients, two visits each, barefoot and shoes: enough for reliability figures."""
    with Store.open(data_dir=folder) as store:
        for k, code in enumerate(("A-01", "A-02", "A-03")):
            store.patients.add(code, sprain_count=k)
            for cond in ("barefoot", "shoes"):
                for v, date in enumerate(("2026-03-02", "2026-04-06")):
                    s = store.sessions.start(code, condition=cond, date=date)
                    for j, pf in enumerate(PF_SETTINGS):
                        t = store.trials.add(s.id, ref_inversion=10.0, ref_plantar_flexion=pf)
                        err = ((k + 1) * 0.7 * (1 if cond == "barefoot" else 0.5) + 0.3 * ((j + v) % 3 - 1)
                               + 0.2 * v * (k - 1))
                        store.results.update_marks(t.id, table_marks(10.0 + err, pf - 0.5 * err), "manual", "test")


@pytest.fixture
def win(qtbot):
    _fill_clinic(Path(os.environ["ANKLESCAN_DATA"]))
    w = MainWindow()
    qtbot.addWidget(w)
    w.resize(1280, 800)
    w.show()
    qtbot.waitExposed(w)
    # the rig opens in the background after the window shows; let it finish as a person would
    qtbot.waitUntil(lambda: w.rig is not None and w.marks_page is not None, timeout=60_000)
    yield w
    w.study.wait_for_jobs()
    w.close()


@pytest.mark.slow
def test_study_report_and_patient_history_by_clicks(qtbot, win, tmp_path):
    SHOTS.mkdir(parents=True, exist_ok=True)
    out = tmp_path / "étude"

    def fill(dialog):
        dialog.patient.setCurrentText("All patients")
        dialog.out.setText(str(out))   # as pasted (typed keys cannot carry "é" under Xvfb)
        dialog.grab().save(str(SHOTS / "study_report_dialog.png"))
        press_accept(dialog)

    with_dialog(qtbot, menu_action(win, "File/Study report…").trigger, fill)
    qtbot.waitUntil(lambda: win.study.last_result is not None or win.banner.kind == "error", timeout=60_000)
    assert win.study.last_result is not None, win.banner.text
    assert (out / "report.pdf").is_file() and (out / "trials.xlsx").is_file()
    rel = pd.read_csv(out / "reliability.csv", encoding="utf-8-sig")
    assert (rel.n_patients == 3).all() and rel.mdc95.notna().all()
    assert "Study report saved" in win.banner.text

    # the patient's history: click the patient in the sidebar, then the menu action
    lst = win.records.patients
    item = lst.findItems("A-02", Qt.MatchFlag.MatchStartsWith)[0]
    rect = lst.visualItemRect(item)
    QTest.mouseClick(lst.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())
    assert win.records.current_code() == "A-02"
    menu_action(win, "File/Patient history…").trigger()
    dialog = win.study.history
    assert dialog is not None and dialog.isVisible()
    qtbot.waitExposed(dialog)
    assert dialog.table.rowCount() == 8   # 2 visits × 2 conditions × 2 axes
    judged = {dialog.table.item(r, 8).text() for r in range(dialog.table.rowCount())}
    assert judged <= {"–", "real change", "within MDC"} and judged - {"–"}
    qtbot.wait(100)
    dialog.grab().save(str(SHOTS / "patient_history.png"))
    win.grab().save(str(SHOTS / "main_window_after_study.png"))
    click(dialog.findChild(QDialogButtonBox).buttons()[0])   # Close
    assert not dialog.isVisible()
    # the same from the sidebar: the patient list's context menu holds it
    item = lst.findItems("A-03", Qt.MatchFlag.MatchStartsWith)[0]
    QTest.mouseClick(lst.viewport(), Qt.MouseButton.LeftButton, pos=lst.visualItemRect(item).center())
    (history,) = [a for a in lst.actions() if a.text() == "Patient history…"]
    history.trigger()
    assert win.study.history is not dialog and win.study.history.isVisible()
    assert "A-03" in win.study.history.windowTitle()
    win.study.history.close()


def test_study_report_refuses_a_foreign_folder(qtbot, win, tmp_path):
    foreign = tmp_path / "papers"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")

    def fill(dialog):
        dialog.out.clear()
        QTest.keyClicks(dialog.out, str(foreign))
        press_accept(dialog)

    with_dialog(qtbot, menu_action(win, "File/Study report…").trigger, fill)
    qtbot.waitUntil(lambda: win.banner.kind == "error", timeout=30_000)
    assert "did not write" in win.banner.text
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
