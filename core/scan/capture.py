"""Capture folders (SPEC section 5): one camera image per manifest frame + manifest.json.

A capture folder holds the pattern set's ``manifest.json`` (optionally with a ``"capture"``
key for device, exposure, timestamps ...) and one image per frame under the SAME file name.
Images may be 8- or 16-bit, gray or colour (BGR/BGRA as OpenCV reads them), but all frames
of one capture must share size and bit depth.

``Capture.frames`` is the stack of gray frames, shape ``(n_frames, H, W)``, in manifest
order and in the images' own integer type (uint8 or uint16): decoding works on the native
integers, which is both faster and exact, and ``max_value`` (255 / 65535) tells it where
the sensor saturates.
"""

from __future__ import annotations

import hashlib
import itertools
import os
import shutil
import sys
import tempfile
from collections import deque
from collections.abc import Generator, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.atomic import atomic_paths, check_replaceable_dir, make_private_dir, mkdtemp_beside, write_json_atomic
from anklescan.core.errors import CaptureError
from anklescan.core.limits import capture_memory_limit, check_image_side, image_size, load_json
from anklescan.core.scan.patterns import FrameKind, PatternSet, imwrite_checked, is_pattern_output, replace_dir

MANIFEST = "manifest.json"
IMAGE_EXTS = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm",
              ".webp", ".jp2", ".exr", ".hdr"}
MAX_VALUE = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}
# A capture is refused as unlit when fewer than this fraction of its pixels are brighter in
# the white frame than in the black one by LIT_CONTRAST of the brightest recorded level (the
# projector was off, the lens capped), and as swapped when ten times more pixels are darker
# in the white frame than brighter (the frames are not what the manifest says).
LIT_MIN_FRACTION = 1e-3
LIT_CONTRAST = 0.02

# A camera image as read: uint8 or uint16 (MAX_VALUE), gray (H, W) or colour (H, W, 3/4).
Image = npt.NDArray[Any]
# What capture_from_images / save_capture take: images in manifest order, or by frame file name.
Images = Mapping[str, Image] | Iterable[Image]


@dataclass
class Capture:
    folder: Path | None
    pattern_set: PatternSet
    frames: Image  # (n_frames, H, W) uint8 or uint16, manifest order
    white_color: npt.NDArray[np.uint8] | None = None  # (H, W, 3) uint8 BGR, None for gray cameras
    metadata: dict[str, Any] = field(default_factory=dict)  # the manifest's "capture" object

    @property
    def max_value(self) -> int:
        return MAX_VALUE[self.frames.dtype]

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.frames.shape[1]), int(self.frames.shape[2]))

    def frame(self, name: str) -> Image:
        frame: Image = self.frames[self.pattern_set.files.index(name)]
        return frame


# ------------------------------------------------------------------------ images
@dataclass(frozen=True)
class _Reference:
    """The first frame of a capture, which every later frame must match in size and depth."""

    name: str
    image: Image


def _to_gray(img: Image, name: str) -> Image:
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 3:
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    if img.ndim == 3 and img.shape[2] == 4:
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY))
    raise CaptureError(f"{name}: unsupported image layout {img.shape}")


def _color_8bit(img: Image) -> npt.NDArray[np.uint8] | None:
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        return None
    bgr = img[:, :, :3]
    if bgr.dtype == np.uint16:
        bgr = (bgr >> 8).astype(np.uint8)
    return np.ascontiguousarray(bgr)


@contextmanager
def _decoder_messages() -> Generator[list[str], None, None]:
    """Collect what image libraries print on stderr (libpng, libjpeg, libtiff write there
    directly, not through OpenCV's log level) so that an error stays one line; yields a
    list that receives the text."""
    lines: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded): nothing to redirect
        yield lines
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(t for t in sink.read(4096).decode("utf-8", "replace").splitlines() if t.strip())


def _describe(img: Image) -> str:
    return f"{img.shape[1]}x{img.shape[0]}"


# ----------------------------------------------------------------------- loading
def load_capture(folder: str | os.PathLike[str]) -> Capture:
    """Load and check a capture folder; every defect raises a one-line CaptureError."""
    folder = Path(folder)
    if not folder.exists():
        raise CaptureError(f"capture folder not found: {folder}")
    if not folder.is_dir():
        raise CaptureError(f"capture path is not a folder: {folder}")
    manifest_path = folder / MANIFEST
    if not manifest_path.is_file():
        raise CaptureError(f"capture {folder} has no {MANIFEST}")
    manifest = load_json(manifest_path, "manifest", CaptureError)
    pset = PatternSet.from_manifest(manifest, str(manifest_path))
    metadata = manifest.get("capture", {})
    if not isinstance(metadata, dict):
        raise CaptureError(f"{manifest_path}: 'capture' must be an object")
    _check_files(folder, pset)

    paths = [folder / f for f in pset.files]
    _check_sizes(paths)
    stack, color = _load_frames(paths, pset.index(FrameKind.WHITE))
    capture = Capture(folder, pset, stack, color, metadata)
    check_lit(capture)
    return capture


def check_distinct_captures(folders: Sequence[str | os.PathLike[str]]) -> None:
    """Refuse a capture given twice to one calibration (one capture per box position or board
    view): the same folder by any spelling (a trailing '/', a symbolic link) or a copy of it
    (the same white frame, byte for byte, which two photographs never are). Its points would
    count twice, and the calibration would claim twice the evidence it has (its SDs too small).
    A folder that cannot be read is left for ``load_capture`` to report."""
    seen: dict[tuple[str, object], Path] = {}
    for f in folders:
        folder = Path(f)
        try:
            pset = PatternSet.from_manifest(load_json(folder / MANIFEST, "manifest", CaptureError),
                                            str(folder / MANIFEST))
            white = (folder / pset.files[pset.index(FrameKind.WHITE)]).read_bytes()
            keys = [("folder", folder.resolve()), ("white", hashlib.sha256(white).digest())]
        except (OSError, CaptureError):
            continue
        for key in keys:
            if key in seen:
                same = "is given twice" if key[0] == "folder" else f"is a copy of {seen[key]} (the same frames)"
                raise CaptureError(f"capture {folder} {same}: give each position or view its own capture")
        seen.update((key, folder) for key in keys)


def _check_sizes(paths: list[Path]) -> None:
    """Refuse oversized or mismatched frames from their headers, before decoding any."""
    sizes: dict[str, tuple[int, int]] = {}
    for p in paths:
        try:
            size = image_size(p)
        except OSError as e:
            raise CaptureError(f"cannot read frame {p}: {e.strerror or e}") from None
        if size is not None:
            check_image_side(*size, f"frame {p.name}", CaptureError)
            sizes[p.name] = size
    if not sizes:
        return  # formats without a readable header: each frame is checked as it is decoded
    (n0, (w, h)), *rest = sizes.items()
    for n1, (w1, h1) in rest:
        if (w1, h1) != (w, h):
            raise CaptureError(f"frame {n1} is {w1}x{h1} but {n0} is {w}x{h}")
    need = len(paths) * w * h * 2  # worst case: 16-bit samples
    limit = capture_memory_limit()
    if need > limit:
        raise CaptureError(f"capture of {len(paths)} frames of {w}x{h} needs {need / 2**30:.1f} GB, "
                           f"more than this computer can decode (limit {limit / 2**30:.1f} GB)")


def _load_frames(paths: list[Path], white_idx: int) -> tuple[Image, npt.NDArray[np.uint8] | None]:
    """(stack, colour) from the frame files. Image libraries print on stderr themselves
    (libpng, libjpeg, libtiff, not through OpenCV's log level): that text is held back while
    decoding, and the last line joins our one-line error when a frame cannot be read."""
    with _decoder_messages() as messages:
        frames = _read_ahead(paths)
        try:
            return _stack(frames, paths, white_idx)
        except _UnreadableFrame as e:
            failure = e
        finally:
            frames.close()  # stop the readers before stderr is restored
    why = f" ({messages[-1].strip()})" if messages else ""
    raise CaptureError(f"{failure}{why}") from None


class _UnreadableFrame(CaptureError):
    pass


def _read_ahead(paths: list[Path], lookahead: int = 4) -> Generator[Image, None, None]:
    """Decoded frames in order, at most ``lookahead`` ahead of the consumer (so memory is
    the stack plus a few frames); PNG/TIFF decoding releases the GIL, so two threads
    roughly halve load time."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        todo = iter(paths)
        pending = deque(pool.submit(_read, p) for p in itertools.islice(todo, lookahead))
        try:
            while pending:
                img = pending.popleft().result()
                nxt = next(todo, None)
                if nxt is not None:
                    pending.append(pool.submit(_read, nxt))
                yield img
        finally:
            for f in pending:
                f.cancel()


def read_image(path: str | os.PathLike[str]) -> Image | None:
    """``cv2.imread(path, IMREAD_UNCHANGED)`` for any path: OpenCV's own path handling crashes
    (segfault) on names that are not valid UTF-8 (a folder copied from a Latin-1 system),
    so we read the bytes and let OpenCV decode them."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise CaptureError(f"cannot read image {path}: {e.strerror or e}") from None
    if not data.size:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return None if img is None else np.asarray(img)


def _read(path: Path) -> Image:
    img = read_image(path)
    if img is None or img.size == 0:
        raise _UnreadableFrame(f"unreadable image {path}: damaged or not an image")
    check_image_side(img.shape[1], img.shape[0], f"frame {path.name}", CaptureError)
    if img.dtype not in MAX_VALUE:
        raise CaptureError(f"{path}: unsupported pixel type {img.dtype} (need 8- or 16-bit)")
    return img


def check_lit(capture: Capture) -> None:
    """Refuse a capture whose white frame is not brighter than its black one: nothing can
    be decoded from it, and an empty result would look like a successful scan."""
    white = capture.frame(capture.pattern_set.files[capture.pattern_set.index(FrameKind.WHITE)])
    black = capture.frame(capture.pattern_set.files[capture.pattern_set.index(FrameKind.BLACK)])
    # contrast relative to the brightest pixels actually recorded, not to the integer type's
    # range: a 12-bit camera stored in 16-bit PNGs never goes past 4095
    brightest = np.maximum(white, black).ravel()
    peak = float(np.partition(brightest, int(0.999 * (brightest.size - 1)))[int(0.999 * (brightest.size - 1))])
    thr = max(1.0, LIT_CONTRAST * peak)
    diff = white.astype(np.int32) - black.astype(np.int32)
    lit, dark = int(np.count_nonzero(diff > thr)), int(np.count_nonzero(diff < -thr))
    if dark > 10 * lit and dark >= LIT_MIN_FRACTION * diff.size:
        raise CaptureError(f"capture {capture.folder or '(in memory)'}: the black frame is brighter than the white one "
                           "(frames swapped or mislabelled in the manifest)")
    if lit < LIT_MIN_FRACTION * diff.size:
        raise CaptureError(f"capture {capture.folder or '(in memory)'}: the white frame is no brighter than the black one "
                           "anywhere: was the projector on, the lens uncovered, the exposure right?")


def _check_files(folder: Path, pset: PatternSet) -> None:
    wanted = set(pset.files)
    present = {p.name for p in folder.iterdir() if p.is_file()}
    missing = [f for f in pset.files if f not in present]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise CaptureError(f"capture {folder}: frame file {missing[0]} is missing{more}")
    # dot files are our own temporaries (CaptureWriter); other non-images are notes etc.
    extra = sorted(n for n in present - wanted
                   if not n.startswith(".") and Path(n).suffix.lower() in IMAGE_EXTS)
    if extra:
        raise CaptureError(f"capture {folder}: image {extra[0]} is not a frame of the manifest")


def _stack(images: Iterable[Image], paths: Sequence[Path],
           white_idx: int) -> tuple[Image, npt.NDArray[np.uint8] | None]:
    stack: Image | None = None
    color: npt.NDArray[np.uint8] | None = None
    first: _Reference | None = None
    for i, (img, path) in enumerate(zip(images, paths, strict=False)):
        if stack is None or first is None:
            first = _Reference(path.name, img)
            stack = np.empty((len(paths),) + img.shape[:2], img.dtype)
        else:
            _check_same(first, path.name, img)
        stack[i] = _to_gray(img, path.name)
        if i == white_idx:
            color = _color_8bit(img)
    if stack is None:
        raise CaptureError("a capture needs at least one frame")
    return stack, color


def _check_same(first: _Reference, name: str, img: Image) -> None:
    fname, fimg = first.name, first.image
    if img.shape[:2] != fimg.shape[:2]:
        raise CaptureError(f"frame {name} is {_describe(img)} but {fname} is {_describe(fimg)}")
    if img.dtype != fimg.dtype:
        raise CaptureError(f"frame {name} is {img.dtype.itemsize * 8}-bit but {fname} is "
                           f"{fimg.dtype.itemsize * 8}-bit (mixed bit depth)")


def capture_from_images(pattern_set: PatternSet, images: Images,
                        metadata: Mapping[str, Any] | None = None) -> Capture:
    """An in-memory capture (e.g. from a simulator), checked like a loaded one."""
    image_list = _as_list(pattern_set, images)
    names = [Path(n) for n in pattern_set.files]
    for img, name in zip(image_list, names, strict=False):
        if not isinstance(img, np.ndarray) or img.dtype not in MAX_VALUE:
            raise CaptureError(f"frame {name}: need an 8- or 16-bit numpy image")
    stack, color = _stack(image_list, names, pattern_set.index(FrameKind.WHITE))
    return Capture(None, pattern_set, stack, color, dict(metadata or {}))


def _as_list(pattern_set: PatternSet, images: Images) -> list[Image]:
    if isinstance(images, Mapping):
        missing = [f for f in pattern_set.files if f not in images]
        if missing:
            raise CaptureError(f"no image for frame {missing[0]}")
        extra = sorted(set(images) - set(pattern_set.files))
        if extra:
            raise CaptureError(f"image {extra[0]} is not a frame of the pattern set")
        return [images[f] for f in pattern_set.files]
    image_list = list(images)
    if len(image_list) != len(pattern_set.frames):
        raise CaptureError(f"got {len(image_list)} images for {len(pattern_set.frames)} frames")
    return image_list


# ----------------------------------------------------------------------- writing
def _manifest_with(pattern_set: PatternSet, metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    m = pattern_set.to_manifest()
    if metadata:
        m["capture"] = _json_safe(metadata)
    return m


def _json_safe(obj: object) -> object:
    """Metadata as strict JSON: a device reporting NaN/inf (an unknown gain, say) becomes
    null, numpy scalars plain numbers; otherwise the manifest could not be read back."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def save_capture(folder: str | os.PathLike[str], pattern_set: PatternSet, images: Images,
                 metadata: Mapping[str, Any] | None = None) -> Path:
    """Write a whole capture atomically: a temporary sibling folder renamed into place."""
    folder = Path(folder)
    image_list = _as_list(pattern_set, images)
    capture_from_images(pattern_set, image_list)  # size/depth checks before touching disk
    if not folder.parent.is_dir():
        raise CaptureError(f"output folder's parent {folder.parent} does not exist")
    check_replaceable_dir(folder, lambda f: is_pattern_output(f, allow_capture=True))
    tmp = Path(mkdtemp_beside(folder))  # 0700
    try:
        for name, img in zip(pattern_set.files, image_list, strict=False):
            imwrite_checked(tmp / name, img)
        write_json_atomic(tmp / MANIFEST, _manifest_with(pattern_set, metadata))
        replace_dir(tmp, folder, lambda f: is_pattern_output(f, allow_capture=True))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class CaptureWriter:
    """Writes frames as they arrive, so a crash loses nothing already captured.

    Each frame goes to a hidden temporary file that is renamed into place; the manifest
    is written last by ``finish()``, so a folder without a manifest is an unfinished
    capture (its frames are complete and can be recovered)."""

    def __init__(self, folder: str | os.PathLike[str], pattern_set: PatternSet,
                 metadata: Mapping[str, Any] | None = None) -> None:
        self.folder = Path(folder)
        self.pattern_set = pattern_set
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._written: dict[str, str] = {}
        self._ref: _Reference | None = None
        if self.folder.exists() and not self.folder.is_dir():
            raise CaptureError(f"capture path {self.folder} exists and is not a folder")
        if self.folder.is_dir() and (self.folder / MANIFEST).exists():
            raise CaptureError(f"capture folder {self.folder} already holds a finished capture")
        if not self.folder.parent.is_dir():
            raise CaptureError(f"capture folder's parent {self.folder.parent} does not exist")
        make_private_dir(self.folder)  # patient data: 0700 whatever the umask
        self.metadata.setdefault("started", _now())

    def add(self, frame_name: str, image: Image) -> Path:
        if frame_name not in self.pattern_set.files:
            raise CaptureError(f"{frame_name} is not a frame of the pattern set")
        if not isinstance(image, np.ndarray) or image.dtype not in MAX_VALUE:
            raise CaptureError(f"frame {frame_name}: need an 8- or 16-bit numpy image")
        if self._ref is None:
            self._ref = _Reference(frame_name, image)
        else:
            _check_same(self._ref, frame_name, image)
        dest = self.folder / frame_name
        # the temporary keeps the real extension so imwrite picks the same encoder; frames are
        # not fsynced one by one (finish() writes the manifest, durably, last)
        with atomic_paths(dest, keep_suffix=True, fsync=False) as (tmp,):
            assert tmp is not None  # atomic_paths yields None only for a None target
            imwrite_checked(tmp, image)
        self._written[frame_name] = _now()
        return dest

    @property
    def missing(self) -> list[str]:
        return [f for f in self.pattern_set.files if f not in self._written]

    def finish(self) -> Path:
        if self.missing:
            raise CaptureError(f"capture {self.folder} incomplete: frame {self.missing[0]} "
                               f"was never added ({len(self.missing)} missing)")
        self.metadata["finished"] = _now()
        self.metadata["frame_times"] = dict(self._written)
        write_json_atomic(self.folder / MANIFEST,
                          _manifest_with(self.pattern_set, self.metadata))
        return self.folder

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        if exc_type is None:
            self.finish()
        return False
