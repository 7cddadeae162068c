"""The paper's manual calibration (§3.2-3.3) in the calibration dialog: click each marker corner
on the camera image (refined to sub-pixel), steer the projector spot onto it and record the
spot, refined to the clicked corner by eight edge frames photographed through app.acquisition
in the background. A mixin of app.calibration_wizard.CalibrationWizard.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt

from anklescan.app.calibration_pages import PAGE_MANUAL, PAGE_REPORT
from anklescan.app.calibration_views import gray_rgb
from anklescan.app.logic.calibration import BoxPoints, cam_pixels_of, refine_click


class ManualCalibration:
    """The manual page's behaviour; the dialog provides ``projector``, ``acquisition``, ``status``,
    ``manual_view`` and the other widgets of app.calibration_pages."""

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

    def _show_manual_frame(self, frame, picture=None, white: bool | None = None) -> None:
        """``picture``: the frame stretched (gray_rgb), when already made in the background."""
        if self.projector.mode == "white" if white is None else white:
            self._white_frame = frame  # clicks are refined on the box under white light, not the spot
        # stretched: under the spot alone the box is dim
        self.manual_view.set_image(gray_rgb(frame) if picture is None else picture)
        self._update_manual_marks()

    def set_manual_image(self, frame) -> None:
        """The image the camera clicks are refined on (the box under white light)."""
        self._last_frame = self._white_frame = frame
        self.manual_view.set_image(gray_rgb(frame))
        self._update_manual_marks()

    def pick_camera(self, x: float, y: float) -> tuple[float, float]:
        if self._white_frame is None:
            return x, y
        u, v = refine_click(self._white_frame, x, y, self.manual_half_window)
        self._manual_cam[self._manual_index] = (u, v)
        self._manual_history.append(("cam", self._manual_index))
        self._update_manual_marks()
        self.manual_goto(self._manual_index)
        return u, v

    def _manual_white(self) -> None:
        self._show_on_projector("white")

    def _manual_spot(self) -> None:
        self._show_on_projector("spot")
        self.projector.activateWindow()

    def keyPressEvent(self, event) -> None:
        # Arrow keys steer the spot from the dialog too, so the camera preview stays in view.
        if self.pages.currentIndex() == PAGE_MANUAL and self.projector.mode == "spot" and event.key() in (
                Qt.Key.Key_Left, Qt.Key.Key_Right, Qt.Key.Key_Up, Qt.Key.Key_Down):
            self.projector.keyPressEvent(event)
            return
        super().keyPressEvent(event)

    def record_spot(self, position=None) -> None:
        """Record the spot's projector pixel for the current point (the paper's projector step),
        refined to the point's camera click when that is on and possible (in the background:
        ``refining`` is True until it is recorded)."""
        if self._refining:
            return
        i = self._manual_index
        steered = tuple(float(c) for c in (self.projector.spot_position if position is None else position))
        note = "spot recorded as steered"
        if self.refine_spot_box.isChecked():
            if i not in self._manual_cam or self._white_frame is None:
                note += " (click the corner on the camera image first to have it refined)"
            else:
                self.refine_projector_spot(self._manual_cam[i], steered,
                                           lambda result: self._spot_refined(i, steered, result))
                return
        self._store_spot(i, steered, steered, note)

    def _spot_refined(self, i: int, steered, result) -> None:
        if result.ok:
            note = "spot refined to the clicked corner by ({:+.2f}, {:+.2f}) projector px".format(*result.shift)
            self._store_spot(i, steered, result.position, note)
        else:
            self._store_spot(i, steered, steered, f"spot recorded as steered, not refined: {result.message}")

    def _store_spot(self, i: int, steered, at, note: str) -> None:
        self._manual_proj[i] = at
        self._manual_steered[i] = steered
        self._manual_history.append(("proj", i))
        self.manual_goto(i)
        self.status.setText(f"Point {i + 1}: {note}.")

    @property
    def refining(self) -> bool:
        return self._refining

    def refined_count(self) -> int:
        return sum(self._manual_proj[i] != self._manual_steered.get(i) for i in self._manual_proj)

    def refine_projector_spot(self, corner_uv, steered, on_done) -> None:
        """Show the eight edge frames around the spot and photograph each (app.acquisition), read
        the projector coordinate at the corner (anklescan.core.calibration.procedures.projector_spot), all in
        the background; then show the spot where it was read and call ``on_done(SpotRefinement)``."""
        from anklescan.core.calibration.procedures.projector_spot import SpotRefinement, refine_spot, refinement_frames
        self._refining = True
        live = self._timer.isActive()
        self._timer.stop()  # the preview would photograph the edge frames as if they were the spot
        frames = refinement_frames(self.projector.projector_size, steered)
        white, settle = self._white_frame, self.settle_s

        def work(acq):
            images = acq.acquire(frames, mode="spot", settle_s=settle)
            return refine_spot(images, corner_uv, steered, white=white)

        def finish(result) -> None:
            self._refining = False
            self.projector.show_spot(*(result.position if result.ok else steered))
            if live:
                self._timer.start()
            on_done(result)

        # a camera or window failure: the steered spot is still recorded
        self.acquisition.run(work, finish, lambda message: finish(
            SpotRefinement(None, steered, f"the refinement frames could not be taken ({message})")))

    def manual_undo(self) -> None:
        if not self._manual_history:
            return
        kind, i = self._manual_history.pop()
        (self._manual_cam if kind == "cam" else self._manual_proj).pop(i, None)
        if kind == "proj":
            self._manual_steered.pop(i, None)
        self.manual_goto(i)

    def manual_observations(self):
        cam = sorted(self._manual_cam)
        proj = sorted(self._manual_proj)
        X = np.array([p[1] for p in self._manual_list])
        return (X[cam], np.array([self._manual_cam[i] for i in cam]).reshape(-1, 2),
                X[proj], np.array([self._manual_proj[i] for i in proj]).reshape(-1, 2))

    def calibrate_manual(self) -> bool:
        from anklescan.core.calibration.procedures.calibrate import calibrate_points
        cam_xyz, cam_uv, proj_xyz, proj_uv = self.manual_observations()
        size_c, size_p = self.camera_size, tuple(self.projector.projector_size)
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
