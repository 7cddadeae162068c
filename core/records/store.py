"""The sessions database: patients, calibrations, sessions, trials and marks (SQLite).

Design (details in docs/sessions.md):
- WAL + synchronous=FULL: readers never block the writer, and a crash or power cut leaves
  the last committed transaction; every write is one ``BEGIN IMMEDIATE … COMMIT``.
- ``BEGIN IMMEDIATE`` takes the write lock up front, so two app instances queue on the busy
  timeout instead of deadlocking when a read transaction tries to upgrade.
- The schema version lives in ``PRAGMA user_version``; ``MIGRATIONS[i]`` upgrades i → i+1,
  each applied in the same transaction as the version bump.
- We never create, repair or delete over an existing file that is not a healthy SQLite
  database: the clinic's data is worth more than a working app.
- Our database is recognised by ``PRAGMA application_id`` (set when it is created; older
  databases of ours by their schema) after opening it READ-ONLY; any other SQLite file is
  refused untouched (no WAL switch, no table, header unchanged).
- A database that cannot be written (file mode without write bits, a read-only folder or
  mount, ``read_only=True``) opens for reading: ``Store.read_only`` is True,
  ``Store.read_only_reason`` says why, and every write method raises AnkleScanError.
- Privacy: the database (and its -wal/-shm, which SQLite creates with the database's mode)
  is 0600 and the folders we create 0700, whatever the umask (core/atomic.py).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import re
import sqlite3
import stat
import urllib.parse
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import platformdirs

from anklescan.core.atomic import PRIVATE_DIR_MODE, PRIVATE_FILE_MODE, make_private, make_private_dir, make_tree_private
from anklescan.core.errors import AnkleScanError
from anklescan.core.measure.angles import DEFAULT_SIGMA_MM, JointCovariance, compute_angles, mismatch
from anklescan.core.vocabulary import (
    ANGLE_FIELDS,
    CONDITIONS,
    LABELS,
    MARK_SOURCES,
    SIDES,
    TRIAL_STATES,
    AxisSummary,
    CalibrationRecord,
    Event,
    MarkRecord,
    MarkSource,
    Patient,
    ReportInput,
    Session,
    SessionSummary,
    Trial,
    TrialState,
    parse_label,
)

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
MOTION_THRESHOLD_MM = 0.5  # default; the app's setting overrides it per call
SCHEMA_VERSION = len(MIGRATIONS)

_CODE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")
PATIENT_CODE_RULE = ("1-32 letters, digits, '.', '_' or '-', starting with a letter or digit "
                     "(a pseudonym, not a name)")


def patient_code_problem(code: str) -> str:
    """Why ``code`` is not a valid patient code, or "" when it is."""
    code = (code or "").strip()
    if not code:
        return "Enter a patient code: " + PATIENT_CODE_RULE + "."
    return "" if _CODE_RE.match(code) else f"'{code}' is not a valid code: use {PATIENT_CODE_RULE}."


# ----------------------------------------------------------------- helpers

def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def default_data_dir() -> Path:
    """ANKLESCAN_DATA if set, else the platform's per-user data folder."""
    env = os.environ.get("ANKLESCAN_DATA")
    if env:
        return Path(env).expanduser()
    return Path(platformdirs.user_data_dir("AnkleScan", appauthor=False))


def sha256_path(path) -> str:
    """sha256 of a file, or of a folder (every file's relative path and content, sorted).

    Folder hashes are independent of listing order and timestamps, so a copied capture
    folder verifies as identical.
    """
    p = Path(path)
    h = hashlib.sha256()
    if p.is_file():
        _hash_file(p, h)
    elif p.is_dir():
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            rel = f.relative_to(p).as_posix().encode()
            h.update(len(rel).to_bytes(8, "big") + rel)
            fh = hashlib.sha256()
            _hash_file(f, fh)
            h.update(fh.digest())
    else:
        raise AnkleScanError(f"cannot hash {p}: no such file or folder")
    return h.hexdigest()


def _hash_file(p: Path, h) -> None:
    try:
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        raise AnkleScanError(f"cannot read {p}: {e.strerror or e}") from None


def _date(value, what: str) -> str | None:
    if value is None or value == "":
        return None
    if isinstance(value, _dt.datetime):
        return value.date().isoformat()
    if isinstance(value, _dt.date):
        return value.isoformat()
    try:
        return _dt.date.fromisoformat(str(value).strip()).isoformat()
    except ValueError:
        raise AnkleScanError(f"{what} {value!r} is not a date (YYYY-MM-DD)") from None


def _opt_float(v, what: str) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise AnkleScanError(f"{what} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise AnkleScanError(f"{what} must be finite")
    return f


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


def _kept_rows(conn: sqlite3.Connection) -> dict[str, set[tuple]]:
    rows: dict[str, set[tuple]] = {}
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


# -------------------------------------------------------------------- a trial's end

@dataclass(frozen=True)
class TrialMotion:
    """How far the subject moved during the scan (None: not measured) and the scan's duration;
    over ``threshold_mm`` the trial is flagged (SPEC: out of the statistics unless kept)."""

    motion_mm: float | None
    motion_sd_mm: float | None = None
    duration_s: float | None = None
    threshold_mm: float = MOTION_THRESHOLD_MM


@dataclass(frozen=True)
class MarkMeasured:
    """An automatic mark as the measurement found it: position (mm), SD (mm) and warning."""

    xyz: tuple[float, float, float]
    sd_mm: float | None = None
    warning: str = ""


@dataclass(frozen=True, eq=False)
class TrialOutcome:
    """Everything a scan's end records, written by ``Store.finish_trial`` in one transaction:
    files with their hashes, motion, the automatic marks (with the joint covariance their angles'
    SD come from), the angles, and the trial's state."""

    status: str                                     # complete | failed | cancelled (TRIAL_STATES)
    note: str = ""
    capture: Path | None = None                     # the capture folder (recorded when it exists)
    cloud: Path | None = None
    capture_sha256: str = ""                        # made in the worker thread: taken as given
    cloud_sha256: str = ""
    motion: TrialMotion | None = None               # None: leave the motion columns as they are
    marks: Mapping[int, MarkMeasured] = field(default_factory=dict)  # label -> automatic mark
    joint: JointCovariance | None = None            # the marks' covariance (the angles' honest ±)


# -------------------------------------------------------------------- store

class Store:
    """One connection to the sessions database. Not shared between threads."""

    def __init__(self, conn: sqlite3.Connection, path: Path, data_dir: Path, timeout: float,
                 read_only_reason: str = ""):
        self._conn = conn
        self.path = path
        self.data_dir = data_dir
        self.timeout = timeout
        self.read_only_reason = read_only_reason  # '' when writable

    @property
    def read_only(self) -> bool:
        """True when the database was opened for reading only (``read_only_reason`` says why)."""
        return bool(self.read_only_reason)

    def _require_writable(self) -> None:
        if self.read_only:
            raise AnkleScanError(f"database {self.path} is open read-only ({self.read_only_reason}); "
                                 "editing is disabled")

    # ------------------------------------------------------------ lifecycle

    @classmethod
    def open(cls, path=None, *, data_dir=None, timeout: float = DEFAULT_TIMEOUT_S,
             read_only: bool = False) -> Store:
        """Open (creating and migrating as needed) the database.

        Files live in ``data_dir``: the argument, else the folder of an explicit ``path``,
        else ANKLESCAN_DATA, else the platform user data folder; the default database is
        ``data_dir/anklescan.sqlite``. An existing file is first inspected read-only and
        refused untouched unless it is a healthy AnkleScan database; one that cannot be
        written (or ``read_only=True``) is opened for reading with ``read_only_reason`` set.
        """
        if path is not None:
            path = Path(path).expanduser()
            data_dir = Path(data_dir) if data_dir is not None else path.parent
        else:
            data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
            path = data_dir / DB_FILENAME
        _check_header(path)
        exists = path.exists() and path.stat().st_size > 0
        if exists:
            _inspect(path, timeout)
        reason = "opened read-only on request" if read_only else _read_only_reason(path, exists)
        if reason:
            if not exists and read_only:
                raise AnkleScanError(f"database {path} does not exist (nothing to open read-only)")
            if not exists:
                raise AnkleScanError(f"cannot create database {path}: {reason}")
            return cls._open_read_only(path, data_dir, timeout, reason)
        try:
            make_private_dir(path.parent, tighten=False)
            _create_private(path)
        except OSError as e:
            raise AnkleScanError(f"cannot create database {path}: {e.strerror or e}") from None
        try:
            conn = sqlite3.connect(path, timeout=timeout, isolation_level=None)
        except sqlite3.Error as e:
            raise _translate(e, path, timeout) from None
        store = cls(conn, path, data_dir, timeout)
        try:
            store._configure()
            store._migrate()
            store._enable_wal()
            store._claim()
            patients = data_dir / "patients"
            if patients.is_dir() and stat.S_IMODE(patients.stat().st_mode) != PRIVATE_DIR_MODE:
                make_tree_private(patients)  # written by a version before files were private
        except ReadOnlyDatabaseError:
            conn.close()
            if not exists:
                raise
            return cls._open_read_only(path, data_dir, timeout, "the system refused to open it for writing")
        except BaseException:
            conn.close()
            raise
        return store

    @classmethod
    def _open_read_only(cls, path: Path, data_dir: Path, timeout: float, reason: str) -> Store:
        conn = None
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
            raise _translate(error, path, timeout) from None
        store = cls(conn, path, data_dir, timeout, reason)
        version = store.schema_version()
        if version != SCHEMA_VERSION:
            conn.close()
            raise AnkleScanError(f"database {path} has schema v{version} and is read-only ({reason}); "
                                 f"this AnkleScan needs v{SCHEMA_VERSION}: open a writable copy to upgrade it")
        return store

    def _claim(self) -> None:
        """Stamp our application id on a database of ours that predates it."""
        with self._errors():
            if self._conn.execute("PRAGMA application_id").fetchone()[0] != APPLICATION_ID:
                with self._write() as c:
                    c.execute(f"PRAGMA application_id = {APPLICATION_ID}")

    def _configure(self) -> None:
        with self._errors():
            c = self._conn
            c.execute(f"PRAGMA busy_timeout = {int(self.timeout * 1000)}")
            c.execute("PRAGMA foreign_keys = ON")

    def _enable_wal(self) -> None:
        """After the schema exists: a new file's first commit (schema + application id) is
        atomic in rollback mode, so a half-made database never looks like a foreign one."""
        with self._errors():
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
        with self._write() as c:
            # Re-read under the write lock: another instance may have migrated meanwhile.
            version = c.execute("PRAGMA user_version").fetchone()[0]
            if version == 0:
                c.execute(f"PRAGMA application_id = {APPLICATION_ID}")  # with the first schema
            for v in range(version, target):
                for stmt in _statements(MIGRATIONS[v]):
                    c.execute(stmt)
                c.execute(f"PRAGMA user_version = {v + 1}")

    def schema_version(self) -> int:
        with self._errors():
            return self._conn.execute("PRAGMA user_version").fetchone()[0]

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ transactions

    @contextmanager
    def _errors(self) -> Iterator[None]:
        try:
            yield
        except sqlite3.Error as e:
            raise _translate(e, self.path, self.timeout) from None

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: all of it is committed, or none of it."""
        self._require_writable()
        with self._errors():
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
                self._conn.execute("COMMIT")
            except BaseException:
                if self._conn.in_transaction:
                    self._conn.execute("ROLLBACK")
                raise

    def _one(self, sql: str, args=()) -> sqlite3.Row | None:
        with self._errors():
            cur = self._conn.execute(sql, args)
            cur.row_factory = sqlite3.Row
            return cur.fetchone()

    def _all(self, sql: str, args=()) -> list[sqlite3.Row]:
        with self._errors():
            cur = self._conn.execute(sql, args)
            cur.row_factory = sqlite3.Row
            return cur.fetchall()

    # ------------------------------------------------------------ patients

    def add_patient(self, code: str, *, sprain_count: int = 0, last_sprain=None,
                    affected_side: str | None = None, notes: str = "") -> Patient:
        code = (code or "").strip()
        if not _CODE_RE.match(code):
            raise AnkleScanError(f"patient code {code!r} must be 1-32 letters, digits, '.', '_' "
                                 "or '-' (a pseudonym, not a name)")
        if not isinstance(sprain_count, int) or sprain_count < 0:
            raise AnkleScanError(f"sprain count must be a whole number >= 0, got {sprain_count!r}")
        if affected_side is not None and affected_side not in SIDES:
            raise AnkleScanError(f"affected side must be one of {', '.join(SIDES)}")
        last = _date(last_sprain, "last sprain date")
        if self._one("SELECT 1 FROM patients WHERE code = ?", (code,)):
            raise AnkleScanError(f"patient code {code} already exists")
        with self._write() as c:
            pid = c.execute(
                "INSERT INTO patients (code, sprain_count, last_sprain, affected_side, notes,"
                " created) VALUES (?, ?, ?, ?, ?, ?)",
                (code, sprain_count, last, affected_side, notes or "", _now())).lastrowid
        return self.get_patient(pid)

    def get_patient(self, key: int | str) -> Patient:
        """By id (int) or pseudonymous code (str)."""
        col = "id" if isinstance(key, int) else "code"
        row = self._one(f"SELECT * FROM patients WHERE {col} = ?", (key,))
        if row is None:
            raise AnkleScanError(f"no patient {key}")
        return Patient(**dict(row))

    def list_patients(self, *, include_archived: bool = True) -> list[Patient]:
        where = "" if include_archived else " WHERE archived IS NULL"
        return [Patient(**dict(r)) for r in self._all(f"SELECT * FROM patients{where} ORDER BY code")]

    def archive_patient(self, patient: int | str, archived: bool = True, *, who: str = "") -> Patient:
        """Archive (hide from the working lists) or restore a patient; nothing is deleted."""
        p = self.get_patient(patient)
        with self._write() as c:
            c.execute("UPDATE patients SET archived = ? WHERE id = ?", (_now() if archived else None, p.id))
            _log(c, "archived" if archived else "restored", "patient", p.id, p.code, who)
        return self.get_patient(p.id)

    # ------------------------------------------------------------ calibrations

    def add_calibration(self, calibration: Mapping | str, *, rms: float | None = None,
                        source: str = "", verified: bool = False) -> CalibrationRecord:
        text = calibration if isinstance(calibration, str) else json.dumps(calibration)
        try:
            json.loads(text)
        except ValueError as e:
            raise AnkleScanError(f"calibration is not valid JSON: {e}") from None
        rms = _opt_float(rms, "calibration RMS")
        with self._write() as c:
            cid = c.execute(
                "INSERT INTO calibrations (created, json, rms, source, verified)"
                " VALUES (?, ?, ?, ?, ?)", (_now(), text, rms, source, int(verified))).lastrowid
        return self.get_calibration(cid)

    def get_calibration(self, cid: int) -> CalibrationRecord:
        row = self._one("SELECT * FROM calibrations WHERE id = ?", (cid,))
        if row is None:
            raise AnkleScanError(f"no calibration {cid}")
        d = dict(row)
        d["verified"] = bool(d["verified"])
        return CalibrationRecord(**d)

    def list_calibrations(self) -> list[CalibrationRecord]:
        """Every calibration kept, newest first (to choose the current one from)."""
        rows = self._all("SELECT * FROM calibrations ORDER BY created DESC, id DESC")
        return [CalibrationRecord(**{**dict(r), "verified": bool(r["verified"])}) for r in rows]

    def set_calibration_verified(self, cid: int, verified: bool) -> CalibrationRecord:
        """Record the outcome of a verification scan of the box for this calibration."""
        self.get_calibration(cid)
        with self._write() as c:
            c.execute("UPDATE calibrations SET verified = ? WHERE id = ?", (int(bool(verified)), cid))
        return self.get_calibration(cid)

    def delete_marks(self, trial_id: int, labels) -> list[MarkRecord]:
        """Remove marks and recompute the trial's angles from those left, in one transaction."""
        trial = self.get_trial(trial_id)
        labs = [int(x) for x in labels]
        with self._write() as c:
            c.executemany("DELETE FROM marks WHERE trial_id = ? AND label = ?", [(trial_id, lab) for lab in labs])
            left = {r[0]: r[1:] for r in c.execute("SELECT label, x, y, z FROM marks WHERE trial_id = ?", (trial_id,))}
            self._store_angles(c, trial, compute_angles(left), None)
        return self.get_marks(trial_id)

    # ------------------------------------------------------------ sessions

    def start_session(self, patient: int | str, *, condition: str, date=None,
                      operator: str = "", calibration_id: int | None = None,
                      notes: str = "") -> Session:
        if condition not in CONDITIONS:
            raise AnkleScanError(f"condition must be one of {', '.join(CONDITIONS)}, "
                                 f"got {condition!r}")
        pid = self.get_patient(patient).id
        if calibration_id is not None:
            self.get_calibration(calibration_id)
        day = _date(date, "session date") or _dt.date.today().isoformat()
        with self._write() as c:
            sid = c.execute(
                "INSERT INTO sessions (patient_id, date, operator, condition, calibration_id,"
                " notes) VALUES (?, ?, ?, ?, ?, ?)",
                (pid, day, operator or "", condition, calibration_id, notes or "")).lastrowid
        return self.get_session(sid)

    def set_session_mark_diameter(self, sid: int, mark_diameter_mm: float | None) -> Session:
        """Keep the marks' diameter with the session (None: measured from each capture)."""
        self.get_session(sid)
        if mark_diameter_mm is not None:
            d = float(mark_diameter_mm)
            if not (math.isfinite(d) and 0 < d <= 100):
                raise AnkleScanError(f"mark diameter must be a positive number of mm, got {mark_diameter_mm!r}")
            mark_diameter_mm = d
        with self._write() as c:
            c.execute("UPDATE sessions SET mark_diameter_mm = ? WHERE id = ?", (mark_diameter_mm, sid))
        return self.get_session(sid)

    def get_session(self, sid: int) -> Session:
        row = self._one("SELECT * FROM sessions WHERE id = ?", (sid,))
        if row is None:
            raise AnkleScanError(f"no session {sid}")
        return Session(**dict(row))

    def list_sessions(self, patient: int | str | None = None, *,
                      include_archived: bool = True) -> list[Session]:
        live = "" if include_archived else " AND archived IS NULL"
        if patient is None:
            rows = self._all(f"SELECT * FROM sessions WHERE 1{live} ORDER BY date, id")
        else:
            pid = self.get_patient(patient).id
            rows = self._all(f"SELECT * FROM sessions WHERE patient_id = ?{live} ORDER BY date, id",
                             (pid,))
        return [Session(**dict(r)) for r in rows]

    def archive_session(self, sid: int, archived: bool = True, *, who: str = "") -> Session:
        """Archive (hide from the working lists) or restore a session; nothing is deleted."""
        s = self.get_session(sid)
        with self._write() as c:
            c.execute("UPDATE sessions SET archived = ? WHERE id = ?", (_now() if archived else None, s.id))
            _log(c, "archived" if archived else "restored", "session", s.id, s.condition, who)
        return self.get_session(s.id)

    # ------------------------------------------------------------ trials

    def add_trial(self, session_id: int, *, ref_inversion: float | None,
                  ref_plantar_flexion: float | None, notes: str = "",
                  calibration_id: int | None = None,
                  status: TrialState | str = TrialState.COMPLETE) -> Trial:
        """A trial with the operator's reference-table set angles (degrees), the calibration
        it is measured with and its state (a scan in progress starts as ``scanning``)."""
        session = self.get_session(session_id)
        ri = _opt_float(ref_inversion, "reference inversion")
        rp = _opt_float(ref_plantar_flexion, "reference plantar flexion")
        status = _check_state(status)
        cid = session.calibration_id if calibration_id is None else calibration_id
        if cid is not None:
            self.get_calibration(cid)
        with self._write() as c:
            tid = c.execute(
                "INSERT INTO trials (session_id, created, ref_inversion, ref_plantar_flexion,"
                " notes, calibration_id, status) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (session_id, _now(), ri, rp, notes or "", cid, status)).lastrowid
        return self.get_trial(tid)

    def set_trial_simulated(self, trial_id: int, simulated: bool = True) -> Trial:
        """Record that the trial was scanned on the simulated rig (a simulated patient)."""
        t = self.get_trial(trial_id)
        with self._write() as c:
            c.execute("UPDATE trials SET simulated = ? WHERE id = ?", (int(bool(simulated)), t.id))
        return self.get_trial(t.id)

    def set_trial_status(self, trial_id: int, status: TrialState | str, note: str = "", *,
                         who: str = "") -> Trial:
        """Move a trial to ``complete``, ``cancelled`` or ``failed`` (with a short note why)."""
        status = _check_state(status)
        t = self.get_trial(trial_id)
        with self._write() as c:
            c.execute("UPDATE trials SET status = ?, status_note = ? WHERE id = ?", (status, note or "", t.id))
            _log(c, status, "trial", t.id, note, who)
        return self.get_trial(t.id)

    def exclude_trial(self, trial_id: int, reason: str, *, who: str = "") -> Trial:
        """Leave a trial out of the statistics and plots, with the clinician's reason."""
        reason = (reason or "").strip()
        if not reason:
            raise AnkleScanError("a reason is needed to exclude a trial")
        t = self.get_trial(trial_id)
        with self._write() as c:
            c.execute("UPDATE trials SET excluded_reason = ? WHERE id = ?", (reason, t.id))
            _log(c, "excluded", "trial", t.id, reason, who)
        return self.get_trial(t.id)

    def restore_trial(self, trial_id: int, *, who: str = "") -> Trial:
        """Undo an exclusion."""
        t = self.get_trial(trial_id)
        with self._write() as c:
            c.execute("UPDATE trials SET excluded_reason = NULL WHERE id = ?", (t.id,))
            _log(c, "restored", "trial", t.id, t.excluded_reason or "", who)
        return self.get_trial(t.id)

    def events(self, entity: str | None = None, entity_id: int | None = None) -> list[Event]:
        """What was done to patients, sessions and trials, oldest first."""
        sql, args = "SELECT * FROM events", []
        if entity is not None:
            sql += " WHERE entity = ?" + (" AND entity_id = ?" if entity_id is not None else "")
            args = [entity] + ([entity_id] if entity_id is not None else [])
        return [Event(**dict(r)) for r in self._all(sql + " ORDER BY id", args)]

    def get_trial(self, tid: int) -> Trial:
        row = self._one("SELECT * FROM trials WHERE id = ?", (tid,))
        if row is None:
            raise AnkleScanError(f"no trial {tid}")
        return _trial(row)

    def list_trials(self, session_id: int) -> list[Trial]:
        rows = self._all("SELECT * FROM trials WHERE session_id = ? ORDER BY id", (session_id,))
        return [_trial(r) for r in rows]

    def set_trial_motion(self, trial_id: int, motion_mm: float | None, motion_sd_mm: float | None = None, *,
                         scan_duration_s: float | None = None,
                         threshold_mm: float = MOTION_THRESHOLD_MM) -> Trial:
        """Record how far the subject moved during the trial's scan (None: not measured) and the
        scan's duration; a trial that moved more than ``threshold_mm`` is flagged, which takes it
        out of the session statistics until ``keep_trial`` says otherwise."""
        self.get_trial(trial_id)
        mm = _opt_float(motion_mm, "motion")
        sd = _opt_float(motion_sd_mm, "motion SD")
        dur = _opt_float(scan_duration_s, "scan duration")
        thr = _opt_float(threshold_mm, "motion threshold")
        if thr is None or thr <= 0:
            raise AnkleScanError(f"motion threshold must be a positive number of mm, got {threshold_mm!r}")
        if (mm is not None and mm < 0) or (sd is not None and sd < 0) or (dur is not None and dur < 0):
            raise AnkleScanError("motion, its SD and the scan duration cannot be negative")
        flagged = mm is not None and mm > thr
        with self._write() as c:
            c.execute("UPDATE trials SET motion_mm = ?, motion_sd_mm = ?, scan_duration_s = ?, motion_flagged = ?"
                      " WHERE id = ?", (mm, sd, dur, int(flagged), trial_id))
        return self.get_trial(trial_id)

    def keep_trial(self, trial_id: int, keep: bool = True, *, who: str = "") -> Trial:
        """The clinician's override: keep a trial flagged for motion in the statistics (or not)."""
        t = self.get_trial(trial_id)
        with self._write() as c:
            c.execute("UPDATE trials SET motion_keep = ? WHERE id = ?", (int(bool(keep)), trial_id))
            _log(c, "kept" if keep else "unkept", "trial", t.id, f"moved {t.motion_mm} mm", who)
        return self.get_trial(trial_id)

    def update_trial_angles(self, trial_id: int, angles: Mapping,
                            reference: Mapping | None = None) -> Trial:
        """Store measured angles (``compute_angles`` output) and the resulting mismatch.

        ``reference`` defaults to the trial's set angles; pass the scanned reference
        table's ``{"inversion": {"value", "sd"}, ...}`` when it was measured (SPEC §3).
        """
        with self._write() as c:
            self._store_angles(c, self.get_trial(trial_id), angles, reference)
        return self.get_trial(trial_id)

    def _store_angles(self, c, trial: Trial, angles: Mapping, reference) -> None:
        cols: dict[str, float | None] = {}
        for name in ANGLE_FIELDS:
            v = angles.get(name)
            cols[name] = _opt_float(v["value"], name) if v else None
            cols[f"{name}_sd"] = _opt_float(v.get("sd"), f"{name} sd") if v else None
        if reference is None and None not in (trial.ref_inversion, trial.ref_plantar_flexion):
            reference = {"inversion": trial.ref_inversion,
                         "plantar_flexion": trial.ref_plantar_flexion}
        have_table = angles.get("table_inversion") and angles.get("table_plantar_flexion")
        mm = mismatch(angles, reference) if (have_table and reference) else {}
        for axis in ("inversion", "plantar_flexion"):
            cols[f"mismatch_{axis}"] = mm[axis]["value"] if mm else None
            cols[f"mismatch_{axis}_sd"] = mm[axis]["sd"] if mm else None
        sets = ", ".join(f"{k} = ?" for k in cols)
        c.execute(f"UPDATE trials SET {sets} WHERE id = ?", (*cols.values(), trial.id))

    def set_trial_files(self, trial_id: int, *, capture=None, cloud=None,
                        capture_sha256: str = "", cloud_sha256: str = "") -> Trial:
        """Record a capture folder and/or cloud file with its sha256 (paths relative to
        the data folder when inside it, so the folder can be moved as a whole). A hash
        already made (by the scan's worker thread) is taken as given."""
        self.get_trial(trial_id)
        cols = {}
        known = {"capture": capture_sha256, "cloud": cloud_sha256}
        for name, p in (("capture", capture), ("cloud", cloud)):
            if p is not None:
                cols[f"{name}_sha256"] = known[name] or sha256_path(p)
                cols[f"{name}_path"] = self._relative(Path(p))
        if not cols:
            return self.get_trial(trial_id)
        with self._write() as c:
            sets = ", ".join(f"{k} = ?" for k in cols)
            c.execute(f"UPDATE trials SET {sets} WHERE id = ?", (*cols.values(), trial_id))
        return self.get_trial(trial_id)

    def finish_trial(self, trial_id: int, outcome: TrialOutcome, *, who: str = "") -> Trial:
        """A scan's end in ONE transaction: files and hashes, motion, the automatic marks with their
        SD and warning, the angles from them, and the state, so a trial is never left half-recorded."""
        _check_state(outcome.status)
        trial = self.get_trial(trial_id)
        files: dict[str, str] = {}
        known = {"capture": outcome.capture_sha256, "cloud": outcome.cloud_sha256}
        for name, p in (("capture", outcome.capture), ("cloud", outcome.cloud)):
            if p is not None:
                files[f"{name}_sha256"] = known[name] or sha256_path(p)
                files[f"{name}_path"] = self._relative(Path(p))
        motion = None
        if outcome.motion is not None:
            m = outcome.motion
            mm, sd = _opt_float(m.motion_mm, "motion"), _opt_float(m.motion_sd_mm, "motion SD")
            dur, thr = _opt_float(m.duration_s, "scan duration"), _opt_float(m.threshold_mm, "motion threshold")
            if thr is None or thr <= 0:
                raise AnkleScanError(f"motion threshold must be a positive number of mm, got {m.threshold_mm!r}")
            if (mm is not None and mm < 0) or (sd is not None and sd < 0) or (dur is not None and dur < 0):
                raise AnkleScanError("motion, its SD and the scan duration cannot be negative")
            motion = (mm, sd, dur, int(mm is not None and mm > thr))
        marks = []
        for key, mark in outcome.marks.items():
            lab = parse_label(key)
            xyz = [_opt_float(v, f"mark {lab} coordinate") for v in mark.xyz]
            if len(xyz) != 3 or None in xyz:
                raise AnkleScanError(f"mark {lab} must have 3 coordinates")
            marks.append((lab, xyz, _opt_float(mark.sd_mm, f"mark {lab} SD"), str(mark.warning or "")))
        joint = outcome.joint
        # the joint covariance holds the measured marks' own SD; any other mark gets the default
        sigma = {lab: 0.0 if joint is not None and lab in joint.labels else DEFAULT_SIGMA_MM for lab in LABELS}
        now = _now()
        with self._write() as c:
            if files:
                c.execute(f"UPDATE trials SET {', '.join(f'{k} = ?' for k in files)} WHERE id = ?",
                          (*files.values(), trial.id))
            if motion is not None:
                c.execute("UPDATE trials SET motion_mm = ?, motion_sd_mm = ?, scan_duration_s = ?, motion_flagged = ?"
                          " WHERE id = ?", (*motion, trial.id))
            if marks:
                c.executemany(
                    "INSERT OR REPLACE INTO marks (trial_id, label, x, y, z, source, placed_by, updated, sd_mm,"
                    " warning) VALUES (?, ?, ?, ?, ?, 'auto', '', ?, ?, ?)",
                    [(trial.id, lab, *xyz, now, sd, warning) for lab, xyz, sd, warning in marks])
                allm = {r[0]: r[1:] for r in c.execute("SELECT label, x, y, z FROM marks WHERE trial_id = ?",
                                                       (trial.id,))}
                self._store_angles(c, trial, compute_angles(allm, sigma_mm=sigma, joint=joint), None)
            c.execute("UPDATE trials SET status = ?, status_note = ? WHERE id = ?",
                      (outcome.status, outcome.note or "", trial.id))
            _log(c, outcome.status, "trial", trial.id, outcome.note, who)
        return self.get_trial(trial.id)

    def _relative(self, p: Path) -> str:
        try:
            return p.resolve().relative_to(self.data_dir.resolve()).as_posix()
        except ValueError:
            return str(p.resolve())

    def resolve(self, stored_path: str) -> Path:
        """Absolute path of a capture/cloud path as stored in a trial."""
        p = Path(stored_path)
        return p if p.is_absolute() else self.data_dir / p

    def trial_dir(self, trial_id: int, create: bool = False) -> Path:
        """``data_dir/patients/<code>/session-<id>/trial-<id>``: where its files belong."""
        if create:
            self._require_writable()
        row = self._one(
            "SELECT p.code, s.id AS sid FROM trials t JOIN sessions s ON s.id = t.session_id"
            " JOIN patients p ON p.id = s.patient_id WHERE t.id = ?", (trial_id,))
        if row is None:
            raise AnkleScanError(f"no trial {trial_id}")
        d = self.data_dir / "patients" / row["code"] / f"session-{row['sid']}" / f"trial-{trial_id}"
        if create:
            try:
                # patients/<code>/session-<id>/trial-<id>: each level private (0700)
                for level in (d.parents[2], d.parents[1], d.parents[0], d):
                    make_private_dir(level)
            except OSError as e:
                raise AnkleScanError(f"cannot create {d}: {e.strerror or e}") from None
        return d

    def verify_trial_files(self, trial_id: int) -> list[str]:
        """Problems with the trial's stored files (missing or changed); [] if all good."""
        t = self.get_trial(trial_id)
        problems = []
        for name in ("capture", "cloud"):
            rel, digest = getattr(t, f"{name}_path"), getattr(t, f"{name}_sha256")
            if rel is None:
                continue
            p = self.resolve(rel)
            if not p.exists():
                problems.append(f"{name} {p} is missing")
            elif sha256_path(p) != digest:
                problems.append(f"{name} {p} has changed since it was recorded")
        return problems

    # ------------------------------------------------------------ marks

    def update_marks(self, trial_id: int, marks: Mapping, source: MarkSource | str, placed_by: str = "",
                     *, sigma_mm=DEFAULT_SIGMA_MM, recompute: bool = True,
                     joint: JointCovariance | None = None) -> list[MarkRecord]:
        """Insert or replace marks (label → xyz mm) and, by default, recompute the trial's
        angles from all its marks in the same transaction, so stored angles never
        disagree with stored marks. ``joint``: the marks' covariance over all sources
        (``MeasureResult.position_covariance``; then ``sigma_mm`` adds to it, give 0)."""
        if source not in MARK_SOURCES:
            raise AnkleScanError(f"mark source must be 'auto' or 'manual', got {source!r}")
        source = MarkSource(source)
        trial = self.get_trial(trial_id)
        clean = {}
        for key, p in marks.items():
            lab = parse_label(key)
            xyz = [_opt_float(v, f"mark {lab} coordinate") for v in p]
            if len(xyz) != 3 or None in xyz:
                raise AnkleScanError(f"mark {lab} must have 3 coordinates")
            clean[lab] = xyz
        now = _now()
        with self._write() as c:
            c.executemany(
                "INSERT OR REPLACE INTO marks (trial_id, label, x, y, z, source, placed_by,"
                " updated) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                [(trial_id, lab, *xyz, source, placed_by or "", now) for lab, xyz in clean.items()])
            if recompute:
                allm = {r[0]: r[1:] for r in c.execute(
                    "SELECT label, x, y, z FROM marks WHERE trial_id = ?", (trial_id,))}
                self._store_angles(c, trial, compute_angles(allm, sigma_mm=sigma_mm, joint=joint), None)
        return self.get_marks(trial_id)

    def set_mark_quality(self, trial_id: int, quality: Mapping) -> list[MarkRecord]:
        """Keep stored marks' position SD (mm) and warning: label → (sd_mm or None, warning)."""
        self.get_trial(trial_id)
        rows = []
        for key, (sd, warning) in quality.items():
            rows.append((_opt_float(sd, f"mark {key} SD"), str(warning or ""), trial_id, parse_label(key)))
        with self._write() as c:
            c.executemany("UPDATE marks SET sd_mm = ?, warning = ? WHERE trial_id = ? AND label = ?", rows)
        return self.get_marks(trial_id)

    def get_marks(self, trial_id: int) -> list[MarkRecord]:
        rows = self._all("SELECT * FROM marks WHERE trial_id = ? ORDER BY label", (trial_id,))
        return [MarkRecord(**{**dict(r), "source": MarkSource(r["source"])}) for r in rows]

    # ------------------------------------------------------------ summaries

    def session_summary(self, session_id: int) -> SessionSummary:
        s = self.get_session(session_id)
        trials = self.list_trials(session_id)
        cal = self.get_calibration(s.calibration_id) if s.calibration_id else None
        counted = [t for t in trials if t.counted]
        incomplete = [t.id for t in counted if t.mismatch_inversion is None]
        moved = [t.id for t in trials if t.excluded_for_motion]
        return SessionSummary(
            session=s, patient=self.get_patient(s.patient_id), calibration=cal, trials=trials,
            inversion=_axis_summary([t.mismatch_inversion for t in counted]),
            plantar_flexion=_axis_summary([t.mismatch_plantar_flexion for t in counted]),
            incomplete_trials=incomplete, moved_trials=moved)

    def report_input(self, session_ids: Sequence[int] | None = None) -> ReportInput:
        """The records a report prints (core.records.report takes these, never the Store): every
        trial row, the patients, the calibrations the rows and sessions name, and the summaries of
        ``session_ids`` (a session report's; none for the study report)."""
        sessions = [self.session_summary(int(i)) for i in (session_ids or ())]
        rows = self.study_rows()
        cids = {r["calibration_id"] for r in rows} | {s.session.calibration_id for s in sessions}
        calibrations = {cid: self.get_calibration(cid) for cid in sorted(c for c in cids if c is not None)}
        return ReportInput(rows, self.list_patients(), calibrations, sessions)

    def study_rows(self) -> list[dict]:
        """Every trial joined with its session, patient and calibration (for stats/CSV)."""
        return [dict(r) for r in self._all(
            "SELECT p.code AS patient_code, p.sprain_count, p.last_sprain, p.affected_side,"
            " s.id AS session_id, s.date AS session_date, s.operator, s.condition,"
            " c.rms AS calibration_rms, t.id AS trial_id, t.*,"
            " COALESCE(t.calibration_id, s.calibration_id) AS calibration_id,"
            " (t.motion_flagged AND NOT t.motion_keep) AS motion_excluded,"
            " (t.status = 'complete' AND t.excluded_reason IS NULL"
            "  AND NOT (t.motion_flagged AND NOT t.motion_keep)) AS counted,"
            # automatic marks count as confirmed once an operator confirmed them (recorded in
            # placed_by, as app.mark_editor does) or moved them (source 'manual')
            " NOT EXISTS (SELECT 1 FROM marks m WHERE m.trial_id = t.id AND m.source = 'auto'"
            " AND m.placed_by NOT LIKE 'confirmed by %') AS marks_confirmed,"
            " (SELECT group_concat('mark ' || m.label || ' ' || m.warning || ' (SD ' || printf('%.2f', m.sd_mm)"
            " || ' mm)', '; ') FROM marks m WHERE m.trial_id = t.id AND m.warning != '') AS mark_warnings"
            " FROM trials t JOIN sessions s ON s.id = t.session_id"
            " JOIN patients p ON p.id = s.patient_id"
            " LEFT JOIN calibrations c ON c.id = COALESCE(t.calibration_id, s.calibration_id)"
            " ORDER BY p.code, s.date, s.id, t.id")]


def _trial(row) -> Trial:
    d = dict(row)
    for k in ("motion_flagged", "motion_keep", "simulated"):
        d[k] = bool(d.get(k) or 0)
    d["status"] = TrialState(d["status"])
    return Trial(**d)


def _axis_summary(values: list[float | None]) -> AxisSummary:
    v = [x for x in values if x is not None]
    if not v:
        return AxisSummary(0, None, None, None, None, None)
    n = len(v)
    mean = sum(v) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in v) / (n - 1)) if n > 1 else None
    return AxisSummary(n, mean, sum(abs(x) for x in v) / n, sd, min(v), max(v))


def _check_state(status: TrialState | str) -> TrialState:
    if status not in TRIAL_STATES:
        raise AnkleScanError(f"trial state must be one of {', '.join(TRIAL_STATES)}, got {status!r}")
    return TrialState(status)


def _log(c: sqlite3.Connection, kind: str, entity: str, entity_id: int, detail: str, who: str) -> None:
    c.execute("INSERT INTO events (time, kind, entity, entity_id, detail, who) VALUES (?, ?, ?, ?, ?, ?)",
              (_now(), kind, entity, entity_id, detail or "", who or ""))


def _statements(script: str) -> list[str]:
    """Split a migration script; executescript() would COMMIT our open transaction."""
    out, buf = [], ""
    for line in script.splitlines(keepends=True):
        buf += line
        if sqlite3.complete_statement(buf):
            out.append(buf.strip())
            buf = ""
    return [s for s in out if s]
