"""Help, Edit and Print for the main window: the user guide (docs/gui.md, shipped in the package
and shown offline), the keyboard shortcuts (read from the window's own actions, so the list is
never stale), the version, the mark editor's Undo / Redo, printing the session plots, and where
files the clinician saves are proposed (the user's documents folder, named by patient and date).
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
import re
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QStandardPaths, Qt, QUrl
from PySide6.QtGui import QKeySequence, QPainter
from PySide6.QtWidgets import (
    QDialog,
    QDialogButtonBox,
    QMainWindow,
    QMenu,
    QTableWidget,
    QTableWidgetItem,
    QTextBrowser,
    QVBoxLayout,
    QWidget,
)

if TYPE_CHECKING:  # QtPrintSupport is loaded only when the user prints (app.review)
    from PySide6.QtPrintSupport import QPrinter

GUIDE = "gui.md"
# keys that act without a menu entry (their widgets' own shortcuts), as a person needs to know them
OTHER_KEYS = (
    ("1 – 7", "3-D marks: choose the mark to place"),
    ("Delete", "3-D marks: delete the chosen mark"),
    ("R / F / L / T", "3-D view: reset, front, lateral, top view"),
    ("Arrow keys (Shift: 10 px)", "Projector window: move the calibration spot"),
    ("Return", "Trial form: check the typed angle"),
)


def version() -> str:
    try:
        return metadata.version("anklescan")
    except metadata.PackageNotFoundError:  # run from a checkout that is not installed
        return "unknown (not installed)"


def docs_folder() -> Path:
    """The user guide's folder: the installed package's ``anklescan.docs``, else the checkout's docs/."""
    try:  # a folder of package data, not a module: its spec says where it is
        spec = importlib.util.find_spec("anklescan.docs")
    except (ImportError, ValueError):
        spec = None
    for location in (spec.submodule_search_locations or []) if spec is not None else []:
        if (Path(location) / GUIDE).is_file():
            return Path(location)
    return Path(__file__).resolve().parent.parent / "docs"


def guide_text() -> str:
    return (docs_folder() / GUIDE).read_text(encoding="utf-8")


class GuideDialog(QDialog):
    """docs/gui.md rendered (Markdown, with its screenshots), read from the package: offline."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("AnkleScan user guide")
        self.resize(860, 700)
        self.browser = QTextBrowser()
        self.browser.setOpenExternalLinks(False)  # patient data stays local: no link leaves the app
        folder = docs_folder()
        self.browser.setSearchPaths([str(folder)])
        try:
            text = guide_text()
        except OSError as exc:
            text = f"# The user guide could not be read\n\n{exc}"
        self.browser.document().setBaseUrl(QUrl.fromLocalFile(str(folder) + "/"))
        self.browser.setMarkdown(text)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.reject)
        layout = QVBoxLayout(self)
        layout.addWidget(self.browser)
        layout.addWidget(buttons)


def shortcut_rows(window: QMainWindow) -> list[tuple[str, str]]:
    """(keys, what) for every menu action with a shortcut, then the widgets' own keys."""
    rows: list[tuple[str, str]] = []

    def walk(menu: QMenu, path: str) -> None:
        for a in menu.actions():
            sub = a.menu()  # a QObject to the type stubs; a QMenu in a widgets application
            if isinstance(sub, QMenu):
                walk(sub, f"{path} ▸ {a.text().replace('&', '')}")
            elif not a.isSeparator() and not a.shortcut().isEmpty():
                keys = a.shortcut().toString(QKeySequence.SequenceFormat.NativeText)
                rows.append((keys, f"{path} ▸ {a.text().replace('&', '')}"))
    for top in window.menuBar().actions():
        menu = top.menu()
        if isinstance(menu, QMenu):
            walk(menu, top.text().replace("&", ""))
    return rows + list(OTHER_KEYS)


class ShortcutsDialog(QDialog):
    def __init__(self, window: QMainWindow):
        super().__init__(window)
        self.setWindowTitle("Keyboard shortcuts")
        rows = shortcut_rows(window)
        self.table = QTableWidget(len(rows), 2)
        self.table.setHorizontalHeaderLabels(["Keys", "Does"])
        self.table.verticalHeader().hide()
        self.table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        for r, (keys, what) in enumerate(rows):
            self.table.setItem(r, 0, QTableWidgetItem(keys))
            self.table.setItem(r, 1, QTableWidgetItem(what))
        self.table.resizeColumnsToContents()
        self.table.horizontalHeader().setStretchLastSection(True)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.reject)
        layout = QVBoxLayout(self)
        layout.addWidget(self.table)
        layout.addWidget(buttons)
        self.resize(620, 520)


def about_text() -> str:
    return (f"<b>AnkleScan {version()}</b><br>Measures functional ankle instability with a structured-light "
            "3-D scanner (one camera, one projector). Patient data stay on this computer.<br>"
            "Help ▸ User guide (F1) explains each step; Help ▸ Keyboard shortcuts lists the keys.")


# ---------------------------------------------------------------------------- save locations

def documents_folder() -> Path:
    """Where files the clinician saves are proposed: the user's documents folder (AnkleScan in it),
    never the patient data folder (which the app keeps to itself)."""
    base = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.DocumentsLocation) or str(Path.home())
    return Path(base) / "AnkleScan"


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "anklescan"


def proposed_path(kind: str, code: str | None, day: str | None, suffix: str) -> Path:
    """``<documents>/AnkleScan/<kind>_<patient code>_<date>.<suffix>``, e.g. report_P-001_2026-12-04.pdf."""
    parts = [kind, code or "", day or _dt.date.today().isoformat()]
    return documents_folder() / (safe_name("_".join(p for p in parts if p)) + suffix)


# ---------------------------------------------------------------------------- print

def print_widget_pages(printer: QPrinter, widgets: list[QWidget], heading: str) -> None:
    """Each widget scaled onto a page of ``printer``, under ``heading`` (e.g. "SIMULATED")."""
    painter = QPainter(printer)
    try:
        for i, widget in enumerate(widgets):
            if i:
                printer.newPage()
            page = printer.pageLayout().paintRectPixels(printer.resolution())
            painter.drawText(0, 0, page.width(), 60, Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignTop, heading)
            image = widget.grab()
            scale = min(page.width() / max(image.width(), 1), (page.height() - 80) / max(image.height(), 1))
            painter.save()
            painter.translate(0, 80)
            painter.scale(scale, scale)
            painter.drawPixmap(0, 0, image)
            painter.restore()
    finally:
        painter.end()
