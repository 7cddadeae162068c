"""Settings kept between runs (screens, camera, thresholds, data folder).

A thin typed layer over QSettings so that every key has one name, one type and one default
in one place. ``ANKLESCAN_SETTINGS`` names an INI file to use instead of the user's settings;
the tests use it so that they never read or change a clinician's real configuration.
"""

from __future__ import annotations

import os
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
    # the level reference table's top, mm, long side first (core.calibration.levelling.TableSpec)
    "table_size": Key("calibration/table_size", "320x220", str),
    # the simulated rig's resolution: 0.75 of 1600x1200 is the least at which marks are found
    # automatically (docs/marks.md), and a scan still takes seconds
    "sim_scale": Key("scan/sim_scale", 0.75, float),
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
