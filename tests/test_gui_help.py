"""Help, Edit and Print as a clinician meets them (issue 42): the user guide offline, the keyboard
shortcuts, the version, Undo / Redo of the marks from the Edit menu, printing, and where saved
files are proposed."""

import subprocess
from pathlib import Path

import pytest
from gui_actions import calibrated_window, dismiss, menu_action, press_accept, with_dialog
from PySide6.QtWidgets import QMessageBox, QTextBrowser

from anklescan.app.help_menu import version
from anklescan.app.logic.settings import CalibrationVerdict
from anklescan.app.main_parts import PAGE_MARKS, PAGE_SESSION

pytestmark = pytest.mark.gui


@pytest.fixture
def win(qtbot, tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))           # the user's documents folder is in here
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "home" / ".config"))
    w = calibrated_window(qtbot)
    w.resize(1280, 800)
    yield w
    w.close()


def test_help_has_the_guide_the_shortcuts_and_the_version(qtbot, win):
    seen = {}

    def read_guide(dialog):
        seen["guide"] = dialog.findChild(QTextBrowser).toPlainText()
        dismiss(dialog)
    with_dialog(qtbot, menu_action(win, "Help/User guide").trigger, read_guide)
    assert "The desktop application" in seen["guide"] and "The simulated rig's patient" in seen["guide"]
    assert "ANKLESCAN_SETTINGS" in seen["guide"]

    def read_keys(dialog):
        t = dialog.table
        seen["keys"] = {t.item(r, 1).text(): t.item(r, 0).text() for r in range(t.rowCount())}
        dismiss(dialog)
    with_dialog(qtbot, menu_action(win, "Help/Keyboard shortcuts").trigger, read_keys)
    keys = seen["keys"]
    assert keys["Edit ▸ Undo"] == "Ctrl+Z" and keys["File ▸ Print…"] == "Ctrl+P"
    assert keys["Scan ▸ Start scan"] == "F5" and "3-D marks: choose the mark to place" in keys

    def read_about(dialog):
        seen["about"] = dialog.text() if isinstance(dialog, QMessageBox) else ""
        press_accept(dialog)
    with_dialog(qtbot, menu_action(win, "Help/About AnkleScan").trigger, read_about)
    assert version() in seen["about"] and version() != "unknown (not installed)"


def test_edit_menu_undoes_and_redoes_the_marks(qtbot, win):
    win.tabs.setCurrentIndex(PAGE_MARKS)
    editor = win.marks_page.editor
    editor.propose_auto({lab: (float(lab), 0.0, 10.0 * lab) for lab in range(1, 8)})
    undo = menu_action(win, "Edit/Undo")
    assert not undo.isEnabled()  # the automatic marks are where the history starts
    editor.show_pick("Mark 1 placed where clicked.")
    editor.place(1, (5.0, 5.0, 5.0))
    undo = menu_action(win, "Edit/Undo move mark 1")
    assert undo.isEnabled()
    undo.trigger()  # Edit ▸ Undo move mark 1
    assert editor.marks[1].xyz == (1.0, 0.0, 10.0)
    assert "placed where clicked" not in editor.pick_label.text() and "Undone" in editor.pick_label.text()
    redo = menu_action(win, "Edit/Redo move mark 1")
    redo.trigger()
    assert editor.marks[1].xyz == (5.0, 5.0, 5.0) and "Redone" in editor.pick_label.text()


def test_print_writes_the_session_plots_and_reports_go_to_the_documents_folder(qtbot, win, tmp_path):
    win.records.add_patient("P-PRN", 0, None)
    win.records.start_session("barefoot")
    win.tabs.setCurrentIndex(PAGE_SESSION)
    qtbot.wait(100)
    with_dialog(qtbot, menu_action(win, "File/Print…").trigger, lambda d: press_accept(d))
    docs = tmp_path / "home" / "Documents" / "AnkleScan"
    (printed,) = docs.glob("print_P-PRN_*.pdf")
    text = subprocess.run(["pdftotext", str(printed), "-"], capture_output=True, text=True, check=True).stdout
    assert "Session plots" in text and "P-PRN" in text
    assert "printed to" in win.banner.text

    proposed = {}

    def look(dialog):
        proposed["path"] = Path(dialog.selectedFiles()[0])
        dismiss(dialog)
    with_dialog(qtbot, menu_action(win, "File/Session report (PDF + CSV)…").trigger, look)
    path = proposed["path"]
    assert path.parent == docs and path.name.startswith("report_P-PRN_") and path.suffix == ".pdf"
    assert not path.is_relative_to(win.data_folder())


def test_an_unwritable_settings_file_is_said_at_once(qtbot, tmp_path, monkeypatch):
    from anklescan.app.main_window import MainWindow
    folder = tmp_path / "settings-folder"
    folder.mkdir()
    monkeypatch.setenv("ANKLESCAN_SETTINGS", str(folder))  # a folder, not a file
    w = MainWindow(open_rig_now=True)
    qtbot.addWidget(w)
    w.show()
    said = w.settings_banner
    assert said.isVisible() and said.kind == "error" and "cannot be kept" in said.label.text()
    assert "ANKLESCAN_SETTINGS" in said.label.text() and "calibration" in said.label.text()
    assert w.settings_label.isVisible() and "NOT saved" in w.settings_label.text()
    w.close()


def test_the_current_calibration_is_chosen_from_the_database(qtbot, win):
    """Settings lost (the current calibration forgotten): the database's calibrations are listed
    with their date, RMS and verification, and one click makes one current again."""
    first_id = win.calibration_id
    win.store.calibrations.set_verified(first_id, True)
    win.settings.calibration_path, win.settings.calibration_id, win.settings.calibration_created = "", None, ""
    win.rig_setup.load_calibration()
    assert win.calibration is None and not win.scan_page.scan_button.isEnabled()
    seen = {}

    def choose(dialog):
        t = dialog.table
        seen["rows"] = [[t.item(r, c).text() for c in range(t.columnCount())] for r in range(t.rowCount())]
        press_accept(dialog, "Use this calibration")
    with_dialog(qtbot, menu_action(win, "Scan/Choose calibration…").trigger, choose)
    (row,) = seen["rows"]
    assert row[0].startswith(str(first_id)) and row[3] == "yes" and row[1][:4].isdigit()
    assert win.calibration is not None and win.calibration_id == first_id
    assert win.settings.calibration_verified is CalibrationVerdict.PASS and win.scan_page.scan_button.isEnabled()
