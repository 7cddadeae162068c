"""The app's start as a clinician meets it when the data folder is not simply free and healthy
(issue 40): another AnkleScan holds the folder (the lock names it and offers read-only), and a
database whose tables are gone (one message, no traceback)."""

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from gui_actions import dismiss, press_accept, with_dialog

from anklescan.app.main_window import MainWindow
from anklescan.core.records.store import (
    APPLICATION_ID,
    DB_FILENAME,
    SCHEMA_VERSION,
    Store,
)

pytestmark = pytest.mark.gui

_HOLD = ("import sys, time\n"
         "from anklescan.core.records.lock import DataFolderLock\n"
         "lock = DataFolderLock(sys.argv[1])\n"
         "assert lock.acquire() is None\n"
         "print('holding', flush=True)\n"
         "time.sleep(120)\n")


@pytest.fixture
def other_app():
    """Another AnkleScan process holding the data folder of the test's settings."""
    folder = Path(os.environ["ANKLESCAN_DATA"])
    with Store.open(data_dir=folder) as store:
        store.patients.add("P-01")
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "holding"
    yield proc
    proc.kill()
    proc.wait()


def _open_window(qtbot, handle):
    """Start the app; ``handle`` answers the question it asks. Returns the window and the
    question's text."""
    made, texts = [], []

    def answer(dialog):
        texts.append(dialog.text())
        handle(dialog)

    with_dialog(qtbot, lambda: made.append(MainWindow()), answer)
    win = made[0]
    qtbot.addWidget(win)
    return win, texts[0]


def test_second_instance_is_told_who_holds_the_folder_and_can_refuse(qtbot, other_app):
    win, question = _open_window(qtbot, dismiss)
    assert "in use" in question and f"process {other_app.pid}" in question
    assert win.session.store is None  # not opened: nothing could be written next to the other copy
    win.show()
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    assert win.banner.kind == "error" and "close the other AnkleScan" in win.banner.label.text()
    win.close()


def test_second_instance_opens_the_folder_read_only_when_asked(qtbot, other_app):
    win, question = _open_window(qtbot, press_accept)
    assert f"process {other_app.pid}" in question
    assert win.session.read_only and [p.code for p in win.session.patients()] == ["P-01"]
    win.show()
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    assert win.banner.kind == "warning" and "read-only" in win.banner.label.text()
    win.close()


def test_the_lock_is_free_again_once_the_other_app_is_gone(qtbot, other_app):
    other_app.kill()
    other_app.wait()
    win = MainWindow()  # no question: the lock died with its holder
    qtbot.addWidget(win)
    assert win.session.writable and [p.code for p in win.session.patients()] == ["P-01"]
    win.close()


def test_a_database_without_its_tables_is_one_message_not_a_crash(qtbot):
    folder = Path(os.environ["ANKLESCAN_DATA"])
    folder.mkdir(parents=True)
    db = folder / DB_FILENAME
    conn = sqlite3.connect(db)
    conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")  # ours, but its tables are gone
    conn.execute("CREATE TABLE unrelated (x)")
    conn.commit()
    conn.close()
    before = db.read_bytes()
    win = MainWindow()
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    assert win.session.store is None  # and its message is what the clinician still sees once the app is ready
    text = win.banner.label.text()
    assert win.banner.kind == "error" and "incomplete" in text and "patients" in text, text
    assert db.read_bytes() == before  # left untouched
    win.close()


def test_a_window_closed_while_its_rig_opens_is_no_crash(qtbot):
    """The window closed (and its widgets deleted) before the rig it opens in the background
    arrives: the rig is released and nothing touches the deleted widgets (an exception in the
    Qt event loop fails this test)."""
    from shiboken6 import delete

    from anklescan.app.background import pending_jobs

    win = MainWindow()
    setup = win.rig_setup
    setup.finish_startup()  # what the window's first event-loop turn does: the rig opens on a thread
    assert setup._starting
    win.close()
    delete(win)  # before any event is processed: the rig cannot have been delivered yet
    qtbot.waitUntil(lambda: pending_jobs() == 0 and not setup._starting, timeout=60_000)
    assert setup.rig is None
