"""Never lose a clinic's data (issue 40): each class of the third battery as a user meets it,
through the command line (real subprocesses or ``cli.main``) and the database's open path.

Every refused case: exit 2, one line naming the problem, nothing written, deleted or changed."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sqlite3
import stat
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.app import cli
from anklescan.core.atomic import (
    STALE_TEMP_AGE_S,
    TEMP_MARKER,
    WriteError,
    atomic_paths,
    check_may_replace,
    claim_output_dir,
    clean_stale_temporaries,
    is_output_of,
    seal_output_dir,
)
from anklescan.core.errors import AnkleScanError
from anklescan.core.limits import Bounded, DateType, SizeType
from anklescan.core.records.lock import DataFolderLock
from anklescan.core.records.store import APPLICATION_ID, SCHEMA_VERSION, Store

ROOT = Path(__file__).resolve().parents[1]


def run(*args, umask: int | None = None, cwd=ROOT) -> subprocess.CompletedProcess:
    pre = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300, preexec_fn=pre)


def assert_refused(done: subprocess.CompletedProcess, *words: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for w in words:
        assert w.lower() in lines[0].lower(), (w, lines[0])


def tree(folder: Path) -> dict[str, tuple[int, str]]:
    """Every entry under ``folder``: its mode and content hash (a folder: 'dir')."""
    out = {}
    for p in sorted(folder.rglob("*")):
        mode = stat.S_IMODE(p.lstat().st_mode)
        content = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
        out[p.relative_to(folder).as_posix()] = (mode, content)
    return out


# ---------------------------------------------------------------- output folders
def _earlier_demo(out: Path) -> None:
    """An earlier complete `demo` output, as claim/seal leave it."""
    claim_output_dir(out, "demo")
    (out / "data").mkdir()
    (out / "report.pdf").write_bytes(b"%PDF-1.4 demo")
    (out / "anklescan.db").write_bytes(b"SQLite format 3\x00 demo")
    (out / "data" / "trial.ply").write_bytes(b"ply")
    seal_output_dir(out, "demo")


def test_demo_refuses_a_folder_holding_a_users_file_beside_an_earlier_demo(tmp_path):
    out = tmp_path / "demo"
    _earlier_demo(out)
    (out / "my_notes.txt").write_text("patient called back")
    before = tree(out)
    assert_refused(run("demo", "--quick", "--out", out), "my_notes.txt", "did not write")
    assert tree(out) == before


def test_demo_refuses_when_its_database_was_replaced_by_another_programs(tmp_path):
    out = tmp_path / "demo"
    _earlier_demo(out)
    (out / "anklescan.db").write_bytes(b"SQLite format 3\x00 another program's data, not the demo's")
    before = tree(out)
    assert_refused(run("demo", "--quick", "--out", out), "anklescan.db", "changed")
    assert tree(out) == before


@pytest.mark.slow
@pytest.mark.parametrize("exists", [False, True])
def test_an_interrupted_demo_leaves_none_of_its_output(tmp_path, monkeypatch, capsys, exists):
    """Ctrl-C (or SIGTERM, the same path) in the middle of `demo` left the database and the
    calibration in --out, unsealed, and the next run refused the folder ("holds no complete earlier
    'demo' output") until the user deleted it by hand."""
    from anklescan.app import demo

    def interrupted(out, scale, progress):
        (out / "calibration.json").write_text("{}")  # the run has written part of its output
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "_calibrate", interrupted)
    out = tmp_path / "demo"
    if exists:
        out.mkdir()  # an empty folder the user made for it stays, empty
    assert cli.main(["-q", "demo", "--quick", "--out", str(out)]) == 130
    assert (list(out.iterdir()) == []) if exists else not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["demo"] if exists else [])


def test_a_folder_without_marker_or_with_a_link_is_refused(tmp_path):
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "x.csv").write_text("1")
    assert_refused(run("demo", "--quick", "--out", plain), "not empty")
    linked = tmp_path / "linked"
    _earlier_demo(linked)
    (linked / "elsewhere").symlink_to(plain)
    with pytest.raises(AnkleScanError, match="elsewhere"):
        claim_output_dir(linked, "demo")
    assert (plain / "x.csv").read_text() == "1"


def test_claim_removes_exactly_what_the_earlier_run_wrote(tmp_path):
    out = tmp_path / "demo"
    _earlier_demo(out)
    assert is_output_of(out, "demo") and not is_output_of(out, "report")
    with pytest.raises(AnkleScanError):  # another command's output is not this one's
        claim_output_dir(out, "report")
    claim_output_dir(out, "demo")
    assert list(out.iterdir()) == [] and stat.S_IMODE(out.stat().st_mode) == 0o700


# ------------------------------------------------------------ database companions
def _store_with_patients(folder: Path, codes: list[str]) -> Path:
    with Store.open(data_dir=folder) as store:
        for c in codes:
            store.patients.add(c)
        return store.path


def _live_wal(folder: Path, codes: list[str]) -> tuple[Path, Path]:
    """A database of ours with a -wal holding the patients ``codes`` (copied while open, as a
    crash leaves it): (database copy, its -wal copy) in ``folder/crashed``."""
    store = Store.open(data_dir=folder)
    store.db._conn.execute("PRAGMA wal_autocheckpoint = 0")
    for c in codes:
        store.patients.add(c)
    crashed = folder / "crashed"
    crashed.mkdir()
    db = crashed / store.path.name
    shutil.copyfile(store.path, db)
    shutil.copyfile(f"{store.path}-wal", f"{db}-wal")
    store.close()
    return db, Path(f"{db}-wal")


def test_a_foreign_wal_is_refused_and_nothing_changes(tmp_path):
    db = _store_with_patients(tmp_path / "clinic", ["P-01", "P-02"])
    _other_db, other_wal = _live_wal(tmp_path / "other", ["X-9"])
    shutil.copyfile(other_wal, f"{db}-wal")
    before = {p.name: p.read_bytes() for p in db.parent.iterdir() if p.is_file()}
    with pytest.raises(AnkleScanError, match="does not belong.*2 patients"):
        Store.open(db)
    assert {p.name: p.read_bytes() for p in db.parent.iterdir() if p.is_file()} == before
    Path(f"{db}-wal").unlink()  # moved away, as the message says: the patients are all there
    with Store.open(db) as store:
        assert [p.code for p in store.patients.all()] == ["P-01", "P-02"]


def test_a_crash_left_wal_of_the_database_itself_is_applied(tmp_path):
    db, _wal = _live_wal(tmp_path / "clinic", ["P-01", "P-02", "P-03"])
    with Store.open(db) as store:
        assert [p.code for p in store.patients.all()] == ["P-01", "P-02", "P-03"]
    assert not [p for p in db.parent.iterdir() if p.name.startswith(".")]  # the private copy is gone


def test_companions_that_are_links_or_foreign_wal_pages_are_refused(tmp_path):
    db = _store_with_patients(tmp_path / "clinic", ["P-01"])
    target = tmp_path / "elsewhere"
    target.write_bytes(b"keep")
    Path(f"{db}-shm").symlink_to(target)
    with pytest.raises(AnkleScanError, match="not a regular file"):
        Store.open(db)
    Path(f"{db}-shm").unlink()
    header = (0x377F0682).to_bytes(4, "big") + (3007000).to_bytes(4, "big") + (1024).to_bytes(4, "big")
    Path(f"{db}-wal").write_bytes(header + bytes(20) + bytes(1024 + 24))
    with pytest.raises(AnkleScanError, match="another database"):
        Store.open(db)
    assert target.read_bytes() == b"keep"


def test_a_database_of_ours_without_its_tables_is_refused(tmp_path):
    db = tmp_path / "anklescan.sqlite"
    conn = sqlite3.connect(db)
    conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    conn.execute("CREATE TABLE patients (id INTEGER PRIMARY KEY)")  # a column short, the rest gone
    conn.commit()
    conn.close()
    before = db.read_bytes()
    with pytest.raises(AnkleScanError, match="incomplete.*patients.code"):
        Store.open(db)
    assert db.read_bytes() == before


# ----------------------------------------------------------------- numeric options
def _actions(parser: argparse.ArgumentParser, prefix: str = ""):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _actions(sub, f"{prefix} {name}".strip())
        else:
            yield prefix, action


def test_every_numeric_option_is_bounded_by_core_limits():
    """Including options others add later: a bare int/float type fails here."""
    typed = [(cmd, a) for cmd, a in _actions(cli.build_parser()) if a.type is not None]
    assert typed
    for cmd, a in typed:
        assert isinstance(a.type, (Bounded, SizeType, DateType)), f"{cmd} {a.option_strings}: type {a.type!r} is not bounded"
        for bad in ("nan", "inf", "-1e309", "1e400", "99999999999", "x"):
            with pytest.raises(argparse.ArgumentTypeError):
                a.type(bad)


@pytest.mark.parametrize("args,words", [
    (["patterns", "--motion-refs", "1000000", "--out", "P"], ["--motion-refs", "out of range"]),
    (["patterns", "--projector", "99999x2", "--out", "P"], ["--projector", "out of range"]),
    (["measure", "C", "--calibration", "K", "--mark-diameter", "1e308", "--out", "R"], ["--mark-diameter"]),
    (["angles", "M", "--sigma", "nan"], ["--sigma"]),
    (["demo", "--sway", "-3", "--out", "D"], ["--sway"]),
])
def test_out_of_range_options_are_one_line_before_any_work(tmp_path, args, words):
    done = run(*args, cwd=tmp_path)
    assert_refused(done, *words)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("exc,words", [(MemoryError(), ["out of memory"]),
                                       (ImportError("libfoo.so: failed to map segment", name="cv2"),
                                        ["library could not be loaded", "cv2"])])
def test_memory_and_library_failures_are_one_line_exit_2(tmp_path, monkeypatch, capsys, exc, words):
    def boom(args):
        raise exc
    marks = tmp_path / "m.csv"
    marks.write_text("label,x,y,z\n1,0,0,1\n")
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub.choices["angles"].set_defaults(func=boom)  # the command fails as under ulimit -v
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    assert cli.main(["angles", str(marks)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(w in err[0] for w in words), err


def test_out_of_range_inputs_are_refused(tmp_path):
    marks = tmp_path / "marks.csv"
    marks.write_text("label,x,y,z\n1,1e308,0,1e308\n2,0,0,0\n3,1,0,1\n4,0,0,0\n")
    assert_refused(run("angles", marks), "out of range")
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2, 3]")
    assert_refused(run("calibrate", "import", listed, "--projector", "1024x768", "--out", tmp_path / "c.json"),
                   "map")
    fs = cv2.FileStorage(str(tmp_path / "zero.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("K1", np.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]])), ("D1", np.zeros((1, 5))),
                       ("K2", np.array([[900.0, 0, 512], [0, 900, 384], [0, 0, 1]])), ("D2", np.zeros((1, 5))),
                       ("R", np.eye(3)), ("T", np.zeros((3, 1))), ("image_size", np.array([1280.0, 960.0]))):
        fs.write(key, value)
    fs.release()
    assert_refused(run("calibrate", "import", tmp_path / "zero.yml", "--projector", "1024x768",
                       "--out", tmp_path / "c.json"), "from the camera")
    assert not (tmp_path / "c.json").exists()


# ------------------------------------------------------------------- permissions
def test_a_read_only_file_of_the_user_is_not_replaced(tmp_path):
    out = tmp_path / "cal.yml"
    out.write_text("mine")
    out.chmod(0o444)
    assert_refused(run("calibrate", "export", tmp_path / "missing.json", "--out", out), "permission denied")
    assert out.read_text() == "mine" and stat.S_IMODE(out.stat().st_mode) == 0o444


def test_another_users_file_the_user_cannot_write_is_not_replaced(tmp_path, monkeypatch):
    """A world-writable folder without the sticky bit lets a rename replace anyone's file; cp would
    say 'Permission denied'. (The other owner is simulated: the tests may run as root.)"""
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(0o777)
    theirs = folder / "result.json"
    theirs.write_text("theirs")
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p).endswith("result.json")
                        else real_access(p, mode, **kw))
    with pytest.raises(WriteError, match="permission denied"):
        check_may_replace(theirs)
    with pytest.raises(WriteError, match="permission denied"), atomic_paths(theirs) as (tmp,):
        tmp.write_text("ours")
    assert theirs.read_text() == "theirs" and sorted(p.name for p in folder.iterdir()) == ["result.json"]


def test_a_folder_swapped_for_a_symlink_during_the_write_does_not_redirect_it(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (b / "out.json").write_text("b's file")
    link = tmp_path / "out"
    link.symlink_to(a)
    with atomic_paths(link / "out.json") as (tmp,):
        tmp.write_text("result")
        link.unlink()
        link.symlink_to(b)  # swapped mid-run
    assert (a / "out.json").read_text() == "result" and (b / "out.json").read_text() == "b's file"
    assert sorted(p.name for p in b.iterdir()) == ["out.json"]


def test_a_trailing_slash_names_a_folder(tmp_path):
    assert_refused(run("calibrate", "export", tmp_path / "missing.json", "--out", f"{tmp_path / 'newdir'}/"),
                   "ends with '/'")
    assert not (tmp_path / "newdir").exists()


# ----------------------------------------------------------------------- privacy
def _modes(folder: Path) -> set[tuple[str, int]]:
    return {("dir" if p.is_dir() else "file", stat.S_IMODE(p.stat().st_mode)) for p in [folder, *folder.rglob("*")]}


def test_outputs_are_private_whatever_the_umask(tmp_path):
    done = run("patterns", "--preset", "paper", "--projector", "64x48", "--out", tmp_path / "pat", umask=0)
    assert done.returncode == 0, done.stderr
    assert _modes(tmp_path / "pat") == {("dir", 0o700), ("file", 0o600)}
    from test_opencv_graycode import opencv_frames
    src = tmp_path / "opencv"
    src.mkdir()
    for i, img in enumerate(opencv_frames(64, 48, 1)):
        cv2.imwrite(str(src / f"graycode_{i:02d}.png"), img)
    src.chmod(0o755)
    done = run("import", "opencv-graycode", src, "--projector", "64x48", "--out", tmp_path / "cap", umask=0)
    assert done.returncode == 0, done.stderr
    assert _modes(tmp_path / "cap") == {("dir", 0o700), ("file", 0o600)}


def test_the_settings_file_is_private_whatever_the_umask(tmp_path):
    code = ("import os, sys; os.umask(0)\n"
            "from anklescan.app.settings import Settings\n"
            "from pathlib import Path\n"
            "s = Settings(sys.argv[1]); s.chosen_data_folder = Path('/clinic/patients'); s.sync()\n")
    path = tmp_path / "conf" / "anklescan.ini"
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    assert done.returncode == 0, done.stderr
    assert "/clinic/patients" in path.read_text()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and stat.S_IMODE(path.parent.stat().st_mode) == 0o700


# ------------------------------------------------------------------- temporaries
def test_a_killed_runs_temporary_is_removed_by_the_next_run_and_nothing_else(tmp_path):
    code = ("import os, sys\n"
            "from anklescan.core.atomic import mkdtemp_beside\n"
            "t = mkdtemp_beside(sys.argv[1]); (t / 'frame.png').write_bytes(b'x' * 1000)\n"
            "os._exit(9)  # killed: no clean-up runs\n")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "pat")], timeout=60)
    left = [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert len(left) == 1 and (left[0] / TEMP_MARKER).exists()
    users = tmp_path / ".pat.mine.tmp"  # looks like ours, but has no marker: the user's
    users.mkdir()
    (users / "keep.txt").write_text("keep")
    done = run("patterns", "--preset", "paper", "--projector", "64x48", "--out", tmp_path / "pat")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [".pat.mine.tmp", "pat"]
    assert (users / "keep.txt").read_text() == "keep"


def test_a_live_or_recent_temporary_of_another_host_is_kept_until_it_is_old(tmp_path):
    t = tmp_path / ".x.abc.tmp"
    t.mkdir()
    (t / TEMP_MARKER).write_text(json.dumps({"host": "other-host", "pid": 1, "created": 1000.0}))
    assert clean_stale_temporaries(tmp_path, now=1000.0 + 60) == [] and t.exists()
    assert clean_stale_temporaries(tmp_path, now=1000.0 + STALE_TEMP_AGE_S + 1) == [t] and not t.exists()


# -------------------------------------------------------------------------- lock
def test_the_lock_names_its_holder_and_dies_with_it(tmp_path):
    code = ("import sys, time\nfrom anklescan.core.records.lock import DataFolderLock\n"
            "l = DataFolderLock(sys.argv[1]); assert l.acquire() is None; print('ok', flush=True); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ok"
        holder = DataFolderLock(tmp_path).acquire()
        assert holder is not None and holder.pid == proc.pid and f"process {proc.pid}" in holder.describe()
    finally:
        proc.kill()
        proc.wait()
    lock = DataFolderLock(tmp_path)
    assert lock.acquire() is None and lock.held
    assert stat.S_IMODE((tmp_path / "anklescan.lock").stat().st_mode) == 0o600
    lock.release()


def test_a_killed_writes_temporary_file_is_removed_by_the_next_write_and_nothing_else(tmp_path):
    code = ("import os, sys\n"
            "from anklescan.core.atomic import atomic_paths\n"
            "with atomic_paths(sys.argv[1]) as (tmp,):\n"
            "    tmp.write_bytes(b'x' * 1000)\n"
            "    os._exit(9)  # killed mid-write: no clean-up runs\n")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "cloud.ply")], timeout=60)
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".cloud.ply.") and "anklescan-tmp" in left[0]
    (tmp_path / ".cloud.ply.notes.tmp").write_text("the user's")  # no marker: never touched
    code = "import sys\nfrom anklescan.core.atomic import write_text_atomic\nwrite_text_atomic(sys.argv[1], 'ok')\n"
    assert subprocess.run([sys.executable, "-c", code, str(tmp_path / "next.txt")], timeout=60).returncode == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [".cloud.ply.notes.tmp", "next.txt"]
