"""Icons and the application style: one calm palette, applied once."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from PySide6.QtGui import QIcon

from anklescan.core.vocabulary import Severity

ICONS = Path(str(files("anklescan.resources")))  # package data (resources/), so installed copies have it

ACCENT = "#1f5f8b"
WARN_BG = "#fff4d6"
WARN_FG = "#7a5300"
ERROR_BG = "#fde8e6"
ERROR_FG = "#8c1d18"
INFO_BG = "#e6f0f7"
INFO_FG = "#1f4a6b"

STYLE = f"""
QMainWindow, QWidget {{ font-size: 10pt; }}
QGroupBox {{ font-weight: 600; border: 1px solid #d5dbe1; border-radius: 6px; margin-top: 12px; padding: 10px 8px 8px 8px; }}
QGroupBox::title {{ subcontrol-origin: margin; left: 10px; padding: 0 4px; color: #33414e; }}
QPushButton#primary {{ background: {ACCENT}; color: white; border: none; border-radius: 5px; padding: 8px 22px;
                      font-weight: 600; }}
QPushButton#primary:disabled {{ background: #9db6c9; }}
QPushButton {{ padding: 5px 14px; }}
QListWidget {{ border: 1px solid #d5dbe1; border-radius: 4px; }}
QProgressBar {{ border: 1px solid #c9d1d8; border-radius: 4px; text-align: center; height: 18px; }}
QProgressBar::chunk {{ background: {ACCENT}; border-radius: 3px; }}
QLabel#rigSimulated {{ background: {WARN_BG}; color: {WARN_FG}; border: 1px solid #e6c76a; border-radius: 4px;
                      padding: 2px 10px; font-weight: 600; }}
QLabel#rigReal {{ color: #2e6b3a; padding: 2px 10px; font-weight: 600; }}
QLabel#heading {{ font-size: 13pt; font-weight: 600; color: #22303c; }}
QLabel#hint {{ color: #5f6b76; }}
"""

_BANNER_BOX = "border-radius: 5px; padding: 8px 12px;"
BANNER_STYLE: dict[Severity, str] = {
    Severity.ERROR: f"background: {ERROR_BG}; color: {ERROR_FG}; border: 1px solid #e3a5a0; {_BANNER_BOX}",
    Severity.WARNING: f"background: {WARN_BG}; color: {WARN_FG}; border: 1px solid #e6c76a; {_BANNER_BOX}",
    Severity.INFO: f"background: {INFO_BG}; color: {INFO_FG}; border: 1px solid #a9c6dd; {_BANNER_BOX}",
}


def app_icon() -> QIcon:
    return QIcon(str(ICONS / "anklescan.svg"))
