"""The records' composition root: ``Store.open`` opens the data folder's database and wires its
repositories. A ``Store`` holds no SQL and computes nothing; it is the one object the app passes
around, and each attribute owns one part:

=================  ==========================================================  =====================
attribute          what it owns                                                module
=================  ==========================================================  =====================
``db``             the file: opening safely, migrations, transactions          ``database.py``
``patients``       patients (pseudonymous codes), archiving                    ``patients.py``
``calibrations``   calibrations kept, verified or not                          ``calibrations.py``
``sessions``       a patient's visits, condition, mark diameter, archiving     ``sessions.py``
``trials``         a trial's row: state, exclusion, motion, files, angles      ``trials.py``
``marks``          the seven marks of a trial                                  ``trials.py``
``files``          where a trial's capture and cloud live, their sha256        ``trials.py``
``results``        marks + the angles from them (and a scan's end) in one tx   ``trial_results.py``
``events``         what was done, by whom                                      ``events.py``
``reports``        the study rows, session summaries and ``ReportInput``       ``report_data.py``
=================  ==========================================================  =====================

The daily checks (``daily_checks.py``) are functions over ``store.db``. Several repositories'
writes are one unit of work inside ``with store.db.transaction(): …`` (transactions nest).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from types import TracebackType

import platformdirs

from anklescan.core.atomic import PRIVATE_DIR_MODE, make_tree_private
from anklescan.core.records.calibrations import CalibrationRepository
from anklescan.core.records.database import (
    APPLICATION_ID,
    DB_FILENAME,
    DEFAULT_TIMEOUT_S,
    MIGRATIONS,
    SCHEMA_VERSION,
    Database,
    ReadOnlyDatabaseError,
)
from anklescan.core.records.events import EventLog
from anklescan.core.records.patients import PATIENT_CODE_RULE, PatientRepository, patient_code_problem
from anklescan.core.records.report_data import ReportData
from anklescan.core.records.sessions import SessionRepository
from anklescan.core.records.trial_results import MarkMeasured, TrialMotion, TrialOutcome, TrialResults
from anklescan.core.records.trials import (
    MOTION_THRESHOLD_MM,
    MarkRepository,
    TrialFiles,
    TrialRepository,
    sha256_path,
)

__all__ = ["APPLICATION_ID", "DB_FILENAME", "MIGRATIONS", "MOTION_THRESHOLD_MM", "PATIENT_CODE_RULE",
           "SCHEMA_VERSION", "MarkMeasured", "ReadOnlyDatabaseError", "Store", "TrialMotion", "TrialOutcome",
           "default_data_dir", "patient_code_problem", "sha256_path"]


def default_data_dir() -> Path:
    """ANKLESCAN_DATA if set, else the platform's per-user data folder."""
    env = os.environ.get("ANKLESCAN_DATA")
    if env:
        return Path(env).expanduser()
    return Path(platformdirs.user_data_dir("AnkleScan", appauthor=False))


class Store:
    """A data folder's records: its database and the repositories over it. Not shared between threads."""

    def __init__(self, db: Database, data_dir: Path):
        self.db = db
        self.data_dir = data_dir
        self.events = EventLog(db)
        self.patients = PatientRepository(db, self.events)
        self.calibrations = CalibrationRepository(db)
        self.sessions = SessionRepository(db, self.patients, self.calibrations, self.events)
        self.files = TrialFiles(db, data_dir)
        self.trials = TrialRepository(db, self.sessions, self.calibrations, self.files, self.events)
        self.marks = MarkRepository(db, self.trials)
        self.results = TrialResults(db, self.trials, self.marks, self.events)
        self.reports = ReportData(db, self.patients, self.calibrations, self.sessions, self.trials)

    @classmethod
    def open(cls, path: str | os.PathLike[str] | None = None, *, data_dir: str | os.PathLike[str] | None = None,
             timeout: float = DEFAULT_TIMEOUT_S, read_only: bool = False) -> Store:
        """Open (creating and migrating as needed) the data folder's database (``Database.open``).

        Files live in ``data_dir``: the argument, else the folder of an explicit ``path``,
        else ANKLESCAN_DATA, else the platform user data folder; the default database is
        ``data_dir/anklescan.sqlite``. One that cannot be written (or ``read_only=True``) is
        opened for reading with ``read_only_reason`` set.
        """
        if path is not None:
            db_path = Path(path).expanduser()
            folder = Path(data_dir) if data_dir is not None else db_path.parent
        else:
            folder = Path(data_dir) if data_dir is not None else default_data_dir()
            db_path = folder / DB_FILENAME
        db = Database.open(db_path, timeout=timeout, read_only=read_only)
        if not db.read_only:
            try:
                patients = folder / "patients"
                if patients.is_dir() and stat.S_IMODE(patients.stat().st_mode) != PRIVATE_DIR_MODE:
                    make_tree_private(patients)  # written by a version before files were private
            except BaseException:
                db.close()
                raise
        return cls(db, folder)

    @property
    def path(self) -> Path:
        return self.db.path

    @property
    def timeout(self) -> float:
        return self.db.timeout

    @property
    def read_only(self) -> bool:
        """True when the database was opened for reading only (``read_only_reason`` says why)."""
        return self.db.read_only

    @property
    def read_only_reason(self) -> str:
        return self.db.read_only_reason

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
