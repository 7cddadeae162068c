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
- ``claim_output_dir`` / ``seal_output_dir``: THE rule for a command that fills an output
  folder in place (``demo``, ``report``): the folder's marker (``OUTPUT_MARKER``) lists every
  file the command wrote, with its size and modification time; the next run removes exactly
  those files and refuses, untouched, a folder holding anything else (a user's note, another
  program's file, a file of ours changed since). ``filling_output_dir`` claims and, when the run
  fails or is interrupted before sealing, removes what it wrote.
- Permissions: an existing file is only ever replaced when the user may write it (as ``cp``
  would), and the final rename goes through a handle on the target's folder opened once, so
  a folder swapped for a symlink during a run cannot redirect it.
- Temporaries (``mkdtemp_beside``) carry a marker naming their process; a killed run's are
  removed by the next run in the same folder once their process is gone (or after
  ``STALE_TEMP_AGE_S``), and nothing without the marker is ever removed.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import socket
import stat
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

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


# A temporary folder holds this file (its process, host and start) until it is renamed into
# place; a folder with it whose process is gone, or older than STALE_TEMP_AGE_S, is a killed
# run's and is removed by the next run in the same folder.
TEMP_MARKER = ".anklescan-temporary"
STALE_TEMP_AGE_S = 24 * 3600.0


@dataclass(frozen=True)
class TempOwner:
    """Who made a temporary folder (read from its TEMP_MARKER)."""

    host: str
    pid: int
    created: float  # time.time()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _read_temp_owner(folder: Path) -> TempOwner | None:
    try:
        with open(folder / TEMP_MARKER, encoding="utf-8") as fh:
            obj = json.loads(fh.read(4096))
        return TempOwner(str(obj["host"]), int(obj["pid"]), float(obj["created"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def clean_stale_temporaries(folder: str | os.PathLike[str], now: float | None = None) -> list[Path]:
    """Remove, in ``folder``, the hidden temporary folders of runs that were killed: only those
    holding our TEMP_MARKER whose process is gone (same host) or that are older than
    STALE_TEMP_AGE_S. Anything without the marker is left alone. Returns what was removed."""
    now = time.time() if now is None else now
    removed: list[Path] = []
    try:
        entries = [e for e in os.scandir(os.fspath(folder)) if e.name.startswith(".")]
    except OSError:
        return removed
    host = socket.gethostname()
    for e in entries:
        try:
            if not e.is_dir(follow_symlinks=False):
                continue
        except OSError:
            continue
        owner = _read_temp_owner(Path(e.path))
        if owner is None or (owner.host == host and owner.pid == os.getpid()):
            continue
        gone = owner.host == host and not _pid_alive(owner.pid)
        if gone or now - owner.created > STALE_TEMP_AGE_S:
            shutil.rmtree(e.path, ignore_errors=True)
            removed.append(Path(e.path))
    return removed


def mkdtemp_beside(target: str | os.PathLike[str], tag: str = "tmp") -> Path:
    """A new private (0700) hidden folder next to ``target``, named within NAME_MAX, holding
    TEMP_MARKER (remove it with ``release_temp_dir`` before renaming the folder into place).
    Killed runs' temporaries in the same folder are removed first (``clean_stale_temporaries``)."""
    target = Path(target)
    clean_stale_temporaries(target.parent)
    prefix, suffix = temp_affixes(target.name, tag)
    try:
        tmp = Path(tempfile.mkdtemp(suffix=suffix, prefix=prefix, dir=target.parent))
    except OSError as e:  # a read-only or full disk: name the user's output, never our temporary
        raise WriteError(f"cannot write {target}: {e.strerror or e}") from None
    marker = {"host": socket.gethostname(), "pid": os.getpid(), "created": time.time(), "for": target.name}
    try:
        fd = os.open(tmp / TEMP_MARKER, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(json.dumps(marker, ensure_ascii=True))
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise WriteError(f"cannot write {target}: {e.strerror or e}") from None
    return tmp


def release_temp_dir(tmp: str | os.PathLike[str]) -> None:
    """Remove a temporary folder's TEMP_MARKER: it is about to become an output."""
    Path(tmp, TEMP_MARKER).unlink(missing_ok=True)


# --------------------------------------------------------------------------- privacy
def make_private(path: str | os.PathLike[str]) -> None:
    """chmod a file 0600 or a folder 0700 (a no-op if it already is)."""
    p = Path(path)
    mode = PRIVATE_DIR_MODE if p.is_dir() else PRIVATE_FILE_MODE
    if stat.S_IMODE(p.stat().st_mode) != mode:
        os.chmod(p, mode)


def make_private_dir(path: str | os.PathLike[str], *, tighten: bool = True) -> Path:
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
        with suppress(FileExistsError):  # created meanwhile by another process
            d.mkdir(mode=PRIVATE_DIR_MODE)
        os.chmod(d, PRIVATE_DIR_MODE)
    if not path.is_dir():
        raise AnkleScanError(f"{path} exists and is not a folder")
    if tighten and not missing:
        make_private(path)
    return path


def make_tree_private(folder: str | os.PathLike[str]) -> int:
    """Make every folder (0700) and file (0600) under ``folder`` private, e.g. patient data
    written by an older version under a 022 umask; symlinks and entries we may not change
    are skipped. Returns the number of entries changed."""
    changed = 0
    for root, _dirs, files in os.walk(str(folder)):
        entries = [(root, PRIVATE_DIR_MODE)] + [(os.path.join(root, f), PRIVATE_FILE_MODE) for f in files]
        for name, mode in entries:
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


# A temporary file carries its marker in its name (a file holds no marker of its own):
# ".<target>.<random>.<host>-<pid>.anklescan-tmp[.ext]", host a short hash of the host name.
_TEMP_FILE_RE = re.compile(r"^\..*\.[0-9a-f]{8}\.(?P<host>[0-9a-f]{6})-(?P<pid>[0-9]{1,10})\.anklescan-tmp(\.[^.]*)?$")
_cleaned_dirs: set[tuple[int, int]] = set()


def _host_tag() -> str:
    return hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]


def _temp_file_tag() -> str:
    return f"{_host_tag()}-{os.getpid()}.anklescan-tmp"


def _clean_stale_temp_files(dir_fd: int, folder: Path, now: float | None = None) -> list[str]:
    """Remove, once per folder and process, the temporary files of killed writes: names with
    our marker whose process is gone (this host) or older than STALE_TEMP_AGE_S (any host).
    Returns the names removed."""
    removed: list[str] = []
    try:
        st = os.fstat(dir_fd)
    except OSError:
        return removed
    key = (st.st_dev, st.st_ino)
    if key in _cleaned_dirs and now is None:
        return removed
    _cleaned_dirs.add(key)
    now = time.time() if now is None else now
    host = _host_tag()
    try:
        names = [e.name for e in os.scandir(dir_fd) if _TEMP_FILE_RE.match(e.name)]
    except OSError:
        return removed
    for name in names:
        m = _TEMP_FILE_RE.match(name)
        if m is None:
            continue
        try:
            est = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISREG(est.st_mode) or est.st_uid != os.getuid():
            continue
        pid = int(m.group("pid"))
        gone = m.group("host") == host and pid != os.getpid() and not _pid_alive(pid)
        if gone or now - est.st_mtime > STALE_TEMP_AGE_S:
            with suppress(OSError):
                os.unlink(name, dir_fd=dir_fd)
                removed.append(name)
    return removed


def check_may_replace(path: str | os.PathLike[str], what: str = "output", dir_fd: int | None = None) -> None:
    """Refuse to replace an existing ``path`` the user could not write, as ``cp`` would: a
    read-only file of their own (a file with no write bit at all is refused even to root), or
    another user's file they have no write permission on (in a world-writable folder without
    the sticky bit a rename would otherwise replace it). A folder or a symbolic link in the
    way is refused too. A missing ``path`` passes."""
    p = Path(path)
    name = p.name if dir_fd is not None else p
    try:
        st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except FileNotFoundError:
        return
    except OSError as e:
        raise WriteError(f"cannot write {what} {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise WriteError(f"cannot write {what} {path}: it is a folder; give a file name")
    if stat.S_ISLNK(st.st_mode):
        raise WriteError(f"{what} {path} is a symbolic link; refusing to replace it (give the real file)")
    if not (st.st_mode & 0o222 and os.access(name, os.W_OK, dir_fd=dir_fd)):
        owner = "" if st.st_uid == os.getuid() else " (it belongs to another user)"
        raise WriteError(f"cannot replace {what} {path}: permission denied{owner}; "
                         "it was left untouched")


def _open_dir(folder: Path) -> int:
    return os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))


def _fd_path(dir_fd: int, folder: Path, name: str) -> Path:
    """A path that reaches ``name`` through the open folder handle (Linux: /proc/self/fd), so a
    writer given a path still writes into the folder that was opened, not a swapped symlink."""
    proc = Path(f"/proc/self/fd/{dir_fd}")
    return proc / name if proc.is_dir() else folder / name


@contextmanager
def atomic_paths(*targets: str | os.PathLike[str] | None, what: str | None = None, keep_suffix: bool = False,
                 fsync: bool = True) -> Iterator[list[Path | None]]:
    """The one atomic-write mechanism: yields a private (0600) temporary sibling per target
    (``None`` for a ``None`` target), to be written by any means (an encoder, a PDF backend);
    when the block ends without error each is flushed to disk (``fsync``) and renamed over its
    target, else every temporary is removed and no target is touched. The targets' folders
    must exist; each is opened once, and the temporary, the rename and the clean-up all go
    through that handle. An existing target the user may not write is refused
    (``check_may_replace``), before and again at the rename. An OSError becomes a WriteError
    "cannot write WHAT: ..." (``what`` defaults to the first target); ``keep_suffix`` ends the
    temporary with the target's extension, for writers that choose the format by it."""
    paths = [None if t is None else Path(t) for t in targets]
    what = what or str(next((p for p in paths if p is not None), ""))
    slots: list[tuple[int, str] | None] = []
    try:
        for t in paths:
            if t is None:
                slots.append(None)
                continue
            if not t.parent.is_dir():
                raise AnkleScanError(f"output folder {t.parent} does not exist")
            dfd = _open_dir(t.parent)
            slots.append((dfd, ""))
            check_may_replace(t, what="output", dir_fd=dfd)
            _clean_stale_temp_files(dfd, t.parent)
            prefix, suffix = temp_affixes(t.name, tag=_temp_file_tag(), keep_suffix=t.suffix if keep_suffix else "")
            for _ in range(100):
                name = f"{prefix}{secrets.token_hex(_RANDOM_CHARS // 2)}{suffix}"
                try:
                    fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0),
                                 PRIVATE_FILE_MODE, dir_fd=dfd)
                except FileExistsError:
                    continue
                os.fchmod(fd, PRIVATE_FILE_MODE)
                os.close(fd)
                break
            else:  # pragma: no cover - 100 collisions of 32 random bits
                raise WriteError(f"cannot write {what}: no free temporary name")
            slots[-1] = (dfd, name)
        yield [None if slot is None or t is None else _fd_path(slot[0], t.parent, slot[1])
               for slot, t in zip(slots, paths, strict=True)]
        for i, (slot, t) in enumerate(zip(slots, paths, strict=True)):
            if slot is not None and t is not None:
                dfd, name = slot
                if fsync:
                    _fsync_at(dfd, name)
                check_may_replace(t, what="output", dir_fd=dfd)
                os.replace(name, t.name, src_dir_fd=dfd, dst_dir_fd=dfd)
                slots[i] = (dfd, "")
                if fsync:
                    _fsync_fd(dfd)
    except OSError as e:
        if isinstance(e, WriteError):
            raise
        raise WriteError(f"cannot write {what}: {e.strerror or e}") from None
    finally:
        for slot in slots:
            if slot is not None:
                dfd, name = slot
                if name:
                    with suppress(OSError):
                        os.unlink(name, dir_fd=dfd)
                os.close(dfd)


def _fsync_at(dir_fd: int, name: str) -> None:
    fd = os.open(name, os.O_RDONLY, dir_fd=dir_fd)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_fd(fd: int) -> None:
    with suppress(OSError):  # some file systems cannot fsync a folder; the rename is still atomic
        os.fsync(fd)


def _fsync(p: Path) -> None:
    with open(p, "rb") as fh:
        os.fsync(fh.fileno())


@contextmanager
def atomic_file(path: str | os.PathLike[str], mode: str = "wb", encoding: str | None = None) -> Iterator[IO[Any]]:
    """A file object on a private (0600) temporary sibling renamed over ``path`` once fully
    written (``atomic_paths``); a missing folder is created private."""
    path = Path(path)
    try:
        if not path.parent.is_dir():
            make_private_dir(path.parent, tighten=False)
    except OSError as e:
        raise WriteError(f"cannot write {path}: {e.strerror or e}") from None
    with atomic_paths(path) as (tmp,):
        assert tmp is not None
        with open(tmp, mode, encoding=encoding) as f:
            yield f


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    with atomic_file(path, "w", encoding="utf-8") as f:
        f.write(text)


def copy_private(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """Copy a file atomically to ``dst``, private (0600) from its creation whatever the umask."""
    with atomic_paths(dst) as (tmp,):
        assert tmp is not None
        with open(src, "rb") as fin, open(tmp, "wb") as fout:
            shutil.copyfileobj(fin, fout, 1 << 20)


def write_json_atomic(path: str | os.PathLike[str], obj: object) -> None:
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


def guard_output(out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None], *, what: str = "output") -> Path:
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


def check_replaceable_dir(folder: str | os.PathLike[str], is_ours: Callable[[Path], bool]) -> None:
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


# ---------------------------------------------------------------- output folders
# The marker of a folder a command fills in place: which command, and every file it wrote
# with its size and modification time (a file changed since is no longer the command's).
OUTPUT_MARKER = ".anklescan-output.json"


@dataclass(frozen=True)
class OutputEntry:
    """One file an output folder's marker says the command wrote."""

    path: str  # relative, '/'-separated
    size: int
    mtime_ns: int


def _read_output_marker(folder: Path, command: str) -> list[OutputEntry] | None:
    """The files listed by ``folder``'s marker, or None when there is no valid, complete marker
    of ``command``."""
    try:
        with open(folder / OUTPUT_MARKER, encoding="utf-8") as fh:
            obj = json.loads(fh.read(64 << 20))
        if obj.get("command") != command or obj.get("complete") is not True:
            return None
        return [OutputEntry(str(e["path"]), int(e["size"]), int(e["mtime_ns"])) for e in obj["files"]]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _walk_output(folder: Path) -> tuple[list[str], list[str], list[str]]:
    """(files, folders, others) under ``folder`` as relative '/'-paths, the marker excluded;
    symbolic links, devices and the like are 'others'."""
    files: list[str] = []
    dirs: list[str] = []
    others: list[str] = []
    for root, dnames, fnames in os.walk(os.fspath(folder)):
        rel_root = Path(root).relative_to(folder)
        for name in dnames + fnames:
            rel = (rel_root / name).as_posix()
            if rel == OUTPUT_MARKER:
                continue
            st = os.lstat(Path(root, name))
            if stat.S_ISDIR(st.st_mode):
                dirs.append(rel)
            elif stat.S_ISREG(st.st_mode):
                files.append(rel)
            else:
                others.append(rel)
        dnames[:] = [d for d in dnames if not os.path.islink(os.path.join(root, d))]
    return files, dirs, others


def claim_output_dir(folder: str | os.PathLike[str], command: str) -> Path:
    """Make ``folder`` ready for ``command`` to fill: create it (0700, parents too) when it is
    missing; use it as it is when empty; when it holds an earlier complete output of the same
    command (``seal_output_dir``'s marker), remove exactly the files that run wrote, unchanged
    since. Anything else (a file the marker does not list, a listed file changed since, a
    link, no marker, an unfinished run's marker) is refused with one line and nothing is
    removed. Call it before any work and write into the folder it returns (the real path,
    resolved once, so a link swapped in later for a part of the given path does not redirect
    the files); call ``seal_output_dir`` when the output is complete."""
    folder = Path(folder)
    if folder.is_symlink():
        raise AnkleScanError(f"output {folder} is a symbolic link; give the real folder or a new one")
    if folder.exists() and not folder.is_dir():
        raise AnkleScanError(f"output {folder} exists and is not a folder; choose a new folder")
    if not folder.exists():
        make_private_dir(folder)
        return folder.resolve()
    try:
        files, dirs, others = _walk_output(folder)
        has_marker = (folder / OUTPUT_MARKER).exists()
    except OSError as e:
        raise AnkleScanError(f"cannot read output folder {folder}: {e.strerror or e}") from None
    if not files and not dirs and not others and not has_marker:
        make_private(folder)
        return folder.resolve()
    listed = _read_output_marker(folder, command)
    if listed is None:
        raise AnkleScanError(f"output folder {folder} is not empty and holds no complete earlier "
                             f"'{command}' output; nothing was changed (choose a new or empty folder)")
    known = {e.path: e for e in listed}
    for rel in others + files:
        entry = known.get(rel)
        if entry is None:
            raise AnkleScanError(f"output folder {folder} holds {rel}, which '{command}' did not write; "
                                 "nothing was changed (move it away or choose a new folder)")
        st = os.lstat(folder / rel)
        if (st.st_size, st.st_mtime_ns) != (entry.size, entry.mtime_ns):
            raise AnkleScanError(f"output folder {folder}: {rel} was changed after '{command}' wrote it; "
                                 "nothing was changed (move it away or choose a new folder)")
    for rel in files:
        (folder / rel).unlink()
    for rel in sorted(dirs, key=lambda d: d.count("/"), reverse=True):
        try:
            (folder / rel).rmdir()
        except OSError:
            raise AnkleScanError(f"output folder {folder}: cannot remove the earlier output's folder {rel}; "
                                 "it holds something else") from None
    (folder / OUTPUT_MARKER).unlink()
    make_private(folder)
    return folder.resolve()


@contextmanager
def filling_output_dir(folder: str | os.PathLike[str], command: str) -> Iterator[Path]:
    """``claim_output_dir`` for a run that fills ``folder`` in place, undone if the run does not
    finish: when the block fails or is interrupted (Ctrl-C, SIGTERM) before ``seal_output_dir``,
    everything in the folder is removed (the claim left it empty, so all of it is this run's) and
    the folder itself when the claim created it; no half-written output is left behind, nor a folder
    the next run would refuse. A refused claim changes nothing; a sealed output is kept."""
    folder = Path(folder)
    existed = folder.exists() or folder.is_symlink()
    real = claim_output_dir(folder, command)
    try:
        yield real
    except BaseException:
        if _read_output_marker(real, command) is None:  # not sealed: the run's partial output
            if existed:
                for entry in list(real.iterdir()):
                    if entry.is_dir() and not entry.is_symlink():
                        shutil.rmtree(entry, ignore_errors=True)
                    else:
                        with suppress(OSError):
                            entry.unlink()
            else:
                shutil.rmtree(real, ignore_errors=True)
        raise


def seal_output_dir(folder: str | os.PathLike[str], command: str) -> int:
    """Write ``folder``'s marker listing every file in it as written by ``command`` (call it
    once the output is complete; the next ``claim_output_dir`` removes exactly these).
    Returns the number of files listed."""
    folder = Path(folder)
    files, _dirs, _others = _walk_output(folder)
    entries = []
    for rel in files:
        st = os.lstat(folder / rel)
        entries.append({"path": rel, "size": st.st_size, "mtime_ns": st.st_mtime_ns})
    write_json_atomic(folder / OUTPUT_MARKER, {"command": command, "complete": True, "files": entries})
    return len(entries)


def is_output_of(folder: str | os.PathLike[str], command: str) -> bool:
    """True when ``folder`` holds a complete, unchanged output of ``command`` and nothing else."""
    folder = Path(folder)
    listed = _read_output_marker(folder, command)
    if listed is None:
        return False
    try:
        files, _dirs, others = _walk_output(folder)
    except OSError:
        return False
    known = {e.path: e for e in listed}
    if others or set(files) - set(known):
        return False
    return all((st.st_size, st.st_mtime_ns) == (known[r].size, known[r].mtime_ns)
               for r in files for st in [os.lstat(folder / r)])
