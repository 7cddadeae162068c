"""Point clouds and binary PLY (what MeshLab, CloudCompare and Open3D read).

Vertex properties: ``float x y z`` (world mm), ``uchar red green blue`` (from the white frame),
``ushort cam_u cam_v`` (the camera pixel each point came from), ``float quality`` (decoding
contrast, 0..1), ``float sigma`` (predicted noise along the camera ray, mm) — the extra properties
are scalar fields in CloudCompare and ignored by viewers that do not know them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
import numpy.typing as npt

from anklescan.core.atomic import atomic_file
from anklescan.core.errors import AnkleScanError

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}

_A = TypeVar("_A", bound=np.generic)


@dataclass(frozen=True)
class _PlyElement:
    """One ``element`` of a PLY header: its name, its count and its (name, numpy type) properties
    (a list property's type is ``"list:<count type>:<item type>"``)."""

    name: str
    count: int
    props: list[tuple[str, str]]


@dataclass(eq=False)
class PointCloud:
    points: npt.NDArray[np.float32]  # (N, 3) float32, world mm
    colors: npt.NDArray[np.uint8] | None = None  # (N, 3) uint8 RGB
    pixels: npt.NDArray[np.uint16] | None = None  # (N, 2) uint16 camera (u, v)
    quality: npt.NDArray[np.float32] | None = None  # (N,) float32
    sigma: npt.NDArray[np.float32] | None = None  # (N,) float32 predicted noise along the camera ray, mm
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, keep: npt.NDArray[np.bool_] | npt.NDArray[np.integer[Any]]) -> PointCloud:
        def pick(a: npt.NDArray[_A] | None) -> npt.NDArray[_A] | None:
            return None if a is None else a[keep]

        return PointCloud(self.points[keep], pick(self.colors), pick(self.pixels), pick(self.quality),
                          pick(self.sigma), dict(self.meta))

    def bounds(self) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        if len(self) == 0:
            raise AnkleScanError("the point cloud is empty")
        return self.points.min(axis=0), self.points.max(axis=0)


def _vertex_dtype(cloud: PointCloud) -> np.dtype[np.void]:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cloud.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if cloud.pixels is not None:
        fields += [("cam_u", "<u2"), ("cam_v", "<u2")]
    if cloud.quality is not None:
        fields += [("quality", "<f4")]
    if cloud.sigma is not None:
        fields += [("sigma", "<f4")]
    return np.dtype(fields)


def write_ply(path: str | os.PathLike[str], cloud: PointCloud, comments: list[str] | None = None) -> None:
    """Binary little-endian PLY, written to a temporary sibling and renamed into place.

    Refuses non-finite coordinates (a broken calibration, never a surface). ``comments``
    may hold any text (a patient's folder name in any script): it is escaped to ASCII."""
    path = Path(path)
    if not np.isfinite(cloud.points).all():
        raise AnkleScanError("the point cloud holds non-finite coordinates; nothing was written")
    dtype = _vertex_dtype(cloud)
    data = np.empty(len(cloud), dtype=dtype)
    data["x"], data["y"], data["z"] = cloud.points[:, 0], cloud.points[:, 1], cloud.points[:, 2]
    if cloud.colors is not None:
        data["red"], data["green"], data["blue"] = cloud.colors[:, 0], cloud.colors[:, 1], cloud.colors[:, 2]
    if cloud.pixels is not None:
        data["cam_u"], data["cam_v"] = cloud.pixels[:, 0], cloud.pixels[:, 1]
    if cloud.quality is not None:
        data["quality"] = cloud.quality
    if cloud.sigma is not None:
        data["sigma"] = cloud.sigma
    inverse = {"<f4": "float", "u1": "uchar", "<u2": "ushort", "|u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment AnkleScan point cloud, world frame, units mm"]
    header += [f"comment {_header_text(c)}" for c in (comments or [])]
    header.append(f"element vertex {len(cloud)}")
    for name in dtype.names or ():
        header.append(f"property {inverse[dtype[name].str]} {name}")
    header.append("end_header")
    with atomic_file(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        data.tofile(f)


def _header_text(text: str) -> str:
    """One ASCII header line: the PLY header is ASCII and line-based, so non-ASCII text is
    written as Python-style escapes (\\xfc, \\u3042) and line breaks cannot end the comment."""
    return str(text).encode("unicode_escape").decode("ascii")


def _parse_header(f: IO[bytes], path: Path) -> tuple[str, list[_PlyElement]]:
    if f.readline().strip() != b"ply":
        raise AnkleScanError(f"{path} is not a PLY file")
    fmt: str | None = None
    elements: list[_PlyElement] = []
    for _ in range(100_000):
        line = f.readline(4096)
        if not line:
            raise AnkleScanError(f"{path}: PLY header has no end_header")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit() or len(words[2]) > 12:
                raise AnkleScanError(f"{path}: bad PLY element line {line[:80]!r}")
            elements.append(_PlyElement(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise AnkleScanError(f"{path}: PLY property before any element")
            if len(words) < 3 or (words[1] == "list" and len(words) != 5):
                raise AnkleScanError(f"{path}: bad PLY property line {line[:80]!r}")
            if words[1] == "list":
                elements[-1].props.append((words[4], "list:" + words[2] + ":" + words[3]))
            elif words[1] in _PLY_TYPES:
                elements[-1].props.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise AnkleScanError(f"{path}: unknown PLY property type {words[1]!r}")
    else:
        raise AnkleScanError(f"{path}: PLY header has no end_header in its first 100000 lines")
    if fmt is None or fmt not in ("binary_little_endian", "ascii"):
        raise AnkleScanError(f"{path}: PLY format {fmt!r} is not supported (binary_little_endian or ascii)")
    return fmt, elements


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read the vertex element of a binary little-endian or ASCII PLY (faces are skipped)."""
    path = Path(path)
    try:
        f = open(path, "rb")  # noqa: SIM115 (closed by the `with f:` below; opened apart so its error reads plainly)
    except OSError as exc:
        raise AnkleScanError(f"cannot open {path}: {exc.strerror}") from None
    try:
        with f:
            return _read_vertices(f, path)
    except (ValueError, TypeError, IndexError) as exc:  # malformed body/types: one line, exit 2
        raise AnkleScanError(f"{path}: malformed PLY ({' '.join(str(exc).split())[:200]})") from None


def _read_vertices(f: IO[bytes], path: Path) -> PointCloud:
    fmt, elements = _parse_header(f, path)
    if not elements or elements[0].name != "vertex":
        raise AnkleScanError(f"{path}: PLY has no vertex element first")
    count, props = elements[0].count, elements[0].props
    if any(t.startswith("list:") for _, t in props):
        raise AnkleScanError(f"{path}: list properties on vertices are not supported")
    left = os.fstat(f.fileno()).st_size - f.tell()
    if fmt == "ascii" and count * 2 * max(len(props), 1) > left:  # >= "0 " per value
        raise AnkleScanError(f"{path}: PLY is truncated (the header claims {count} vertices)")
    if fmt == "ascii":
        rows = np.loadtxt(f, max_rows=count, ndmin=2)
        data = np.empty(count, dtype=[(n, t) for n, t in props])
        for i, (n, _) in enumerate(props):
            data[n] = rows[:, i]
    else:
        dtype = np.dtype([(n, "<" + t if t[0] in "fiu" and t[1] != "1" else t) for n, t in props])
        if count * dtype.itemsize > left:  # before allocating: a header can claim anything
            raise AnkleScanError(f"{path}: PLY is truncated ({left // max(dtype.itemsize, 1)} of {count} vertices)")
        data = np.fromfile(f, dtype=dtype, count=count)
        if data.shape[0] != count:
            raise AnkleScanError(f"{path}: PLY is truncated ({data.shape[0]} of {count} vertices)")
    names = data.dtype.names or ()
    for n in ("x", "y", "z"):
        if n not in names:
            raise AnkleScanError(f"{path}: PLY vertices have no '{n}'")
    points = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float32)
    colors = np.stack([data["red"], data["green"], data["blue"]], axis=1).astype(np.uint8) \
        if {"red", "green", "blue"} <= set(names) else None
    pixels = np.stack([data["cam_u"], data["cam_v"]], axis=1).astype(np.uint16) \
        if {"cam_u", "cam_v"} <= set(names) else None
    quality = data["quality"].astype(np.float32) if "quality" in names else None
    sigma = data["sigma"].astype(np.float32) if "sigma" in names else None
    return PointCloud(points, colors, pixels, quality, sigma)
