"""Settings kept between runs (screens, camera, thresholds, data folder), in QSettings.

The settings themselves, one typed attribute each with its key and default, are
app.logic.settings.AppSettings'; this is where they are kept: the user's QSettings, or the INI file
``ANKLESCAN_SETTINGS`` names instead (the tests use it so that they never read or change a
clinician's real configuration). A location that cannot be written is said at start-up
(``Settings.problem``), never lost silently.
"""

from __future__ import annotations

import os
from contextlib import suppress
from pathlib import Path

from PySide6.QtCore import QSettings

from anklescan.app.logic.settings import AppSettings


class Settings(AppSettings):
    def __init__(self, path: str | os.PathLike[str] | None = None) -> None:
        path = path or os.environ.get("ANKLESCAN_SETTINGS")
        if path:
            self._qs = QSettings(str(path), QSettings.Format.IniFormat)
        else:
            self._qs = QSettings("AnkleScan", "AnkleScan")
        self._make_private()

    def _make_private(self) -> None:
        """The settings say where patient data lives: the file is 0600 and a folder made for it
        0700 whatever the umask. The file is created private before Qt first writes it (Qt keeps
        an existing file's mode when it saves)."""
        from anklescan.core.atomic import PRIVATE_FILE_MODE, make_private, make_private_dir
        name = self._qs.fileName()
        if not name:
            return
        try:
            make_private_dir(Path(name).parent, tighten=False)
            fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE)
            os.fchmod(fd, PRIVATE_FILE_MODE)
            os.close(fd)
        except FileExistsError:
            with suppress(OSError):  # not ours to change: leave it
                make_private(name)
        except OSError:
            pass  # an unwritable settings folder: Qt keeps the settings in memory

    def load(self, key: str) -> object | None:
        value: object | None = self._qs.value(key)
        return value

    def store(self, key: str, value: object) -> None:
        self._qs.setValue(key, value)

    def sync(self) -> None:
        self._qs.sync()
        self._make_private()

    @property
    def location(self) -> str:
        return self._qs.fileName()

    def problem(self) -> str:
        """Why settings set now would be lost (the accepted calibration, the operator, ...), in
        one sentence for the banner; "" when they are kept."""
        where = Path(self.location)
        named = " (named by ANKLESCAN_SETTINGS)" if os.environ.get("ANKLESCAN_SETTINGS") else ""
        if where.is_dir():
            return (f"The settings location {where}{named} is a folder, not a file: settings cannot be kept, so the "
                    "accepted calibration and the operator will be lost on restart. Name a file instead.")
        if not self._qs.isWritable():
            return (f"The settings file {where}{named} cannot be written: the accepted calibration and the operator "
                    "will be lost on restart. Make it writable (or Scan ▸ Choose calibration… after each start).")
        self._qs.sync()
        if self._qs.status() != QSettings.Status.NoError:
            return (f"The settings file {where}{named} could not be saved ({self._qs.status().name}): the accepted "
                    "calibration and the operator will be lost on restart.")
        return ""

    @property
    def data_folder_from_environment(self) -> bool:
        """ANKLESCAN_DATA names the data folder: a folder chosen in File ▸ Data folder does not apply."""
        return bool(os.environ.get("ANKLESCAN_DATA"))

    @property
    def data_folder(self) -> Path:
        """The one answer to "where are the patients' data": ANKLESCAN_DATA, else the folder chosen
        in File ▸ Data folder, else the command line's default (core.records.store.default_data_dir).
        Releases before this one defaulted to ~/AnkleScan in the app: a database there is kept."""
        from anklescan.core.records.store import DB_FILENAME, default_data_dir
        env, chosen = self.data_folder_from_environment, self.chosen_data_folder
        if env or chosen is None:
            legacy = Path.home() / "AnkleScan"
            return legacy if not env and (legacy / DB_FILENAME).exists() else default_data_dir()
        return chosen.expanduser()
