"""Structured-light pattern sets: Gray code with inverses, white/black, phase shifting.

Conventions (SPEC section 4): the centre of projector column ``c`` is the continuous
coordinate ``c``.  A Gray code with ``stripe`` columns per code decodes to the centre of
its stripe, ``code * stripe + (stripe - 1) / 2``.  The phase frames are

    I_k(c) = 0.5 + 0.5 * cos(2*pi*(c - k*P/N) / P),   k = 0 .. N-1

so the N-step phase ``atan2(sum I_k sin d_k, sum I_k cos d_k)`` with ``d_k = 2*pi*k/N`` is
``2*pi*c/P``: phase 0 at column 0, and the decoded column at the centre of projector
column ``c`` is exactly ``c``.  A projector pixel is a box of width 1 around ``c``; box
filtering a cosine keeps its phase, so the convention holds for a real camera too.

Rows (axis ``"row"``) use the same formulas with the row index.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.atomic import PRIVATE_FILE_MODE, check_replaceable_dir, mkdtemp_beside, release_temp_dir, write_json_atomic
from anklescan.core.errors import CaptureError
from anklescan.core.limits import (
    MAX_FRAMES,
    MAX_GRAY_BITS,
    MAX_IMAGE_SIDE,
    MAX_MOTION_REFS,
    MAX_PHASE_STEPS,
    check_image_side,
    load_json,
)
from anklescan.core.vocabulary import Axis, TextEnum

FORMAT = "anklescan-patterns"
VERSION = 1


class FrameKind(TextEnum):
    """What a projected frame shows (the manifest's ``kind``)."""
    WHITE = "white"
    BLACK = "black"
    GRAY = "gray"
    PHASE = "phase"
    REPEAT = "repeat"


KINDS: tuple[FrameKind, ...] = tuple(FrameKind)
CODED_KINDS: tuple[FrameKind, ...] = (FrameKind.GRAY, FrameKind.PHASE)  # the kinds that encode an axis
FLAT_KINDS: tuple[FrameKind, ...] = (FrameKind.WHITE, FrameKind.BLACK)
AXES: tuple[Axis, ...] = (Axis.COLUMN, Axis.ROW)  # the axes a frame encodes
AXIS_TAG: dict[Axis, str] = {Axis.COLUMN: "col", Axis.ROW: "row"}
PRESETS = ("default", "paper", "short")
PAPER_BITS = 8  # the paper projects 8 Gray sheets (+ inverses, white, black): 18 frames
DEFAULT_PERIOD = 8  # projector px; column noise scales with the period, and at 8 px projector defocus
# still leaves ~80 % modulation (measured on the simulated rig: 0.08 mm RMS on the leg vs 0.11 at 16).
# With 8 steps, projector-gamma harmonics up to order 6 cancel.
DEFAULT_STEPS = 8
SHORT_STEPS = 4  # "short" preset, for slow cameras: 4 phase steps, Gray code to 2-px stripes (24 frames)
# Motion references (core/scan/motion.py): a quadrature pair of phase frames (shifts 0 and steps/4)
# repeated at evenly spaced times, compared with the same frames of the main set.
MOTION_REF_SHIFTS_QUARTER = (0, 1)  # in quarters of the steps: shift 0 and shift steps/4
PHASE_FORMULA = "I_k(c) = 0.5 + 0.5*cos(2*pi*(c - k*period/steps)/period), k = shift"

_T = TypeVar("_T")
# One frame to build: its kind and the Frame keyword fields (a repeat carries the spec it repeats).
FrameSpec = tuple["FrameKind", dict[str, Any]]


def _required(value: _T | None, what: str) -> _T:
    """A frame field its kind needs; a frame without it is a malformed pattern set."""
    if value is None:
        raise CaptureError(f"pattern frame is missing its {what}")
    return value


@dataclass(frozen=True)
class Frame:
    """One projected frame and what it encodes.

    ``bit`` counts from the most significant (0) of ``bits``; ``stripe`` is the number
    of projector columns (rows) per Gray code.  For phase frames ``shift`` is the step
    index k (the pattern moves by ``k * period / steps`` pixels).
    """

    file: str
    kind: FrameKind
    axis: Axis | None = None
    bit: int | None = None
    bits: int | None = None
    stripe: int | None = None
    inverse: bool = False
    period: float | None = None
    shift: int | None = None
    steps: int | None = None
    of: str | None = None  # kind "repeat": the file name of the frame this one shows again

    def to_dict(self) -> dict[str, object]:
        d: dict[str, object] = {"file": self.file, "kind": self.kind}
        if self.kind == FrameKind.GRAY:
            d.update(axis=self.axis, bit=self.bit, bits=self.bits, stripe=self.stripe,
                     inverse=self.inverse)
        elif self.kind == FrameKind.PHASE:
            d.update(axis=self.axis, period=self.period, shift=self.shift, steps=self.steps)
        elif self.kind == FrameKind.REPEAT:
            d.update(of=self.of)
        return d


@dataclass(frozen=True)
class AxisCode:
    """The frames that encode one axis, as indices into ``PatternSet.frames``."""

    axis: Axis
    size: int  # projector width (column) or height (row)
    bits: int
    stripe: int
    gray: tuple[int, ...]  # frame index of bit i (MSB first)
    gray_inv: tuple[int, ...]
    period: float | None = None
    steps: int | None = None
    phase: tuple[int, ...] = ()  # frame index of step k

    @property
    def n_codes(self) -> int:
        """Codes that exist on the projector (higher Gray codes are never projected)."""
        return -(-self.size // self.stripe)

    def code_centre(self, code: int) -> float:
        """Continuous projector coordinate of a stripe's centre (SPEC section 4)."""
        return code * self.stripe + (self.stripe - 1) / 2.0


@dataclass
class PatternSet:
    preset: str
    width: int
    height: int
    frames: list[Frame]
    axes: tuple[Axis, ...] = (Axis.COLUMN,)
    _codes: dict[Axis, AxisCode] | None = field(default=None, init=False, repr=False, compare=False)

    # ----------------------------------------------------------------- structure
    @property
    def files(self) -> list[str]:
        return [f.file for f in self.frames]

    def index(self, kind: FrameKind) -> int:
        """Frame index of the (single) white or black frame."""
        for i, f in enumerate(self.frames):
            if f.kind == kind:
                return i
        raise CaptureError(f"pattern set has no {kind} frame")

    def axis_code(self, axis: Axis) -> AxisCode | None:
        if self._codes is None:
            self._codes = {a: _axis_code(self, a) for a in self.axes}
        return self._codes.get(axis)

    def code(self, axis: Axis) -> AxisCode:
        """``axis``' code; a one-line CaptureError when the set does not encode that axis."""
        ac = self.axis_code(axis)
        if ac is None:
            raise CaptureError(f"pattern set has no {axis} code")
        return ac

    # ------------------------------------------------------------------ manifest
    def to_manifest(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "preset": self.preset,
            "projector": {"width": self.width, "height": self.height},
            "axes": list(self.axes),
            "conventions": {
                "pixel_centre": "projector column c's centre is the continuous coordinate c",
                "gray": "reflected binary Gray code of floor(c/stripe), bit 0 = MSB, "
                        "white (255) where the bit is 1; inverse frames are 255 - frame",
                "gray_decoded": "code*stripe + (stripe-1)/2",
                "phase": PHASE_FORMULA,
                "repeat": "the same image as the frame named by 'of', shown again later in the "
                          "capture (motion reference); decoders that do not measure motion skip it",
            },
            "frames": [f.to_dict() for f in self.frames],
        }

    @classmethod
    def from_manifest(cls, m: Any, source: str = "manifest") -> PatternSet:
        """Build and validate a pattern set; any defect raises a one-line CaptureError."""
        if not isinstance(m, dict):
            raise CaptureError(f"{source}: expected a JSON object, got {type(m).__name__}")
        for key in ("format", "version", "preset", "projector", "axes", "frames"):
            if key not in m:
                raise CaptureError(f"{source}: missing key '{key}'")
        if m["format"] != FORMAT:
            raise CaptureError(f"{source}: format is {m['format']!r}, expected {FORMAT!r}")
        if m["version"] != VERSION:
            raise CaptureError(f"{source}: unsupported version {m['version']!r} "
                               f"(expected {VERSION})")
        proj = m["projector"]
        if not isinstance(proj, dict) or not all(
                _is_pos_int(proj.get(k)) for k in ("width", "height")):
            raise CaptureError(f"{source}: projector width/height must be positive integers, "
                               f"got {proj!r}")
        check_image_side(proj["width"], proj["height"], f"{source}: projector", CaptureError)
        axes = m["axes"]
        if (not isinstance(axes, list) or not axes or any(a not in AXES for a in axes)
                or len(set(axes)) != len(axes)):
            raise CaptureError(f"{source}: axes must be a non-empty list of {AXES}, got {axes!r}")
        if not isinstance(m["frames"], list) or not m["frames"]:
            raise CaptureError(f"{source}: 'frames' must be a non-empty list")
        if len(m["frames"]) > MAX_FRAMES:
            raise CaptureError(f"{source}: {len(m['frames'])} frames is more than any pattern set "
                               f"(at most {MAX_FRAMES})")
        frames = [_frame_from_dict(d, i, source) for i, d in enumerate(m["frames"])]
        pset = cls(str(m["preset"]), int(proj["width"]), int(proj["height"]), frames,
                   tuple(Axis(a) for a in axes))
        pset.validate(source)
        return pset

    def validate(self, source: str = "pattern set") -> None:
        files = self.files
        seen: set[str] = set()
        for name in files:
            if name in seen:
                raise CaptureError(f"{source}: duplicate frame file name '{name}'")
            if not name or os.path.basename(name) != name or name.startswith("."):
                raise CaptureError(f"{source}: frame file name '{name}' must be a plain name")
            seen.add(name)
        for kind in FLAT_KINDS:
            n = sum(f.kind == kind for f in self.frames)
            if n != 1:
                raise CaptureError(f"{source}: expected exactly one {kind} frame, found {n}")
        for f in self.frames:
            if f.kind == FrameKind.REPEAT and (f.of not in seen or f.of == f.file
                                               or self.frames[files.index(f.of)].kind == FrameKind.REPEAT):
                raise CaptureError(f"{source}: repeat frame '{f.file}' must name another, "
                                   f"non-repeat frame of the set in 'of' (got {f.of!r})")
            if f.kind in CODED_KINDS and f.axis not in self.axes:
                raise CaptureError(f"{source}: frame '{f.file}' encodes axis {f.axis!r} "
                                   f"not listed in axes {list(self.axes)}")
        self._codes = None
        for a in self.axes:
            _axis_code(self, a, source)


def _is_pos_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v > 0


def _frame_from_dict(d: object, i: int, source: str) -> Frame:
    if not isinstance(d, dict):
        raise CaptureError(f"{source}: frame #{i} is not an object")
    for key in ("file", "kind"):
        if key not in d:
            raise CaptureError(f"{source}: frame #{i} is missing '{key}'")
    name, kind = d["file"], d["kind"]
    if not isinstance(name, str):
        raise CaptureError(f"{source}: frame #{i} file name must be a string")
    if kind not in KINDS:
        raise CaptureError(f"{source}: frame '{name}' has unknown kind {kind!r} "
                           f"(expected one of {KINDS})")
    kind = FrameKind(kind)
    if kind in FLAT_KINDS:
        return Frame(name, kind)
    if kind == FrameKind.REPEAT:
        if not isinstance(d.get("of"), str):
            raise CaptureError(f"{source}: repeat frame '{name}' needs 'of', the file name it repeats")
        return Frame(name, kind, of=d["of"])
    need = ("axis", "bit", "bits", "stripe", "inverse") if kind == FrameKind.GRAY else \
        ("axis", "period", "shift", "steps")
    for key in need:
        if key not in d:
            raise CaptureError(f"{source}: {kind} frame '{name}' is missing '{key}'")
    if d["axis"] not in AXES:
        raise CaptureError(f"{source}: frame '{name}' has unknown axis {d['axis']!r}")
    axis = Axis(d["axis"])
    if kind == FrameKind.GRAY:
        if not (_is_pos_int(d["bits"]) and d["bits"] <= MAX_GRAY_BITS and _is_pos_int(d["stripe"])
                and d["stripe"] <= MAX_IMAGE_SIDE and isinstance(d["bit"], int) and 0 <= d["bit"] < d["bits"]
                and isinstance(d["inverse"], bool)):
            raise CaptureError(f"{source}: gray frame '{name}' has bad bit/bits/stripe/inverse "
                               f"({d['bit']!r}/{d['bits']!r}/{d['stripe']!r}/{d['inverse']!r})")
        return Frame(name, kind, axis, d["bit"], d["bits"], d["stripe"], d["inverse"])
    period, shift, steps = d["period"], d["shift"], d["steps"]
    if not (isinstance(period, (int, float)) and not isinstance(period, bool)
            and 0 < period <= 2 * MAX_IMAGE_SIDE and math.isfinite(period)
            and _is_pos_int(steps) and 3 <= steps <= MAX_PHASE_STEPS
            and isinstance(shift, int) and 0 <= shift < steps):
        raise CaptureError(f"{source}: phase frame '{name}' has bad period/shift/steps "
                           f"({period!r}/{shift!r}/{steps!r})")
    return Frame(name, kind, axis, period=float(period), shift=shift, steps=steps)


def _axis_code(pset: PatternSet, axis: Axis, source: str = "pattern set") -> AxisCode:
    size = pset.width if axis == Axis.COLUMN else pset.height
    gray = [f for f in pset.frames if f.kind == FrameKind.GRAY and f.axis == axis]
    if not gray:
        raise CaptureError(f"{source}: axis '{axis}' has no gray frames")
    bits = {f.bits for f in gray}
    stripes = {f.stripe for f in gray}
    if len(bits) != 1 or len(stripes) != 1:
        raise CaptureError(f"{source}: {axis} gray frames disagree on bits/stripe")
    nbits = _required(bits.pop(), f"{axis} gray bits")
    stripe = _required(stripes.pop(), f"{axis} gray stripe")
    if stripe * 2 ** nbits < size:
        raise CaptureError(f"{source}: {axis} code of {nbits} bits x stripe {stripe} covers "
                           f"{stripe * 2 ** nbits} < projector size {size}")
    idx = {(f.bit, f.inverse): i for i, f in enumerate(pset.frames)
           if f.kind == FrameKind.GRAY and f.axis == axis}
    if len(idx) != len(gray):
        raise CaptureError(f"{source}: {axis} has a repeated gray bit")
    for b in range(nbits):
        for inv in (False, True):
            if (b, inv) not in idx:
                raise CaptureError(f"{source}: {axis} gray bit {b}"
                                   f"{' inverse' if inv else ''} frame is missing")
    phase = [(i, f) for i, f in enumerate(pset.frames) if f.kind == FrameKind.PHASE and f.axis == axis]
    period: float | None = None
    steps: int | None = None
    order: tuple[int, ...] = ()
    if phase:
        periods = {f.period for _, f in phase}
        stepss = {f.steps for _, f in phase}
        if len(periods) != 1 or len(stepss) != 1:
            raise CaptureError(f"{source}: {axis} phase frames disagree on period/steps")
        period = _required(periods.pop(), f"{axis} phase period")
        steps = _required(stepss.pop(), f"{axis} phase steps")
        by_shift = {_required(f.shift, "phase shift"): i for i, f in phase}
        if len(by_shift) != len(phase) or sorted(by_shift) != list(range(steps)):
            raise CaptureError(f"{source}: {axis} phase needs shifts 0..{steps - 1} once each, "
                               f"got {sorted(_required(f.shift, 'phase shift') for _, f in phase)}")
        if period < 2 * stripe:
            # unwrapping needs the Gray code to within +-period/2
            raise CaptureError(f"{source}: {axis} phase period {period:g} is shorter than two "
                               f"Gray stripes ({stripe})")
        order = tuple(by_shift[k] for k in range(steps))
    return AxisCode(axis, size, nbits, stripe,
                    tuple(idx[(b, False)] for b in range(nbits)),
                    tuple(idx[(b, True)] for b in range(nbits)),
                    period, steps, order)


# ---------------------------------------------------------------------- building
def make_pattern_set(preset: str = "default", width: int = 1024, height: int = 768,
                     axes: tuple[Axis | str, ...] = (Axis.COLUMN,), period: float = DEFAULT_PERIOD,
                     steps: int = DEFAULT_STEPS, motion_refs: int = 0) -> PatternSet:
    """``paper``: white, black, 8 Gray bits + inverses (18 frames for one axis).
    ``default``: Gray code down to single pixels + inverses, white, black, and
    ``steps``-step phase shifting of ``period`` pixels per axis.
    ``short`` (slow cameras): Gray code to 2-px stripes, ``SHORT_STEPS`` phase steps.
    ``motion_refs`` (>= 2, phase presets): that many repeats of a quadrature pair of the first
    axis' phase frames, the first pair before everything, the last after everything, the rest
    evenly between (``kind: "repeat"``; core/scan/motion.py measures the subject's motion from them)."""
    if preset not in PRESETS:
        raise CaptureError(f"unknown pattern preset {preset!r} (expected one of {PRESETS})")
    if not (_is_pos_int(width) and _is_pos_int(height)) or width < 2 or height < 2:
        raise CaptureError(f"projector size must be at least 2x2, got {width}x{height}")
    check_image_side(width, height, "projector", CaptureError)
    given = tuple(axes)
    if not given or any(a not in AXES for a in given) or len(set(given)) != len(given):
        raise CaptureError(f"axes must be a non-empty subset of {AXES}, got {given!r}")
    axis_list = tuple(Axis(a) for a in given)
    specs: list[FrameSpec] = [(FrameKind.WHITE, {}), (FrameKind.BLACK, {})]
    for axis in axis_list:
        size = width if axis == Axis.COLUMN else height
        full = max(1, math.ceil(math.log2(size)))
        nbits = min(PAPER_BITS, full) if preset == "paper" else max(1, full - 1) if preset == "short" else full
        # paper: 8 bits whatever the size, so stripes are 2**(full-8) wide (4 for 1024)
        stripe = 2 ** (full - nbits)
        for b in range(nbits):
            for inv in (False, True):
                specs.append((FrameKind.GRAY, dict(axis=axis, bit=b, bits=nbits, stripe=stripe,
                                           inverse=inv)))
        if preset == "short" and steps == DEFAULT_STEPS:
            steps = SHORT_STEPS
        if preset in ("default", "short"):
            for k in range(steps):
                specs.append((FrameKind.PHASE, dict(axis=axis, period=float(period), shift=k,
                                            steps=steps)))
    n_refs = int(motion_refs)
    if n_refs:
        if n_refs < 2 or preset == "paper" or steps % 4:
            raise CaptureError(f"motion references need a phase preset with steps a multiple of 4 "
                               f"and at least 2 of them, got {motion_refs!r} ({preset}, {steps} steps)")
        if n_refs > MAX_MOTION_REFS or len(specs) + 2 * n_refs > MAX_FRAMES:
            raise CaptureError(f"{n_refs} motion references are beyond any scan (at most {MAX_MOTION_REFS}, "
                               f"and {MAX_FRAMES} frames in all)")
        specs = _with_motion_refs(specs, axis_list[0], n_refs, steps)
    digits = max(2, len(str(len(specs) - 1)))
    names = [_file_name(i, digits, kind, kw) for i, (kind, kw) in enumerate(specs)]
    by_spec = {(kind, tuple(sorted(kw.items()))): n for n, (kind, kw) in zip(names, specs, strict=True)
               if kind != FrameKind.REPEAT}
    frames = [Frame(n, kind, of=by_spec[kw["of"]]) if kind == FrameKind.REPEAT else Frame(n, kind, **kw)
              for n, (kind, kw) in zip(names, specs, strict=True)]
    pset = PatternSet(preset, width, height, frames, axis_list)
    pset.validate()
    return pset


def _with_motion_refs(specs: list[FrameSpec], axis: Axis, n_refs: int, steps: int) -> list[FrameSpec]:
    """Insert ``n_refs`` quadrature pairs of ``axis``' phase frames, evenly spread in time."""
    pair = [s for s in specs if s[0] == FrameKind.PHASE and s[1]["axis"] == axis
            and s[1]["shift"] in tuple(q * steps // 4 for q in MOTION_REF_SHIFTS_QUARTER)]
    keys = [(FrameKind.REPEAT, {"of": (FrameKind.PHASE, tuple(sorted(kw.items()))), "ref": j})
            for _, kw in pair for j in [0]]
    n_main = len(specs)
    out: list[FrameSpec] = []
    at = [round(j * n_main / (n_refs - 1)) for j in range(n_refs)]
    for i in range(n_main + 1):
        for j, pos in enumerate(at):
            if pos == i:
                out.extend((FrameKind.REPEAT, {"of": k[1]["of"], "ref": j}) for k in keys)
        if i < n_main:
            out.append(specs[i])
    return out


def _file_name(i: int, digits: int, kind: FrameKind, kw: dict[str, Any]) -> str:
    head = f"{i:0{digits}d}_"
    if kind in FLAT_KINDS:
        return f"{head}{kind}.png"
    if kind == FrameKind.REPEAT:
        of = dict(kw["of"][1])
        return f"{head}ref{kw['ref']}_{AXIS_TAG[of['axis']]}_phase_s{of['shift']}.png"
    tag = AXIS_TAG[kw["axis"]]
    if kind == FrameKind.GRAY:
        return f"{head}{tag}_gray_b{kw['bit']:02d}{'_inv' if kw['inverse'] else ''}.png"
    return f"{head}{tag}_phase_p{kw['period']:g}_s{kw['shift']}.png"


def gray_profile(n: int, bit: int, bits: int, stripe: int) -> npt.NDArray[np.uint8]:
    """0/1 value of Gray bit ``bit`` (0 = MSB) for coordinates 0..n-1."""
    code = np.arange(n, dtype=np.int64) // stripe
    gray = code ^ (code >> 1)
    return ((gray >> (bits - 1 - bit)) & 1).astype(np.uint8)


def _cos_period(u: npt.NDArray[np.floating[Any]], period: float | np.floating[Any]) -> npt.NDArray[np.floating[Any]]:
    """cos(2*pi*u/period), evaluated on the folded argument min(m, P - m), m = u mod P.

    Folding makes mirror-image samples bit-identical, so 8-bit rounding errors are
    symmetric and cancel in the N-step sums: the decoded column is exact at centres."""
    m = np.mod(u, period)
    m = np.minimum(m, period - m)
    out: npt.NDArray[np.floating[Any]] = np.cos(m * (2 * np.pi / period))
    return out


def phase_profile(n: int, period: float, shift: int, steps: int) -> npt.NDArray[np.float64]:
    c = np.arange(n, dtype=np.float64)
    return (0.5 + 0.5 * _cos_period(c - shift * period / steps, period)).astype(np.float64, copy=False)


def render_frame(pset: PatternSet, frame: Frame) -> npt.NDArray[np.uint8]:
    """The projector image (uint8, height x width) of one frame."""
    h, w = pset.height, pset.width
    if frame.kind == FrameKind.REPEAT:
        return render_frame(pset, pset.frames[pset.files.index(_required(frame.of, "repeated frame"))])
    if frame.kind == FrameKind.WHITE:
        return np.full((h, w), 255, np.uint8)
    if frame.kind == FrameKind.BLACK:
        return np.zeros((h, w), np.uint8)
    n = w if frame.axis == Axis.COLUMN else h
    prof: npt.NDArray[np.uint8]
    if frame.kind == FrameKind.GRAY:
        prof = gray_profile(n, _required(frame.bit, "gray bit"), _required(frame.bits, "gray bits"),
                            _required(frame.stripe, "gray stripe")) * np.uint8(255)
        if frame.inverse:
            prof = 255 - prof
    else:
        prof = np.rint(255.0 * phase_profile(n, _required(frame.period, "phase period"),
                                             _required(frame.shift, "phase shift"),
                                             _required(frame.steps, "phase steps"))).astype(np.uint8)
    # build from a 1-D profile: broadcasting is far cheaper than evaluating per pixel
    if frame.axis == Axis.COLUMN:
        return np.ascontiguousarray(np.broadcast_to(prof[None, :], (h, w)))
    return np.ascontiguousarray(np.broadcast_to(prof[:, None], (h, w)))


def render_all(pset: PatternSet) -> list[npt.NDArray[np.uint8]]:
    return [render_frame(pset, f) for f in pset.frames]


def pattern_value(frame: Frame, u: npt.NDArray[np.floating[Any]]) -> npt.NDArray[np.float32]:
    """Projector intensity in [0, 1] (float32) at continuous coordinates ``u``.

    Gray stripes switch at pixel boundaries (``c + 0.5``); the phase frames are the
    continuous cosine, which is what a box-pixel projector shows once its optics blur
    the pixel grid (box filtering keeps the phase, only the amplitude drops)."""
    if frame.kind == FrameKind.REPEAT:
        raise CaptureError("pattern_value: resolve a repeat frame to the frame it repeats first")
    if frame.kind == FrameKind.WHITE:
        return np.ones_like(u, dtype=np.float32)
    if frame.kind == FrameKind.BLACK:
        return np.zeros_like(u, dtype=np.float32)
    if frame.kind == FrameKind.GRAY:
        bits = _required(frame.bits, "gray bits")
        code = np.floor((u + 0.5) / _required(frame.stripe, "gray stripe")).astype(np.int64)
        code = np.clip(code, 0, 2 ** bits - 1)
        bit = ((code ^ (code >> 1)) >> (bits - 1 - _required(frame.bit, "gray bit"))) & 1
        if frame.inverse:
            bit = 1 - bit
        return bit.astype(np.float32)
    period = _required(frame.period, "phase period")
    shifted = u - np.float32(_required(frame.shift, "phase shift") * period / _required(frame.steps, "phase steps"))
    # the float32 period keeps float32 arithmetic (and the tested bit pattern) in the fold
    return (0.5 + 0.5 * _cos_period(shifted, np.float32(period))).astype(np.float32)


def simulate_frames(pset: PatternSet, column_map: npt.ArrayLike, row_map: npt.ArrayLike | None = None, *,
                    albedo: npt.ArrayLike = 0.8, ambient: float = 0.05, blur: float = 0.0, noise: float = 0.0,
                    gamma: float = 1.0, dtype: npt.DTypeLike = np.uint8,
                    rng: np.random.Generator | None = None) -> npt.NDArray[Any]:
    """A synthetic capture: camera pixel (x, y) sees projector point
    (column_map, row_map); intensity = ambient + albedo * pattern**gamma, Gaussian blur
    of ``blur`` camera px, additive noise ``noise`` (fraction of full scale), clipped and
    quantised to ``dtype``.  Returns the (n_frames, H, W) stack in manifest order."""
    rng = np.random.default_rng(0) if rng is None else rng
    full = 255.0 if np.dtype(dtype) == np.uint8 else 65535.0
    shape = np.shape(column_map)
    # blur needs the scene beyond the image border: continue the maps linearly (odd
    # reflection) instead of mirroring the pattern, which would shift phases there
    pad = int(math.ceil(4 * blur)) + 1 if blur > 0 else 0
    crop = (slice(pad, pad + shape[0]), slice(pad, pad + shape[1]))

    def extend(m: npt.ArrayLike, **how: Any) -> npt.NDArray[np.float32]:
        a = np.broadcast_to(np.asarray(m, np.float32), shape)
        return np.pad(a, pad, **how) if pad else a

    columns = extend(column_map, mode="reflect", reflect_type="odd")
    rows = None if row_map is None else extend(row_map, mode="reflect", reflect_type="odd")
    albedos = extend(albedo, mode="edge")
    out = np.empty((len(pset.frames),) + shape, dtype)
    for i, f in enumerate(pset.frames):
        if f.kind == FrameKind.REPEAT:
            f = pset.frames[pset.files.index(_required(f.of, "repeated frame"))]
        if f.kind in CODED_KINDS and f.axis == Axis.ROW:
            if rows is None:
                raise CaptureError("simulate_frames needs a row map for row patterns")
            u = rows
        else:
            u = columns
        img = pattern_value(f, u)
        if gamma != 1.0:
            img = np.power(img, np.float32(gamma))
        img = np.float32(ambient) + albedos * img
        if blur > 0:
            img = np.asarray(cv2.GaussianBlur(img, (0, 0), blur), np.float32)[crop]
        if noise > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise)
        out[i] = np.clip(np.rint(img * full), 0, full).astype(dtype)
    return out


# ----------------------------------------------------------------------- writing
def _unlink_quiet(p: str | os.PathLike[str]) -> None:
    with contextlib.suppress(OSError):
        os.unlink(p)


def imwrite_checked(path: str | os.PathLike[str], image: npt.NDArray[Any]) -> None:
    # encode + write ourselves: cv2.imwrite crashes on paths that are not valid UTF-8, and
    # the file is created private (frames are patient data) whatever the umask
    try:
        ok, data = cv2.imencode(Path(path).suffix or ".png", image)
    except cv2.error:
        ok = False
    if not ok:
        raise CaptureError(f"could not encode image {path}")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), PRIVATE_FILE_MODE)
    with os.fdopen(fd, "wb") as fh:
        os.fchmod(fh.fileno(), PRIVATE_FILE_MODE)
        fh.write(data.tobytes())


def replace_dir(tmp_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str],
                is_ours: Callable[[Path], bool] | None = None) -> None:
    """Move a finished temporary directory into place.

    An existing ``out_dir`` is renamed aside first and removed only after the new one is
    in place, so at every instant ``out_dir`` is either the old or the new complete set.
    Only an empty folder or an earlier output of ours (``is_ours``, default
    ``is_pattern_output``: a pattern set, never a capture) is replaced: a folder with any
    other file is refused untouched.
    """
    out_dir = Path(out_dir)
    old: Path | None = None
    check_replaceable_dir(out_dir, is_ours or is_pattern_output)
    release_temp_dir(tmp_dir)
    if out_dir.exists():
        old = Path(mkdtemp_beside(out_dir, "old"))
        release_temp_dir(old)
        os.rmdir(old)
        os.replace(out_dir, old)
    try:
        os.replace(tmp_dir, out_dir)
    except BaseException:
        if old is not None:  # put the earlier output back: never leave neither
            os.replace(old, out_dir)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_patterns(pset: PatternSet, out_dir: str | os.PathLike[str]) -> Path:
    """Write one 8-bit PNG per frame plus manifest.json, atomically (tmp dir + rename)."""
    out_dir = Path(out_dir)
    parent = out_dir.parent
    if not parent.is_dir():
        raise CaptureError(f"output folder's parent {parent} does not exist")
    check_replaceable_dir(out_dir, is_pattern_output)  # refuse before the long rendering
    tmp = Path(mkdtemp_beside(out_dir))
    try:
        for f in pset.frames:
            imwrite_checked(tmp / f.file, render_frame(pset, f))
        write_json_atomic(tmp / "manifest.json", pset.to_manifest())
        replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def load_manifest(path: str | os.PathLike[str]) -> PatternSet:
    path = Path(path)
    return PatternSet.from_manifest(load_json(path, "manifest", CaptureError), str(path))


def is_pattern_output(folder: str | os.PathLike[str], allow_capture: bool = False) -> bool:
    """True when ``folder`` holds only an earlier pattern set of ours: a valid manifest.json
    and nothing but its frames. A camera capture (a manifest with a "capture" object) is
    someone's scan, so it counts only with ``allow_capture``."""
    folder = Path(folder)
    try:
        manifest = load_json(folder / "manifest.json", "manifest", CaptureError)
        pset = PatternSet.from_manifest(manifest, str(folder / "manifest.json"))
        entries = list(folder.iterdir())
    except (CaptureError, OSError):
        return False
    if "capture" in manifest and not allow_capture:
        return False
    allowed = set(pset.files) | {"manifest.json"}
    if not all(e.name in allowed and e.is_file() and not e.is_symlink() for e in entries):
        return False
    # A capture made by photographing the pattern folder file by file has the same manifest and
    # names (SPEC §5): only frames that are still exactly our renders make the folder ours.
    return allow_capture or all(_is_our_render(folder / f.file, pset, f) for f in pset.frames
                                if (folder / f.file).exists())


def _is_our_render(path: Path, pset: PatternSet, frame: Frame) -> bool:
    """``path`` decodes to exactly the image ``write_patterns`` writes for ``frame`` (lossless PNG)."""
    try:
        img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except (OSError, ValueError, cv2.error):
        return False
    return img is not None and np.array_equal(img, render_frame(pset, frame))


__all__ = ["Frame", "AxisCode", "PatternSet", "make_pattern_set", "render_frame",
           "render_all", "pattern_value", "simulate_frames", "write_patterns", "load_manifest", "gray_profile", "phase_profile",
           "PHASE_FORMULA"]
