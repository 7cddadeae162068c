"""Every chosen plate placed again by its image on its own face's plane, and the kit's size from those fits.

A plate's rim fit reads its outline as half-contrast edges. Seen at 40-78° from its normal, the
near half of that outline is the side wall's (those edges are dropped), so the centre along the
view rests on the far rim and the radius: it follows the radius one for one, and edges read under
a blur of a pixel lie inside the rim. Measured on the simulated rig (docs/marks.md, "The model's three stages", item 4):
rim fits 0.15-0.46 mm off along the view where the image model, on the true plane with the true
radius, is within 0.02 mm.

``mark_plate_image``'s model draws the face, its lit side wall and its cast shadow and fits them
to every pixel of the plate's image. Here the plane is the plate's own: through its fitted centre
with its fitted normal, its height corrected by the face's decoded points (``fit_plate_image``).
The face's radius is fitted too: the ellipse's long axis is not foreshortened, so it is known at
any view. The kit's radius is the one given, or the weighted mean of the other table plates'
fitted radii (facing up: a leg's plate bares more wall); each centre is then conditioned on it
through its covariance with its own fitted radius.

On a leg the surface falls away under the rim; where the skin round the plate decodes, the model
draws it (``mark_surround``). A plate keeps its rim fit where the image fit fails, leaves its
reach, or its drawing is not its image (``mark_plate_image.model_holds``: residuals past the
noise and the model's error).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_plate_image import FacePlane, FitShape, PlateImageFit, fit_plate_image, model_holds
from anklescan.core.measure.mark_types import Mark
from anklescan.core.vocabulary import MarkKind


@dataclass(frozen=True)
class KitRadius:
    """The kit's face radius and its SD, mm."""

    radius_mm: float
    sd_mm: float


def refit_plates(marks: Sequence[Mark], image: np.ndarray, points: np.ndarray, cal: Calibration,
                 radius_mm: float, given: bool, thickness_mm: float | None = None) -> tuple[list[Mark], KitRadius | None]:
    """``marks`` with each plate's centre and covariance from its image fit where the model
    holds, and the kit's radius those fits measure (None where ``given``, or no fit holds).
    ``radius_mm``: the kit's radius, given or measured from the rims (the fits' start);
    ``thickness_mm``: the kit's thickness (the plates' median step), each fit's start, else its
    plate's own step; ``points``: (H, W, 3) decoded world points per camera pixel."""
    fits = [_image_fit(m, image, points, cal, radius_mm, thickness_mm) for m in marks]
    # the radius from plates on the table (facing up): a leg curving away under a plate bares
    # more of its wall than the model's plane below does, and reads its radius large
    held = [f for m, f in zip(marks, fits, strict=True) if f is not None and abs(m.normal[2]) >= CONFIG.leg_normal_max_z]
    out = []
    for m, fit in zip(marks, fits, strict=True):
        if fit is None:
            out.append(m)
            continue
        kit = KitRadius(radius_mm, CONFIG.radius_prior_sd_mm) if given else pooled([f for f in held if f is not fit])
        out.append(_placed(m, fit, kit, cal))
    return out, (None if given else pooled(held))


def pooled(fits: Sequence[PlateImageFit]) -> KitRadius | None:
    """The fitted radii's weighted mean, its SD at least their scatter's over their number."""
    if not fits:
        return None
    r = np.array([f.radius_mm for f in fits])
    w = 1.0 / np.maximum(np.array([f.radius_sd for f in fits]), 1e-6) ** 2
    mean = float(np.sum(w * r) / np.sum(w))
    sd = math.sqrt(1.0 / float(np.sum(w)))
    if len(fits) > 1:
        sd = max(sd, math.sqrt(float(np.sum(w * (r - mean) ** 2) / np.sum(w)) / (len(fits) - 1)))
    return KitRadius(mean, sd)


def _image_fit(mark: Mark, image: np.ndarray, points: np.ndarray, cal: Calibration,
               radius_mm: float, thickness_mm: float | None) -> PlateImageFit | None:
    """The plate's image fit with its radius free, on its face's plane, started at the kit's
    ``thickness_mm`` where known; None for a sticker, or where the fit fails or the model does
    not hold."""
    if mark.kind is not MarkKind.PLATE or mark.step_mm is None or mark.step_mm <= CONFIG.sticker_max_step_mm:
        return None
    n = mark.normal if mark.normal @ (cal.camera.center - mark.centre) >= 0 else -mark.normal
    # the plane's own point is the plate's centre: its tilt moves nothing there
    plane = FacePlane(mark.centre, n, math.sqrt(max(float(n @ mark.covariance @ n), 0.0)), 0.0)
    shape = FitShape(CONFIG.plate_refit_reach, CONFIG.plate_refit_subsamples, free_radius=True)
    # every plate is one of the kit: its own step can read far off (a quarter of the kit's, on a
    # table plate whose surround decodes sparsely), and the fit's window, the points it keeps
    # (those between the face and the table that far below) and its thickness's bound follow
    # the thickness it starts at
    start = mark.step_mm if thickness_mm is None else thickness_mm
    fit = fit_plate_image(image, points, cal, plane, mark.centre, radius_mm, start, shape)
    if fit is None or fit.centre_radius_cov is None:
        return None
    if model_holds(fit):
        return fit
    # a plate the search found rests on its rim's points, and needs no more of its face to
    # decode; but where too few do to test the face's height, the image fit stands on its plane's
    # alone, which a grazing ray carries along the view: it replaces the rim fit only where it is
    # the surer of the two along its longest axis
    surer = _major_variance(fit.covariance) < _major_variance(mark.covariance)
    return fit if surer and model_holds(fit, untested_height=True) else None


def _major_variance(cov: np.ndarray) -> float:
    """mm²: a covariance's largest eigenvalue."""
    return float(np.linalg.eigvalsh(cov)[-1])


def _placed(mark: Mark, fit: PlateImageFit, kit: KitRadius | None, cal: Calibration) -> Mark:
    """``mark`` at the image fit's centre, conditioned on the kit's radius where known: the
    centre moves by its covariance with the fitted radius over the radii's variance."""
    centre, cov = fit.centre, fit.covariance
    if kit is not None and fit.centre_radius_cov is not None:
        s2 = fit.radius_sd**2 + kit.sd_mm**2
        k = fit.centre_radius_cov / max(s2, 1e-12)
        centre = centre + k * (kit.radius_mm - fit.radius_mm)
        cov = cov - np.outer(k, fit.centre_radius_cov)
        cov = 0.5 * (cov + cov.T)
    uv = cal.camera.project(centre[None])[0]
    return replace(mark, centre=centre, covariance=cov, pixel=(float(uv[0]), float(uv[1])))
