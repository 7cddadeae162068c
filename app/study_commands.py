"""``anklescan report`` and ``anklescan export`` (SPEC §6–7): the clinic's study and its exports, from a
data folder's database alone (no capture is read). The database is opened read-only: a report never
changes the records; the only file it may add to the data folder is the site's MDC (site_mdc.json)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from anklescan.app.cli_commands import Progress
from anklescan.core.errors import AnkleScanError

if TYPE_CHECKING:
    from anklescan.core.records.store import Store

T = TypeVar("T")

DEMO_DB = "anklescan.db"   # `anklescan demo --out DIR` keeps its database here, its files under DIR/data


def open_data_folder(folder: str | Path) -> Store:
    """The data folder's database, read-only: DIR/anklescan.sqlite (the app's), or a demo folder's."""
    from anklescan.core.records.store import DB_FILENAME, Store

    d = Path(folder)
    if not d.is_dir():
        raise AnkleScanError(f"data folder {d} does not exist or is not a folder")
    if (d / DB_FILENAME).is_file():
        return Store.open(d / DB_FILENAME, data_dir=d, read_only=True)
    if (d / DEMO_DB).is_file():
        return Store.open(d / DEMO_DB, data_dir=d / "data", read_only=True)
    raise AnkleScanError(f"{d} holds no AnkleScan database ({DB_FILENAME}); give the app's data folder")


def cmd_report(args: argparse.Namespace) -> int:
    from anklescan.core.records.study import StudyFilter, write_study_folder

    if args.date_from and args.date_to and args.date_from > args.date_to:
        raise AnkleScanError(f"--from {args.date_from} is after --to {args.date_to}")
    progress = Progress(args.quiet)
    flt = StudyFilter(args.patient, args.date_from, args.date_to)
    with open_data_folder(args.data) as store:
        data = store.reports.report_input()
    out = write_study_folder(data, Path(args.out), flt, data_dir=Path(args.data), progress=progress,
                             keep_site_mdc=True)
    kept = f"; the site's MDC kept in {out.site_mdc_path}" if out.site_mdc_path else ""
    print(f"wrote the study of {out.trials} trials ({flt.text()}) to {out.folder}: report.pdf ({out.pages} pages), "
          f"trials.csv, trials.xlsx, data_dictionary.csv, position_sense.csv, reliability.csv{kept}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from anklescan.core.records import tables

    out = Path(args.out)
    if not out.parent.is_dir():
        raise AnkleScanError(f"output folder {out.parent} does not exist")
    if out.is_dir():
        raise AnkleScanError(f"--out {out} is a folder; give a file name")
    with open_data_folder(args.data) as store:
        if args.format == "c3d":
            if args.trial is None:
                raise AnkleScanError("--format c3d exports one trial's marks: give --trial N")
            from anklescan.core.records.c3d import write_c3d

            trial = _get(store.trials.get, args.trial, "trial")
            marks = {m.label: (m.x, m.y, m.z) for m in store.marks.all(trial.id)}
            if not marks:
                raise AnkleScanError(f"trial {trial.id} has no marks (state {trial.status}); nothing to export")
            session = store.sessions.get(trial.session_id)
            patient = store.patients.get(session.patient_id)
            n = write_c3d(marks, out, description=patient.code)
            # a trial the statistics leave out is still exported (its marks are what they are), but said so
            aside = "" if trial.counted else f"; the trial is not counted in the statistics ({trial.state_text})"
            print(f"wrote trial {trial.id}'s marks ({n} of 7, mm, labels 1-7) as C3D to {out}{aside}")
            return 0
        from anklescan.core.records.fhir import session_bundle, write_bundle

        if args.trial is not None:
            trial = _get(store.trials.get, args.trial, "trial")
            sid, only = trial.session_id, {trial.id}
        else:
            sid, only = _get(store.sessions.get, args.session, "session").id, None
        session = store.sessions.get(sid)
        patient = store.patients.get(session.patient_id)
        rows = [r for r in store.reports.study_rows() if r.session_id == sid and (only is None or r.trial_id in only)]
    bundle = session_bundle(tables.trial_rows(rows), patient.code, patient.affected_side)
    write_bundle(bundle, out)
    print(f"wrote a FHIR R4 Bundle of {len(bundle['entry']) - 1} Observation(s) (session {sid}) to {out}")
    return 0


def _get(getter: Callable[[int], T], key: int, what: str) -> T:
    try:
        return getter(key)
    except (KeyError, LookupError, AnkleScanError):
        raise AnkleScanError(f"no {what} {key} in the database") from None
