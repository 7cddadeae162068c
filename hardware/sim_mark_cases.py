"""The marks' accuracy as a table of cases: one row, one simulated capture, one expectation.

A ``Case`` is a row of ``tests/data/mark_cases.csv`` (or a drawn combination,
``Case.drawn``): the table's posture, the marks' type, size and thickness, the camera's read
noise and blur, the room's ambient light, whether the size is given, and optionally a drawn
clinic set-up (``sim_variety.draw_variant``), the rig's layout, ankle disks that nearly touch and
a camera that sees the table obliquely. ``run_case`` renders it on the simulated rig, measures it
with ``measure_capture`` and the rig's true calibration and judges the result against the
issue's targets (all seven found and labelled right, centres within ``TARGET_CENTRE_MM``, angles
within ``TARGET_ANGLE_DEG``):

- ``RIGHT``: complete and within the targets;
- ``REFUSED``: not complete, with one line saying what was found and what is missing;
- ``WRONG``: complete, but a centre or an angle beyond its target or a label wrong (a wrong answer);
- ``CRASH``: an exception, or a refusal that is not one clear line.

A row expects ``right`` (the contract's conditions) or ``right_or_refused`` (harsher images:
never a wrong answer). tests/test_mark_cases.py runs the rows marked ``suite``;
``benchmarks/bench_marks.py --cases`` runs them all.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from anklescan.core.vocabulary import MarkKind
from anklescan.hardware.sim_scene import leg_scene
from anklescan.hardware.sim_variety import (
    Conditions,
    draw_conditions,
    draw_variant,
    view_devices,
    view_for_table,
)
from anklescan.hardware.simrig import Optics, RigLayout, SimRig

TARGET_CENTRE_MM = 0.3  # issue #38's targets under the contract's conditions
TARGET_ANGLE_DEG = 0.2
WRONG_LABEL_MM = 3.0  # a labelled mark further than this from its label's true mark is another mark
DEFAULT_DIAMETER_MM = 15.0  # the default scene's marks (leg_scene: mark_radius 7.5, 1.5 mm thick)
DEFAULT_THICKNESS_MM = 1.5
CASES_FILE = Path(__file__).resolve().parents[1] / "tests" / "data" / "mark_cases.csv"


class Expectation(StrEnum):
    RIGHT = "right"
    RIGHT_OR_REFUSED = "right_or_refused"


class SizeMode(StrEnum):
    MEASURED = "measured"  # the marks' diameter found from the capture
    GIVEN = "given"  # the true diameter given, as --mark-diameter does


class Outcome(StrEnum):
    RIGHT = "right"
    REFUSED = "refused"
    WRONG = "WRONG"
    CRASH = "CRASH"


@dataclass(frozen=True)
class Case:
    """One row. ``None``: the default scene's (or the drawn variant's) own value."""

    name: str
    inversion: float
    plantar_flexion: float
    expect: Expectation
    group: str = ""
    mark_type: MarkKind | None = None
    diameter_mm: float | None = None
    thickness_mm: float | None = None
    noise_255: float | None = None  # read noise in 1/255 of full scale (rig default 2)
    camera_blur_px: float | None = None  # full-resolution camera px (rig default 0.6)
    ambient: float | None = None  # of the projector's full white (rig default 0.04)
    size: SizeMode = SizeMode.MEASURED
    variant: int | None = None  # draw_variant's seed: a clinic's leg, marks, optics and camera
    layout: RigLayout | None = None  # the projector round the camera
    ankle_gap_mm: float | None = None  # leg_scene's ankle_mark_gap_mm: adjacent ankle disks
    table_view_deg: float | None = None  # camera placed to see the table top this far from its normal
    lateral_mark_deg: float | None = None  # leg_scene's lateral_mark_deg
    seed: int = 0  # the camera noise's
    scale: float = 0.75  # the rig's resolution (1: 1600x1200)
    suite: bool = False  # run by tests/test_mark_cases.py
    xfail: str = ""  # why today's detector fails it (the suite expects the failure, not strictly)
    note: str = ""

    @classmethod
    def drawn(cls, seed: int, harsh: bool = False, scale: float = 0.75) -> Case:
        """A drawn combination: ``draw_variant(seed)`` with ``draw_conditions(seed, harsh)``."""
        c: Conditions = draw_conditions(seed, harsh)
        v = draw_variant(seed)
        return cls(name=f"{'harsh' if harsh else 'drawn'} {seed}", inversion=c.inversion, plantar_flexion=c.plantar_flexion,
                   expect=Expectation.RIGHT_OR_REFUSED if harsh else Expectation.RIGHT,
                   group="drawn, harsh" if harsh else "drawn, contract", mark_type=v.mark_type,
                   diameter_mm=c.adjacent_diameter_mm or v.diameter,
                   thickness_mm=round(float(v.scene["mark_thickness"]), 2), noise_255=round(c.noise_sigma * 255, 2),
                   camera_blur_px=c.camera_blur_px, ambient=c.ambient,
                   size=SizeMode.GIVEN if c.size_given else SizeMode.MEASURED, variant=seed,
                   ankle_gap_mm=c.ankle_gap_mm, table_view_deg=c.table_view_deg, seed=seed, scale=scale)

    def describe(self) -> str:
        """The row's conditions in a few words."""
        kind = self.mark_type or (draw_variant(self.variant).mark_type if self.variant is not None else MarkKind.PLATE)
        parts = [f"{self.inversion:g}/{self.plantar_flexion:g}", f"{kind} {self.true_diameter():.3g} mm"
                 + (f" x {self.thickness_mm:g}" if self.thickness_mm is not None else ""),
                 f"size {self.size}"]
        parts += [f"{label} {v:g}" for label, v in (("noise", self.noise_255), ("blur", self.camera_blur_px),
                                                     ("ambient", self.ambient), ("variant", self.variant),
                                                     ("gap", self.ankle_gap_mm), ("table seen at", self.table_view_deg),
                                                     ("lateral", self.lateral_mark_deg)) if v is not None]
        return ", ".join(parts + ([self.layout] if self.layout else []) + [f"scale {self.scale:g}"])

    def optics(self) -> dict[str, float]:
        """The rows' optics overrides (Optics' fields)."""
        return {k: v for k, v in (("noise_sigma", None if self.noise_255 is None else self.noise_255 / 255.0),
                                  ("camera_blur_px", self.camera_blur_px), ("ambient", self.ambient)) if v is not None}

    def rig(self) -> SimRig:
        """The simulated rig this row describes."""
        if self.variant is not None:
            # the variant as drawn (draw_variant's own type, size or layout would shift its later draws)
            v = draw_variant(self.variant)
            scene = {**v.scene, "mark_type": self.mark_type or v.mark_type,
                     "mark_radius": (self.diameter_mm or v.diameter) / 2}
            view = v.view
            overrides: dict[str, Any] = self.optics()  # Optics' float fields, by name
            optics = replace(v.optics, **overrides)
            layout = self.layout or v.layout
        else:
            scene = {"mark_type": self.mark_type or MarkKind.PLATE,
                     "mark_radius": (self.diameter_mm or DEFAULT_DIAMETER_MM) / 2}
            view = None
            own: dict[str, Any] = self.optics()
            optics = replace(Optics(), **own)
            layout = self.layout or RigLayout.SIDE
        for key, value in (("mark_thickness", self.thickness_mm), ("ankle_mark_gap_mm", self.ankle_gap_mm),
                           ("lateral_mark_deg", self.lateral_mark_deg)):
            if value is not None:
                scene[key] = value
        if self.table_view_deg is not None:
            view = view_for_table(self.table_view_deg, self.inversion, self.plantar_flexion, view)
        camera, projector = view_devices(view, self.scale, layout) if view is not None else (None, None)
        return SimRig(leg_scene(self.inversion, self.plantar_flexion, **scene), camera, projector, scale=self.scale,
                      optics=optics, seed=self.seed, layout=layout)

    def true_diameter(self) -> float:
        if self.variant is not None:
            return self.diameter_mm or draw_variant(self.variant).diameter
        return self.diameter_mm or DEFAULT_DIAMETER_MM


@dataclass(frozen=True)
class CaseResult:
    """What ``run_case`` found for one row, judged against the targets."""

    case: Case
    outcome: Outcome
    centre_errors_mm: dict[str, float] = field(default_factory=dict)  # per labelled mark
    angle_errors_deg: dict[str, float] = field(default_factory=dict)  # per angle reported
    wrong_labels: tuple[str, ...] = ()  # labels given to another mark (or to a false one)
    message: str = ""  # the refusal's line, or the exception
    seconds: float = 0.0  # measure_capture's time

    @property
    def passed(self) -> bool:
        return self.outcome == Outcome.RIGHT or (self.outcome == Outcome.REFUSED
                                                 and self.case.expect == Expectation.RIGHT_OR_REFUSED)

    def line(self) -> str:
        """One line: PASS/FAIL, the outcome, the worst errors, the conditions, the refusal."""
        worst_c = max(self.centre_errors_mm.items(), key=lambda kv: kv[1], default=None)
        worst_a = max(self.angle_errors_deg.items(), key=lambda kv: abs(kv[1]), default=None)
        figures = (f"centre {worst_c[1]:.3f} mm ({worst_c[0]})" if worst_c else "no centre") + ", " + (
            f"angle {worst_a[1]:+.3f} deg ({worst_a[0].replace('_', ' ')})" if worst_a else "no angle")
        return (f"{'PASS' if self.passed else 'FAIL'} {self.outcome:7s} {self.case.name}: {figures}"
                + (f"; wrong labels {','.join(self.wrong_labels)}" if self.wrong_labels else "")
                + f" [{self.case.describe()}; expect {self.case.expect}; {self.seconds:.1f} s]"
                + (f" -- {self.message}" if self.message else ""))


def captured(rig: SimRig) -> Any:
    """The rig's capture of the default pattern set, along the stripe axes its calibration scans."""
    from anklescan.core.scan.capture import capture_from_images
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.core.scan.triangulate import scan_axes

    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=scan_axes(rig.true_calibration()))
    return capture_from_images(pset, rig.capture_many(render_all(pset)))


def judge(case: Case, result: Any, truth_marks: Mapping[str, np.ndarray], truth_angles: Mapping[str, float],
          seconds: float = 0.0) -> CaseResult:
    """``measure_capture``'s ``result`` against the true marks and angles. A refusal is one line and
    labels no mark wrongly (nearest another true mark, or over ``WRONG_LABEL_MM`` from its own)."""
    labelled = result.marks.labelled
    errors = {k: float(np.linalg.norm(np.asarray(m.centre) - truth_marks[k])) for k, m in sorted(labelled.items())}
    wrong = tuple(k for k, m in sorted(labelled.items())
                  if min(truth_marks, key=lambda t: float(np.linalg.norm(truth_marks[t] - np.asarray(m.centre)))) != k
                  or errors[k] > WRONG_LABEL_MM)
    angles = {k: float(v.value - truth_angles[k]) for k, v in result.angles.items() if k in truth_angles}
    if result.complete:
        within = (not wrong and all(e <= TARGET_CENTRE_MM for e in errors.values())
                  and all(math.isfinite(a) and abs(a) <= TARGET_ANGLE_DEG for a in angles.values())
                  and len(angles) == len(truth_angles))
        return CaseResult(case, Outcome.RIGHT if within else Outcome.WRONG, errors, angles, wrong, "", seconds)
    message = str(result.marks.message())
    if wrong:  # a refusal that labels another mark (or a false one) still tells the clinician a wrong place
        return CaseResult(case, Outcome.WRONG, errors, angles, wrong, message, seconds)
    clear = bool(message.strip()) and "\n" not in message
    return CaseResult(case, Outcome.REFUSED if clear else Outcome.CRASH, errors, angles, wrong,
                      message if clear else f"a refusal that is not one line: {message!r}", seconds)


def run_case(case: Case) -> CaseResult:
    """Render, measure and judge one row; an exception is a CRASH, reported, not raised."""
    from anklescan.core.measure.pipeline import measure_capture

    try:
        rig = case.rig()
        cap = captured(rig)
        given = case.true_diameter() if case.size == SizeMode.GIVEN else None
        t0 = time.perf_counter()
        result = measure_capture(cap, rig.true_calibration(), given)
        dt = time.perf_counter() - t0
        truth = rig.mark_truth()
        return judge(case, result, truth.marks, truth.angles, dt)
    except Exception as exc:  # noqa: BLE001 (a crash is a finding to report, not a reason to stop a sweep)
        return CaseResult(case, Outcome.CRASH, message=f"{type(exc).__name__}: {exc}"[:300])


# ---- the table ----------------------------------------------------------------------------------

_CONVERT: dict[str, Callable[[str], Any]] = {
    "mark_type": MarkKind, "expect": Expectation, "size": SizeMode, "layout": RigLayout, "variant": int, "seed": int,
    "suite": lambda s: s.strip().lower() in ("yes", "true", "1")}


def _value(name: str, text: str, kind: str) -> Any:
    text = text.strip()
    if name in _CONVERT:
        return _CONVERT[name](text)
    if "float" in kind:
        return float(text)
    return text


def load_cases(path: Path | str = CASES_FILE) -> list[Case]:
    """The rows of a cases CSV (a header naming Case's fields; empty cells: the default; lines
    starting with '#' are comments). ValueError naming the row for a bad cell or an unknown column."""
    kinds = {f.name: str(f.type) for f in fields(Case)}
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(line for line in fh if line.strip() and not line.lstrip().startswith("#")))
    cases: list[Case] = []
    for i, row in enumerate(rows, start=1):
        unknown = set(row) - set(kinds)
        if unknown:
            raise ValueError(f"{path}: unknown column(s) {', '.join(sorted(str(u) for u in unknown))}")
        try:
            values = {k: _value(k, v, kinds[k]) for k, v in row.items() if v is not None and v.strip() != ""}
            cases.append(Case(**values))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: row {i} ({row.get('name', '?')}): {exc}") from exc
    names = [c.name for c in cases]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: case names repeat: {sorted({n for n in names if names.count(n) > 1})}")
    return cases


CSV_COLUMNS = tuple(f.name for f in fields(Case))


def case_row(case: Case) -> str:
    """The CSV row that ``load_cases`` reads back as ``case`` (to paste a drawn case into the table)."""
    cells = []
    for name in CSV_COLUMNS:
        v = getattr(case, name)
        if v is None or v == "" or (name == "suite" and not v):
            cells.append("")
        elif isinstance(v, bool):
            cells.append("yes" if v else "")
        elif isinstance(v, float):
            cells.append(f"{v:g}")
        else:
            cells.append(str(v))
    return ",".join(f'"{c}"' if "," in c else c for c in cells)


def summary(results: Iterable[CaseResult]) -> list[str]:
    """Per group and in all: how many rows passed, and found right / refused / wrong / crashed."""
    by_group: dict[str, list[CaseResult]] = {}
    for r in results:
        by_group.setdefault(r.case.group or "-", []).append(r)
    everything = [r for rs in by_group.values() for r in rs]
    lines = []
    for group, rs in [*by_group.items(), ("all", everything)]:
        counts = {o: sum(r.outcome == o for r in rs) for o in Outcome}
        lines.append(f"{group}: {sum(r.passed for r in rs)}/{len(rs)} pass; right {counts[Outcome.RIGHT]}, "
                     f"refused {counts[Outcome.REFUSED]}, WRONG {counts[Outcome.WRONG]}, CRASH {counts[Outcome.CRASH]}")
    return lines
