"""Typed results of one disk's fit (docs/marks.md, "Stages"): a ``DiskFit`` (the model's
parameters with their covariance) or a ``Refusal`` (which check failed, and the one line that
says so with its figures)."""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import numpy as np


class RefusalReason(enum.Enum):
    """Why a candidate is not a mark: the check of ``mark_fit`` that failed."""

    TOO_SMALL = "too small to fit"
    NOT_ELLIPTICAL = "not elliptical"
    TOO_FEW_POINTS = "too few decoded 3-D points"
    NOT_FLAT = "not flat"
    WRONG_AREA = "wrong image size for its depth"
    NO_EDGE = "no clear edge"
    NO_SURFACE = "no decoded surface around a sticker"
    NOT_A_CIRCLE = "edge points do not form a circle"
    EDGES_ON_A_LINE = "edge points lie on a line"
    RADIUS_OUT_OF_RANGE = "free radius outside the searched range"
    WRONG_RADIUS = "free radius not the marks' size"
    EDGES_SCATTER = "edge points scatter about the circle"
    SHORT_ARC = "too short an arc"
    GRAZING_LIGHT = "lit too obliquely"
    PARTLY_HIDDEN = "partly in a shadow or hidden"
    OUTLINE_THROUGH = "an outline runs through its face"
    FACE_NOT_SMOOTH = "face not smooth"
    LIT_EDGES_ON_A_LINE = "the lit image's edges lie on a line"
    IMAGES_DISAGREE = "the lit and corrected images place it apart"


@dataclass(frozen=True, eq=False)
class SurfaceStep:
    """A disk's face over the surface around it (``marks_surface.surface_step``)."""

    step_mm: float  # height of the face over the surface (a plate's thickness; a sticker ~0)
    step_sd: float  # its SD, mm (with the quadric's RMS misfit as a 3-SD bound)
    normal: np.ndarray  # (3,) unit normal of the surrounding surface at the disk's centre
    slope_cov: np.ndarray  # (2, 2) covariance of that surface's slope along the local frame's axes, rad²
    ring_decoded: float  # share of the ring around the disk with a 3-D point


@dataclass(frozen=True)
class Refusal:
    """A candidate refused: ``reason`` the check, ``detail`` the one-line message with figures."""

    reason: RefusalReason
    detail: str

    def __str__(self) -> str:
        return self.detail


@dataclass(frozen=True, eq=False)
class DiskFit:
    """One disk model fitted to its rim's edge points (plate: plane + far-side circle; sticker:
    circle along the local quadric). World mm."""

    centre: np.ndarray  # (3,) centre of the face (a sticker: the skin under its centre)
    normal: np.ndarray  # (3,) unit, towards the camera
    radius: float  # the free fit's radius
    radius_sd: float  # its SD
    edge_rms: float  # edge points about the fitted circle
    face_rms: float  # face (plate) or surface (sticker) points about their fit
    covariance: np.ndarray  # (3, 3) of the centre
    n_edge: int  # edge points used

    def moved(self, centre: np.ndarray, covariance: np.ndarray) -> DiskFit:
        """The same fit with another centre and covariance."""
        return dataclasses.replace(self, centre=centre, covariance=covariance)
