"""Settings kept between runs (screens, camera, thresholds, data folder).

A thin typed layer over QSettings so that every key has one name, one type and one default
in one place. ``ANKLESCAN_SETTINGS`` names an INI file to use instead of the user's settings;
the tests use it so that they never read or change a clinician's real configuration. A
location that cannot be written is said at start-up (``Settings.problem``), never lost silently.
"""

from __future__ import annotations

import os
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

from PySide6.QtCore import QSettings


@dataclass(frozen=True)
class Key:
    name: str
    default: object
    kind: type


KEYS = {
    "projector_screen": Key("projector/screen", "", str),       # QScreen.name(); "" = automatic
    "projector_size": Key("projector/size", "", str),  # "WxH"; "": the projector monitor's (app.rig)
    "camera_backend": Key("camera/backend", "simulated", str),
    "camera_device": Key("camera/device", "", str),
    "camera_exposure_ms": Key("camera/exposure_ms", 0.0, float),  # 0 = the device's default
    "camera_gain": Key("camera/gain", 0.0, float),
    "settle_ms": Key("scan/settle_ms", 30, int),
    # the current calibration (app.logic.calibration): its file, database id, when made, last verification
    "calibration_path": Key("calibration/current_path", "", str),
    "calibration_id": Key("calibration/current_id", "", str),     # "" when not in a database
    "calibration_created": Key("calibration/current_created", "", str),  # ISO 8601
    "calibration_verified": Key("calibration/verified", "", str),  # "", "pass" or "fail"
    "calibration_verified_at": Key("calibration/verified_at", "", str),
    "calibration_max_age_days": Key("calibration/max_age_days", 30.0, float),  # older: the banner warns
    # the daily check (app.logic.daily_check): "off", "warn" or "block" a scan when the last check failed
    # or is older than the age; the known-angle object's set angles and the tolerance, as last typed
    "daily_check_policy": Key("daily_check/policy", "warn", str),
    "daily_check_max_age_hours": Key("daily_check/max_age_hours", 24.0, float),
    "daily_check_inversion": Key("daily_check/inversion", 0.0, float),
    "daily_check_plantar_flexion": Key("daily_check/plantar_flexion", 0.0, float),
    "daily_check_tolerance": Key("daily_check/tolerance", 0.3, float),
    # the level reference table's top, mm, long side first (core.calibration.levelling.TableSpec)
    "table_size": Key("calibration/table_size", "320x220", str),
    # the simulated rig's resolution: 0.75 of 1600x1200 is the least at which marks are found
    # automatically (docs/marks.md), and a scan still takes seconds
    "sim_scale": Key("scan/sim_scale", 0.75, float),
    # who stands on the simulated rig (hardware.sim_patient.PatientProfile): "no sprain" or "sprain history"
    "sim_patient": Key("scan/sim_patient", "no sprain", str),
    "sim_sway_mm": Key("scan/sim_sway_mm", 0.0, float),  # the simulated patient sways ±this, mm (0: still)
    "pattern_preset": Key("scan/pattern_preset", "default", str),
    # a trial whose subject moved more than this during the scan is flagged (core/scan/motion.py)
    "motion_threshold_mm": Key("scan/motion_threshold_mm", 0.5, float),
    "saturation_level": Key("thresholds/saturation_level", 250, int),
    "data_folder": Key("data/folder", "", str),  # "" = the one default, see Settings.data_folder
    "window_geometry": Key("window/geometry", b"", bytes),
    "operator": Key("clinic/operator", "", str),  # asked once, then signs sessions and marks
}


class Settings:
    def __init__(self, path: str | os.PathLike | None = None):
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

    def get(self, key: str):
        spec = KEYS[key]
        value = self._qs.value(spec.name, spec.default)
        if spec.kind is bytes:
            return bytes(value) if value else b""
        try:
            return spec.kind(value)
        except (TypeError, ValueError):
            return spec.default  # a hand-edited or stale value must not stop the app starting

    def set(self, key: str, value) -> None:
        self._qs.setValue(KEYS[key].name, value)

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
    def data_folder(self) -> Path:
        """The one answer to "where are the patients' data": ANKLESCAN_DATA, else the folder chosen
        in File ▸ Data folder, else the command line's default (core.records.store.default_data_dir).
        Releases before this one defaulted to ~/AnkleScan in the app: a database there is kept."""
        from anklescan.core.records.store import DB_FILENAME, default_data_dir
        env, chosen = os.environ.get("ANKLESCAN_DATA"), self.get("data_folder")
        if env or not chosen:
            legacy = Path.home() / "AnkleScan"
            return legacy if not env and (legacy / DB_FILENAME).exists() else default_data_dir()
        return Path(chosen).expanduser()

    @property
    def projector_size(self) -> tuple[int, int]:
        try:
            w, h = (int(v) for v in str(self.get("projector_size")).lower().split("x"))
            return w, h
        except ValueError:
            return 1024, 768
