"""The paper's manual calibration (§3.2-3.3) in the calibration dialog: click each marker corner
on the camera image (refined to sub-pixel), steer the projector spot onto it and record the
spot, refined to the clicked corner by eight edge frames photographed through app.acquisition
in the background. A mixin of app.calibration_wizard.CalibrationWizard.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QKeyEvent
from PySide6.QtWidgets import QCheckBox, QDialog, QLabel, QStackedWidget

from anklescan.app.calibration_pages import PAGE_MANUAL, PAGE_REPORT, ProjectorShows
from anklescan.app.calibration_views import ZoomView, gray_rgb
from anklescan.app.logic.calibration import BoxPoints, cam_pixels_of, refine_click

if TYPE_CHECKING:
    from anklescan.app.acquisition import Acquisition
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.calibration.procedures.calibrate import CalibrationReport
    from anklescan.core.calibration.procedures.projector_spot import SpotRefinement

    _DialogBase = QDialog  # the mixin's host: mypy sees the dialog's methods (super().keyPressEvent)
else:
    _DialogBase = object


class PointKind(Enum):
    """Which of a control point's two observations a manual step recorded."""

    CAMERA = "cam"
    PROJECTOR = "proj"


@dataclass(frozen=True)
class ManualStep:
    """One recorded observation, for undo."""

    kind: PointKind
    index: int  # the point's index in ``manual_points()``


class ManualObservations(NamedTuple):
    """The manual page's control points: box coordinates (mm) with their camera and projector pixels."""

    cam_xyz: np.ndarray  # (N, 3)
    cam_uv: np.ndarray  # (N, 2)
    proj_xyz: np.ndarray  # (M, 3)
    proj_uv: np.ndarray  # (M, 2) projector (column, row)


class ManualCalibration(_DialogBase):
    """The manual page's behaviour; the dialog provides ``projector``, ``acquisition``, ``status``,
    ``manual_view`` and the other widgets of app.calibration_pages."""

    # set by the dialog's __init__
    camera_size: tuple[int, int]
    settle_s: float
    points: BoxPoints | None
    calibration: Calibration | None
    report: CalibrationReport | None
    _manual_index: int
    _manual_list: list[tuple[str, np.ndarray]]  # (label, box coordinates in mm) of each point
    _manual_cam: dict[int, tuple[float, float]]  # point index -> (u, v)
    _manual_proj: dict[int, tuple[float, float]]  # point index -> (column, row)
    _manual_steered: dict[int, tuple[float, float]]  # point index -> (column, row) where the operator left the spot
    _manual_history: list[ManualStep]  # for undo
    _refining: bool
    _white_frame: np.ndarray | None
    _last_frame: np.ndarray | None

    if TYPE_CHECKING:  # the rest of the dialog: app.calibration_wizard and app.calibration_pages
        projector: ProjectorWindow
        acquisition: Acquisition
        _timer: QTimer
        pages: QStackedWidget
        status: QLabel
        manual_view: ZoomView
        manual_prompt: QLabel
        manual_counts: QLabel
        refine_spot_box: QCheckBox

        def go(self, page: int) -> None: ...
        def _show_on_projector(self, what: ProjectorShows) -> None: ...
        def show_report(self, board_white: np.ndarray | None = None) -> None: ...

    @property
    def manual_half_window(self) -> int:
        # ~10 mm on the box at the working distance, at any camera resolution
        return max(2, round(4 * self.camera_size[0] / 1600))

    def manual_goto(self, index: int) -> None:
        self._manual_index = int(np.clip(index, 0, len(self._manual_list) - 1))
        label, X = self._manual_list[self._manual_index]
        have = ("camera ✓" if self._manual_index in self._manual_cam else "camera —") + " · " + \
            ("projector ✓" if self._manual_index in self._manual_proj else "projector —")
        self.manual_prompt.setText(f"Point {self._manual_index + 1} of {len(self._manual_list)}: {label} "
                                   f"({X[0]:.0f}, {X[1]:.0f}, {X[2]:.0f}) mm   [{have}]")
        self._update_manual_marks()

    def _update_manual_marks(self) -> None:
        self.manual_view.set_marks(list(self._manual_cam.values()), self._manual_cam.get(self._manual_index))
        self.manual_counts.setText(f"{len(self._manual_cam)} camera points, {len(self._manual_proj)} projector "
                                   "points recorded (at least 8 of each, on two or more faces)")

    def _show_manual_frame(self, frame: np.ndarray, picture: np.ndarray | None = None,
                           white: bool | None = None) -> None:
        """``picture``: the frame stretched (gray_rgb), when already made in the background."""
        if self.projector.mode == "white" if white is None else white:
            self._white_frame = frame  # clicks are refined on the box under white light, not the spot
        # stretched: under the spot alone the box is dim
        self.manual_view.set_image(gray_rgb(frame) if picture is None else picture)
        self._update_manual_marks()

    def set_manual_image(self, frame: np.ndarray) -> None:
        """The image the camera clicks are refined on (the box under white light)."""
        self._last_frame = self._white_frame = frame
        self.manual_view.set_image(gray_rgb(frame))
        self._update_manual_marks()

    def pick_camera(self, x: float, y: float) -> tuple[float, float]:
        if self._white_frame is None:
            return x, y
        u, v = refine_click(self._white_frame, x, y, self.manual_half_window)
        self._manual_cam[self._manual_index] = (u, v)
        self._manual_history.append(ManualStep(PointKind.CAMERA, self._manual_index))
        self._update_manual_marks()
        self.manual_goto(self._manual_index)
        return u, v

    def _manual_white(self) -> None:
        self._show_on_projector("white")

    def _manual_spot(self) -> None:
        self._show_on_projector("spot")
        self.projector.activateWindow()

    def keyPressEvent(self, event: QKeyEvent) -> None:
        # Arrow keys steer the spot from the dialog too, so the camera preview stays in view.
        if self.pages.currentIndex() == PAGE_MANUAL and self.projector.mode == "spot" and event.key() in (
                Qt.Key.Key_Left, Qt.Key.Key_Right, Qt.Key.Key_Up, Qt.Key.Key_Down):
            self.projector.keyPressEvent(event)
            return
        super().keyPressEvent(event)

    def record_spot(self, position: tuple[float, float] | None = None) -> None:
        """Record the spot's projector pixel for the current point (the paper's projector step),
        refined to the point's camera click when that is on and possible (in the background:
        ``refining`` is True until it is recorded)."""
        if self._refining:
            return
        i = self._manual_index
        x, y = self.projector.spot_position if position is None else position
        steered = (float(x), float(y))
        note = "spot recorded as steered"
        if self.refine_spot_box.isChecked():
            if i not in self._manual_cam or self._white_frame is None:
                note += " (click the corner on the camera image first to have it refined)"
            else:
                self.refine_projector_spot(self._manual_cam[i], steered,
                                           lambda result: self._spot_refined(i, steered, result))
                return
        self._store_spot(i, steered, steered, note)

    def _spot_refined(self, i: int, steered: tuple[float, float], result: SpotRefinement) -> None:
        if result.position is not None:  # result.ok
            note = "spot refined to the clicked corner by ({:+.2f}, {:+.2f}) projector px".format(*result.shift)
            self._store_spot(i, steered, result.position, note)
        else:
            self._store_spot(i, steered, steered, f"spot recorded as steered, not refined: {result.message}")

    def _store_spot(self, i: int, steered: tuple[float, float], at: tuple[float, float], note: str) -> None:
        self._manual_proj[i] = at
        self._manual_steered[i] = steered
        self._manual_history.append(ManualStep(PointKind.PROJECTOR, i))
        self.manual_goto(i)
        self.status.setText(f"Point {i + 1}: {note}.")

    @property
    def refining(self) -> bool:
        return self._refining

    def refined_count(self) -> int:
        return sum(self._manual_proj[i] != self._manual_steered.get(i) for i in self._manual_proj)

    def refine_projector_spot(self, corner_uv: tuple[float, float], steered: tuple[float, float],
                              on_done: Callable[[SpotRefinement], None]) -> None:
        """Show the eight edge frames around the spot and photograph each (app.acquisition), read
        the projector coordinate at the corner (anklescan.core.calibration.procedures.projector_spot), all in
        the background; then show the spot where it was read and call ``on_done(SpotRefinement)``."""
        from anklescan.core.calibration.procedures.projector_spot import SpotRefinement, refine_spot, refinement_frames
        self._refining = True
        live = self._timer.isActive()
        self._timer.stop()  # the preview would photograph the edge frames as if they were the spot
        frames = refinement_frames(self.projector.projector_size, steered)
        white, settle = self._white_frame, self.settle_s

        def work(acq: Acquisition) -> SpotRefinement:
            images = acq.acquire(frames, mode="spot", settle_s=settle)
            assert white is not None, "record_spot refines only once a white frame was clicked on"
            return refine_spot(images, corner_uv, steered, white=white)

        def finish(result: SpotRefinement) -> None:
            self._refining = False
            self.projector.show_spot(*(result.position if result.position is not None else steered))
            if live:
                self._timer.start()
            on_done(result)

        # a camera or window failure: the steered spot is still recorded
        self.acquisition.run(work, finish, lambda message: finish(
            SpotRefinement(None, steered, f"the refinement frames could not be taken ({message})")))

    def manual_undo(self) -> None:
        if not self._manual_history:
            return
        step = self._manual_history.pop()
        kind, i = step.kind, step.index
        (self._manual_cam if kind is PointKind.CAMERA else self._manual_proj).pop(i, None)
        if kind is PointKind.PROJECTOR:
            self._manual_steered.pop(i, None)
        self.manual_goto(i)

    def manual_observations(self) -> ManualObservations:
        cam = sorted(self._manual_cam)
        proj = sorted(self._manual_proj)
        X = np.array([p[1] for p in self._manual_list])
        return ManualObservations(X[cam], np.array([self._manual_cam[i] for i in cam]).reshape(-1, 2),
                                  X[proj], np.array([self._manual_proj[i] for i in proj]).reshape(-1, 2))

    def calibrate_manual(self) -> bool:
        from anklescan.core.calibration.procedures.calibrate import calibrate_points
        cam_xyz, cam_uv, proj_xyz, proj_uv = self.manual_observations()
        size_c, size_p = self.camera_size, self.projector.projector_size  # a tuple already
        try:
            # hand-picked points are reported, not edited: nothing is left out
            cal, report = calibrate_points(cam_xyz, cam_uv, proj_xyz, proj_uv, camera_size=size_c,
                                           projector_size=size_p, radial_terms=2)
        except Exception as exc:
            self.status.setText(f"Manual calibration failed: {exc}")
            return False
        cal.extra["source"] = "manual control points (paper §3.2-3.3)"
        cal.extra["manual"] = {"camera_points": len(cam_xyz), "projector_points": len(proj_xyz),
                               "projector_points_refined": self.refined_count()}
        white = self._white_frame if self._white_frame is not None else np.zeros(size_c[::-1], np.uint8)
        self.points = BoxPoints(np.asarray(white, np.float32), cam_xyz, cam_uv, proj_xyz, proj_uv,
                                cam_pixels_of(proj_xyz, cam_xyz, cam_uv))
        self.calibration, self.report = cal, report
        self.show_report()
        self.go(PAGE_REPORT)
        return True
