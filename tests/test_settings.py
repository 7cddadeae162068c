"""The settings (app.logic.settings, kept by app.settings): one typed attribute per setting, and
the settings file's keys and values unchanged from the releases that read them by string key."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from anklescan.app.logic.settings import (
    AppSettings,
    CalibrationVerdict,
    CheckPolicy,
    MemorySettings,
    PatternPreset,
)
from anklescan.app.settings import Settings
from anklescan.hardware.sim_patient import PatientProfile

# written by the release before the settings were typed (Settings.set(key, value) for every key, then
# sync), every value other than its default
WRITTEN_BEFORE = r"""[calibration]
current_created=2026-12-04T12:00:00+00:00
current_id=7
current_path=/data/calibrations/calibration_20261204T1200Z.json
max_age_days=14
table_size=300x200
verified=fail
verified_at=2026-12-04T12:05:00+00:00

[camera]
backend=opencv
device=/dev/video2
exposure_ms=12.5
gain=3

[clinic]
operator=Dr. A. Clinician

[daily_check]
inversion=10
max_age_hours=12
plantar_flexion=-5.5
policy=block
tolerance=0.25

[data]
folder=/data/anklescan

[projector]
screen=HDMI-1
size=1280x800

[scan]
motion_threshold_mm=0.75
pattern_preset=short
settle_ms=45
sim_patient=sprain history
sim_scale=0.5
sim_sway_mm=2

[thresholds]
saturation_level=240

[window]
geometry="@Variant(\0\0\0\x7f\0\0\0\x18PySide::PyObjectWrapper\0\0\0\0!\x80\x4\x95\x16\0\0\0\0\0\0\0\x43\x12\0\x3\x6\t\f\xf\x12\x15\x18\x1b\x1e!$'\0\xff=\n\x94.)"
"""

# what each setting reads from that file
READ = {
    "projector_screen": "HDMI-1", "projector_size": (1280, 800), "camera_backend": "opencv",
    "camera_device": "/dev/video2", "camera_exposure_ms": 12.5, "camera_gain": 3.0, "settle_ms": 45,
    "calibration_path": "/data/calibrations/calibration_20261204T1200Z.json", "calibration_id": 7,
    "calibration_created": "2026-12-04T12:00:00+00:00", "calibration_verified": CalibrationVerdict.FAIL,
    "calibration_verified_at": "2026-12-04T12:05:00+00:00", "calibration_max_age_days": 14.0,
    "daily_check_policy": CheckPolicy.BLOCK, "daily_check_max_age_hours": 12.0, "daily_check_inversion": 10.0,
    "daily_check_plantar_flexion": -5.5, "daily_check_tolerance": 0.25, "table_size": "300x200",
    "sim_scale": 0.5, "sim_patient": PatientProfile.SPRAIN_HISTORY, "sim_sway_mm": 2.0,
    "pattern_preset": PatternPreset.SHORT, "motion_threshold_mm": 0.75, "saturation_level": 240,
    "chosen_data_folder": Path("/data/anklescan"), "window_geometry": bytes(range(0, 40, 3)) + b"\x00\xff=\n",
    "operator": "Dr. A. Clinician",
}


def test_a_settings_file_written_before_reads_the_same_and_is_written_byte_for_byte(tmp_path):
    before = tmp_path / "before.ini"
    before.write_text(WRITTEN_BEFORE, encoding="utf-8")
    assert set(READ) == set(AppSettings.all_settings())  # every setting is in the file
    old = Settings(before)
    read = {name: getattr(old, name) for name in READ}
    assert read == READ
    assert all(type(read[name]) is type(value) for name, value in READ.items())
    again = Settings(tmp_path / "again.ini")
    for name, value in read.items():
        setattr(again, name, value)
    again.sync()
    assert (tmp_path / "again.ini").read_bytes() == before.read_bytes()


def test_the_settings_file_is_the_one_ANKLESCAN_SETTINGS_names(tmp_path, monkeypatch):
    path = tmp_path / "named.ini"
    monkeypatch.setenv("ANKLESCAN_SETTINGS", str(path))
    s = Settings()
    s.settle_ms, s.daily_check_policy = 12, CheckPolicy.OFF
    s.sync()
    assert Path(s.location) == path and s.problem() == ""
    assert "settle_ms=12" in path.read_text() and "policy=off" in path.read_text()
    assert Settings(path).settle_ms == 12 and Settings().daily_check_policy is CheckPolicy.OFF


@pytest.mark.parametrize("kept", ["memory", "new file"])
def test_unset_settings_read_their_defaults(tmp_path, kept):
    s = MemorySettings() if kept == "memory" else Settings(tmp_path / "new" / "s.ini")
    for name, setting in AppSettings.all_settings().items():
        assert getattr(s, name) == setting.default, name
    assert s.daily_check_policy is CheckPolicy.WARN and s.sim_patient is PatientProfile.NO_SPRAIN
    assert s.calibration_verified is CalibrationVerdict.NONE and s.projector_size is None


@pytest.mark.parametrize(("name", "stored", "expected"), [
    ("daily_check_policy", "sometimes", CheckPolicy.WARN),   # a typo must not turn the check off
    ("daily_check_policy", " BLOCK ", CheckPolicy.BLOCK),
    ("settle_ms", "fast", 30),
    ("settle_ms", "12.5", 30),
    ("sim_scale", "", 0.75),
    ("projector_size", "big", None),
    ("projector_size", "800X600", (800, 600)),
    ("sim_patient", "somebody", PatientProfile.NO_SPRAIN),
    ("pattern_preset", "fancy", PatternPreset.DEFAULT),
    ("calibration_id", "abc", None),
    ("calibration_verified", "maybe", CalibrationVerdict.NONE),
    ("chosen_data_folder", "", None),
])
def test_a_hand_edited_value_that_cannot_be_read_is_the_default(tmp_path, name, stored, expected):
    setting = AppSettings.all_settings()[name]
    group, key = setting.key.split("/")
    (tmp_path / "s.ini").write_text(f"[{group}]\n{key}={stored}\n")
    assert getattr(Settings(tmp_path / "s.ini"), name) == expected


def test_the_pattern_presets_are_the_scanners():
    from anklescan.core.scan.patterns import PRESETS
    assert [p.value for p in PatternPreset] == list(PRESETS)


def test_reading_the_settings_loads_neither_numpy_nor_qt_in_the_logic():
    """The window reads its settings before anything slow is imported; the logic layer has no Qt."""
    code = ("import sys, anklescan.app.logic.settings as s; m = s.MemorySettings(); m.sim_patient; "
            "print(sorted({n.split('.')[0] for n in sys.modules} & {'numpy', 'PySide6', 'shiboken6'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
