"""One AnkleScan per data folder: an advisory lock that names its holder.

``DataFolderLock(folder).acquire()`` takes an exclusive ``flock`` on ``folder/LOCK_FILENAME``
(0600) and writes who holds it (host, process id, since when). The operating system releases
the lock when the holder exits or crashes, so a stale file never blocks anyone: only a live
holder does. A second instance gets the holder back instead and can offer to open the folder
read-only (``Store.open(read_only=True)``). Where the file cannot be made (a read-only
folder or medium) there is nothing to protect and no lock is taken.
"""

from __future__ import annotations

import json
import os
import socket
from contextlib import suppress
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no advisory lock, the database's own locks remain
    fcntl = None  # type: ignore[assignment]

LOCK_FILENAME = "anklescan.lock"


@dataclass(frozen=True)
class LockHolder:
    """Who holds a data folder: the host, the process and since when (ISO 8601, UTC)."""

    host: str
    pid: int
    since: str

    def describe(self) -> str:
        where = "this computer" if self.host == socket.gethostname() else f"computer {self.host}"
        try:
            since = datetime.fromisoformat(self.since).astimezone().strftime("%Y-%m-%d %H:%M")
        except (ValueError, TypeError):
            since = self.since or "an unknown time"
        return f"AnkleScan on {where} (process {self.pid}) since {since}"


class DataFolderLock:
    """The lock of one data folder; ``acquire`` once, ``release`` when the folder is closed."""

    def __init__(self, folder: str | os.PathLike[str]):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILENAME
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> LockHolder | None:
        """Take the lock: None when taken (or when no lock can be made here), else the holder."""
        if self._fd is not None or fcntl is None:
            return None
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o600)
        except OSError:
            return None  # a read-only folder: nothing can be written to it, by us or another copy
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _read_holder(fd)
            os.close(fd)
            if holder.host == socket.gethostname() and holder.pid == os.getpid():
                return None  # this process holds it already (a second window of the same app)
            return holder
        me = LockHolder(socket.gethostname(), os.getpid(),
                        datetime.now(UTC).isoformat(timespec="seconds"))
        data = json.dumps({"host": me.host, "pid": me.pid, "since": me.since}).encode()
        with suppress(OSError):  # the lock holds even if its description cannot be written
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
        self._fd = fd
        return None

    def release(self) -> None:
        if self._fd is None:
            return
        with suppress(OSError):
            os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing the descriptor releases the flock
        self._fd = None


def _read_holder(fd: int) -> LockHolder:
    try:
        obj = json.loads(os.pread(fd, 4096, 0).decode("utf-8", "replace") or "{}")
        return LockHolder(str(obj.get("host", "?")), int(obj.get("pid", 0)), str(obj.get("since", "")))
    except (OSError, ValueError, TypeError, AttributeError):
        return LockHolder("?", 0, "")
