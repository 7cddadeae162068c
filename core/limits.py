"""Sanity limits on everything read from a user's files, checked before any allocation.

A careless or damaged input (a manifest claiming 2e10 Gray bits, a 20000x20000 frame, a
calibration JSON nested 200,000 levels deep, a 5,000-digit integer, ``Infinity``) must be
refused with one line and exit 2, quickly, instead of exhausting memory or surfacing as an
internal error. The limits sit far beyond any real camera, projector or rig, so they never
refuse a real input; each is a documented constant here so the other modules share them.

- ``load_json`` / ``parse_json``: THE way to read a user's JSON (manifest, calibration, ...):
  size, nesting depth, integer length and finite floats are checked; ``is_json_numbers``: a
  value that must be numbers is numbers (not ``true`` or ``"1000"``).
- ``image_size``: an image file's width and height from its header, without decoding it.
- ``check_image_side``: a width/height against ``MAX_IMAGE_SIDE``.
- ``require_finite``: a result (dict/list/array of numbers) must hold only finite numbers.
- ``check_input_file``: an input read whole is a regular file of sane size (the CLI applies
  it to every path argument; not /dev/zero, a FIFO or a 10 GB "CSV").
- ``bounded_int`` / ``bounded_float`` / ``size_type``: THE argparse ``type=`` of every numeric
  command-line option (``type=bounded_float(0, MAX_MM, "mm")``): a value outside its range,
  not finite or not a number is one line and exit 2 before any work. A new option takes one
  of these with a bound from this module; a bare ``type=int`` / ``type=float`` is a bug.
- ``MAX_COORDINATE_MM``: any coordinate read from a user's file (marks, control points).

Related helpers elsewhere: ``anklescan.core.atomic.guard_output`` (an output never replaces an input),
``anklescan.core.scan.capture.read_image`` (decode any path, including names that are not valid UTF-8,
on which ``cv2.imread`` crashes).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import stat
import struct
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from anklescan.core.errors import AnkleScanError

# numpy is imported inside the functions that need it: the command line builds its parser
# (with this module's option types) before any command runs, and --help must stay instant.

# Largest camera or projector side we accept, px. The largest sensors sold (~150 MP medium
# format) are ~14200 px wide and projectors stop at 8K (7680): 16384 leaves room.
MAX_IMAGE_SIDE = 16384
# Most frames a capture / pattern set may hold (ours: 2 + 2x11 Gray + 8 phase per axis = 62).
MAX_FRAMES = 1024
# Gray code bits per axis: 2**16 stripes already exceed MAX_IMAGE_SIDE.
MAX_GRAY_BITS = 16
# Phase-shift steps per axis (ours: 8; the literature uses 3..32).
MAX_PHASE_STEPS = 256
# A capture's frame stack may use at most this fraction of physical memory (decoding needs
# a few times the stack again), and never more than MAX_CAPTURE_BYTES.
MAX_CAPTURE_MEMORY_FRACTION = 0.25
MAX_CAPTURE_BYTES = 8 << 30
# Calibrations (SPEC section 4): values beyond these are a corrupted or mistyped file, not a
# rig. Focal lengths in px (a 16384 px sensor behind a 1000 mm lens is still < 1e6 px), the
# principal point within 10 image sizes of the image (offset projector lenses put it just
# outside), distortion coefficients of real lenses are O(1) (fisheyes O(10)), and a device
# more than 100 m from the world origin is not in the room.
MIN_FOCAL_PX = 1.0
MAX_FOCAL_PX = 1e6
MAX_PRINCIPAL_POINT_SIZES = 10.0
MAX_DISTORTION = 1e3
MAX_TRANSLATION_MM = 1e5
# The camera-projector baseline, mm: depth resolution scales with it, and real rigs use
# 100-400 mm; below 1 mm (a projector "at the camera") nothing can be triangulated.
MIN_BASELINE_MM = 1.0
# Any single input file a command reads whole (CSV of marks or control points, JSON, a
# device's calibration export): ours are kB to a few MB.
MAX_INPUT_FILE_BYTES = 256 << 20
# JSON files we read are a few kB (a manifest) to a few MB (a calibration with reports).
MAX_JSON_BYTES = 64 << 20
MAX_JSON_DEPTH = 64
MAX_JSON_INT_DIGITS = 30  # far beyond any count or id; Python refuses > 4300 digits anyway
# Repeats of a phase pair spread over a scan to measure motion (ours: 3, at most 2 frames each).
MAX_MOTION_REFS = 64
# Any coordinate in a user's file (marks, control points), mm: 100 m is beyond any room, and
# far below the range where the angles' arithmetic loses its precision (1e308 gave 135°).
MAX_COORDINATE_MM = 1e5
# Lengths given on the command line (a board square, a motion threshold, sigma), mm.
MAX_OPTION_MM = 1e4
# A mark's diameter, mm: SPEC section 2 allows 8-25 mm; 4x that is a typing error, not a mark.
MAX_MARK_DIAMETER_MM = 100.0
# A simulated patient's drift for `demo --sway`, mm (beyond it no mark is found at all).
MAX_SWAY_MM = 50.0
# Inner corners of a calibration chessboard, per side.
MAX_BOARD_CORNERS = 500


# ------------------------------------------------------------------------------ JSON
class _NumberError(ValueError):
    pass


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_JSON_INT_DIGITS:
        raise _NumberError(f"an integer of {len(text.lstrip('-'))} digits is out of range")
    return int(text)


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _NumberError(f"number {text[:20]}{'...' if len(text) > 20 else ''} is out of range")
    return value


def _parse_constant(name: str) -> NoReturn:
    raise _NumberError(f"{name} is not a finite number")


def _depth_ok(obj: object) -> bool:
    stack: list[tuple[object, int]] = [(obj, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            return False
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values() if isinstance(v, (dict, list)))
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node if isinstance(v, (dict, list)))
    return True


def parse_json(text: str, where: str, error: type[AnkleScanError] = AnkleScanError) -> Any:
    """``json.loads`` for untrusted text: any defect raises ``error`` naming ``where``. The value
    is JSON's (a dict, list, str, number, bool or None): the caller checks its shape."""
    try:
        obj = json.loads(text, parse_int=_parse_int, parse_float=_parse_float,
                         parse_constant=_parse_constant)
    except _NumberError as e:
        raise error(f"{where}: {e}") from None
    except json.JSONDecodeError as e:
        raise error(f"{where} is not valid JSON (line {e.lineno}: {e.msg})") from None
    except RecursionError:
        raise error(f"{where}: JSON nested more than {MAX_JSON_DEPTH} levels deep") from None
    if not _depth_ok(obj):
        raise error(f"{where}: JSON nested more than {MAX_JSON_DEPTH} levels deep")
    return obj


def is_json_numbers(value: object, null_ok: bool = False) -> bool:
    """True when ``value`` is a JSON number or a (nested) list of them (``null`` too with
    ``null_ok``). ``true``/``false`` and strings are not numbers: numpy would read ``true`` as
    1 and ``"1000"`` as 1000.0, so a mistyped file would load as another calibration without
    a word; check with this before ``np.asarray(value, dtype=float)``."""
    stack = [value]
    while stack:
        node = stack.pop()
        if isinstance(node, list):
            stack.extend(node)
        elif not (isinstance(node, (int, float)) and not isinstance(node, bool)) and not (null_ok and node is None):
            return False
    return True


def check_input_file(path: str | os.PathLike[str], what: str, error: type[AnkleScanError] = AnkleScanError,
                     limit: int = MAX_INPUT_FILE_BYTES) -> None:
    """An input read whole must be a regular file (not /dev/zero, a FIFO, a socket) of at
    most ``limit`` bytes; folders pass (their files are checked by whoever reads them)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except OSError as e:
        raise error(f"cannot read {what} {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        return
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{what} {path} is not a regular file (a device, pipe or socket)")
    if st.st_size > limit:
        raise error(f"{what} {path} is {st.st_size / 2**20:.0f} MB, larger than any input of ours "
                    f"({limit >> 20} MB at most)")


def load_json(path: str | os.PathLike[str], what: str, error: type[AnkleScanError] = AnkleScanError) -> Any:
    """Read and parse a user's JSON file (``what`` names it in messages, e.g. 'manifest')."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{what} {path} is a folder, not a file")
    check_input_file(path, what, error, MAX_JSON_BYTES)
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_JSON_BYTES + 1)
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise error(f"{what} {path} is a folder, not a file") from None
    except OSError as e:
        raise error(f"cannot read {what} {path}: {e.strerror or e}") from None
    if len(data) > MAX_JSON_BYTES:
        raise error(f"{what} {path} is larger than {MAX_JSON_BYTES >> 20} MB; not a file of ours")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{what} {path} is not UTF-8 text (byte {e.start})") from None
    return parse_json(text, f"{what} {path}", error)


# ------------------------------------------------------------------- option types
@dataclass(frozen=True)
class Bounded:
    """An argparse ``type=``: parses a number and refuses one outside [lo, hi] (``lo_open``:
    lo itself excluded), NaN and infinities, each with one line naming the range and unit."""

    lo: float
    hi: float
    integer: bool = False
    unit: str = ""
    lo_open: bool = False

    @property
    def __name__(self) -> str:  # argparse names the type in its messages
        return "integer" if self.integer else "number"

    def describe(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        lo = f"{self.lo:g}" if not self.integer else f"{int(self.lo)}"
        hi = f"{self.hi:g}" if not self.integer else f"{int(self.hi)}"
        if self.lo_open:
            return f"more than {lo} and at most {hi}{unit}"
        return f"{lo} to {hi}{unit}"

    def __call__(self, text: str) -> float | int:
        raw = str(text).strip()
        kind = "a whole number" if self.integer else "a number"
        if len(raw) > 40:
            raise argparse.ArgumentTypeError(f"expected {kind} ({self.describe()}), not {raw[:40]!r}...")
        try:
            value: float | int = int(raw) if self.integer else float(raw)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind} ({self.describe()}), not {raw!r}") from None
        ok = (self.lo < value if self.lo_open else self.lo <= value) and value <= self.hi
        if not ok:  # NaN fails every comparison
            raise argparse.ArgumentTypeError(f"{raw} is out of range: expected {self.describe()}")
        return value


def bounded_int(lo: int, hi: int, unit: str = "") -> Callable[[str], int]:
    """argparse ``type=`` for a whole number in [lo, hi]."""
    return Bounded(lo, hi, integer=True, unit=unit)  # type: ignore[return-value]


def bounded_float(lo: float, hi: float, unit: str = "", *, lo_open: bool = False) -> Callable[[str], float]:
    """argparse ``type=`` for a finite number in [lo, hi] (``lo_open``: lo excluded, e.g. a
    length that must be positive: ``bounded_float(0, MAX_OPTION_MM, "mm", lo_open=True)``)."""
    return Bounded(lo, hi, unit=unit, lo_open=lo_open)


@dataclass(frozen=True)
class SizeType:
    """argparse ``type=`` for WIDTHxHEIGHT (pixels, or a board's corners), each side 1..max_side."""

    max_side: int = MAX_IMAGE_SIDE
    example: str = "1024x768"

    @property
    def __name__(self) -> str:
        return "size"

    def __call__(self, text: str) -> tuple[int, int]:
        raw = str(text).strip()
        try:
            w_text, h_text = raw.lower().split("x")
            if len(w_text) > 6 or len(h_text) > 6:
                raise ValueError
            w, h = int(w_text), int(h_text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. {self.example}, not {raw[:40]!r}") from None
        if not (0 < w <= self.max_side and 0 < h <= self.max_side):
            raise argparse.ArgumentTypeError(f"{w}x{h} is out of range: each side 1 to {self.max_side}")
        return w, h


def size_type(max_side: int = MAX_IMAGE_SIDE, example: str = "1024x768") -> Callable[[str], tuple[int, int]]:
    """argparse ``type=`` for WIDTHxHEIGHT, each side 1..``max_side``."""
    return SizeType(max_side, example)


@dataclass(frozen=True)
class DateType:
    """argparse ``type=`` for a calendar date YYYY-MM-DD (ISO 8601), returned as that text."""

    @property
    def __name__(self) -> str:
        return "date"

    def __call__(self, text: str) -> str:
        import datetime as _dt

        raw = str(text).strip()
        try:
            return _dt.date.fromisoformat(raw[:10] if len(raw) == 10 else "x").isoformat()
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a date YYYY-MM-DD, not {raw[:40]!r}") from None


def date_type() -> Callable[[str], str]:
    """argparse ``type=`` for a calendar date (YYYY-MM-DD)."""
    return DateType()


# ---------------------------------------------------------------------------- images
def check_image_side(width: int, height: int, what: str, error: type[AnkleScanError] = AnkleScanError) -> None:
    """Refuse a size no real camera or projector has (before anything is allocated)."""
    import numpy as np

    for v in (width, height):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
            raise error(f"{what}: size {width}x{height} is not a positive whole number of pixels")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise error(f"{what}: size {width}x{height} is beyond any real camera or projector "
                    f"(at most {MAX_IMAGE_SIDE} px a side)")


def _png_size(head: bytes) -> tuple[int, int] | None:
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        return struct.unpack(">II", head[16:24])
    return None


def image_size(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """(width, height) from an image file's header without decoding the pixels, or None
    when the format's header cannot be read this way (the caller then decodes one frame)."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(32)
    size = _png_size(head)
    if size is not None:
        return int(size[0]), int(size[1])
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow ships with matplotlib
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DecompressionBombWarning: we apply our own limit
            with Image.open(path) as im:
                return int(im.size[0]), int(im.size[1])
    except Image.DecompressionBombError:
        return MAX_IMAGE_SIDE + 1, MAX_IMAGE_SIDE + 1
    except Exception:  # noqa: BLE001 - unknown to Pillow (EXR, HDR ...): decode instead
        return None


def capture_memory_limit() -> int:
    """Bytes a capture's frame stack may take on this machine."""
    try:
        phys = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        phys = 16 << 30
    return int(min(MAX_CAPTURE_BYTES, MAX_CAPTURE_MEMORY_FRACTION * phys))


# --------------------------------------------------------------------------- results
def require_finite(obj: object, what: str, error: type[AnkleScanError] = AnkleScanError) -> None:
    """Raise ``error`` when a number anywhere in ``obj`` (dict/list/tuple/array) is NaN or
    infinite: a nonsense input must never surface as ``nan`` in a result."""
    import numpy as np

    stack: list[tuple[object, str]] = [(obj, what)]
    while stack:
        node, where = stack.pop()
        if isinstance(node, Mapping):
            stack.extend((v, f"{where}.{k}") for k, v in node.items())
        elif isinstance(node, (list, tuple)):
            stack.extend((v, f"{where}[{i}]") for i, v in enumerate(node))
        elif isinstance(node, np.ndarray):
            if node.dtype.kind in "fc" and not np.isfinite(node).all():
                raise error(f"{where} is not finite (the input is out of range)")
        elif isinstance(node, (float, np.floating)) and not math.isfinite(node):
            raise error(f"{where} is not finite (the input is out of range)")
