"""Adapter between the app and the hardware layer (hardware.camera / hardware.simrig).

The app needs one object that says what is connected: a camera, the projector's resolution,
whether the rig is simulated, the simulated projector to feed (the simulated camera
photographs what it shows) and, on the simulated rig, its true calibration. The hardware
modules are imported inside the functions so the window shows before they load.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from anklescan.app.logic.settings import AppSettings
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.hardware.camera import Camera, ProjectorOutput
    from anklescan.hardware.sim_patient import SimulatedPatient, Stance
    from anklescan.hardware.simrig import SimRig, SimulatedCamera

SIMULATED = "simulated"


@dataclass
class Rig:
    backend: str
    camera: Camera                   # on the simulated rig a hardware.simrig.SimulatedCamera
    projector_size: tuple[int, int]
    simulated: bool
    sim_projector: ProjectorOutput | None = None  # the simulated projector; fed with what the window paints
    calibration: Calibration | None = None        # when known (the simulated rig's true one)
    sim_patient: SimulatedPatient | None = None   # standing on the simulated rig
    stance: Stance | None = None                  # of the last trial set up

    def set_profile(self, profile: str) -> None:
        """Who stands on the simulated rig ("no sprain", "sprain history"); no effect on a real rig."""
        if not self.simulated:
            return
        from anklescan.hardware.sim_patient import PatientProfile, SimulatedPatient

        self.sim_patient = SimulatedPatient(PatientProfile.parse(profile), seed=0)  # the same answers each start

    def set_sway(self, amplitude_mm: float) -> None:
        """The simulated patient sways sideways, ±A mm at up to A mm/s, while scanned (0: stands still)."""
        if self.simulated:
            _set_sway(self._sim_rig(), amplitude_mm)

    @property
    def profile_label(self) -> str:
        return self.sim_patient.profile.label if self.sim_patient is not None else ""

    def stand_patient(self, reference: tuple[float | None, float | None], condition: str) -> Stance | None:
        """Before a trial on the simulated rig: the reference table at ``reference`` (the angles the
        clinician typed), the simulated patient setting the adjustable table to match, the scene
        the camera sees changed to it. Returns the Stance (None on a real rig)."""
        if not self.simulated or self.sim_patient is None:
            return None
        stance = self.sim_patient.stance(reference, condition)
        camera = self._sim_camera()
        current = camera.rig
        posed = current.with_scene(self.sim_patient.scene(stance))
        posed.motion = current.motion
        if posed.motion is not None:
            posed.motion.reset()
        camera.rig = posed
        self.stance = stance
        return stance

    def _sim_camera(self) -> SimulatedCamera:
        """The simulated camera (asked only on the simulated rig, whose camera open_rig made one)."""
        from anklescan.hardware.simrig import SimulatedCamera

        assert isinstance(self.camera, SimulatedCamera), "a simulated rig has a simulated camera"
        return self.camera

    def _sim_rig(self) -> SimRig:
        """The simulated rig (the scene and its sway) the simulated camera photographs."""
        return self._sim_camera().rig

    @property
    def description(self) -> str:
        if self.simulated:
            who = f" · simulated patient: {self.profile_label.lower()}" if self.sim_patient is not None else ""
            return f"SIMULATED rig — no hardware connected{who}"
        return f"Camera: {camera_name(self.camera)} · projector {self.projector_size[0]}×{self.projector_size[1]}"

    def close(self) -> None:
        try:
            self.camera.close()
        except Exception:
            pass  # closing a camera that is already gone must not stop the app


def camera_name(camera: Camera) -> str:
    try:
        return camera.info.name
    except Exception:  # a camera that has gone away cannot describe itself
        return type(camera).__name__


def available_backends() -> list[tuple[str, str]]:
    """(key, label) of camera backends; the simulated rig is always present and first."""
    from anklescan.hardware import camera

    return [(SIMULATED, "Simulated rig")] + camera.available_backends()


def list_devices(backend: str) -> list[tuple[str, str]]:
    """(device id, label) for ``backend``; the simulated rig has exactly one camera."""
    if backend == SIMULATED:
        return [("", "Simulated camera")]
    from anklescan.hardware import camera

    return [(d.id, d.label) for d in camera.list_devices(backend)]


def backend_problem(backend: str) -> str:
    """Why ``backend`` cannot be used on this computer ("" when it can)."""
    if backend == SIMULATED:
        return ""
    from anklescan.hardware import camera

    return camera.backend_problem(backend)


def projector_resolution(settings: AppSettings | None = None) -> tuple[int, int]:
    """The real projector's resolution: the ``projector_size`` setting when it is set, else that
    of the monitor the projector window goes to (the ``projector_screen`` setting, else the
    second monitor; asked only on the UI thread, where Qt allows it), else FALLBACK_PROJECTOR_SIZE."""
    from anklescan.app.logic.settings import FALLBACK_PROJECTOR_SIZE
    from anklescan.app.settings import Settings

    settings = settings or Settings()
    return settings.projector_size or _display_size(settings.projector_screen) or FALLBACK_PROJECTOR_SIZE


def _display_size(preferred: str) -> tuple[int, int] | None:
    from PySide6.QtCore import QThread
    from PySide6.QtGui import QGuiApplication

    app = QGuiApplication.instance()
    if app is None or QThread.currentThread() is not app.thread():
        return None
    from anklescan.app.projector_window import choose_screen

    screen = choose_screen(QGuiApplication.screens(), QGuiApplication.primaryScreen(), preferred)
    if screen is None:
        return None
    size, ratio = screen.geometry().size(), screen.devicePixelRatio()
    return round(size.width() * ratio), round(size.height() * ratio)


def open_rig(backend: str = SIMULATED, scale: float = 0.75, device: str = "",
             projector_size: tuple[int, int] | None = None, profile: str = "no sprain") -> Rig:
    """``projector_size`` is the real projector's resolution (``projector_resolution()`` when not
    given: the setting or the connected monitor); the simulated rig has its own. ``profile`` is
    the simulated patient's (hardware.sim_patient.PatientProfile's value)."""
    if backend != SIMULATED:
        from anklescan.hardware import camera

        # a (width, height) pair (a list from the settings file becomes a tuple)
        size = (projector_size[0], projector_size[1]) if projector_size else projector_resolution()
        return Rig(backend, camera.open_camera(backend, device), size, simulated=False)
    from anklescan.hardware import simrig

    rig = simrig.SimRig(scale=scale)
    _sway_from_environment(rig)
    cam, projector = simrig.simulated_devices(rig)
    cam.open()
    opened = Rig(SIMULATED, cam, projector.size, True, projector, rig.true_calibration())
    opened.set_profile(profile)
    return opened


def _sway_from_environment(rig: SimRig) -> None:
    """ANKLESCAN_SIM_SWAY_MM=A: the simulated patient sways sideways, +-A mm at up to A mm/s
    (hardware/sim_sway.py; every camera grab is a webcam frame, 30 ms, later). Each frame is
    then rendered at its own pose, so the camera preview and scans are slower."""
    import os

    try:
        amplitude = float(os.environ.get("ANKLESCAN_SIM_SWAY_MM", "") or 0.0)
    except ValueError:
        return
    _set_sway(rig, amplitude)


def _set_sway(rig: SimRig, amplitude: float) -> None:
    if 0 < amplitude < 100:
        from anklescan.hardware.sim_sway import FRAME_S, Sway, SwayClock

        rig.motion = SwayClock(Sway((1.0, 0.0, 0.0), amplitude_mm=amplitude, speed_mm_s=amplitude),
                               FRAME_S["webcam"])
    else:
        rig.motion = None
