"""Patients, sessions and trials, the accepted calibration, and who is measuring.

``SessionLogic`` owns the sessions database of the data folder and every write the windows ask
for. A write that fails leaves the database as it was and is reported through ``notice``
(kind, text) — the windows show it in their banner; nothing here raises into the UI.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from anklescan.app.logic.events import Event
from anklescan.app.logic.settings import AppSettings
from anklescan.core.vocabulary import Patient, Session, Severity, StudyRow, Trial

if TYPE_CHECKING:
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.records.lock import DataFolderLock, LockHolder
    from anklescan.core.records.store import Store

T = TypeVar("T")


class SessionLogic:
    settings: AppSettings  # app.settings.Settings, or app.logic.settings.MemorySettings

    def __init__(self, settings: AppSettings) -> None:
        self.settings = settings
        self.store: Store | None = None
        self.folder: Path | None = None
        self.calibration: Calibration | None = None  # the accepted calibration scans are measured with (None: blocked)
        self.calibration_id: int | None = None  # its row in this data folder's database
        self.notice: Event[[Severity, str]] = Event()  # (kind, text)
        self.storeOpened: Event[[]] = Event()  # after a (re)open, the lists must be rebuilt
        # asked when another AnkleScan holds the data folder: the message -> open it read-only?
        # (the window asks the user; None: refuse to open it)
        self.ask_read_only: Callable[[str], bool] | None = None
        self._lock: DataFolderLock | None = None  # the open folder's

    # ---- the database -----------------------------------------------------------------
    def open_store(self, folder: Path) -> None:
        from anklescan.core.records.store import Store
        if self.store is not None:
            self.store.close()
            self.store = None
        self._release_lock()
        self.folder = Path(folder)
        try:
            holder = self._lock_folder(self.folder)
            if holder is not None:
                text = (f"The data folder {self.folder} is in use by {holder.describe()}. Two copies writing "
                        "one folder could lose a clinic's data.")
                if self.ask_read_only is None or not self.ask_read_only(text):
                    self.notice.emit(Severity.ERROR, f"{text} It was not opened: close the other AnkleScan first.")
                    self.storeOpened.emit()
                    return
                self.store = Store.open(data_dir=self.folder, read_only=True)
                self.notice.emit(Severity.WARNING, f"{text} Opened read-only: you can review it, but changes "
                                 "cannot be saved.")
                self.storeOpened.emit()
                return
            self.store = store = Store.open(data_dir=self.folder)
            if store.read_only:
                self.notice.emit(Severity.WARNING,
                                 f"The sessions database is read-only ({store.read_only_reason}): "
                                 "you can review it, but changes cannot be saved.")
        except Exception as exc:
            self.store = None
            self.notice.emit(Severity.ERROR, f"The sessions database could not be opened: {exc}")
        self.storeOpened.emit()

    def close(self) -> None:
        if self.store is not None:
            self.store.close()
            self.store = None
        self._release_lock()

    def _lock_folder(self, folder: Path) -> LockHolder | None:
        """Take the folder's single-instance lock; the other holder (LockHolder) when in use."""
        import os

        from anklescan.core.atomic import make_private_dir
        from anklescan.core.records.lock import DataFolderLock
        from anklescan.core.records.store import DB_FILENAME
        db = folder / DB_FILENAME
        try:
            if db.exists() and not (db.stat().st_mode & 0o222 and os.access(db, os.W_OK)):
                return None  # opened read-only anyway: nothing to guard, and the folder is left as it is
            make_private_dir(folder, tighten=False)
        except OSError:
            return None  # cannot be created: Store.open says why
        lock = DataFolderLock(folder)
        holder = lock.acquire()
        if holder is None:
            self._lock = lock
        return holder

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    @property
    def read_only(self) -> bool:
        return self.store is not None and self.store.read_only

    @property
    def read_only_reason(self) -> str:
        return self.store.read_only_reason if self.store is not None and self.store.read_only else ""

    @property
    def writable(self) -> bool:
        return self.store is not None and not self.store.read_only

    def _open(self) -> Store:
        """The open database, where the windows reach only with one open (``_write`` reports the error)."""
        if self.store is None:
            raise RuntimeError("no sessions database is open")
        return self.store

    def _write(self, what: str, write: Callable[[], T]) -> T | None:
        """Run one database write; on failure say so (``what`` begins the message) and return None."""
        try:
            return write()
        except Exception as exc:
            self.notice.emit(Severity.ERROR, f"{what}: {exc}" if what else str(exc))
            return None

    # ---- reading ----------------------------------------------------------------------
    def patients(self, include_archived: bool = False) -> list[Patient]:
        return [] if self.store is None else self.store.patients.all(include_archived=include_archived)

    def sessions(self, patient_id: int | None, include_archived: bool = False) -> list[Session]:
        if self.store is None or patient_id is None:
            return []
        return self.store.sessions.all(patient_id, include_archived=include_archived)

    def trials(self, session_id: int | None) -> list[Trial]:
        return [] if self.store is None or session_id is None else self.store.trials.all(session_id)

    def trial(self, trial_id: int | None) -> Trial | None:
        return None if self.store is None or trial_id is None else self.store.trials.get(int(trial_id))

    def session(self, session_id: int | None) -> Session | None:
        return None if self.store is None or session_id is None else self.store.sessions.get(session_id)

    def existing_patient(self, code: str) -> Patient | None:
        """The patient (archived ones too) that a new ``code`` would duplicate, or None. Codes are
        compared without case: "p-017" typed for P-017 would split one patient's records in two."""
        wanted = code.strip().casefold()
        return next((p for p in self.patients(include_archived=True) if p.code.casefold() == wanted), None)

    def session_title(self, session_id: int) -> str:
        store = self._open()
        s = store.sessions.get(session_id)
        return f"{store.patients.get(s.patient_id).code}, {s.condition}, {s.date}"

    def session_rows(self, session_id: int | None) -> list[StudyRow]:
        if self.store is None or session_id is None:
            return []
        return [r for r in self.store.reports.study_rows() if r.session_id == session_id]

    # ---- patients and sessions --------------------------------------------------------
    def require_store(self) -> bool:
        """True when there is a database to write to; otherwise say how to get one."""
        if self.store is None:
            self.notice.emit(Severity.ERROR, "No sessions database: choose a data folder first (File ▸ Data folder).")
        return self.store is not None

    def add_patient(self, code: str, sprain_count: int = 0, side: str | None = None,
                    last_sprain: str | None = None) -> Patient | None:
        if not self.require_store():
            return None
        return self._write("", lambda: self._open().patients.add(code, sprain_count=sprain_count, affected_side=side,
                                                                last_sprain=last_sprain))

    def start_session(self, patient_id: int | None, condition: str) -> Session | None:
        if patient_id is None or self.store is None:
            self.notice.emit(Severity.WARNING, "Select or add a patient first (File ▸ New patient…).")
            return None
        if not self.operator:  # the question was cancelled: a session nobody signed is not started
            self.notice.emit(Severity.WARNING, "No session was started: a session is signed by who measures. "
                             "Enter your name or initials (File ▸ Operator…), then start the session.")
            return None
        return self._write("The session could not be started", lambda: self._open().sessions.start(
            patient_id, condition=condition, calibration_id=self.calibration_id, operator=self.operator))

    def set_mark_diameter(self, session_id: int | None, value: float | None) -> bool:
        """Keep the marks' diameter with the session (None: measured from each scan)."""
        if session_id is None or self.store is None or self.store.read_only:  # not writable
            return True
        store = self.store
        if store.sessions.get(session_id).mark_diameter_mm == value:
            return True
        done = self._write("The mark diameter could not be saved",
                           lambda: store.sessions.set_mark_diameter(session_id, value) or True)
        return bool(done)

    @property
    def operator(self) -> str:
        return self.settings.operator

    def set_operator(self, name: str) -> None:
        if name.strip():
            self.settings.operator = name.strip()

    # ---- trial states -----------------------------------------------------------------
    def exclude_trial(self, trial_id: int, reason: str) -> bool:
        if not reason.strip():
            self.notice.emit(Severity.WARNING, "A trial is excluded only with a reason; nothing was changed.")
            return False
        done = self._write("", lambda: self._open().trials.exclude(trial_id, reason, who=self.operator) or True)
        return done is not None

    def restore_trial(self, trial_id: int) -> bool:
        """Undo an exclusion; for a trial flagged because the patient moved, keep it in the statistics."""
        store = self._open()
        write: Callable[[], Trial]
        if store.trials.get(trial_id).excluded_reason is not None:
            write = lambda: store.trials.restore(trial_id, who=self.operator)  # noqa: E731
        else:
            write = lambda: store.trials.keep(trial_id, who=self.operator)  # noqa: E731
        return self._write("", lambda: write() or True) is not None

    def can_exclude(self, trial: Trial | None) -> bool:
        return bool(trial and self.writable and trial.excluded_reason is None)

    def can_restore(self, trial: Trial | None) -> bool:
        return bool(trial and self.writable and (trial.excluded_reason is not None or trial.excluded_for_motion))

    def archive_session(self, session_id: int) -> bool:
        return self._write("", lambda: self._open().sessions.archive(session_id, who=self.operator) or True) is not None

    def archive_patient(self, patient_id: int) -> bool:
        return self._write("", lambda: self._open().patients.archive(patient_id, who=self.operator) or True) is not None

    # ---- the calibration --------------------------------------------------------------
    def use_calibration(self, cal: Calibration | None, cid: int | None) -> None:
        """Make ``cal`` the one scans are measured with; ``cid`` is its id where it was accepted,
        which may be another data folder's database: it is added to this one when it is not there."""
        self.calibration, self.calibration_id = cal, self._calibration_in_store(cal, cid)

    def _calibration_in_store(self, cal: Calibration | None, cid: int | None) -> int | None:
        if cal is None or self.store is None:
            return None
        from anklescan.core.calibration.model.file import calibration_to_dict
        data = calibration_to_dict(cal)
        try:
            if cid is not None and self.store.calibrations.get(cid).data == data:
                return cid
        except Exception:
            pass
        try:
            return self.store.calibrations.add(data, source="current calibration").id
        except Exception:
            return None

    def trial_calibration(self, trial: Trial, session: Session) -> Calibration | None:
        """The calibration a trial was measured with (None when unknown or unreadable)."""
        cid = trial.calibration_id or session.calibration_id
        if cid is None:
            return None
        try:
            from anklescan.core.calibration.model.file import calibration_from_dict
            return calibration_from_dict(self._open().calibrations.get(cid).data)
        except Exception:
            return None
