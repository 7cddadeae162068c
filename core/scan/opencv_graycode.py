"""Bring a capture made with OpenCV's ``structured_light.GrayCodePattern`` in as a capture (SPEC §5).

OpenCV's order is: for each column bit, most significant first, the pattern then its inverse;
then the row bits the same way; then white, then black.  The non-inverse frame is bright where
the Gray bit is 1 (OpenCV decodes ``bit = frame > inverse``), which is our own convention, so
the frames are copied byte for byte and only a manifest is written.

procam-calibration (kamino410) draws those patterns at ``1 / step`` of the projector's size and
blows each code pixel up to ``step x step`` projector pixels: projector pixel (x, y) shows code
(x // step, y // step).  That is exactly our Gray ``stripe`` of ``step`` pixels, whose decoded
coordinate is the stripe centre ``code * step + (step - 1) / 2``.  Plain OpenCV is ``step`` 1.

The number of bits per axis is OpenCV's ``ceil(log2(codes))`` with ``codes = ceil(size / step)``;
the frame count of the source folder must match it exactly, which catches a wrong
``--projector`` or ``--step`` before anything is written.
"""

from __future__ import annotations

import math
import os
import re
import shutil
from pathlib import Path

from anklescan.core.atomic import copy_private, mkdtemp_beside, write_json_atomic
from anklescan.core.errors import CaptureError
from anklescan.core.scan.capture import IMAGE_EXTS, MANIFEST, load_capture
from anklescan.core.scan.patterns import Frame, FrameKind, PatternSet, replace_dir
from anklescan.core.vocabulary import Axis

PRESET = "opencv-graycode"


def opencv_bits(size: int, step: int) -> int:
    """OpenCV's bit count for one axis of ``size`` projector pixels at ``step`` pixels per code."""
    codes = -(-size // step)
    return max(1, math.ceil(math.log2(codes)))


def opencv_pattern_set(width: int, height: int, step: int, files: list[str]) -> PatternSet:
    """The manifest of an OpenCV Gray-code sequence whose frames are ``files`` in OpenCV order."""
    if not (isinstance(step, int) and step >= 1):
        raise CaptureError(f"--step must be a positive integer, not {step!r}")
    if width < 2 or height < 2:
        raise CaptureError(f"projector size must be at least 2x2, got {width}x{height}")
    cb, rb = opencv_bits(width, step), opencv_bits(height, step)
    need = 2 * (cb + rb) + 2
    if len(files) != need:
        raise CaptureError(
            f"{len(files)} images, but OpenCV's Gray code for a {width}x{height} projector at step {step} "
            f"has {need} frames ({cb} column bits, {rb} row bits, each with its inverse, then white, black): "
            f"check --projector and --step")
    frames: list[Frame] = []
    it = iter(files)
    for axis, bits in ((Axis.COLUMN, cb), (Axis.ROW, rb)):
        for b in range(bits):
            for inv in (False, True):
                frames.append(Frame(next(it), FrameKind.GRAY, axis, b, bits, step, inv))
    frames += [Frame(next(it), FrameKind.WHITE), Frame(next(it), FrameKind.BLACK)]
    pset = PatternSet(PRESET, width, height, frames, (Axis.COLUMN, Axis.ROW))
    pset.validate("opencv-graycode import")
    return pset


def _natural_key(name: str) -> list[int | str]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def source_frames(src: Path) -> list[str]:
    """The image files of ``src`` in frame order (natural sort: graycode_2 before graycode_10)."""
    if not src.exists():
        raise CaptureError(f"source folder not found: {src}")
    if not src.is_dir():
        raise CaptureError(f"source is not a folder: {src}")
    names = [p.name for p in src.iterdir()
             if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTS]
    if not names:
        raise CaptureError(f"source folder {src} holds no images")
    return sorted(names, key=_natural_key)


def import_opencv_graycode(src: str | os.PathLike[str], out: str | os.PathLike[str], width: int, height: int,
                           step: int = 1) -> PatternSet:
    """Copy ``src`` (never modified) into a new capture folder ``out`` with its manifest, atomically."""
    src, out = Path(src), Path(out)
    files = source_frames(src)
    pset = opencv_pattern_set(width, height, step, files)
    try:
        same = out.resolve() == src.resolve() or src.resolve() in out.resolve().parents
    except OSError:
        same = False
    if same:
        raise CaptureError(f"output {out} is the source folder or inside it; choose another --out")
    if out.is_symlink():  # found before copying anything, and said as every folder output says it
        raise CaptureError(f"output {out} is a symbolic link; give the real folder or a new one")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CaptureError(f"output {out} already exists and is not an empty folder; choose another --out")
    if not out.parent.is_dir():
        raise CaptureError(f"output folder's parent {out.parent} does not exist")
    tmp = mkdtemp_beside(out)  # 0700, marked: a killed run's is removed by the next
    try:
        for name in files:
            copy_private(src / name, tmp / name)  # frames are patient data: 0600 whatever the umask
        manifest = pset.to_manifest()
        manifest["capture"] = {"imported_from": str(src), "tool": "OpenCV structured_light.GrayCodePattern",
                               "graycode_step": step}
        write_json_atomic(tmp / MANIFEST, manifest)
        try:
            load_capture(tmp)  # every frame readable, one size, one bit depth: or nothing is written
        except CaptureError as e:
            # the frames are byte copies: name the user's file, not our hidden temporary's
            raise CaptureError(str(e).replace(str(tmp), str(src))) from None
        if out.exists():
            out.rmdir()  # the empty folder the user made for it
        replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return pset
