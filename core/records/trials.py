"""Trials (table ``trials``), their marks (table ``marks``) and their files on disk.

- ``TrialRepository``: a trial's row: created with its reference angles and state, then its
  state, exclusion, motion, simulated flag and the angles it was measured at (``TrialAngles``,
  computed by the caller: ``core/records/trial_results.py``).
- ``MarkRepository``: the seven marks' stored positions, SD and warning.
- ``TrialFiles``: where a trial's capture and cloud live in the data folder, their sha256 as
  recorded, and whether they still match.

The SQL is here; nothing here computes an angle.
"""

from __future__ import annotations

import hashlib
import sqlite3
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Protocol

from anklescan.core.atomic import make_private_dir
from anklescan.core.errors import AnkleScanError
from anklescan.core.records.calibrations import CalibrationRepository
from anklescan.core.records.database import Database
from anklescan.core.records.events import EventLog
from anklescan.core.records.fields import now, opt_float
from anklescan.core.records.sessions import SessionRepository
from anklescan.core.vocabulary import (
    MARK_SOURCES,
    TRIAL_STATES,
    MarkLabel,
    MarkRecord,
    MarkSource,
    Trial,
    TrialAngles,
    TrialState,
    parse_label,
)

MOTION_THRESHOLD_MM = 0.5  # default; the app's setting overrides it per call
Xyz = tuple[float, float, float]


def check_state(status: TrialState | str) -> TrialState:
    """The trial state ``status`` names, or one clear error."""
    if status not in TRIAL_STATES:
        raise AnkleScanError(f"trial state must be one of {', '.join(TRIAL_STATES)}, got {status!r}")
    return TrialState(status)


def _trial(row: sqlite3.Row) -> Trial:
    d = dict(row)
    for k in ("motion_flagged", "motion_keep", "simulated"):
        d[k] = bool(d.get(k) or 0)
    d["status"] = TrialState(str(d["status"]))
    return Trial(**d)  # the table's columns are Trial's fields


# ----------------------------------------------------------------- files

class _Hash(Protocol):
    def update(self, data: bytes, /) -> None: ...


def sha256_path(path: str | Path) -> str:
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


def _hash_file(p: Path, h: _Hash) -> None:
    try:
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        raise AnkleScanError(f"cannot read {p}: {e.strerror or e}") from None


class TrialFiles:
    """A trial's capture folder and cloud: ``data_dir/patients/<code>/session-<id>/trial-<id>``,
    stored relative to the data folder (so it can be moved as a whole) with their sha256."""

    def __init__(self, db: Database, data_dir: Path):
        self._db = db
        self.data_dir = data_dir

    def relative(self, p: Path) -> str:
        """How a path is stored: relative to the data folder when inside it, else absolute."""
        try:
            return p.resolve().relative_to(self.data_dir.resolve()).as_posix()
        except ValueError:
            return str(p.resolve())

    def resolve(self, stored_path: str) -> Path:
        """Absolute path of a capture/cloud path as stored in a trial."""
        p = Path(stored_path)
        return p if p.is_absolute() else self.data_dir / p

    def columns(self, *, capture: Path | None = None, cloud: Path | None = None, capture_sha256: str = "",
                cloud_sha256: str = "") -> dict[str, str]:
        """The trial columns recording these files: path and sha256 (a hash already made, by the
        scan's worker thread, is taken as given)."""
        cols: dict[str, str] = {}
        known = {"capture": capture_sha256, "cloud": cloud_sha256}
        for name, p in (("capture", capture), ("cloud", cloud)):
            if p is not None:
                cols[f"{name}_sha256"] = known[name] or sha256_path(p)
                cols[f"{name}_path"] = self.relative(Path(p))
        return cols

    def trial_dir(self, trial_id: int, create: bool = False) -> Path:
        """``data_dir/patients/<code>/session-<id>/trial-<id>``: where its files belong."""
        if create:
            self._db.require_writable()
        row = self._db.one(
            "SELECT p.code, s.id AS sid FROM trials t JOIN sessions s ON s.id = t.session_id"
            " JOIN patients p ON p.id = s.patient_id WHERE t.id = ?", (trial_id,))
        if row is None:
            raise AnkleScanError(f"no trial {trial_id}")
        d = self.data_dir / "patients" / str(row["code"]) / f"session-{row['sid']}" / f"trial-{trial_id}"
        if create:
            try:
                # patients/<code>/session-<id>/trial-<id>: each level private (0700)
                for level in (d.parents[2], d.parents[1], d.parents[0], d):
                    make_private_dir(level)
            except OSError as e:
                raise AnkleScanError(f"cannot create {d}: {e.strerror or e}") from None
        return d

    def verify(self, trial: Trial) -> list[str]:
        """Problems with the trial's stored files (missing or changed); [] if all good."""
        problems = []
        for name, rel, digest in (("capture", trial.capture_path, trial.capture_sha256),
                                  ("cloud", trial.cloud_path, trial.cloud_sha256)):
            if rel is None:
                continue
            p = self.resolve(rel)
            if not p.exists():
                problems.append(f"{name} {p} is missing")
            elif sha256_path(p) != digest:
                problems.append(f"{name} {p} has changed since it was recorded")
        return problems


# ----------------------------------------------------------------- trials

class TrialRepository:
    """The ``trials`` table."""

    def __init__(self, db: Database, sessions: SessionRepository, calibrations: CalibrationRepository,
                 files: TrialFiles, events: EventLog):
        self._db = db
        self._sessions = sessions
        self._calibrations = calibrations
        self._files = files
        self._events = events

    def add(self, session_id: int, *, ref_inversion: float | None, ref_plantar_flexion: float | None,
            notes: str = "", calibration_id: int | None = None,
            status: TrialState | str = TrialState.COMPLETE) -> Trial:
        """A trial with the operator's reference-table set angles (degrees), the calibration
        it is measured with and its state (a scan in progress starts as ``scanning``)."""
        session = self._sessions.get(session_id)
        ri = opt_float(ref_inversion, "reference inversion")
        rp = opt_float(ref_plantar_flexion, "reference plantar flexion")
        status = check_state(status)
        cid = session.calibration_id if calibration_id is None else calibration_id
        if cid is not None:
            self._calibrations.get(cid)
        with self._db.transaction() as c:
            tid = c.execute(
                "INSERT INTO trials (session_id, created, ref_inversion, ref_plantar_flexion,"
                " notes, calibration_id, status) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (session_id, now(), ri, rp, notes or "", cid, status)).lastrowid
        assert tid is not None
        return self.get(tid)

    def get(self, tid: int) -> Trial:
        row = self._db.one("SELECT * FROM trials WHERE id = ?", (tid,))
        if row is None:
            raise AnkleScanError(f"no trial {tid}")
        return _trial(row)

    def all(self, session_id: int) -> list[Trial]:
        """A session's trials, in the order they were made."""
        rows = self._db.all("SELECT * FROM trials WHERE session_id = ? ORDER BY id", (session_id,))
        return [_trial(r) for r in rows]

    def _update(self, trial_id: int, cols: Mapping[str, object]) -> None:
        if cols:
            with self._db.transaction() as c:
                c.execute(f"UPDATE trials SET {', '.join(f'{k} = ?' for k in cols)} WHERE id = ?",
                          (*cols.values(), trial_id))

    def set_simulated(self, trial_id: int, simulated: bool = True) -> Trial:
        """Record that the trial was scanned on the simulated rig (a simulated patient)."""
        t = self.get(trial_id)
        self._update(t.id, {"simulated": int(bool(simulated))})
        return self.get(t.id)

    def set_status(self, trial_id: int, status: TrialState | str, note: str = "", *, who: str = "") -> Trial:
        """Move a trial to ``complete``, ``cancelled`` or ``failed`` (with a short note why)."""
        status = check_state(status)
        t = self.get(trial_id)
        with self._db.transaction():
            self._update(t.id, {"status": status, "status_note": note or ""})
            self._events.log(status, "trial", t.id, note, who)
        return self.get(t.id)

    def exclude(self, trial_id: int, reason: str, *, who: str = "") -> Trial:
        """Leave a trial out of the statistics and plots, with the clinician's reason."""
        reason = (reason or "").strip()
        if not reason:
            raise AnkleScanError("a reason is needed to exclude a trial")
        t = self.get(trial_id)
        with self._db.transaction():
            self._update(t.id, {"excluded_reason": reason})
            self._events.log("excluded", "trial", t.id, reason, who)
        return self.get(t.id)

    def restore(self, trial_id: int, *, who: str = "") -> Trial:
        """Undo an exclusion."""
        t = self.get(trial_id)
        with self._db.transaction():
            self._update(t.id, {"excluded_reason": None})
            self._events.log("restored", "trial", t.id, t.excluded_reason or "", who)
        return self.get(t.id)

    def set_motion(self, trial_id: int, motion_mm: float | None, motion_sd_mm: float | None = None, *,
                   scan_duration_s: float | None = None, threshold_mm: float = MOTION_THRESHOLD_MM) -> Trial:
        """Record how far the subject moved during the trial's scan (None: not measured) and the
        scan's duration; a trial that moved more than ``threshold_mm`` is flagged, which takes it
        out of the session statistics until ``keep`` says otherwise."""
        self.get(trial_id)
        mm = opt_float(motion_mm, "motion")
        sd = opt_float(motion_sd_mm, "motion SD")
        dur = opt_float(scan_duration_s, "scan duration")
        thr = opt_float(threshold_mm, "motion threshold")
        if thr is None or thr <= 0:
            raise AnkleScanError(f"motion threshold must be a positive number of mm, got {threshold_mm!r}")
        if (mm is not None and mm < 0) or (sd is not None and sd < 0) or (dur is not None and dur < 0):
            raise AnkleScanError("motion, its SD and the scan duration cannot be negative")
        self._update(trial_id, {"motion_mm": mm, "motion_sd_mm": sd, "scan_duration_s": dur,
                                "motion_flagged": int(mm is not None and mm > thr)})
        return self.get(trial_id)

    def keep(self, trial_id: int, keep: bool = True, *, who: str = "") -> Trial:
        """The clinician's override: keep a trial flagged for motion in the statistics (or not)."""
        t = self.get(trial_id)
        with self._db.transaction():
            self._update(t.id, {"motion_keep": int(bool(keep))})
            self._events.log("kept" if keep else "unkept", "trial", t.id, f"moved {t.motion_mm} mm", who)
        return self.get(trial_id)

    def set_files(self, trial_id: int, *, capture: Path | None = None, cloud: Path | None = None,
                  capture_sha256: str = "", cloud_sha256: str = "") -> Trial:
        """Record a capture folder and/or cloud file with its sha256 (``TrialFiles.columns``)."""
        self.get(trial_id)
        self._update(trial_id, self._files.columns(capture=capture, cloud=cloud, capture_sha256=capture_sha256,
                                                   cloud_sha256=cloud_sha256))
        return self.get(trial_id)

    def set_angles(self, trial_id: int, angles: TrialAngles) -> None:
        """Store the angles a trial was measured at (every column: None clears one)."""
        self._update(trial_id, {f.name: getattr(angles, f.name) for f in fields(TrialAngles)})

    def verify_files(self, trial_id: int) -> list[str]:
        """Problems with the trial's stored files (missing or changed); [] if all good."""
        return self._files.verify(self.get(trial_id))


# ----------------------------------------------------------------- marks

@dataclass(frozen=True)
class MarkPosition:
    """A mark to store: its label and position (world mm), with the automatic mark's SD and
    warning (None / "" for one placed by hand)."""

    label: MarkLabel
    xyz: Xyz
    sd_mm: float | None = None
    warning: str = ""


def mark_position(key: MarkLabel | str, xyz: Iterable[object], sd_mm: object = None,
                  warning: str = "") -> MarkPosition:
    """A checked ``MarkPosition`` from a label and three coordinates (one clear error if not)."""
    lab = parse_label(key)
    coords = [opt_float(v, f"mark {lab} coordinate") for v in xyz]
    if len(coords) != 3 or None in coords:
        raise AnkleScanError(f"mark {lab} must have 3 coordinates")
    x, y, z = (float(c or 0.0) for c in coords)
    return MarkPosition(lab, (x, y, z), opt_float(sd_mm, f"mark {lab} SD"), str(warning or ""))


def mark_source(source: MarkSource | str) -> MarkSource:
    """The mark source ``source`` names, or one clear error."""
    if source not in MARK_SOURCES:
        raise AnkleScanError(f"mark source must be 'auto' or 'manual', got {source!r}")
    return MarkSource(source)


class MarkRepository:
    """The ``marks`` table: at most one of each label 1-7 per trial."""

    def __init__(self, db: Database, trials: TrialRepository):
        self._db = db
        self._trials = trials

    def put(self, trial_id: int, marks: Sequence[MarkPosition], source: MarkSource, placed_by: str = "",
            *, with_quality: bool = False) -> None:
        """Insert or replace marks; ``with_quality`` also writes their SD and warning (an automatic
        mark as the measurement found it), else those columns keep their default."""
        stamp = now()
        with self._db.transaction() as c:
            if with_quality:
                c.executemany(
                    "INSERT OR REPLACE INTO marks (trial_id, label, x, y, z, source, placed_by, updated, sd_mm,"
                    " warning) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    [(trial_id, m.label, *m.xyz, source, placed_by or "", stamp, m.sd_mm, m.warning) for m in marks])
            else:
                c.executemany(
                    "INSERT OR REPLACE INTO marks (trial_id, label, x, y, z, source, placed_by,"
                    " updated) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    [(trial_id, m.label, *m.xyz, source, placed_by or "", stamp) for m in marks])

    def delete(self, trial_id: int, labels: Iterable[MarkLabel]) -> None:
        with self._db.transaction() as c:
            c.executemany("DELETE FROM marks WHERE trial_id = ? AND label = ?",
                          [(trial_id, int(lab)) for lab in labels])

    def set_quality(self, trial_id: int, quality: Mapping[MarkLabel | str, tuple[object, str]]) -> list[MarkRecord]:
        """Keep stored marks' position SD (mm) and warning: label → (sd_mm or None, warning)."""
        self._trials.get(trial_id)
        rows = [(opt_float(sd, f"mark {key} SD"), str(warning or ""), trial_id, parse_label(key))
                for key, (sd, warning) in quality.items()]
        with self._db.transaction() as c:
            c.executemany("UPDATE marks SET sd_mm = ?, warning = ? WHERE trial_id = ? AND label = ?", rows)
        return self.all(trial_id)

    def positions(self, trial_id: int) -> dict[MarkLabel, Xyz]:
        """label → (x, y, z) mm of every stored mark of the trial (in the caller's transaction)."""
        return {int(r["label"]): (r["x"], r["y"], r["z"])
                for r in self._db.all("SELECT label, x, y, z FROM marks WHERE trial_id = ?", (trial_id,))}

    def all(self, trial_id: int) -> list[MarkRecord]:
        """The trial's stored marks, by label."""
        rows = self._db.all("SELECT * FROM marks WHERE trial_id = ? ORDER BY label", (trial_id,))
        return [MarkRecord(**{**dict(r), "source": MarkSource(r["source"])}) for r in rows]
