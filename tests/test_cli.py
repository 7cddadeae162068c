"""The command line as a user runs it: real subprocesses, exit codes, one-line errors, no partial files."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from anklescan.core.calibration.model.file import calibration_to_dict, save_calibration
from anklescan.core.scan.capture import save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.core.scan.pointcloud import read_ply
from anklescan.hardware.sim_accuracy import evaluate
from anklescan.hardware.simrig import RigLayout, SimRig

ROOT = Path(__file__).resolve().parents[1]


def run(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A small simulated capture of the leg and the rig's true calibration."""
    work = tmp_path_factory.mktemp("cli")
    rig = SimRig(scale=0.25)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    capture = save_capture(work / "capture", pset, [rig.capture(img) for img in render_all(pset)])
    cal = work / "calibration.json"
    save_calibration(rig.true_calibration(), cal)
    return rig, capture, cal


def assert_user_error(done, *words):
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("anklescan: error:"), done.stderr
    assert "Traceback" not in done.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_patterns_command(tmp_path):
    done = run("patterns", "--out", tmp_path / "p", "--projector", "256x192", "--preset", "paper")
    assert done.returncode == 0, done.stderr
    manifest = json.loads((tmp_path / "p" / "manifest.json").read_text())
    files = [f["file"] for f in manifest["frames"]]
    assert len(files) == 18
    img = cv2.imread(str(tmp_path / "p" / files[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (192, 256) and img.dtype == np.uint8


def test_reconstruct_writes_an_accurate_cloud(tmp_path):
    rig = SimRig(scale=0.5)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    capture = save_capture(tmp_path / "capture", pset, [rig.capture(img) for img in render_all(pset)])
    save_calibration(rig.true_calibration(), tmp_path / "cal.json")
    out = tmp_path / "cloud.ply"
    done = run("reconstruct", capture, "--calibration", tmp_path / "cal.json", "--out", out)
    assert done.returncode == 0, done.stderr
    cloud = read_ply(out)
    acc = evaluate(cloud, rig.truth())["subject"]
    # half resolution measures 0.133 mm, 0.064 %, 91 %; full resolution 0.089 mm, 0.043 %, 95.3 %
    # (benchmarks/bench_reconstruct.py): these bounds leave room for the noise's seed only
    assert acc.rms_mm < 0.16 and acc.outlier_fraction < 0.002 and acc.coverage > 0.88


def _copy(capture: Path, dest: Path) -> Path:
    shutil.copytree(capture, dest)
    return dest


def _bad_capture(tmp_path, capture, case):
    c = _copy(capture, tmp_path / "bad")
    files = json.loads((c / "manifest.json").read_text())["frames"]
    name = files[5]["file"]
    if case == "missing":
        (c / name).unlink()
    elif case == "extra":
        shutil.copy(c / name, c / "zz_extra.png")
    elif case == "size":
        img = cv2.imread(str(c / name), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(c / name), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))
    elif case == "unreadable":
        (c / name).write_bytes(b"this is not a png")
    elif case == "manifest":
        (c / "manifest.json").write_text("{ broken")
    return c, name


@pytest.mark.parametrize("case, words", [
    ("missing", ["missing"]), ("extra", ["zz_extra.png"]), ("size", ["200x150", "400x300"]), ("unreadable", ["read"]),
    ("manifest", ["manifest"]),
])
def test_bad_capture_is_one_line_exit_2_and_no_ply(tmp_path, scan, case, words):
    _, capture, cal = scan
    bad, name = _bad_capture(tmp_path, capture, case)
    out = tmp_path / "cloud.ply"
    done = run("reconstruct", bad, "--calibration", cal, "--out", out)
    assert_user_error(done, *words)
    if case in ("missing", "size", "unreadable"):
        assert name in done.stderr
    assert not out.exists() and not list(tmp_path.glob(".cloud.ply*"))


def test_bad_calibration(tmp_path, scan):
    rig, capture, cal = scan
    broken = calibration_to_dict(rig.true_calibration())
    broken["camera"]["R"][0][0] = 3.0
    (tmp_path / "c.json").write_text(json.dumps(broken))
    assert_user_error(run("reconstruct", capture, "--calibration", tmp_path / "c.json", "--out", tmp_path / "o.ply"),
                      "not a rotation")
    (tmp_path / "m.json").write_text("[1, 2")
    assert_user_error(run("reconstruct", capture, "--calibration", tmp_path / "m.json", "--out", tmp_path / "o.ply"),
                      "not valid JSON")
    other = SimRig(scale=0.5).true_calibration()  # a calibration of another camera size
    save_calibration(other, tmp_path / "big.json")
    assert_user_error(run("reconstruct", capture, "--calibration", tmp_path / "big.json", "--out", tmp_path / "o.ply"),
                      "calibrated camera is 800x600")
    assert not (tmp_path / "o.ply").exists()


def test_angles_command(tmp_path):
    csv = tmp_path / "marks.csv"
    csv.write_text("label,x,y,z\n1,10,0,400\n2,0,0,0\n3,40,30,400\n4,40,0,0\n5,0,0,0\n6,100,0,0\n7,0,100,0\n")
    done = run("angles", csv)
    assert done.returncode == 0, done.stderr
    assert "leg_inversion" in done.stdout
    csv.write_text("label,x,y\n1,1,2\n")
    assert_user_error(run("angles", csv))


def test_missing_capture_folder(tmp_path, scan):
    _, _, cal = scan
    assert_user_error(run("reconstruct", tmp_path / "nowhere", "--calibration", cal, "--out", tmp_path / "o.ply"))


@pytest.mark.parametrize("cam_csv, words", [
    ("X,Y,Z,u,v\n1,2,3,4,5\n", ["at least 6"]),
    ("X,Y,Z,u\n1,2,3,4\n", ["v"]),
    ("X,Y,Z,u,v\n" + "".join(f"{i},{j},0,{100 + i},{200 + j}\n" for i in range(3) for j in range(3)), ["coplanar"]),
    ("X,Y,Z,u,v\n1,2,3,nan,5\n" + "".join(f"{i},{i * i},{i ** 3},{i},{i}\n" for i in range(8)), ["finite"]),
])
def test_calibrate_points_bad_input(tmp_path, cam_csv, words):
    (tmp_path / "cam.csv").write_text(cam_csv)
    (tmp_path / "proj.csv").write_text("X,Y,Z,u\n" + "".join(f"{i},{i * i},{i ** 3},{i}\n" for i in range(8)))
    done = run("calibrate", "points", "--camera", tmp_path / "cam.csv", "--projector", tmp_path / "proj.csv",
               "--out", tmp_path / "cal.json")
    assert_user_error(done)
    assert any(w in done.stderr for w in words), done.stderr
    assert not (tmp_path / "cal.json").exists()


def test_calibrate_box_without_a_box(tmp_path, scan):
    _, capture, _ = scan
    done = run("calibrate", "box", capture, "--out", tmp_path / "cal.json")
    assert_user_error(done, "markers")
    assert not (tmp_path / "cal.json").exists()


# ---- any projector placement (SPEC §5, §6) ---------------------------------------------------
@pytest.fixture(scope="module")
def above(tmp_path_factory):
    """The projector ABOVE the camera: the baseline runs along the projector's columns."""
    work = tmp_path_factory.mktemp("above")
    rig = SimRig(scale=0.25, layout=RigLayout.ABOVE)
    cal = work / "calibration.json"
    save_calibration(rig.true_calibration(), cal)
    return rig, work, cal


def _simulate(rig, folder, axes):
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=axes)
    return save_capture(folder, pset, [rig.capture(img) for img in render_all(pset)])


def test_default_patterns_reconstruct_a_projector_above_the_camera(tmp_path, above):
    rig, _, cal = above
    patterns = tmp_path / "patterns"
    assert run("patterns", "--out", patterns, "--projector", f"{rig.projector.width}x{rig.projector.height}").returncode == 0
    manifest = json.loads((patterns / "manifest.json").read_text())
    assert manifest["axes"] == ["column", "row"]  # the default works whatever side the projector is on
    capture = tmp_path / "capture"
    shutil.copytree(patterns, capture)
    for f in manifest["frames"]:
        cv2.imwrite(str(capture / f["file"]), rig.capture(cv2.imread(str(patterns / f["file"]), cv2.IMREAD_UNCHANGED)))
    done = run("reconstruct", capture, "--calibration", cal, "--out", tmp_path / "cloud.ply")
    assert done.returncode == 0, done.stderr
    acc = evaluate(read_ply(tmp_path / "cloud.ply"), rig.truth())["subject"]
    assert acc.median_mm < 0.15 and acc.outlier_fraction < 0.004 and acc.coverage > 0.7, acc
    # with the calibration, the patterns command asks for the rows alone
    done = run("patterns", "--out", tmp_path / "p2", "--calibration", cal)
    assert done.returncode == 0 and "row stripes" in done.stdout, done.stdout
    assert json.loads((tmp_path / "p2" / "manifest.json").read_text())["axes"] == ["row"]


def test_stripes_along_the_baseline_are_exit_2_and_no_file(tmp_path, above):
    rig, work, cal = above
    capture = _simulate(rig, tmp_path / "columns", ("column",))
    out = tmp_path / "cloud.ply"
    assert_user_error(run("reconstruct", capture, "--calibration", cal, "--out", out), "baseline", "columns", "row")
    assert not out.exists() and not list(tmp_path.glob(".cloud.ply*"))


def test_rows_with_a_column_only_calibration_are_exit_2(tmp_path, above):
    rig, _, _ = above
    obj = calibration_to_dict(rig.true_calibration())
    obj["projector"]["axis"] = "column"
    obj["projector"]["K"][1] = None  # SPEC §4: row intrinsics unknown
    (tmp_path / "col.json").write_text(json.dumps(obj))
    capture = _simulate(rig, tmp_path / "rows", ("row",))
    out = tmp_path / "cloud.ply"
    assert_user_error(run("reconstruct", capture, "--calibration", tmp_path / "col.json", "--out", out),
                      "knows only the projector's columns")
    assert not out.exists()
    # and the patterns command, asked for this rig, says the calibration cannot serve it
    assert_user_error(run("patterns", "--out", tmp_path / "p", "--calibration", tmp_path / "col.json"), "baseline")


def test_an_all_black_capture_is_exit_2_and_no_file(tmp_path, scan):
    _, capture, cal = scan
    black = _copy(capture, tmp_path / "black")
    for f in json.loads((black / "manifest.json").read_text())["frames"]:
        img = cv2.imread(str(black / f["file"]), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(black / f["file"]), np.zeros_like(img))
    out = tmp_path / "cloud.ply"
    # refused where the capture is read (an unlit capture), before decoding finds nothing
    assert_user_error(run("reconstruct", black, "--calibration", cal, "--out", out), "white frame is no brighter")
    assert not out.exists() and not list(tmp_path.glob(".cloud.ply*"))


# ---- arguments that are words, not files (audit-cli) -----------------------------------------
@pytest.mark.parametrize("args", [
    ["patterns", "--projector", "64x48", "--out", "default"],  # --preset's default is the word 'default'
    ["patterns", "--projector", "64x48", "--preset", "paper", "--out", "paper"],
])
def test_an_output_named_like_a_keyword_can_be_written_again(tmp_path, args):
    """A keyword option's value (--preset default) is not an input even when a folder has its name:
    rerunning the command onto its own earlier output replaces it (it was refused as 'the input')."""
    for _ in range(2):
        done = run(*args, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
    assert (tmp_path / args[-1] / "manifest.json").is_file()


def test_a_path_argument_naming_the_output_is_still_refused(tmp_path, scan):
    _, capture, cal = scan
    out = tmp_path / "cal.json"
    shutil.copy(cal, out)
    assert_user_error(run("reconstruct", capture, "--calibration", out, "--out", tmp_path / "." / "cal.json"),
                      "is the input")


@pytest.mark.parametrize("argv", [["-q"], ["-v"], []])
def test_no_command_with_only_global_flags_is_the_desktop_app(monkeypatch, argv):
    """SPEC §6: `anklescan` is the desktop application; `anklescan -q` was an AttributeError traceback."""
    from anklescan.app import cli

    started = []
    monkeypatch.setattr(cli, "cmd_gui", lambda args: started.append(args.qt_args) or 0)
    assert cli.main(argv) == 0
    assert started == [[]]


@pytest.mark.parametrize("rows, words", [
    ("1,10,0,400,5\n", ["t.csv:2", "5 fields", "header has 4"]),  # z written with a decimal comma: 400,5
    ("1,10,0\n", ["t.csv:2", "3 fields"]),
])
def test_angles_rows_not_matching_the_header_are_malformed(tmp_path, rows, words):
    """`angles` took the first fields of a longer row (z = 400 from '400,5'), exit 0."""
    csv = tmp_path / "t.csv"
    csv.write_text("label,x,y,z\n" + rows + "2,0,0,0\n3,40,30,400\n4,40,0,0\n")
    assert_user_error(run("angles", csv), *words)
    csv.write_text("label,x,x,y,z\n1,10,0,0,400\n2,0,0,0,0\n")  # which x is the mark's?
    assert_user_error(run("angles", csv), "repeats a column")


def test_angles_errors_name_the_line_of_the_file(tmp_path):
    """Blank lines were dropped before counting: the error named line 3 for a value on line 5."""
    csv = tmp_path / "m.csv"
    csv.write_text("label,x,y,z\n\n1,10,0,400\n\n2,0,0,abc\n")
    assert_user_error(run("angles", csv), "m.csv:5", "abc")


@pytest.mark.parametrize("out", [".", "./", ".."])
def test_a_folder_output_onto_the_current_folder_is_one_clear_line(tmp_path, out):
    """`patterns --out .` in an empty folder put its temporary inside '.', then said the folder "holds
    files this command did not write"; `import --out .` said "Invalid argument (.)"."""
    here = tmp_path / "here"
    here.mkdir()
    assert_user_error(run("patterns", "--projector", "64x48", "--out", out, cwd=here), "current folder")
    assert list(here.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["here"]


@pytest.mark.parametrize("make, words", [
    (lambda p: p.mkdir(), ["is a folder"]),
    (lambda p: p.write_bytes(b"label,x,y,z\n1,10,0,400\xe9\n"), ["not UTF-8", "byte 22"]),  # a Latin-1 export
])
def test_csv_inputs_that_cannot_be_read_say_why_plainly(tmp_path, make, words):
    """The line quoted Python's exception ("[Errno 21] Is a directory: 'm.csv'", "'utf-8' codec
    can't decode byte 0xe9 in position 22: invalid continuation byte")."""
    make(tmp_path / "m.csv")
    for args in (["angles", tmp_path / "m.csv"],
                 ["calibrate", "points", "--camera", tmp_path / "m.csv", "--projector", tmp_path / "m.csv",
                  "--out", tmp_path / "c.json"]):
        done = run(*args)
        assert_user_error(done, *words)
        assert "Errno" not in done.stderr and "codec" not in done.stderr
