"""The daily check in the app, without widgets: where its capture goes, the camera that scans the
object, running the check on the capture, keeping the result, and what the last check says about
starting a scan (warn or refuse, the ``daily_check_policy`` setting).

The dialog (app.daily_check) scans the object through the ordinary acquisition path
(app.scan_worker.ScanController, a background job) and calls these.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from anklescan.app.logic.settings import AppSettings, CheckPolicy
from anklescan.core.calibration.procedures.daily_check import CheckResult, CheckSettings, run_check
from anklescan.core.records.daily_checks import (
    DEFAULT_MAX_AGE_HOURS,
    CheckStanding,
    DailyCheckRecord,
    add_check,
    last_check,
    standing,
)

if TYPE_CHECKING:
    from anklescan.app.logic.session import SessionLogic
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.hardware.camera import Camera

CHECKS_FOLDER = "daily_checks"  # in the data folder: one capture per check, kept


class _RigView(Protocol):
    """What the check needs of the app's rig."""

    simulated: bool
    camera: Camera


def check_camera(rig: _RigView, inversion_deg: float, plantar_flexion_deg: float) -> Camera:
    """What photographs the object: on the simulated rig a simulated camera on the wedge block at the
    set angles (same devices, same projector image); on real hardware the rig's own camera.
    ``rig`` is app.rig.Rig (not imported here: that module reaches for Qt)."""
    if not rig.simulated or not hasattr(rig.camera, "rig"):
        return rig.camera
    from anklescan.app.logic.calibration import _scene_camera
    from anklescan.hardware.sim_check import check_scene
    return _scene_camera(rig, check_scene(inversion_deg, plantar_flexion_deg), "Simulated camera (check object)")


def new_check_folder(data_folder: Path, now: _dt.datetime | None = None) -> Path:
    """A new, empty capture folder for one check (not created: the capture writer does it)."""
    from anklescan.core.atomic import make_private_dir
    base = make_private_dir(Path(data_folder) / CHECKS_FOLDER)
    stamp = (now or _dt.datetime.now()).strftime("%Y%m%d-%H%M%S")
    folder, n = base / stamp, 1
    while folder.exists():
        n += 1
        folder = base / f"{stamp}-{n}"
    return folder


def check_folder(folder: Path, calibration: Calibration, inversion_deg: float, plantar_flexion_deg: float,
                 tolerance_deg: float) -> CheckResult:
    """The check on a capture folder (in a background job)."""
    from anklescan.core.scan.capture import load_capture
    return run_check(load_capture(folder), calibration, inversion_deg, plantar_flexion_deg,
                     CheckSettings(tolerance_deg=tolerance_deg))


def record_check(session: SessionLogic, result: CheckResult) -> DailyCheckRecord | None:
    """Keep the result in the data folder's database (None without a writable one)."""
    store = session.store
    if store is None or store.read_only:
        return None
    return add_check(store, result, calibration_id=session.calibration_id, who=session.operator or "")


def check_standing(session: SessionLogic, settings: AppSettings) -> CheckStanding | None:
    """What the last check says about scanning now; None when the policy is off or there is no database."""
    if settings.daily_check_policy is CheckPolicy.OFF or session.store is None:
        return None
    hours = settings.daily_check_max_age_hours
    return standing(last_check(session.store), calibration_id=session.calibration_id,
                    max_age_hours=hours if hours > 0 else DEFAULT_MAX_AGE_HOURS)
