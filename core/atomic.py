"""Writing files safely: atomically, privately, and never over the command's own inputs.

- ``atomic_paths`` (the one mechanism; several targets at once, any writer) and
  ``atomic_file`` / ``write_text_atomic`` / ``write_json_atomic`` on it: the content goes to a
  temporary sibling (same folder, so the rename cannot cross file systems), is flushed to
  disk, and is renamed over the target; on any error the temporary is removed and the target
  is untouched. Temporary names are shortened so that they never exceed NAME_MAX even when
  the target's own name is close to it (``temp_affixes``).
- Privacy: everything written here is patient data, so files are 0600 and folders we create
  0700 whatever the umask (``PRIVATE_FILE_MODE``, ``make_private_dir``, ``make_private``).
- ``guard_output``: refuse an output path that is, or resolves to, one of the command's
  inputs (same path, symlink, hard link, relative spelling, inside an input folder, or a
  folder holding an input). Every command that writes calls it before computing anything.
- ``check_replaceable_dir``: an existing output folder may only be replaced when it is
  empty or holds nothing but an earlier output of ours; foreign files are never deleted.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path

from anklescan.core.errors import AnkleScanError

PRIVATE_FILE_MODE = 0o600
PRIVATE_DIR_MODE = 0o700
NAME_MAX = 255  # bytes in one path component on ext4, xfs, btrfs, APFS, NTFS (UTF-16 units)
_RANDOM_CHARS = 8  # what tempfile adds between prefix and suffix


# ------------------------------------------------------------------------ temp names
def temp_affixes(name: str, tag: str = "tmp", keep_suffix: str = "") -> tuple[str, str]:
    """``(prefix, suffix)`` for ``tempfile.mkstemp/mkdtemp`` next to a file called ``name``.

    The result is hidden (leading dot), says what it is a temporary of, and — with the 8
    random characters tempfile inserts — stays within NAME_MAX bytes however long ``name``
    is. ``keep_suffix`` (e.g. '.png') ends the name so encoders chosen by extension work.
    """
    suffix = f".{tag}{keep_suffix}"
    budget = NAME_MAX - 2 - _RANDOM_CHARS - len(suffix.encode()) - 8  # 8: margin
    stem = name.encode("utf-8", "surrogateescape")[:max(budget, 1)].decode("utf-8", "ignore")
    return f".{stem}.", suffix


def mkdtemp_beside(target: str | os.PathLike, tag: str = "tmp") -> Path:
    """A new private (0700) hidden folder next to ``target``, named within NAME_MAX."""
    target = Path(target)
    prefix, suffix = temp_affixes(target.name, tag)
    return Path(tempfile.mkdtemp(suffix=suffix, prefix=prefix, dir=target.parent))


# --------------------------------------------------------------------------- privacy
def make_private(path: str | os.PathLike) -> None:
    """chmod a file 0600 or a folder 0700 (a no-op if it already is)."""
    p = Path(path)
    mode = PRIVATE_DIR_MODE if p.is_dir() else PRIVATE_FILE_MODE
    if stat.S_IMODE(p.stat().st_mode) != mode:
        os.chmod(p, mode)


def make_private_dir(path: str | os.PathLike, *, tighten: bool = True) -> Path:
    """Create ``path`` (and missing parents) as 0700 whatever the umask; with ``tighten``
    an existing ``path`` itself is made 0700 too (existing parents are left alone)."""
    path = Path(path)
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    for d in reversed(missing):
        try:
            d.mkdir(mode=PRIVATE_DIR_MODE)
        except FileExistsError:
            pass  # created meanwhile by another process
        os.chmod(d, PRIVATE_DIR_MODE)
    if not path.is_dir():
        raise AnkleScanError(f"{path} exists and is not a folder")
    if tighten and not missing:
        make_private(path)
    return path


def make_tree_private(folder: str | os.PathLike) -> int:
    """Make every folder (0700) and file (0600) under ``folder`` private, e.g. patient data
    written by an older version under a 022 umask; symlinks and entries we may not change
    are skipped. Returns the number of entries changed."""
    changed = 0
    for root, dirs, files in os.walk(folder):
        for name, mode in [(root, PRIVATE_DIR_MODE)] + [(os.path.join(root, f), PRIVATE_FILE_MODE) for f in files]:
            try:
                st = os.lstat(name)
                if not stat.S_ISLNK(st.st_mode) and stat.S_IMODE(st.st_mode) != mode:
                    os.chmod(name, mode)
                    changed += 1
            except OSError:
                pass
    return changed


# --------------------------------------------------------------------------- writing
class WriteError(OSError, AnkleScanError):
    """An output could not be written (full disk, no permission, a folder in the way): one
    line naming the target, never our temporary. Still an OSError for callers that
    catch those."""


@contextmanager
def atomic_paths(*targets: str | os.PathLike | None, what: str | None = None, keep_suffix: bool = False,
                 fsync: bool = True):
    """The one atomic-write mechanism: yields a private (0600) temporary sibling per target
    (``None`` for a ``None`` target), to be written by any means (an encoder, a PDF backend);
    when the block ends without error each is flushed to disk (``fsync``) and renamed over its
    target, else every temporary is removed and no target is touched. The targets' folders
    must exist. An OSError becomes a WriteError "cannot write WHAT: ..." (``what`` defaults to
    the first target); ``keep_suffix`` ends the temporary with the target's extension, for
    writers that choose the format by it."""
    paths = [None if t is None else Path(t) for t in targets]
    what = what or str(next((p for p in paths if p is not None), ""))
    tmps: list[Path | None] = []
    try:
        for t in paths:
            if t is None:
                tmps.append(None)
                continue
            if not t.parent.is_dir():
                raise AnkleScanError(f"output folder {t.parent} does not exist")
            prefix, suffix = temp_affixes(t.name, keep_suffix=t.suffix if keep_suffix else "")
            fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=t.parent)  # 0600
            os.close(fd)
            tmps.append(Path(name))
        yield tmps
        for tmp, t in zip(tmps, paths):
            if tmp is not None:
                if fsync:
                    _fsync(tmp)
                os.replace(tmp, t)
    except OSError as e:
        if isinstance(e, WriteError):
            raise
        raise WriteError(f"cannot write {what}: {e.strerror or e}") from None
    finally:
        for tmp in tmps:
            if tmp is not None:
                tmp.unlink(missing_ok=True)


def _fsync(p: Path) -> None:
    with open(p, "rb") as fh:
        os.fsync(fh.fileno())


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", encoding: str | None = None):
    """A file object on a private (0600) temporary sibling renamed over ``path`` once fully
    written (``atomic_paths``); a missing folder is created private."""
    path = Path(path)
    try:
        if not path.parent.is_dir():
            make_private_dir(path.parent, tighten=False)
    except OSError as e:
        raise WriteError(f"cannot write {path}: {e.strerror or e}") from None
    with atomic_paths(path) as (tmp,):
        with open(tmp, mode, encoding=encoding) as f:
            yield f


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_file(path, "w", encoding="utf-8") as f:
        f.write(text)


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """JSON with NaN/Infinity refused (they are not JSON, and mean a broken result)."""
    try:
        text = json.dumps(obj, indent=2, allow_nan=False)
    except ValueError:
        raise AnkleScanError(f"refusing to write {Path(path).name}: it holds a non-finite number") from None
    write_text_atomic(path, text + "\n")


# ------------------------------------------------------------------------ out guards
def _identity(p: Path) -> tuple[int, int] | None:
    try:
        st = p.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _inside(child: str, parent: str) -> bool:
    try:
        return os.path.commonpath([child, parent]) == parent
    except ValueError:  # different drives (Windows)
        return False


def guard_output(out: str | os.PathLike, inputs, *, what: str = "output") -> Path:
    """Refuse an output that would overwrite, replace or land inside one of ``inputs``.

    Call it in every command (and GUI action) that writes a file or folder, before any
    work, with every path the command reads::

        guard_output(args.out, [args.capture, args.calibration])

    Refused (AnkleScanError, one line): ``out`` is the same file or folder as an input by
    any spelling (relative path, ``..``, symlink, hard link); ``out`` lies inside an input
    folder (it would add to or replace a file of, e.g., a capture); ``out`` is a folder
    that contains an input (replacing it would delete the input); ``out`` is a hard link
    to a file inside an input folder; ``out`` is empty or an existing device, pipe or socket
    (``/dev/null`` would be replaced by a file). ``None`` inputs are skipped. Returns
    ``Path(out)``.
    """
    if not str(out).strip():
        raise AnkleScanError(f"{what} is empty; give a file or folder name")
    out_path = Path(out)
    try:
        mode = out_path.stat().st_mode
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise AnkleScanError(f"{what} {out} is a device, pipe or socket, not a file; choose a file name")
    out_real = os.path.realpath(out_path)
    out_id = _identity(out_path)
    for inp in inputs:
        if inp is None:
            continue
        in_path = Path(inp)
        in_real = os.path.realpath(in_path)
        in_id = _identity(in_path)
        same = out_real == in_real or (out_id is not None and out_id == in_id)
        if same:
            raise AnkleScanError(f"{what} {out} is the input {inp}; refusing to overwrite it "
                                 "(choose another output name)")
        if in_path.is_dir() and _inside(out_real, in_real):
            raise AnkleScanError(f"{what} {out} is inside the input folder {inp}; "
                                 "choose a path outside it")
        if _inside(in_real, out_real):
            raise AnkleScanError(f"{what} {out} contains the input {inp}; refusing to replace it")
        if out_id is not None and in_path.is_dir() and out_path.is_file():
            ids = {_identity(f) for f in in_path.iterdir()}
            if out_id in ids:
                raise AnkleScanError(f"{what} {out} is a link to a file of the input folder {inp}; "
                                     "refusing to overwrite it")
    return out_path


def check_replaceable_dir(folder: str | os.PathLike, is_ours) -> None:
    """Refuse to replace an existing ``folder`` unless it is empty or ``is_ours(folder)``.

    ``is_ours`` decides whether every entry is an earlier output of the same kind (e.g. a
    pattern set: manifest.json plus exactly its frames). Anything else — a document, other
    data, a sub-folder — means the user pointed at the wrong folder, and deleting it would
    lose data the command never wrote.
    """
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return
    if folder.is_symlink():
        raise AnkleScanError(f"output {folder} is a symbolic link; give the real folder or a new one")
    if not folder.is_dir():
        raise AnkleScanError(f"output {folder} exists and is not a folder; choose a new folder")
    try:
        empty = not any(folder.iterdir())
    except OSError as e:
        raise AnkleScanError(f"cannot read output folder {folder}: {e.strerror or e}") from None
    if not empty and not is_ours(folder):
        raise AnkleScanError(f"output folder {folder} holds files this command did not write; "
                             "refusing to replace it (choose a new or empty folder)")
