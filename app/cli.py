"""The ``anklescan`` command line (SPEC §6).

Every command turns a user's mistake into one line on stderr and exit code 2, and never leaves
a partly written output file (outputs are written to a temporary sibling and renamed).

Guards every command gets from ``main`` (so a new sub-command is covered without doing
anything): argument errors are one line and exit 2 (``_Parser.error``); ``--out`` may not
name, resolve to, sit inside or contain any existing path given as another argument
(``anklescan.core.atomic.guard_output`` over every path-like argument, before the command runs);
SIGTERM takes the same clean-up path as Ctrl-C (temporaries removed), exit 143; every error
message is folded onto one line, and library warnings (numpy, OpenCV) never reach stderr.
A command with inputs that are not plain arguments (a folder named in a file) calls
``guard_output(out, inputs)`` itself.
The commands themselves are in app/cli_commands.py; their imports are made inside each command
so that ``anklescan gui`` starts without loading the reconstruction stack and ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import signal
import sys
import warnings
from collections.abc import Callable
from types import FrameType
from typing import NoReturn

from anklescan.app.cli_commands import (
    cmd_angles,
    cmd_calibrate_board,
    cmd_calibrate_box,
    cmd_calibrate_export,
    cmd_calibrate_import,
    cmd_calibrate_level,
    cmd_calibrate_points,
    cmd_check,
    cmd_demo,
    cmd_gui,
    cmd_import_opencv_graycode,
    cmd_measure,
    cmd_patterns,
    cmd_reconstruct,
    set_verbose,
)
from anklescan.app.study_commands import cmd_export, cmd_report
from anklescan.core.limits import (
    MAX_BOARD_CORNERS,
    MAX_IMAGE_SIDE,
    MAX_MARK_DIAMETER_MM,
    MAX_MOTION_REFS,
    MAX_OPTION_MM,
    MAX_SWAY_MM,
    bounded_float,
    bounded_int,
    date_type,
    size_type,
)
from anklescan.core.output_files import OutputFile

EXIT_USER_ERROR = 2
EXIT_INTERNAL = 1
EXIT_TERMINATED = 128 + signal.SIGTERM
# Signals that end a command the way Ctrl-C does: temporaries removed, exit 128 + signal.
_CLEAN_EXIT_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))
# Every numeric option's type is one of anklescan.core.limits' bounded types (one mechanism,
# one-line errors, exit 2); a new option takes one too (bounded_int, bounded_float, size_type).
_size = size_type()
_BOARD = size_type(MAX_BOARD_CORNERS, "9x7")
_LENGTH_MM = bounded_float(0, MAX_OPTION_MM, "mm", lo_open=True)
_DEGREES = bounded_float(-90, 90, "°", lo_open=True)
_TOLERANCE_DEG = bounded_float(0, 90, "°", lo_open=True)
_AREA_CM2 = bounded_float(0, 1e6, "cm²", lo_open=True)
_DATE = date_type()
_RECORD_ID = bounded_int(1, 10**9)  # a trial or session number (far beyond any clinic's database)

# What every sub-parser's ``set_defaults(func=...)`` names: the command, given the parsed arguments,
# returning the exit code.
Command = Callable[[argparse.Namespace], int]


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage block) and exit 2, like every other error."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USER_ERROR, f"{_one_line(f'{self.prog}: error: {message}')} (see --help)\n")


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised in the main thread so that every ``except BaseException``
    clean-up (temporary files and folders) runs exactly as for Ctrl-C."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signum)
        self.signum = signum


def _on_sigterm(signum: int, frame: FrameType | None) -> NoReturn:
    for s in _CLEAN_EXIT_SIGNALS:  # a second signal must not interrupt the clean-up
        signal.signal(s, signal.SIG_IGN)
    raise Terminated(signum)


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="anklescan", description="Structured-light 3-D scanner for ankle posture.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="progress messages on stderr even when it is not a terminal (else stdout)")
    # no command (``anklescan -q``, not only a bare ``anklescan``) is the desktop app, as SPEC §6 says
    p.set_defaults(func=cmd_gui, qt_args=[])
    sub = p.add_subparsers(dest="command")

    g = sub.add_parser("gui", help="the desktop application (default)")
    g.add_argument("qt_args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    g.set_defaults(func=cmd_gui)

    d = sub.add_parser("demo", help="a whole simulated study (calibration, two simulated patients, "
                                    "three sessions, report) on the built-in simulated rig, no hardware")
    d.add_argument("--out", required=True, help="output folder")
    d.add_argument("--quick", action="store_true", help="one condition, four settings (a quick look)")
    d.add_argument("--study", action="store_true",
                   help="the paper's whole study: 4 patients with a sprain history and 4 without, barefoot and "
                        "in shoes, 3 trials each, and a retest visit four weeks on (96 scans, about 6 minutes)")
    d.add_argument("--sway", type=bounded_float(0, MAX_SWAY_MM, "mm"), default=0.0, metavar="MM",
                   help="one trial in three: the patient drifts up to MM mm during the scan (slower: each frame is "
                        "rendered at its own pose); moved trials are flagged")
    d.add_argument("--camera", choices=("webcam", "dslr"), default="webcam",
                   help="frame timing of the simulated camera for --sway (webcam 30 ms, DSLR 2 s a frame)")
    d.add_argument("--full-resolution", action="store_true",
                   help="simulate the 1600x1200 camera and 1024x768 projector (default: 0.75 of it, for speed)")
    d.set_defaults(func=cmd_demo, out_is_folder=True)

    pt = sub.add_parser("patterns", help="write the projector patterns and manifest.json")
    pt.add_argument("--out", required=True)
    pt.add_argument("--projector", type=_size, default=None,
                    help="projector resolution WxH (default: the calibration's, else 1024x768)")
    pt.add_argument("--preset", default="default", choices=["default", "paper", "short"],
                    help="default; paper (the paper's 18 frames); short (fewer frames, for slow cameras)")
    pt.add_argument("--motion-refs", type=bounded_int(0, MAX_MOTION_REFS), default=None,
                    help="repeats of a phase-frame pair spread over the scan, to measure how far the subject moved "
                         "(default: 9 for default, 7 for short, 0 for paper; 0 = none)")
    pt.add_argument("--axes", default=None,
                    help="column, row or column,row (default: both, which work whatever side of the camera the "
                         "projector stands on; with --calibration, what that rig needs; the paper preset: column)")
    pt.add_argument("--calibration", help="pick the stripe axes this rig needs: columns for a projector beside "
                                          "the camera, rows above or below it, both diagonal")
    pt.set_defaults(func=cmd_patterns, out_is_folder=True)

    r = sub.add_parser("reconstruct", help="decode + triangulate a capture to a PLY point cloud")
    r.add_argument("capture")
    r.add_argument("--calibration", required=True)
    r.add_argument("--out", required=True)
    r.set_defaults(func=cmd_reconstruct, out_file=OutputFile.POINT_CLOUD)

    c = sub.add_parser("calibrate", help="calibrate camera and projector")
    csub = c.add_subparsers(dest="calibrate_command", required=True)
    cp = csub.add_parser("points", help="the paper's two-step calibration from control points")
    cp.add_argument("--camera", required=True, nargs="+", action="extend",
                    help="CSV(s) with columns X,Y,Z,u,v; several (or the option repeated): e.g. the box at two heights")
    cp.add_argument("--projector", required=True, nargs="+", action="extend",
                    help="CSV(s) with columns X,Y,Z,u; several as for --camera")
    cp.add_argument("--out", required=True)
    cp.add_argument("--camera-size", type=_size, default=(1600, 1200), help="camera resolution WxH")
    cp.add_argument("--projector-size", type=_size, default=(1024, 768), help="projector resolution WxH")
    cp.set_defaults(func=cmd_calibrate_points, out_file=OutputFile.CALIBRATION)
    cb = csub.add_parser("box", help="automatic calibration from a scan of the calibration box")
    cb.add_argument("captures", nargs="+", metavar="CAPTURE",
                    help="one capture per box position: first at the table's height (it defines the world frame), "
                         "then at the knee's")
    cb.add_argument("--out", required=True)
    cb.set_defaults(func=cmd_calibrate_box, out_file=OutputFile.CALIBRATION)
    cbo = csub.add_parser("board", help="camera and projector from Gray-code captures of a printed chessboard")
    cbo.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture folders (column and row patterns)")
    cbo.add_argument("--board", type=_BOARD, required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x7")
    cbo.add_argument("--square", type=_LENGTH_MM, required=True, metavar="MM", help="square side, mm")
    cbo.add_argument("--distortion", default="k1k2",
                     help="free lens distortion terms: k1, k1k2 (default), k1k2p (+ tangential), full (+ k3), "
                          "for both devices or CAMERA/PROJECTOR such as k1/k1k2")
    cbo.add_argument("--out", required=True)
    cbo.set_defaults(func=cmd_calibrate_board, out_file=OutputFile.CALIBRATION)
    cl = csub.add_parser("level", help="the same calibration in the clinic's frame, from a scan of the level table")
    cl.add_argument("calibration", metavar="CAL.json")
    cl.add_argument("capture", metavar="TABLE_CAPTURE")
    cl.add_argument("--out", required=True)
    cl.add_argument("--table-size", default=None, metavar="LxW",
                    help="the reference table's top in mm, long side first (default 320x220: docs/calibration.md)")
    cl.set_defaults(func=cmd_calibrate_level, out_file=OutputFile.CALIBRATION)
    ci = csub.add_parser("import", help="an OpenCV FileStorage (XML/YAML) projector-camera calibration")
    ci.add_argument("file")
    ci.add_argument("--projector", type=_size, required=True, help="projector resolution WxH")
    ci.add_argument("--camera", type=_size, default=None, help="camera resolution WxH (if not in the file)")
    ci.add_argument("--unit", default="mm", choices=["mm", "cm", "m", "in"], help="the file's length unit")
    ci.add_argument("--out", required=True)
    ci.set_defaults(func=cmd_calibrate_import, out_file=OutputFile.CALIBRATION)
    ce = csub.add_parser("export", help="our calibration as an OpenCV FileStorage (.yml, .xml or .json)")
    ce.add_argument("calibration", metavar="CAL.json")
    ce.add_argument("--out", required=True)
    ce.set_defaults(func=cmd_calibrate_export, out_file=OutputFile.OPENCV_CALIBRATION)

    im = sub.add_parser("import", help="bring another tool's capture in as a capture")
    isub = im.add_subparsers(dest="import_command", required=True)
    io = isub.add_parser("opencv-graycode", help="OpenCV GrayCodePattern frames (procam-calibration's step)")
    io.add_argument("src", metavar="SRC", help="folder of the frames, in OpenCV's order by name")
    io.add_argument("--projector", type=_size, required=True, help="projector resolution WxH")
    io.add_argument("--step", type=bounded_int(1, MAX_IMAGE_SIDE), default=1, help="projector pixels per code (graycode_step)")
    io.add_argument("--out", required=True)
    io.set_defaults(func=cmd_import_opencv_graycode, out_is_folder=True)

    m = sub.add_parser("measure", help="reconstruct, find and label the 7 marks, compute the angles")
    m.add_argument("capture", metavar="CAPTURE", help="a capture folder (frames + manifest.json)")
    m.add_argument("--calibration", required=True, metavar="FILE", help="the rig's calibration JSON")
    m.add_argument("--mark-diameter", type=bounded_float(0, MAX_MARK_DIAMETER_MM, "mm", lo_open=True), default=None,
                   metavar="MM",
                   help="the marks' diameter in mm (default: measured from the capture)")
    m.add_argument("--out", required=True, metavar="RESULT.json",
                   help="the result file to write (marks, angles ± SD, motion); written only for a complete "
                        "measurement")
    m.add_argument("--motion-threshold", type=_LENGTH_MM, default=0.5, metavar="MM",
                   help="flag the trial when the subject moved more than this during the scan, mm (default 0.5)")
    m.set_defaults(func=cmd_measure, out_file=OutputFile.MEASUREMENT)

    ck = sub.add_parser("check", help="the daily check: measure a known-angle object and compare with its set angles")
    ck.add_argument("capture")
    ck.add_argument("--calibration", required=True)
    ck.add_argument("--inversion", type=_DEGREES, required=True, metavar="DEG", help="the object's set inversion")
    ck.add_argument("--plantar-flexion", type=_DEGREES, required=True, metavar="DEG",
                    help="the object's set plantar flexion")
    ck.add_argument("--tolerance", type=_TOLERANCE_DEG, default=0.3, metavar="DEG",
                    help="largest difference on either axis that passes, degrees (default 0.3)")
    ck.add_argument("--flatness", type=_LENGTH_MM, default=0.3, metavar="MM",
                    help="largest sag of the flat top that passes, mm (default 0.3; the object must be flatter)")
    ck.add_argument("--min-area", type=_AREA_CM2, default=100.0, metavar="CM2",
                    help="the object's top is at least this large, cm² (default 100)")
    ck.add_argument("--out", default=None, metavar="CHECK.json")
    ck.set_defaults(func=cmd_check, out_file=OutputFile.DAILY_CHECK)

    rp = sub.add_parser("report", help="the study from a data folder's own database (SPEC §7)")
    rp.add_argument("--data", required=True, metavar="DIR", help="the data folder (its anklescan.sqlite)")
    rp.add_argument("--out", required=True, metavar="OUTDIR",
                    help="a new or empty folder, or an earlier report's (replaced)")
    rp.add_argument("--patient", default=None, metavar="CODE", help="one patient's trials only")
    rp.add_argument("--from", dest="date_from", type=_DATE, default=None, metavar="YYYY-MM-DD",
                    help="visits on or after this date")
    rp.add_argument("--to", dest="date_to", type=_DATE, default=None, metavar="YYYY-MM-DD",
                    help="visits on or before this date")
    rp.set_defaults(func=cmd_report, out_is_folder=True)

    ex = sub.add_parser("export", help="one trial's marks as C3D, or a session's results as FHIR (SPEC §7)")
    ex.add_argument("--data", required=True, metavar="DIR", help="the data folder (its anklescan.sqlite)")
    which = ex.add_mutually_exclusive_group(required=True)
    which.add_argument("--trial", type=_RECORD_ID, metavar="N", help="the trial's number (trials.csv `trial`)")
    which.add_argument("--session", type=_RECORD_ID, metavar="N", help="the session's number")
    ex.add_argument("--format", required=True, choices=("c3d", "fhir"))
    ex.add_argument("--out", required=True, metavar="FILE")
    ex.set_defaults(func=cmd_export)

    a = sub.add_parser("angles", help="SPEC §3 angles from labelled marks (label,x,y,z)")
    a.add_argument("marks")
    a.add_argument("--sigma", type=_LENGTH_MM, default=0.2, help="mark position uncertainty, mm (default 0.2)")
    a.set_defaults(func=cmd_angles)
    _declare_non_path_options(p)
    return p


# Free-text option values that are codes or words, never files (a patient code, stripe axes, a
# distortion model, a table size, Qt's own arguments).
_TEXT_OPTIONS = frozenset({"patient", "axes", "distortion", "table_size", "qt_args"})


def _declare_non_path_options(parser: argparse.ArgumentParser) -> None:
    """Set ``non_path_options`` on every (sub-)parser: the arguments whose values never name a
    file: keywords (``choices``: ``--preset default``, ``--camera webcam``, ``--format fhir``),
    typed values, flags and _TEXT_OPTIONS. ``_path_arguments`` skips them, so a folder that
    happens to be called like a keyword (``patterns --out default``, run twice) is not taken
    for the command's input. Any other string argument is a path, a new one included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _declare_non_path_options(sub)
    words = {a.dest for a in parser._actions
             if a.choices is not None or a.type is not None or a.nargs == 0 or a.dest in _TEXT_OPTIONS}
    parser.set_defaults(non_path_options=frozenset(words))


def _path_arguments(args: argparse.Namespace) -> list[str | os.PathLike[str]]:
    """Every path argument other than --out that names an existing file or folder: the inputs
    (not a keyword or code that happens to be a file's name too: ``_declare_non_path_options``)."""
    values: list[str | os.PathLike[str]] = []
    not_paths: frozenset[str] = getattr(args, "non_path_options", frozenset())
    for key, v in vars(args).items():
        if key == "out" or key in not_paths or callable(v):
            continue
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(item, (str, os.PathLike)) and str(item) and os.path.lexists(item):
                values.append(item)
    return values


MAX_MESSAGE_CHARS = 400  # a message quoting a 5000-digit "number" must stay readable


def _one_line(text: object) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= MAX_MESSAGE_CHARS else line[:MAX_MESSAGE_CHARS - 1] + "…"


def _say(text: str) -> None:
    print(f"anklescan: {_one_line(text)}", file=sys.stderr, flush=True)


# Everything a command writes is patient data or derived from it: private whatever the
# user's umask (files 0600, folders 0700 from their creation, not chmod-ed at the end).
PRIVATE_UMASK = 0o077


def _check_out_kind(args: argparse.Namespace) -> None:
    """A trailing '/' means a folder, as a user (and cp, mv) would read it: a command that
    writes one file refuses it instead of writing a file called like the folder. A command
    writing a folder declares it with ``set_defaults(out_is_folder=True)``."""
    from anklescan.core.errors import AnkleScanError

    out = getattr(args, "out", None)
    if out is None or getattr(args, "out_is_folder", False):
        return
    text = os.fsdecode(out)
    if text.endswith(("/", os.sep)) or (os.altsep and text.endswith(os.altsep)):
        raise AnkleScanError(f"--out {text} ends with '/', which names a folder, but this command writes "
                             f"one file: give a file name (e.g. {text.rstrip('/' + os.sep)}/result)")
    from anklescan.core.atomic import check_may_replace
    from anklescan.core.output_files import may_replace

    check_may_replace(out, "--out")
    kind = _output_file(args)
    if kind is not None and not may_replace(out, kind):
        raise AnkleScanError(f"--out {text} is a file this command did not write (not a {kind}); it was left "
                             "untouched: give another name, or move that file away first")


def _output_file(args: argparse.Namespace) -> OutputFile | None:
    """The kind of file the command writes at --out (``export``'s by its --format)."""
    if args.func is cmd_export:
        return OutputFile.C3D if args.format == "c3d" else OutputFile.FHIR_BUNDLE
    kind: OutputFile | None = getattr(args, "out_file", None)
    return kind


def _check_not_current_folder(out: str | os.PathLike[str]) -> None:
    """--out may not be the folder the user stands in, or one above it ('.', '..'): a folder output
    is built beside its target, which for '.' is inside it, and replacing it would leave the
    user's shell in a removed folder. (The desktop app's folders are chosen whole, so this is the
    command line's rule, not guard_output's.)"""
    from anklescan.core.errors import AnkleScanError

    try:
        cwd = os.path.realpath(os.getcwd())
    except OSError:  # the current folder was removed: nothing to protect
        return
    target = os.path.realpath(out)
    try:
        above = os.path.commonpath([cwd, target]) == target
    except ValueError:  # on different drives (Windows): not above it
        above = False
    if above:
        raise AnkleScanError(f"--out {os.fsdecode(out)} is the current folder or holds it; give a new folder's name")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args = parser.parse_args(argv or ["gui"])
    umask = os.umask(PRIVATE_UMASK)
    try:
        if args.func is cmd_gui:
            return _run_gui(args)
        return _run(args)
    finally:
        os.umask(umask)


def _run_gui(args: argparse.Namespace) -> int:
    """The desktop app: a Qt or OpenGL library that cannot be loaded is one line and exit 2."""
    command: Command = args.func
    try:
        return command(args)
    except ImportError as exc:
        _say(f"error: a library the desktop application needs could not be loaded ({exc.name or 'unknown'}: "
             f"{exc}); check the installation and the memory limits")
        return EXIT_USER_ERROR
    except MemoryError:
        _say("error: out of memory while starting the desktop application")
        return EXIT_USER_ERROR


def _run(args: argparse.Namespace) -> int:
    from anklescan.core.errors import AnkleScanError

    set_verbose(getattr(args, "verbose", False))
    # OpenCV's own log lines ("[ WARN:0@...]") would add to the one error line; read when
    # cv2 is first imported, which the commands do lazily after this point
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    # file names that are not valid UTF-8 print as their bytes, never crash a print; a stream
    # that is not a text file (None under pythonw, a replacement without reconfigure) is left as it is
    if isinstance(sys.stdout, io.TextIOWrapper):
        with contextlib.suppress(ValueError):
            sys.stdout.reconfigure(errors="surrogateescape")
    previous = {s: signal.signal(s, _on_sigterm) for s in _CLEAN_EXIT_SIGNALS} if _main_thread() else {}
    try:
        with warnings.catch_warnings():
            # Nonsense input is refused by validation; stray numpy/OpenCV warnings on stderr
            # would break the one-line-error contract without telling the user more.
            warnings.simplefilter("ignore")
            inputs = _path_arguments(args)
            if inputs:
                from anklescan.core.limits import check_input_file

                for path in inputs:  # no /dev/zero, FIFO or 10 GB "CSV" read whole
                    check_input_file(path, "input")
            if getattr(args, "out", None) is not None:
                from anklescan.core.atomic import guard_output

                guard_output(args.out, inputs, what="--out")
                _check_not_current_folder(args.out)
                _check_out_kind(args)
            command: Command = args.func
            return command(args)
    except AnkleScanError as exc:
        _say(f"error: {exc}")
        return EXIT_USER_ERROR
    except BrokenPipeError:
        # stdout closed early (``| head``): end quietly like other tools, and keep Python
        # from printing a second error when it flushes stdout at exit
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except MemoryError:
        _say("error: out of memory: the input is larger than this computer can process "
             "(or a memory limit such as ulimit -v is set); nothing was written")
        return EXIT_USER_ERROR
    except ImportError as exc:
        # a library that cannot be loaded (missing, damaged, or no memory to map it: ulimit -v)
        _say(f"error: a library could not be loaded ({exc.name or 'unknown'}: {exc}); "
             "check the installation and the memory limits; nothing was written")
        return EXIT_USER_ERROR
    except OSError as exc:
        # Disk full, permissions, a vanished file: the user's environment, not a bug.
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        _say(f"error: {getattr(exc, 'strerror', None) or exc or type(exc).__name__}{where}")
        return EXIT_USER_ERROR
    except Terminated as exc:
        _say(f"terminated by {signal.Signals(exc.signum).name}; temporary files removed")
        return 128 + exc.signum
    except KeyboardInterrupt:
        _say("interrupted")
        return 130
    except Exception as exc:  # noqa: BLE001 - last line of defence: one line, never a traceback
        if os.environ.get("ANKLESCAN_DEBUG"):
            raise
        _say(f"internal error: {type(exc).__name__}: {exc} (set ANKLESCAN_DEBUG=1 for details)")
        return EXIT_INTERNAL
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    sys.exit(main())
