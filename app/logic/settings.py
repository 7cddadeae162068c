"""The app's settings as typed attributes, without Qt: one name, one type, one default, one place.

Every setting is a class attribute of ``AppSettings`` (a ``Setting``): ``settings.settle_ms`` reads
it (its default when it was never set, or when a hand-edited or stale value cannot be read) and
``settings.settle_ms = 20`` writes it. A closed set of values is an enum (``CheckPolicy``,
``CalibrationVerdict``, ``PatternPreset``, hardware.sim_patient's ``PatientProfile``).

Where the values are kept is the subclass's: app.settings.Settings keeps them in QSettings (the
user's, or the INI file ``ANKLESCAN_SETTINGS`` names), ``MemorySettings`` in a dict (the logic's
tests). The settings file's keys and values are those written before the settings were typed
(tests/test_settings.py loads such a file and writes it again byte for byte).

This module imports neither Qt nor numpy: the app reads its settings before anything slow loads.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Generic, TypeVar, overload

from anklescan.hardware.sim_patient import PatientProfile

T = TypeVar("T")
E = TypeVar("E", bound=Enum)

# the projector's resolution when neither the ``projector_size`` setting nor a monitor says (app.rig)
FALLBACK_PROJECTOR_SIZE = (1024, 768)


class CheckPolicy(Enum):
    """What a failed or stale daily check does to the start of a scan (the ``daily_check_policy`` setting)."""

    OFF = "off"  # no word at the start of a scan
    WARN = "warn"  # the scan starts, the banner says why the rig is not known good
    BLOCK = "block"  # the scan is refused until a check passes


class CalibrationVerdict(Enum):
    """The current calibration's last verification (app.logic.calibration)."""

    NONE = ""  # not verified since it became current
    PASS = "pass"
    FAIL = "fail"


class PatternPreset(Enum):
    """The projected pattern set (core.scan.patterns.PRESETS: the values are its names)."""

    DEFAULT = "default"
    PAPER = "paper"
    SHORT = "short"


@dataclass(frozen=True)
class Setting(Generic[T]):
    """One setting: its key in the settings file, its default, and how a stored value is read back
    (``read`` raises TypeError or ValueError for a value it cannot read) and written."""

    key: str
    default: T
    read: Callable[[object], T]
    write: Callable[[T], object]

    @overload
    def __get__(self, obj: None, owner: type[object]) -> Setting[T]: ...

    @overload
    def __get__(self, obj: AppSettings, owner: type[object]) -> T: ...

    def __get__(self, obj: AppSettings | None, owner: type[object]) -> Setting[T] | T:
        if obj is None:
            return self
        stored = obj.load(self.key)
        if stored is None:
            return self.default
        try:
            return self.read(stored)
        except (TypeError, ValueError):
            return self.default  # a hand-edited or stale value must not stop the app starting

    def __set__(self, obj: AppSettings, value: T) -> None:
        obj.store(self.key, self.write(value))


def _text(key: str, default: str = "") -> Setting[str]:
    return Setting(key, default, str, str)


def _number(key: str, default: float) -> Setting[float]:
    return Setting(key, default, _float, float)


def _whole(key: str, default: int) -> Setting[int]:
    return Setting(key, default, _int, int)


def _float(stored: object) -> float:
    return float(str(stored))


def _int(stored: object) -> int:
    return int(str(stored))


def _choice(key: str, default: E) -> Setting[E]:
    kind = type(default)
    return Setting(key, default, lambda stored: kind(str(stored).strip().lower()), lambda value: value.value)


def _read_size(stored: object) -> tuple[int, int] | None:
    text = str(stored).strip().lower()
    if not text:
        return None
    w, h = (int(v) for v in text.split("x"))  # "WxH"; anything else: ValueError
    return w, h


def _write_size(size: tuple[int, int] | None) -> str:
    return "" if size is None else f"{size[0]}x{size[1]}"


def _read_id(stored: object) -> int | None:
    text = str(stored)
    return int(text) if text.isdigit() else None


def _write_id(value: int | None) -> str:
    return "" if value is None else str(value)


def _read_folder(stored: object) -> Path | None:
    text = str(stored)
    return Path(text) if text else None


def _write_folder(folder: Path | None) -> str:
    return "" if folder is None else str(folder)


def _read_bytes(stored: object) -> bytes:
    return bytes(stored) if stored else b""  # type: ignore[call-overload]  # QSettings gives bytes or a QByteArray


def _write_bytes(value: bytes) -> bytes:
    return value


class AppSettings(ABC):
    """The settings kept between runs; ``load``/``store``/``sync`` are where they are kept."""

    # the projector: its monitor (QScreen.name(); "" = automatic) and resolution (None: its monitor's, app.rig)
    projector_screen = _text("projector/screen")
    projector_size = Setting("projector/size", None, _read_size, _write_size)
    camera_backend = _text("camera/backend", "simulated")
    camera_device = _text("camera/device")
    camera_exposure_ms = _number("camera/exposure_ms", 0.0)  # 0 = the device's default
    camera_gain = _number("camera/gain", 0.0)
    settle_ms = _whole("scan/settle_ms", 30)
    # the current calibration (app.logic.calibration): its file, database id, when made (ISO 8601),
    # its last verification and when
    calibration_path = _text("calibration/current_path")
    calibration_id = Setting("calibration/current_id", None, _read_id, _write_id)  # None: not in a database
    calibration_created = _text("calibration/current_created")
    calibration_verified = _choice("calibration/verified", CalibrationVerdict.NONE)
    calibration_verified_at = _text("calibration/verified_at")
    calibration_max_age_days = _number("calibration/max_age_days", 30.0)  # older: the banner warns
    # the daily check (app.logic.daily_check): what a failed or stale check does to a scan, the age
    # after which it is stale; the known-angle object's set angles and the tolerance, as last typed
    daily_check_policy = _choice("daily_check/policy", CheckPolicy.WARN)
    daily_check_max_age_hours = _number("daily_check/max_age_hours", 24.0)
    daily_check_inversion = _number("daily_check/inversion", 0.0)
    daily_check_plantar_flexion = _number("daily_check/plantar_flexion", 0.0)
    daily_check_tolerance = _number("daily_check/tolerance", 0.3)
    # the level reference table's top, mm, long side first (core.calibration.procedures.levelling.TableSpec)
    table_size = _text("calibration/table_size", "320x220")
    # the simulated rig's resolution: 0.75 of 1600x1200 is the least at which marks are found
    # automatically (docs/marks.md), and a scan still takes seconds
    sim_scale = _number("scan/sim_scale", 0.75)
    sim_patient = _choice("scan/sim_patient", PatientProfile.NO_SPRAIN)  # who stands on the simulated rig
    sim_sway_mm = _number("scan/sim_sway_mm", 0.0)  # the simulated patient sways ±this, mm (0: still)
    pattern_preset = _choice("scan/pattern_preset", PatternPreset.DEFAULT)
    # a trial whose subject moved more than this during the scan is flagged (core/scan/motion.py)
    motion_threshold_mm = _number("scan/motion_threshold_mm", 0.5)
    saturation_level = _whole("thresholds/saturation_level", 250)
    # the data folder chosen in File ▸ Data folder (None: the default; app.settings.Settings.data_folder)
    chosen_data_folder = Setting("data/folder", None, _read_folder, _write_folder)
    window_geometry = Setting("window/geometry", b"", _read_bytes, _write_bytes)
    operator = _text("clinic/operator")  # asked once, then signs sessions and marks

    @classmethod
    def all_settings(cls) -> dict[str, Setting[object]]:
        """Every setting by its attribute name."""
        return {name: value for name, value in vars(AppSettings).items() if isinstance(value, Setting)}

    @abstractmethod
    def load(self, key: str) -> object | None:
        """The value kept under ``key`` (text, when read from an INI file); None when there is none."""

    @abstractmethod
    def store(self, key: str, value: object) -> None:
        """Keep ``value`` under ``key``."""

    @abstractmethod
    def sync(self) -> None:
        """Write what was set where it is kept."""


class MemorySettings(AppSettings):
    """Settings kept in memory only (the logic's tests, a run that must not touch the user's)."""

    def __init__(self) -> None:
        self._values: dict[str, object] = {}

    def load(self, key: str) -> object | None:
        return self._values.get(key)

    def store(self, key: str, value: object) -> None:
        self._values[key] = value

    def sync(self) -> None:
        """Nothing to write: the values are kept as they are set."""
