"""The sessions database file: opening it safely, its schema and migrations, and transactions.

Nothing here knows patients or trials: the repositories (``patients.py``, ``calibrations.py``,
``sessions.py``, ``trials.py``, ``events.py``, ``daily_checks.py``) own their tables' SQL and go
through a ``Database``. ``Database.open`` is the one way in (details in docs/sessions.md):

- We never create, repair or delete over an existing file that is not a healthy SQLite
  database of ours: it is inspected READ-ONLY first (``_inspect``): the header, the
  -wal/-shm/-journal companions (regular files of the database's owner, a -wal of this
  database's page size), a -wal with transactions replayed on a private copy (and refused if
  it would lose a patient, calibration, session or trial), our ``PRAGMA application_id`` (older
  databases of ours by their schema), every table and column its schema version has, and a
  clean ``quick_check``. Any other SQLite file is refused untouched.
- The schema version lives in ``PRAGMA user_version``; ``MIGRATIONS[i]`` upgrades i → i+1,
  each applied in the same transaction as the version bump.
- WAL + synchronous=FULL: readers never block the writer, and a crash or power cut leaves
  the last committed transaction. Every write is one ``BEGIN IMMEDIATE … COMMIT``
  (``Database.transaction``), which takes the write lock up front, so two app instances queue
  on the busy timeout instead of deadlocking when a read transaction tries to upgrade.
  Transactions nest: an inner one joins the outer, so several repositories' writes are one
  unit of work (``with db.transaction(): …``), all committed or none.
- A database that cannot be written (file mode without write bits, a read-only folder or
  mount, ``read_only=True``) opens for reading: ``read_only_reason`` says why, and every
  write raises AnkleScanError.
- Privacy: the database (and its -wal/-shm, which SQLite creates with the database's mode)
  is 0600 and the folders we create 0700, whatever the umask (core/atomic.py).
- The data folder's single-instance lock is ``core/records/lock.py`` (taken by the app).
"""

from __future__ import annotations

import os
import sqlite3
import stat
import urllib.parse
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from anklescan.core.atomic import PRIVATE_FILE_MODE, make_private, make_private_dir
from anklescan.core.errors import AnkleScanError

DB_FILENAME = "anklescan.sqlite"
DEFAULT_TIMEOUT_S = 10.0
_SQLITE_MAGIC = b"SQLite format 3\x00"
# PRAGMA application_id of our databases: "AnkS" (SQLite's header field for exactly this).
APPLICATION_ID = 0x416E6B53
# Databases of ours created before APPLICATION_ID existed are recognised by these columns.
_SCHEMA_MARKER = {"patients": {"code", "sprain_count", "affected_side"},
                  "sessions": {"patient_id", "condition", "calibration_id"},
                  "trials": {"session_id", "ref_inversion", "mismatch_inversion", "capture_sha256"},
                  "marks": {"trial_id", "label", "source", "placed_by"}}

# ----------------------------------------------------------------- schema

_V1 = """
CREATE TABLE patients (
    id INTEGER PRIMARY KEY,
    code TEXT NOT NULL UNIQUE,
    sprain_count INTEGER NOT NULL DEFAULT 0 CHECK (sprain_count >= 0),
    last_sprain TEXT,
    affected_side TEXT CHECK (affected_side IN ('left', 'right', 'both')),
    notes TEXT NOT NULL DEFAULT '',
    created TEXT NOT NULL
);
CREATE TABLE calibrations (
    id INTEGER PRIMARY KEY,
    created TEXT NOT NULL,
    json TEXT NOT NULL,
    rms REAL,
    source TEXT NOT NULL DEFAULT ''
);
CREATE TABLE sessions (
    id INTEGER PRIMARY KEY,
    patient_id INTEGER NOT NULL REFERENCES patients(id),
    date TEXT NOT NULL,
    operator TEXT NOT NULL DEFAULT '',
    condition TEXT NOT NULL,
    calibration_id INTEGER REFERENCES calibrations(id),
    notes TEXT NOT NULL DEFAULT ''
);
CREATE TABLE trials (
    id INTEGER PRIMARY KEY,
    session_id INTEGER NOT NULL REFERENCES sessions(id),
    created TEXT NOT NULL,
    ref_inversion REAL,
    ref_plantar_flexion REAL,
    leg_inversion REAL, leg_inversion_sd REAL,
    leg_plantar_flexion REAL, leg_plantar_flexion_sd REAL,
    table_inversion REAL, table_inversion_sd REAL,
    table_plantar_flexion REAL, table_plantar_flexion_sd REAL,
    mismatch_inversion REAL, mismatch_inversion_sd REAL,
    mismatch_plantar_flexion REAL, mismatch_plantar_flexion_sd REAL,
    capture_path TEXT,
    capture_sha256 TEXT,
    notes TEXT NOT NULL DEFAULT ''
);
CREATE TABLE marks (
    trial_id INTEGER NOT NULL REFERENCES trials(id) ON DELETE CASCADE,
    label INTEGER NOT NULL CHECK (label BETWEEN 1 AND 7),
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL,
    source TEXT NOT NULL CHECK (source IN ('auto', 'manual')),
    placed_by TEXT NOT NULL DEFAULT '',
    updated TEXT NOT NULL,
    PRIMARY KEY (trial_id, label)
);
"""

# v2: point clouds are kept next to captures, calibrations can be marked verified, and
# the per-session / per-patient look-ups the reports do get indexes.
_V2 = """
ALTER TABLE calibrations ADD COLUMN verified INTEGER NOT NULL DEFAULT 0;
ALTER TABLE trials ADD COLUMN cloud_path TEXT;
ALTER TABLE trials ADD COLUMN cloud_sha256 TEXT;
CREATE INDEX trials_session ON trials(session_id);
CREATE INDEX sessions_patient ON sessions(patient_id);
"""

# v3: trials have a lifecycle (scanning → complete, cancelled or failed), can be excluded
# with a reason and restored, and record the calibration they were measured with; patients
# and sessions can be archived; every such change is kept in an events log, so that nothing a
# clinician did is lost (nothing is ever deleted).
_V3 = """
ALTER TABLE trials ADD COLUMN status TEXT NOT NULL DEFAULT 'complete'
    CHECK (status IN ('scanning', 'complete', 'cancelled', 'failed'));
ALTER TABLE trials ADD COLUMN status_note TEXT NOT NULL DEFAULT '';
ALTER TABLE trials ADD COLUMN excluded_reason TEXT;
ALTER TABLE trials ADD COLUMN calibration_id INTEGER REFERENCES calibrations(id);
ALTER TABLE patients ADD COLUMN archived TEXT;
ALTER TABLE sessions ADD COLUMN archived TEXT;
CREATE TABLE events (
    id INTEGER PRIMARY KEY,
    time TEXT NOT NULL,
    kind TEXT NOT NULL,
    entity TEXT NOT NULL,
    entity_id INTEGER NOT NULL,
    detail TEXT NOT NULL DEFAULT '',
    who TEXT NOT NULL DEFAULT ''
);
"""

# v4: the marks' diameter kept with the session (NULL: measured from each capture).
_V4 = """
ALTER TABLE sessions ADD COLUMN mark_diameter_mm REAL;
"""


# v5: motion during the scan (issue 18, core/scan/motion.py): the subject's largest displacement and its
# SD, the scan's duration, whether it moved more than the threshold, and the clinician's choice
# to keep a flagged trial in the statistics anyway.
_V5 = """
ALTER TABLE trials ADD COLUMN motion_mm REAL;
ALTER TABLE trials ADD COLUMN motion_sd_mm REAL;
ALTER TABLE trials ADD COLUMN scan_duration_s REAL;
ALTER TABLE trials ADD COLUMN motion_flagged INTEGER NOT NULL DEFAULT 0;
ALTER TABLE trials ADD COLUMN motion_keep INTEGER NOT NULL DEFAULT 0;
"""

# the daily check (issue 37, core/records/daily_checks.py): each scan of the known-angle
# object with its date, the calibration it checked, the set and measured angles, pass or fail.
_V_DAILY_CHECKS = """
CREATE TABLE daily_checks (
    id INTEGER PRIMARY KEY,
    time TEXT NOT NULL,
    calibration_id INTEGER REFERENCES calibrations(id),
    expected_inversion REAL NOT NULL,
    expected_plantar_flexion REAL NOT NULL,
    measured_inversion REAL NOT NULL,
    measured_inversion_sd REAL,
    measured_plantar_flexion REAL NOT NULL,
    measured_plantar_flexion_sd REAL,
    sag_mm REAL,
    tolerance_deg REAL NOT NULL,
    passed INTEGER NOT NULL CHECK (passed IN (0, 1)),
    summary TEXT NOT NULL DEFAULT '',
    who TEXT NOT NULL DEFAULT ''
);
"""

# issue 42: a trial scanned on the built-in simulated rig is a simulated patient's, and every list,
# report and CSV says so; an automatic mark keeps its position SD and why it is less certain
# ("overexposed"), so the 3-D view, the marks table and the report show it after the scan too.
_V_SIMULATED = """
ALTER TABLE trials ADD COLUMN simulated INTEGER NOT NULL DEFAULT 0;
ALTER TABLE marks ADD COLUMN sd_mm REAL;
ALTER TABLE marks ADD COLUMN warning TEXT NOT NULL DEFAULT '';
"""

MIGRATIONS: list[str] = [_V1, _V2, _V3, _V4, _V5, _V_DAILY_CHECKS, _V_SIMULATED]
SCHEMA_VERSION = len(MIGRATIONS)



def _errname(e: sqlite3.Error) -> str:
    return getattr(e, "sqlite_errorname", "") or ""


class ReadOnlyDatabaseError(AnkleScanError):
    """SQLite refused to write, or to open for writing (a read-only mount our checks could
    not see, say): an existing database is then opened for reading instead."""


def _translate(e: sqlite3.Error, path: Path, timeout: float) -> AnkleScanError:
    """One clear line for the sqlite failures a user can actually run into."""
    name, msg = _errname(e), " ".join(str(e).split())
    if name.startswith("SQLITE_BUSY") or name.startswith("SQLITE_LOCKED") or "locked" in msg:
        return AnkleScanError(
            f"database {path} is locked by another program (waited {timeout:g} s); "
            "close the other AnkleScan window or try again")
    if name.startswith("SQLITE_FULL") or "full" in msg:
        return AnkleScanError(f"cannot write to database {path}: disk is full; "
                              "the change was not saved, earlier data is intact")
    if name.startswith("SQLITE_NOTADB") or name.startswith("SQLITE_CORRUPT") or \
            "not a database" in msg or "malformed" in msg:
        return AnkleScanError(f"database {path} is damaged ({msg}); it was left untouched, "
                              "restore it from a backup")
    if name.startswith("SQLITE_READONLY"):
        return ReadOnlyDatabaseError(f"database {path} is read-only; cannot save changes")
    if name.startswith("SQLITE_CANTOPEN"):
        return ReadOnlyDatabaseError(f"cannot access database {path}: {msg}")
    if name.startswith("SQLITE_IOERR"):
        return AnkleScanError(f"cannot access database {path}: {msg}")
    if isinstance(e, sqlite3.IntegrityError):
        return AnkleScanError(f"database rejected the change: {msg}")
    return AnkleScanError(f"database {path}: {msg}")


def _check_header(path: Path) -> None:
    """Refuse a non-SQLite file before sqlite ever touches it (it would never be ours)."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return
    except OSError as e:
        raise AnkleScanError(f"cannot access database {path}: {e.strerror or e}") from None
    if size == 0:
        return  # sqlite treats an empty file as a new database; nothing to lose
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as e:
        raise AnkleScanError(f"cannot read database {path}: {e.strerror or e}") from None
    if head != _SQLITE_MAGIC:
        raise AnkleScanError(f"{path} is not an AnkleScan database (not SQLite); "
                             "it was left untouched")


def _uri(path: Path, query: str) -> str:
    return f"file:{urllib.parse.quote(str(path.resolve()))}?{query}"


def _header_fields(path: Path) -> tuple[int, int, int]:
    """(journal version byte: 1 rollback, 2 WAL; user_version; application_id) from the
    100-byte database header, read without SQLite."""
    with open(path, "rb") as fh:
        head = fh.read(100)
    page = int.from_bytes(head[16:18], "big")
    if len(head) < 100 or head[21:24] != b"\x40\x20\x20" or not (page == 1 or (
            512 <= page <= 32768 and page & (page - 1) == 0)):
        raise AnkleScanError(f"database {path} is damaged (invalid SQLite header); it was left "
                             "untouched, restore it from a backup")
    return head[18], int.from_bytes(head[60:64], "big"), int.from_bytes(head[68:72], "big")


# A -wal shorter than its 32-byte header holds no transaction: SQLite ignores it.
_WAL_HEADER_BYTES = 32
_WAL_MAGIC = (0x377F0682, 0x377F0683)
# Rows a database of ours never loses (patients, calibrations, sessions, trials are archived,
# never deleted): a -wal whose replay would remove one is not this database's.
_KEPT_ROWS = {"patients": "code", "calibrations": "id", "sessions": "patient_id", "trials": "session_id"}
_EXPECTED_SCHEMA: dict[int, dict[str, set[str]]] = {}


def _expected_schema(version: int) -> dict[str, set[str]]:
    """Tables and their columns a database of schema ``version`` has (MIGRATIONS applied to an
    empty database in memory)."""
    if version not in _EXPECTED_SCHEMA:
        conn = sqlite3.connect(":memory:")
        try:
            for v in range(min(version, SCHEMA_VERSION)):
                for stmt in _statements(MIGRATIONS[v]):
                    conn.execute(stmt)
            _EXPECTED_SCHEMA[version] = _columns(conn)
        finally:
            conn.close()
    return _EXPECTED_SCHEMA[version]


def _columns(conn: sqlite3.Connection) -> dict[str, set[str]]:
    columns = {}
    for (table,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
        columns[table] = {r[1] for r in conn.execute(f"PRAGMA table_info(\"{table}\")")}
    return columns


def _check_contents(conn: sqlite3.Connection, path: Path, where: str = "") -> None:
    """Refuse what ``conn`` shows unless it is a healthy database of ours (or a blank SQLite
    file): our application id (or, before it existed, our tables), every table and column its
    schema version has, and a clean quick_check. ``where`` adds to the messages (e.g. 'once
    its -wal is applied')."""
    app_id = conn.execute("PRAGMA application_id").fetchone()[0]
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    columns = _columns(conn)
    suffix = f" {where}" if where else ""
    if app_id not in (0, APPLICATION_ID):
        raise AnkleScanError(f"{path} is an SQLite database of another program (application id {app_id:#x})"
                             f"{suffix}, not AnkleScan's; it was left untouched")
    blank = not columns and version == 0  # an empty SQLite file holds nothing to lose
    if app_id != APPLICATION_ID and not blank and not all(
            cols <= columns.get(t, set()) for t, cols in _SCHEMA_MARKER.items()):
        raise AnkleScanError(f"{path} is an SQLite database of another program{suffix}, not AnkleScan's; "
                             "it was left untouched")
    if 0 < version <= SCHEMA_VERSION:
        missing: list[str] = []
        for table, cols in _expected_schema(version).items():
            if table not in columns:
                missing.append(f"table {table}")
            else:
                missing += [f"{table}.{c}" for c in sorted(cols - columns[table])]
        if missing:
            shown = ", ".join(missing[:4]) + (f" and {len(missing) - 4} more" if len(missing) > 4 else "")
            raise AnkleScanError(f"database {path} is incomplete{suffix}: schema v{version} but {shown} "
                                 "missing; it was left untouched, restore it from a backup")
    bad = conn.execute("PRAGMA quick_check(1)").fetchone()[0]
    if bad != "ok":
        raise AnkleScanError(f"database {path} is damaged{suffix} ({' '.join(str(bad).split())}); it was "
                             "left untouched, restore it from a backup")


def _kept_rows(conn: sqlite3.Connection) -> dict[str, set[tuple[object, ...]]]:
    rows: dict[str, set[tuple[object, ...]]] = {}
    tables = _columns(conn)
    for table, key in _KEPT_ROWS.items():
        if key in tables.get(table, set()) and "id" in tables[table]:
            rows[table] = set(conn.execute(f"SELECT id, {key} FROM {table}").fetchall())
    return rows


def _check_companions(path: Path) -> Path | None:
    """Check the database's -wal, -shm and -journal before SQLite sees them: regular files (not
    links), the database file's owner, and a -wal whose header is a WAL's with the database's
    page size. Returns the -wal when it holds transactions SQLite would apply, else None."""
    try:
        db = os.stat(path)
        with open(path, "rb") as fh:
            head = fh.read(100)
    except OSError as e:
        raise AnkleScanError(f"cannot read database {path}: {e.strerror or e}") from None
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page == 1 else page
    wal_with_frames = None
    for suffix in ("-wal", "-shm", "-journal"):
        companion = Path(f"{path}{suffix}")
        try:
            st = os.lstat(companion)
        except FileNotFoundError:
            continue
        except OSError as e:
            raise AnkleScanError(f"cannot read {companion}: {e.strerror or e}") from None
        untouched = "the database and it were left untouched"
        if not stat.S_ISREG(st.st_mode):
            raise AnkleScanError(f"{companion} (the database's {suffix[1:]} file) is not a regular file "
                                 f"(a link, folder or device); {untouched}")
        if st.st_uid != db.st_uid:
            raise AnkleScanError(f"{companion} (the database's {suffix[1:]} file) belongs to another user than "
                                 f"the database; {untouched}")
        if suffix == "-wal" and st.st_size > _WAL_HEADER_BYTES:
            try:
                with open(companion, "rb") as fh:
                    wal_head = fh.read(_WAL_HEADER_BYTES)
            except OSError as e:
                raise AnkleScanError(f"cannot read {companion}: {e.strerror or e}") from None
            magic, wal_page = int.from_bytes(wal_head[0:4], "big"), int.from_bytes(wal_head[8:12], "big")
            if magic not in _WAL_MAGIC:
                raise AnkleScanError(f"{companion} is not an SQLite -wal file; {untouched} "
                                     "(move it away if no program uses it)")
            if wal_page != page:
                raise AnkleScanError(f"{companion} belongs to another database (its pages are {wal_page} bytes, "
                                     f"the database's {page}); {untouched} (move it away if no program uses it)")
            wal_with_frames = companion
        if suffix == "-journal" and st.st_size > 0:
            raise AnkleScanError(f"{companion}: a rollback journal beside a database in WAL mode is not ours; "
                                 f"{untouched}")
    return wal_with_frames


def _inspect_with_wal(path: Path, wal: Path, timeout: float) -> None:
    """What SQLite would make of the database once it applies ``wal``, found on a private copy
    (the real files are not touched): the same checks as without a -wal, and no patient,
    calibration, session or trial of the database lost (they are archived, never deleted)."""
    from anklescan.core.atomic import copy_private, mkdtemp_beside

    before_conn = None
    try:
        before_conn = sqlite3.connect(_uri(path, "mode=ro&immutable=1"), uri=True, isolation_level=None)
        before = _kept_rows(before_conn)
    except sqlite3.Error as e:
        raise _translate(e, path, timeout) from None
    finally:
        if before_conn is not None:
            before_conn.close()
    try:
        tmp = mkdtemp_beside(path, "check")
    except OSError:
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix=".anklescan-check."))  # 0700; a read-only data folder
    conn = None
    try:
        copy = tmp / "copy.sqlite"
        copy_private(path, copy)
        copy_private(wal, Path(f"{copy}-wal"))
        conn = sqlite3.connect(copy, timeout=timeout, isolation_level=None)
        where = f"once its -wal ({wal.name}) is applied"
        try:
            _check_contents(conn, path, where)
            after = _kept_rows(conn)
        except AnkleScanError as e:
            raise AnkleScanError(f"{e} (the -wal may belong to another database: move it away if no program "
                                 "uses it)") from None
        lost = {t: len(rows - after.get(t, set())) for t, rows in before.items()}
        lost = {t: n for t, n in lost.items() if n}
        if lost:
            what = ", ".join(f"{n} {t}" for t, n in lost.items())
            raise AnkleScanError(f"{wal} does not belong to database {path}: applying it would remove {what}; "
                                 "the database and the -wal were left untouched (move the -wal away if no "
                                 "program uses the database)")
    except sqlite3.Error as e:
        raise _translate(e, path, timeout) from None
    except OSError as e:
        raise AnkleScanError(f"cannot check database {path}: {e.strerror or e}") from None
    finally:
        if conn is not None:
            conn.close()
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)


def _inspect(path: Path, timeout: float) -> None:
    """Refuse, untouched, an existing SQLite file that is not a healthy database of ours.

    Read-only throughout: its companions are checked first (``_check_companions``); a -wal
    with transactions is applied to a private copy and the result checked
    (``_inspect_with_wal``); without one the file is read as immutable (so no -wal/-shm
    appear next to someone else's file).
    """
    try:
        _journal, _version, app_id = _header_fields(path)
    except OSError as e:
        raise AnkleScanError(f"cannot read database {path}: {e.strerror or e}") from None
    if app_id not in (0, APPLICATION_ID):
        raise AnkleScanError(f"{path} is an SQLite database of another program (application id "
                             f"{app_id:#x}), not AnkleScan's; it was left untouched")
    wal = _check_companions(path)
    if wal is not None:
        _inspect_with_wal(path, wal, timeout)
        return
    conn = None
    try:
        conn = sqlite3.connect(_uri(path, "mode=ro&immutable=1"), uri=True, timeout=timeout, isolation_level=None)
        _check_contents(conn, path)
    except sqlite3.Error as e:
        raise _translate(e, path, timeout) from None
    finally:
        if conn is not None:
            conn.close()


def _read_only_reason(path: Path, exists: bool) -> str:
    """Why the database cannot be written ('' if it can), checked before SQLite tries."""
    folder = path.parent if path.parent.exists() else next(p for p in path.parents if p.exists())
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "it is on a read-only file system"
    except (OSError, AttributeError):
        pass
    if exists:
        mode = path.stat().st_mode
        if not mode & 0o222:
            return f"the file is marked read-only (mode {mode & 0o777:o})"
        if not os.access(path, os.W_OK):
            return "you do not have permission to write the file"
    if not os.access(folder, os.W_OK):
        return f"the folder {folder} cannot be written"
    return ""


def _create_private(path: Path) -> None:
    """Create the database file 0600 (SQLite gives -wal/-shm the same mode), or tighten ours."""
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE))
        os.chmod(path, PRIVATE_FILE_MODE)
        return
    except FileExistsError:
        pass
    for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm")):
        try:
            make_private(p)
        except OSError:
            pass  # not ours to change (another owner) or gone: leave it



def _statements(script: str) -> list[str]:
    """Split a migration script; executescript() would COMMIT our open transaction."""
    out, buf = [], ""
    for line in script.splitlines(keepends=True):
        buf += line
        if sqlite3.complete_statement(buf):
            out.append(buf.strip())
            buf = ""
    return [s for s in out if s]


# ----------------------------------------------------------------- the database

Params = Sequence[object]


class Database:
    """One connection to the sessions database file. Not shared between threads."""

    def __init__(self, conn: sqlite3.Connection, path: Path, timeout: float, read_only_reason: str = ""):
        self._conn = conn
        self.path = path
        self.timeout = timeout
        self.read_only_reason = read_only_reason  # '' when writable
        self._depth = 0         # nesting of transaction(): the outermost one commits
        self._doomed = False    # an inner transaction failed: the outermost one rolls back

    @property
    def read_only(self) -> bool:
        """True when the database was opened for reading only (``read_only_reason`` says why)."""
        return bool(self.read_only_reason)

    def require_writable(self) -> None:
        if self.read_only:
            raise AnkleScanError(f"database {self.path} is open read-only ({self.read_only_reason}); "
                                 "editing is disabled")

    # ------------------------------------------------------------ opening

    @classmethod
    def open(cls, path: Path, *, timeout: float = DEFAULT_TIMEOUT_S, read_only: bool = False) -> Database:
        """Open (creating and migrating as needed) the database file ``path``.

        An existing file is first inspected read-only and refused untouched unless it is a
        healthy AnkleScan database; one that cannot be written (or ``read_only=True``) is opened
        for reading with ``read_only_reason`` set.
        """
        _check_header(path)
        exists = path.exists() and path.stat().st_size > 0
        if exists:
            _inspect(path, timeout)
        reason = "opened read-only on request" if read_only else _read_only_reason(path, exists)
        if reason:
            if not exists and read_only:
                what = "is empty (0 bytes: no records)" if path.exists() else "does not exist"
                raise AnkleScanError(f"database {path} {what}; nothing to open read-only")
            if not exists:
                raise AnkleScanError(f"cannot create database {path}: {reason}")
            return cls._open_read_only(path, timeout, reason)
        try:
            make_private_dir(path.parent, tighten=False)
            _create_private(path)
        except OSError as e:
            raise AnkleScanError(f"cannot create database {path}: {e.strerror or e}") from None
        try:
            conn = sqlite3.connect(path, timeout=timeout, isolation_level=None)
        except sqlite3.Error as e:
            raise _translate(e, path, timeout) from None
        db = cls(conn, path, timeout)
        try:
            db._configure()
            db._migrate()
            db._enable_wal()
            db._claim()
        except ReadOnlyDatabaseError:
            conn.close()
            if not exists:
                raise
            return cls._open_read_only(path, timeout, "the system refused to open it for writing")
        except BaseException:
            conn.close()
            raise
        return db

    @classmethod
    def _open_read_only(cls, path: Path, timeout: float, reason: str) -> Database:
        conn = None
        error: sqlite3.Error | None = None
        # Without a -wal there is nothing but the file to read: immutable=1 reads it without
        # creating -wal/-shm next to an archive. A -wal a writer left behind needs mode=ro
        # (and a -shm) to be read; immutable=1 is the fallback when that cannot be made.
        wal = Path(f"{path}-wal")
        has_wal = wal.exists() and wal.stat().st_size > 0
        for query in (("mode=ro", "mode=ro&immutable=1") if has_wal else ("mode=ro&immutable=1",)):
            try:
                conn = sqlite3.connect(_uri(path, query), uri=True, timeout=timeout, isolation_level=None)
                conn.execute("PRAGMA query_only = ON")
                conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
                break
            except sqlite3.Error as e:
                if conn is not None:
                    conn.close()
                conn, error = None, e
        if conn is None:
            assert error is not None
            raise _translate(error, path, timeout) from None
        db = cls(conn, path, timeout, reason)
        version = db.schema_version()
        if version != SCHEMA_VERSION:
            conn.close()
            raise AnkleScanError(f"database {path} has schema v{version} and is read-only ({reason}); "
                                 f"this AnkleScan needs v{SCHEMA_VERSION}: open a writable copy to upgrade it")
        return db

    def _claim(self) -> None:
        """Stamp our application id on a database of ours that predates it."""
        with self.errors():
            if self._conn.execute("PRAGMA application_id").fetchone()[0] != APPLICATION_ID:
                with self.transaction() as c:
                    c.execute(f"PRAGMA application_id = {APPLICATION_ID}")

    def _configure(self) -> None:
        with self.errors():
            c = self._conn
            c.execute(f"PRAGMA busy_timeout = {int(self.timeout * 1000)}")
            c.execute("PRAGMA foreign_keys = ON")

    def _enable_wal(self) -> None:
        """After the schema exists: a new file's first commit (schema + application id) is
        atomic in rollback mode, so a half-made database never looks like a foreign one."""
        with self.errors():
            c = self._conn
            mode = c.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise AnkleScanError(f"database {self.path}: cannot enable WAL journal "
                                     f"(got {mode}); is it on a network drive?")
            # FULL: in WAL mode NORMAL can lose the last commits on power loss; clinical
            # records are small, so the extra fsync is cheap.
            c.execute("PRAGMA synchronous = FULL")
            # integrity was checked read-only by _inspect before this connection existed

    def _migrate(self, target: int = SCHEMA_VERSION) -> None:
        version = self.schema_version()
        if version > SCHEMA_VERSION:
            raise AnkleScanError(f"database {self.path} has schema v{version}, newer than this "
                                 f"AnkleScan (v{SCHEMA_VERSION}); update the program")
        if version >= target:
            return
        with self.transaction() as c:
            # Re-read under the write lock: another instance may have migrated meanwhile.
            version = c.execute("PRAGMA user_version").fetchone()[0]
            if version == 0:
                c.execute(f"PRAGMA application_id = {APPLICATION_ID}")  # with the first schema
            for v in range(version, target):
                for stmt in _statements(MIGRATIONS[v]):
                    c.execute(stmt)
                c.execute(f"PRAGMA user_version = {v + 1}")

    def schema_version(self) -> int:
        with self.errors():
            version: int = self._conn.execute("PRAGMA user_version").fetchone()[0]
            return version

    def close(self) -> None:
        self._conn.close()

    # ------------------------------------------------------------ transactions and queries

    @contextmanager
    def errors(self) -> Iterator[None]:
        """SQLite's failures as one clear AnkleScanError line (``_translate``)."""
        try:
            yield
        except sqlite3.Error as e:
            raise _translate(e, self.path, self.timeout) from None

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: all of it is committed, or none of it.

        Nested, it joins the transaction already open (the unit of work): only the outermost
        commits, and a failure anywhere inside rolls all of it back, even if a caller in between
        caught the error."""
        self.require_writable()
        if self._depth:
            self._depth += 1
            try:
                yield self._conn
            except BaseException:
                self._doomed = True
                raise
            finally:
                self._depth -= 1
            return
        with self.errors():
            self._conn.execute("BEGIN IMMEDIATE")
            self._depth, self._doomed = 1, False
            try:
                yield self._conn
                if self._doomed:
                    raise AnkleScanError("a change inside the transaction failed; none of it was saved")
                self._conn.execute("COMMIT")
            except BaseException:
                if self._conn.in_transaction:
                    self._conn.execute("ROLLBACK")
                raise
            finally:
                self._depth, self._doomed = 0, False

    def one(self, sql: str, args: Params = ()) -> sqlite3.Row | None:
        """The first row of a query (columns by name), or None."""
        with self.errors():
            cur = self._conn.execute(sql, args)
            cur.row_factory = sqlite3.Row
            row: sqlite3.Row | None = cur.fetchone()
            return row

    def all(self, sql: str, args: Params = ()) -> list[sqlite3.Row]:
        """Every row of a query (columns by name)."""
        with self.errors():
            cur = self._conn.execute(sql, args)
            cur.row_factory = sqlite3.Row
            rows: list[sqlite3.Row] = cur.fetchall()
            return rows
