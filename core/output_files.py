"""What each command's single output file is, and whether a file already at ``--out`` is one.

A command replaces an existing ``--out`` only when it is a file of the kind that command
writes (an earlier run's result, calibration, cloud ...) or empty: a mistyped name never
destroys a user's other file (``measure --out notes.txt``). Each kind is recognised from its
first bytes or its top-level JSON keys, read with a size cap, never from its name.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import Any

# bytes read to recognise a file: a PLY header, a C3D header block; a JSON output larger than
# this is not one of ours (a RESULT.json is ~10 kB, a calibration with its covariance ~200 kB)
_HEAD_BYTES = 4096
_MAX_JSON_BYTES = 16 << 20


class OutputFile(StrEnum):
    """The single-file outputs of the command line (SPEC §4, §6, §7)."""

    POINT_CLOUD = "point cloud (PLY)"
    CALIBRATION = "calibration (JSON)"
    OPENCV_CALIBRATION = "OpenCV calibration (FileStorage)"
    MEASUREMENT = "measurement result (JSON)"
    DAILY_CHECK = "daily check result (JSON)"
    C3D = "C3D file"
    FHIR_BUNDLE = "FHIR bundle (JSON)"


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(_HEAD_BYTES)


def _json_keys(path: Path) -> dict[str, Any] | None:
    """The top-level object of a JSON file (None: not one, or too large to be ours)."""
    if path.stat().st_size > _MAX_JSON_BYTES:
        return None
    try:
        data = json.loads(path.read_bytes())
    except (ValueError, RecursionError):
        return None
    return data if isinstance(data, dict) else None


def _has_keys(*keys: str) -> Callable[[Path], bool]:
    def test(path: Path) -> bool:
        data = _json_keys(path)
        return data is not None and all(k in data for k in keys)
    return test


def _is_point_cloud(path: Path) -> bool:
    head = _head(path)
    return head.startswith(b"ply") and b"comment AnkleScan point cloud" in head.split(b"end_header", 1)[0]


def _is_c3d(path: Path) -> bool:
    head = _head(path)
    return len(head) >= 512 and head[1] == 0x50  # the C3D header's key byte (the file's signature)


def _is_fhir_bundle(path: Path) -> bool:
    data = _json_keys(path)
    return data is not None and data.get("resourceType") == "Bundle"


def _is_opencv_calibration(path: Path) -> bool:
    """A FileStorage holding a projector-camera calibration (our export's or procam-calibration's
    names); cv2 is imported here only, where this kind is asked about."""
    import cv2

    try:
        fs = cv2.FileStorage(os.fspath(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # a file it cannot parse raises, in one form or the other
        return False
    try:
        return bool(fs.isOpened()) and any(not fs.getNode(k).empty() for k in ("K1", "cam_int"))
    finally:
        fs.release()


_TESTS: dict[OutputFile, Callable[[Path], bool]] = {
    OutputFile.POINT_CLOUD: _is_point_cloud,
    OutputFile.CALIBRATION: _has_keys("camera", "projector"),
    OutputFile.OPENCV_CALIBRATION: _is_opencv_calibration,
    OutputFile.MEASUREMENT: _has_keys("marks", "angles"),
    OutputFile.DAILY_CHECK: _has_keys("measured", "expected", "passed"),
    OutputFile.C3D: _is_c3d,
    OutputFile.FHIR_BUNDLE: _is_fhir_bundle,
}


def may_replace(path: str | os.PathLike[str], kind: OutputFile) -> bool:
    """True where ``path`` is missing, empty, or a file of ``kind``; False for any other file
    (and for one that cannot be read: it is left alone)."""
    p = Path(path)
    try:
        if not p.is_file():
            return not os.path.lexists(p)
        return p.stat().st_size == 0 or _TESTS[kind](p)
    except OSError:
        return False
