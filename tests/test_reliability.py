"""Never lose or expose a clinic's data (issue 15): every bad input is exit 2 with exactly one
line on stderr and nothing written, changed or deleted; outputs never replace inputs; patient
files are private; other programs' databases are never touched; read-only archives open."""

import hashlib
import json
import os
import shutil
import signal
import sqlite3
import stat
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.app.cli import main
from anklescan.core.atomic import guard_output, temp_affixes
from anklescan.core.calibration.model.file import save_calibration
from anklescan.core.errors import AnkleScanError
from anklescan.core.limits import MAX_IMAGE_SIDE, load_json
from anklescan.core.records.store import APPLICATION_ID, Store
from anklescan.core.scan.capture import CaptureWriter, save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.core.scan.pointcloud import read_ply
from anklescan.hardware.simrig import SimRig

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- helpers
def snapshot(folder: Path) -> dict:
    """Every entry under ``folder`` (hidden ones too) with its content hash and mode."""
    out = {}
    for p in sorted(folder.rglob("*")):
        key = p.relative_to(folder).as_posix()
        if p.is_symlink():
            out[key] = ("link", os.readlink(p))
        elif p.is_file():
            out[key] = (hashlib.sha256(p.read_bytes()).hexdigest(), stat.S_IMODE(p.stat().st_mode))
        else:
            out[key] = ("dir", stat.S_IMODE(p.stat().st_mode))
    return out


def cli(capfd, *args) -> tuple[int, list[str]]:
    code = main(["-q", *map(str, args)])
    err = capfd.readouterr().err
    return code, [line for line in err.splitlines() if line.strip()]


def assert_refused(capfd, tmp_path, *args, words=()):
    """Exit 2, exactly one stderr line naming the problem, and the folder unchanged."""
    before = snapshot(tmp_path)
    code, lines = cli(capfd, *args)
    assert code == 2, lines
    assert len(lines) == 1 and lines[0].startswith("anklescan"), lines
    for w in words:
        assert w in lines[0], lines[0]
    assert snapshot(tmp_path) == before
    return lines[0]


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    work = tmp_path_factory.mktemp("rel")
    rig = SimRig(scale=0.25)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    save_capture(work / "capture", pset, [rig.capture(img) for img in render_all(pset)])
    save_calibration(rig.true_calibration(), work / "cal.json")
    return work


@pytest.fixture
def work(tmp_path, scan):
    """A private copy of the scan in tmp_path: capture/, cal.json, camera/projector CSVs."""
    shutil.copytree(scan / "capture", tmp_path / "capture")
    shutil.copy(scan / "cal.json", tmp_path / "cal.json")
    (tmp_path / "cam.csv").write_text("X,Y,Z,u,v\n0,0,0,1,1\n")
    (tmp_path / "proj.csv").write_text("X,Y,Z,u\n0,0,0,1\n")
    return tmp_path


def _manifest(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims ``width``x``height`` (its pixel data is one row)."""
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * (width + 1)))
            + chunk(b"IEND", b""))


# ------------------------------------------------------------------ outputs vs inputs
@pytest.mark.parametrize("case", ["same", "relative", "symlink", "hardlink", "inside-capture",
                                  "capture-frame", "parent-of-input", "measure", "points-csv", "box-frame"])
def test_out_that_is_an_input_is_refused(capfd, work, case):
    os.chdir(work)
    cal = "cal.json"
    if case == "symlink":
        os.symlink("cal.json", "link.json")
    if case == "hardlink":
        os.link("cal.json", "hard.json")
    args = {
        "same": ["reconstruct", "capture", "--calibration", cal, "--out", cal],
        "relative": ["reconstruct", "capture", "--calibration", cal, "--out", f"../{work.name}/cal.json"],
        "symlink": ["reconstruct", "capture", "--calibration", cal, "--out", "link.json"],
        "hardlink": ["reconstruct", "capture", "--calibration", cal, "--out", "hard.json"],
        "inside-capture": ["reconstruct", "capture", "--calibration", cal, "--out", "capture/scan.ply"],
        "capture-frame": ["reconstruct", "capture", "--calibration", cal, "--out", "capture/manifest.json"],
        "parent-of-input": ["reconstruct", "capture", "--calibration", cal, "--out", "."],
        "measure": ["measure", "capture", "--calibration", cal, "--out", cal],
        "points-csv": ["calibrate", "points", "--camera", "cam.csv", "--projector", "proj.csv", "--out", "cam.csv"],
        "box-frame": ["calibrate", "box", "capture", "--out", "capture/00_white.png"],
    }[case]
    assert_refused(capfd, work, *args, words=("--out",))


@pytest.mark.parametrize("command", ["reconstruct", "calibrate box", "calibrate export", "check"])
def test_out_onto_a_file_the_command_did_not_write_is_refused(capfd, work, command):
    """A mistyped --out naming the user's other file (notes, a photo's PLY, a spreadsheet) is
    refused, the file untouched; the command's own earlier output, or an empty file, is replaced."""
    os.chdir(work)
    out = work / "notes.txt"
    out.write_text("the patient's history, typed by hand\n")
    args = {"reconstruct": ["reconstruct", "capture", "--calibration", "cal.json"],
            "calibrate box": ["calibrate", "box", "capture"],
            "calibrate export": ["calibrate", "export", "cal.json"],
            "check": ["check", "capture", "--calibration", "cal.json", "--inversion", "0", "--plantar-flexion", "0"],
            }[command]
    line = assert_refused(capfd, work, *args, "--out", out, words=("did not write", "left untouched"))
    assert "notes.txt" in line


def test_out_replaces_the_commands_own_earlier_output(capfd, work):
    os.chdir(work)
    ply = work / "scan.ply"
    assert cli(capfd, "reconstruct", "capture", "--calibration", "cal.json", "--out", ply)[0] == 0
    first = ply.read_bytes()
    ply.write_bytes(first[:-12])  # an earlier cloud of ours (another run's): replaced
    assert cli(capfd, "reconstruct", "capture", "--calibration", "cal.json", "--out", ply)[0] == 0
    assert ply.read_bytes() == first
    other = work / "other.ply"  # another program's PLY of the same name is not ours
    other.write_bytes(b"ply\nformat ascii 1.0\ncomment scanned elsewhere\nelement vertex 0\nend_header\n")
    assert_refused(capfd, work, "reconstruct", "capture", "--calibration", "cal.json", "--out", other,
                   words=("did not write",))
    empty = work / "empty.yml"
    empty.touch()
    assert cli(capfd, "calibrate", "export", "cal.json", "--out", empty)[0] == 0
    assert cli(capfd, "calibrate", "export", "cal.json", "--out", empty)[0] == 0  # its own export, again
    assert empty.stat().st_size > 0


@pytest.mark.parametrize("out", ["/dev/null", ""])
def test_out_that_is_a_device_or_empty_is_refused(capfd, work, out):
    assert_refused(capfd, work, "reconstruct", work / "capture", "--calibration", work / "cal.json", "--out", out)
    assert os.path.exists("/dev/null") and not os.path.isfile("/dev/null")


def test_guard_output_helper(tmp_path):
    inp = tmp_path / "in.json"
    inp.write_text("{}")
    folder = tmp_path / "cap"
    folder.mkdir()
    (folder / "a.png").write_bytes(b"x")
    os.link(folder / "a.png", tmp_path / "elsewhere.png")
    for out in (inp, tmp_path / "." / "in.json", folder / "new.ply", tmp_path, tmp_path / "elsewhere.png"):
        with pytest.raises(AnkleScanError):
            guard_output(out, [inp, folder])
    assert guard_output(tmp_path / "fine.ply", [inp, folder, None]) == tmp_path / "fine.ply"


def test_patterns_never_deletes_files_it_did_not_write(capfd, tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "thesis.docx").write_text("years of work")
    assert_refused(capfd, tmp_path, "patterns", "--out", docs, "--projector", "64x48", words=("did not write",))
    # an earlier pattern output is replaced; one with a file added to it is not
    assert cli(capfd, "patterns", "--out", tmp_path / "p", "--projector", "64x48")[0] == 0
    assert cli(capfd, "patterns", "--out", tmp_path / "p", "--projector", "32x24", "--preset", "paper")[0] == 0
    assert _manifest(tmp_path / "p")["projector"] == {"width": 32, "height": 24}
    (tmp_path / "p" / "notes.txt").write_text("mine")
    assert_refused(capfd, tmp_path, "patterns", "--out", tmp_path / "p", "--projector", "64x48")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["docs", "p"]  # no temporaries left
    # a camera capture is someone's scan: patterns never replace it
    pset = make_pattern_set("paper", 16, 8)
    save_capture(tmp_path / "scan", pset, render_all(pset), metadata={"device": "camera"})
    assert_refused(capfd, tmp_path, "patterns", "--out", tmp_path / "scan", "--projector", "64x48")


def test_patterns_never_replace_a_capture_photographed_from_them(capfd, tmp_path):
    """SPEC §5: a camera that photographs the pattern folder file by file makes a capture with the
    same manifest.json and file names. `patterns --out` onto it deleted the scan (exit 0)."""
    assert cli(capfd, "patterns", "--out", tmp_path / "p", "--projector", "64x48")[0] == 0
    shutil.copytree(tmp_path / "p", tmp_path / "scan")
    for f in _manifest(tmp_path / "scan")["frames"]:  # the "photographs": dimmer, offset
        img = cv2.imread(str(tmp_path / "p" / f["file"]), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(tmp_path / "scan" / f["file"]), (img // 2 + 20).astype(np.uint8))
    assert_refused(capfd, tmp_path, "patterns", "--out", tmp_path / "scan", "--projector", "64x48",
                   words=("did not write",))
    # the pattern folder itself is still ours and is replaced
    assert cli(capfd, "patterns", "--out", tmp_path / "p", "--projector", "32x24")[0] == 0


def test_sigterm_during_patterns_leaves_no_temporary(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "anklescan.app.cli", "-q", "patterns", "--out", str(tmp_path / "big"),
                             "--projector", "8000x6000"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(p.name.startswith(".big.") for p in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM
    assert len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------- inputs that simply work
def test_non_ascii_capture_folder_and_long_output_name(capfd, work):
    folder = work / "Müller_ミュラー"
    shutil.copytree(work / "capture", folder)
    out = work / ("a" * 250 + ".ply")  # 254 bytes: legal, and the temporary must fit too
    code, lines = cli(capfd, "reconstruct", folder, "--calibration", work / "cal.json", "--out", out)
    assert code == 0, lines
    head = out.read_bytes().split(b"end_header")[0]
    head.decode("ascii")
    assert b"M\\xfcller" in head
    assert len(read_ply(out)) > 1000
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    assert not [p for p in work.iterdir() if p.name.startswith(".")]
    latin1 = Path(os.fsdecode(bytes(work / "capture")[:-len(b"capture")] + b"M\xfcller"))  # not UTF-8
    shutil.copytree(work / "capture", latin1)
    code, lines = cli(capfd, "reconstruct", latin1, "--calibration", work / "cal.json", "--out", work / "l.ply")
    assert code == 0 and len(read_ply(work / "l.ply")) > 1000, lines
    prefix, suffix = temp_affixes("é" * 200)
    assert len((prefix + "x" * 8 + suffix).encode()) <= 255


# --------------------------------------------------------------- nonsense: exit 2, 1 line
def _edit_manifest(work, fn):
    m = _manifest(work / "capture")
    fn(m)
    (work / "capture" / "manifest.json").write_text(json.dumps(m))


def _frames(work) -> list[Path]:
    return [work / "capture" / f["file"] for f in _manifest(work / "capture")["frames"]]


def _swap(m):
    kinds = {f["kind"]: f for f in m["frames"]}
    kinds["white"]["file"], kinds["black"]["file"] = kinds["black"]["file"], kinds["white"]["file"]


def _all_black(work):
    for p in _frames(work):
        cv2.imwrite(str(p), np.zeros_like(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)))


def _bits(m):
    for f in m["frames"]:
        if f["kind"] == "gray":
            f["bits"] = 20_000_000_000


def _huge_frames(work):
    for p in _frames(work):
        p.write_bytes(_png_header_only(20000, 20000))


@pytest.mark.parametrize("case, words", [
    ("swapped", ["swapped"]),
    ("all-black", ["white frame is no brighter"]),
    ("period-infinity", ["Infinity"]),
    ("deep-manifest", ["nested"]),
    ("huge-int-manifest", ["digits"]),
    ("bits-2e10", ["bits"]),
    ("huge-frames", [str(MAX_IMAGE_SIDE)]),
])
def test_nonsense_capture(capfd, work, case, words):
    if case == "swapped":
        _edit_manifest(work, _swap)
    elif case == "all-black":
        _all_black(work)
    elif case == "period-infinity":
        (work / "capture" / "manifest.json").write_text(
            (work / "capture" / "manifest.json").read_text().replace('"period": 8.0', '"period": Infinity'))
    elif case == "deep-manifest":
        (work / "capture" / "manifest.json").write_text("[" * 200_000 + "]" * 200_000)
    elif case == "huge-int-manifest":
        _edit_manifest(work, lambda m: m.__setitem__("version", 0))
        text = (work / "capture" / "manifest.json").read_text().replace('"version": 0', '"version": ' + "7" * 5000)
        (work / "capture" / "manifest.json").write_text(text)
    elif case == "bits-2e10":
        _edit_manifest(work, _bits)
    elif case == "huge-frames":
        _huge_frames(work)
    t0 = time.perf_counter()
    assert_refused(capfd, work, "reconstruct", work / "capture", "--calibration", work / "cal.json",
                   "--out", work / "x.ply", words=words)
    assert time.perf_counter() - t0 < 10  # refused before decoding, not after minutes
    if case in ("swapped", "all-black"):
        assert_refused(capfd, work, "calibrate", "box", work / "capture", "--out", work / "box.json", words=words)


@pytest.mark.parametrize("case, words", [
    ("K", ["fx"]), ("t", ["100 m"]), ("dist", ["dist"]), ("deep", ["nested"]), ("bigint", ["digits"]),
    ("nan", ["finite"]),
])
def test_absurd_calibration_refused_at_load(capfd, work, case, words):
    cal = json.loads((work / "cal.json").read_text())
    if case == "K":
        cal["camera"]["K"][0][0] = 1e-300
    elif case == "t":
        cal["projector"]["t"][2] = 1e308
    elif case == "dist":
        cal["camera"]["dist"] = [1e300, 0, 0, 0, 0]
    text = json.dumps(cal)
    if case == "deep":
        text = "{\"a\":" * 200_000 + "1" + "}" * 200_000
    elif case == "bigint":
        text = text.replace('"width": ', '"width": ' + "9" * 5000, 1)
    elif case == "nan":
        text = text.replace('"t": [', '"t": [NaN, ', 1)
    (work / "bad.json").write_text(text)
    assert_refused(capfd, work, "reconstruct", work / "capture", "--calibration", work / "bad.json",
                   "--out", work / "x.ply", words=words)


@pytest.mark.parametrize("where, value, words", [
    (("camera", "K", 0, 0), "1000", ["camera.K", "not numeric"]),  # numpy would read 1000.0
    (("camera", "K", 0, 0), True, ["camera.K", "not numeric"]),    # numpy would read fx = 1
    (("projector", "dist", 0), "0.1", ["projector.dist"]),
    (("camera", "width"), True, ["camera.width"]),                  # bool is an int in Python
    (("volume", "min", 0), "0", ["volume"]),
    (("model_error", "sd_mm"), "0.05", ["model_error"]),
])
def test_calibration_values_of_the_wrong_json_type_are_refused(capfd, work, where, value, words):
    """SPEC §4's numbers must be JSON numbers: a string or true/false in their place was read as a
    number (fx = "1000" -> 1000.0, fx = true -> 1.0) and the scan was made with it, exit 0."""
    cal = json.loads((work / "cal.json").read_text())
    cal.setdefault("volume", {"min": [0, 0, 0], "max": [1, 1, 1]})
    cal.setdefault("model_error", {"sd_mm": 0.0, "growth_mm_per_mm": 0.0})
    node = cal
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    (work / "typed.json").write_text(json.dumps(cal))
    assert_refused(capfd, work, "reconstruct", work / "capture", "--calibration", work / "typed.json",
                   "--out", work / "x.ply", words=words)


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
def test_special_file_inputs_are_refused(capfd, tmp_path, special):
    if special == "fifo":
        special = tmp_path / "fifo"
        os.mkfifo(special)
    assert_refused(capfd, tmp_path, "angles", special, words=("regular file",))
    label = "9" * 5000  # a message quoting it stays one readable line
    (tmp_path / "m.csv").write_text(f"label,x,y,z\n{label},1,2,3\n")
    line = assert_refused(capfd, tmp_path, "angles", tmp_path / "m.csv", words=("label",))
    assert len(line) < 500


def test_control_points_out_of_range_are_refused(capfd, tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-1, 1, (40, 3)) * 1e150
    (tmp_path / "cam.csv").write_text("X,Y,Z,u,v\n" + "".join(f"{a},{b},{c},10,20\n" for a, b, c in xyz))
    (tmp_path / "proj.csv").write_text("X,Y,Z,u\n" + "".join(f"{a},{b},{c},10\n" for a, b, c in xyz))
    assert_refused(capfd, tmp_path, "calibrate", "points", "--camera", tmp_path / "cam.csv",
                   "--projector", tmp_path / "proj.csv", "--out", tmp_path / "c.json", words=("out of range",))


def test_angles_with_no_computable_angle_is_an_error(capfd, tmp_path):
    (tmp_path / "marks.csv").write_text("label,x,y,z\n1,0,0,0\n")
    assert_refused(capfd, tmp_path, "angles", tmp_path / "marks.csv", words=("no angle",))


def test_angles_out_of_range_is_an_error(capfd, tmp_path):
    rows = "".join(f"{i},{1e200 * (i % 3 + 1)},{1e200 * (i % 2)},{1e199 * i}\n" for i in range(1, 8))
    (tmp_path / "marks.csv").write_text("label,x,y,z\n" + rows)
    assert_refused(capfd, tmp_path, "angles", tmp_path / "marks.csv", words=("out of range",))


@pytest.mark.parametrize("args", [
    ["calibrate", "points", "--camera", "c.csv", "--projector", "p.csv", "--out", "x.json",
     "--projector-size", "100000x100000"],
    ["patterns", "--out", "p", "--projector", "30000x30000"],
    ["patterns", "--out", "p", "--projector", "9" * 5000 + "x2"],
    ["reconstruct"],
    ["nonsense-command"],
    ["angles", "m.csv", "--sigma", "nan"],
])
def test_argument_errors_are_one_line(capfd, tmp_path, args):
    os.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capfd.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "usage" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_cli_size_limit_is_the_documented_constant():
    from anklescan.app.cli import _size

    assert _size.max_side == MAX_IMAGE_SIDE


def test_truncated_png_is_one_line_without_libpng_noise(work):
    frame = _frames(work)[3]
    frame.write_bytes(frame.read_bytes()[:300])
    done = subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", "reconstruct", str(work / "capture"),
                           "--calibration", str(work / "cal.json"), "--out", str(work / "x.ply")],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and frame.name in lines[0], done.stderr
    assert not (work / "x.ply").exists()


@pytest.mark.parametrize("damage", ["16-bit", "corrupt-idat", "text", "empty", "float", "jpeg-truncated"])
def test_damaged_frames_are_one_line(capfd, work, damage):
    frame = _frames(work)[3]
    img = cv2.imread(str(frame), cv2.IMREAD_UNCHANGED)
    if damage == "16-bit":
        cv2.imwrite(str(frame), img.astype(np.uint16) * 256)
    elif damage == "corrupt-idat":
        data = bytearray(frame.read_bytes())
        data[60] ^= 0xFF
        frame.write_bytes(bytes(data))
    elif damage == "text":
        frame.write_text("not an image")
    elif damage == "empty":
        frame.write_bytes(b"")
    elif damage == "float":
        frame.write_bytes(cv2.imencode(".tiff", img.astype(np.float32))[1].tobytes())
    elif damage == "jpeg-truncated":
        data = cv2.imencode(".jpg", img)[1].tobytes()
        frame.write_bytes(data[:len(data) // 2])
    assert_refused(capfd, work, "reconstruct", work / "capture", "--calibration", work / "cal.json",
                   "--out", work / "x.ply", words=(frame.name,))


def test_json_loader_limits(tmp_path):
    ok = tmp_path / "ok.json"
    ok.write_text(json.dumps({"a": [1, 2.5, {"b": None}], "big": 10 ** 20}))
    assert load_json(ok, "test")["big"] == 10 ** 20
    for text in ("[" * 100 + "]" * 100, "1e999", "-Infinity", "9" * 40, "\"a\"\xff"):
        (tmp_path / "bad.json").write_bytes(text.encode("latin-1"))
        with pytest.raises(AnkleScanError):
            load_json(tmp_path / "bad.json", "test")


# --------------------------------------------------------------------------- privacy
def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_patient_data_is_private_whatever_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        store = Store.open(data_dir=tmp_path / "data")
        store.patients.add("P1")
        session = store.sessions.start("P1", condition="barefoot")
        trial = store.trials.add(session.id, ref_inversion=0, ref_plantar_flexion=0)
        trial_dir = store.files.trial_dir(trial.id, create=True)
        pset = make_pattern_set("paper", 16, 8)
        with CaptureWriter(trial_dir / "capture", pset) as writer:
            for frame, img in zip(pset.frames, render_all(pset), strict=False):
                writer.add(frame.file, img)
        assert (tmp_path / "data" / "anklescan.sqlite-wal").exists()
        for p in [tmp_path / "data", *(tmp_path / "data").rglob("*")]:
            assert _mode(p) == (0o700 if p.is_dir() else 0o600), p
        store.close()
        save_capture(tmp_path / "cap2", pset, render_all(pset))
        assert {_mode(p) for p in (tmp_path / "cap2").iterdir()} == {0o600}
        assert _mode(tmp_path / "cap2") == 0o700
    finally:
        os.umask(old)


def test_older_data_folders_are_made_private_on_open(tmp_path):
    with Store.open(data_dir=tmp_path) as s:
        s.patients.add("P1")
    old = tmp_path / "patients" / "P1" / "session-1" / "trial-1" / "capture"
    old.mkdir(parents=True)
    (old / "00_white.png").write_bytes(b"x")
    for p in [tmp_path / "patients", *(tmp_path / "patients").rglob("*")]:
        os.chmod(p, 0o755 if p.is_dir() else 0o644)  # as an older version left them
    os.chmod(tmp_path / "anklescan.sqlite", 0o644)
    Store.open(data_dir=tmp_path).close()
    for p in [tmp_path / "patients", *(tmp_path / "patients").rglob("*"), tmp_path / "anklescan.sqlite"]:
        assert _mode(p) == (0o700 if p.is_dir() else 0o600), p


# ------------------------------------------------------------------ foreign databases
def _foreign(path: Path, kind: str) -> None:
    c = sqlite3.connect(path)
    if kind == "clash":
        c.execute("CREATE TABLE patients (id INTEGER PRIMARY KEY, name TEXT)")
    else:
        c.execute("CREATE TABLE notes (body BLOB)")
        c.executemany("INSERT INTO notes VALUES (?)", [(os.urandom(600),) for _ in range(100)])
    if kind == "app-id":
        c.execute("PRAGMA application_id = 1234")
    c.commit()
    c.close()
    if kind == "damaged":
        data = bytearray(path.read_bytes())
        data[4096 * 2 + 8:4096 * 2 + 400] = os.urandom(392)
        path.write_bytes(bytes(data))


@pytest.mark.parametrize("kind", ["healthy", "clash", "app-id", "damaged"])
def test_other_programs_databases_are_refused_untouched(tmp_path, kind):
    path = tmp_path / "other.sqlite"
    _foreign(path, kind)
    before = snapshot(tmp_path)
    with pytest.raises(AnkleScanError) as exc:
        Store.open(path)
    assert "\n" not in str(exc.value) and "untouched" in str(exc.value)
    assert snapshot(tmp_path) == before  # header, journal mode, tables, no -wal/-shm


def test_our_database_is_marked_and_older_ones_recognised(tmp_path):
    with Store.open(tmp_path / "a.sqlite") as s:
        s.patients.add("P1")
    c = sqlite3.connect(tmp_path / "a.sqlite")
    assert c.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID
    c.execute("PRAGMA application_id = 0")  # as made before the id existed
    c.commit()
    c.close()
    with Store.open(tmp_path / "a.sqlite") as s:
        assert [p.code for p in s.patients.all()] == ["P1"] and not s.read_only
    c = sqlite3.connect(tmp_path / "a.sqlite")
    assert c.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID


def test_read_only_copy_opens_for_reading(tmp_path):
    with Store.open(tmp_path / "live" / "anklescan.sqlite") as s:
        s.patients.add("P1")
    shutil.copytree(tmp_path / "live", tmp_path / "archive")
    db = tmp_path / "archive" / "anklescan.sqlite"
    os.chmod(db, 0o444)
    before = snapshot(tmp_path / "archive")
    with Store.open(db) as s:
        assert s.read_only and "read-only" in s.read_only_reason
        assert [p.code for p in s.patients.all()] == ["P1"]
        for write in (lambda: s.patients.add("P2"), lambda: s.files.trial_dir(1, create=True),
                      lambda: s.calibrations.add({})):
            with pytest.raises(AnkleScanError, match="read-only"):
                write()
    assert snapshot(tmp_path / "archive") == before
    with Store.open(tmp_path / "live" / "anklescan.sqlite", read_only=True) as s:
        assert s.read_only and s.read_only_reason


def test_damaged_database_is_one_line(tmp_path):
    path = tmp_path / "a.sqlite"
    with Store.open(path) as s:
        for i in range(200):
            s.patients.add(f"P{i}", notes="x" * 400)
    data = bytearray(path.read_bytes())
    pages = len(data) // 4096  # the patients' rows fill the second half (the first holds every table's root)
    for page in range(pages // 2, pages - 1):
        data[4096 * page + 8:4096 * page + 300] = os.urandom(292)
    path.write_bytes(bytes(data))
    before = snapshot(tmp_path)
    with pytest.raises(AnkleScanError, match="damaged") as exc:
        Store.open(path)
    assert "\n" not in str(exc.value)
    assert snapshot(tmp_path) == before


def test_a_dim_12_bit_capture_in_16_bit_files_is_not_called_unlit(tmp_path):
    from anklescan.core.scan.capture import capture_from_images, check_lit

    pset = make_pattern_set("paper", 64, 48)
    frames = [(img.astype(np.uint16) * 4 + 40) for img in render_all(pset)]  # 12-bit range, dim
    check_lit(capture_from_images(pset, frames))
    with pytest.raises(AnkleScanError, match="swapped"):
        check_lit(capture_from_images(pset, [frames[1], frames[0], *frames[2:]]))
    with pytest.raises(AnkleScanError, match="no brighter"):
        check_lit(capture_from_images(pset, [np.full_like(f, 40) for f in frames]))


@pytest.mark.parametrize("header", [
    "element vertex 999999999999\nproperty float x\nproperty float y\nproperty float z\n",
    "element vertex 10\nproperty float x\nproperty float x\nproperty float z\n",
    "element vertex many\nproperty float x\n",
    "element vertex 3\nproperty\n",
])
@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_damaged_ply_is_one_clear_error(tmp_path, header, fmt):
    path = tmp_path / "bad.ply"
    path.write_bytes(f"ply\nformat {fmt} 1.0\n{header}end_header\n".encode() + b"1 2 3\n" * 2)
    with pytest.raises(AnkleScanError) as exc:
        read_ply(path)
    assert "\n" not in str(exc.value)


def test_capture_metadata_with_nan_still_reads_back(tmp_path):
    from anklescan.core.scan.capture import load_capture

    pset = make_pattern_set("paper", 16, 8)
    with CaptureWriter(tmp_path / "cap", pset, {"gain": float("nan"), "exposure": np.float32(2.5)}) as w:
        for frame, img in zip(pset.frames, render_all(pset), strict=False):
            w.add(frame.file, img)
    meta = load_capture(tmp_path / "cap").metadata
    assert meta["gain"] is None and meta["exposure"] == 2.5


@pytest.fixture
def read_only_mount(tmp_path):
    """A tmpfs remounted read-only (needs root; skipped elsewhere)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        def make_read_only():
            subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
        yield mnt, make_read_only
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.parametrize("detected", [True, False])
def test_database_on_a_read_only_mount_opens_for_reading(read_only_mount, monkeypatch, detected):
    mnt, make_read_only = read_only_mount
    with Store.open(mnt / "anklescan.sqlite") as s:
        s.patients.add("P1")
    make_read_only()
    if not detected:  # a mount the statvfs flag does not reveal: SQLite's refusal decides
        monkeypatch.setattr("anklescan.core.records.database._read_only_reason", lambda path, exists: "")
    with Store.open(mnt / "anklescan.sqlite") as s:
        assert s.read_only and s.read_only_reason
        assert [p.code for p in s.patients.all()] == ["P1"]
        with pytest.raises(AnkleScanError, match="read-only"):
            s.patients.add("P2")


def test_an_unwritable_output_folder_is_named_not_our_temporary(read_only_mount, capfd):
    """A folder output on a read-only disk: the line named the hidden temporary
    ("Read-only file system (.../.p.1k8luznx.tmp)"), a path the user never gave."""
    mnt, make_read_only = read_only_mount
    make_read_only()
    code, lines = cli(capfd, "patterns", "--out", mnt / "p", "--projector", "64x48")
    assert code == 2 and len(lines) == 1, lines
    assert f"cannot write {mnt / 'p'}:" in lines[0] and "Read-only" in lines[0] and ".tmp" not in lines[0], lines
