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
import os
import signal
import sys
import warnings

from anklescan.app.cli_commands import (cmd_angles, cmd_calibrate_board, cmd_calibrate_box, cmd_calibrate_export,
                                        cmd_calibrate_import, cmd_calibrate_level, cmd_calibrate_points, cmd_demo,
                                        cmd_gui, cmd_import_opencv_graycode, cmd_measure, cmd_patterns,
                                        cmd_reconstruct, set_verbose)

EXIT_USER_ERROR = 2
EXIT_INTERNAL = 1
EXIT_TERMINATED = 128 + signal.SIGTERM
# Signals that end a command the way Ctrl-C does: temporaries removed, exit 128 + signal.
_CLEAN_EXIT_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))
# Largest projector / camera side accepted on the command line (same as anklescan.core.limits, which
# is not imported here so that --help stays instant).
MAX_SIDE = 16384


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage block) and exit 2, like every other error."""

    def error(self, message: str):
        self.exit(EXIT_USER_ERROR, f"{_one_line(f'{self.prog}: error: {message}')} (see --help)\n")


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised in the main thread so that every ``except BaseException``
    clean-up (temporary files and folders) runs exactly as for Ctrl-C."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signum)
        self.signum = signum


def _on_sigterm(signum, frame):
    for s in _CLEAN_EXIT_SIGNALS:  # a second signal must not interrupt the clean-up
        signal.signal(s, signal.SIG_IGN)
    raise Terminated(signum)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        if len(w) > 6 or len(h) > 6:
            raise ValueError
        w, h = int(w), int(h)
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1024x768, not {text[:40]!r}") from None
    if w > MAX_SIDE or h > MAX_SIDE:
        raise argparse.ArgumentTypeError(f"{w}x{h} is beyond any real camera or projector "
                                         f"(at most {MAX_SIDE} px a side)")
    return w, h


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, not {text[:40]!r}") from None
    if not 0 < v < 1e6:  # math.isfinite without importing math: nan fails both comparisons
        raise argparse.ArgumentTypeError(f"expected a positive finite number, not {text[:40]!r}")
    return v


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (v > 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive number, not {text!r}")
    return v


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, not {text!r}")
    return v


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="anklescan", description="Structured-light 3-D scanner for ankle posture.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="progress messages on stderr even when it is not a terminal (else stdout)")
    sub = p.add_subparsers(dest="command")

    g = sub.add_parser("gui", help="the desktop application (default)")
    g.add_argument("qt_args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    g.set_defaults(func=cmd_gui)

    d = sub.add_parser("demo", help="a whole clinical session on the built-in simulated rig")
    d.add_argument("--out", required=True, help="output folder")
    d.add_argument("--quick", action="store_true", help="one condition, four settings (a quick look)")
    d.add_argument("--study", action="store_true",
                   help="the paper's whole study: 4 patients with a sprain history and 4 without, barefoot and "
                        "in shoes, 3 trials each (48 scans, several minutes)")
    d.add_argument("--sway", type=float, default=0.0, metavar="MM",
                   help="one trial in three: the patient drifts up to MM mm during the scan (slower: each frame is "
                        "rendered at its own pose); moved trials are flagged")
    d.add_argument("--camera", choices=("webcam", "dslr"), default="webcam",
                   help="frame timing of the simulated camera for --sway (webcam 30 ms, DSLR 2 s a frame)")
    d.add_argument("--full-resolution", action="store_true",
                   help="simulate the 1600x1200 camera and 1024x768 projector (default: 0.75 of it, for speed)")
    d.set_defaults(func=cmd_demo)

    pt = sub.add_parser("patterns", help="write the projector patterns and manifest.json")
    pt.add_argument("--out", required=True)
    pt.add_argument("--projector", type=_size, default=None,
                    help="projector resolution WxH (default: the calibration's, else 1024x768)")
    pt.add_argument("--preset", default="default", choices=["default", "paper", "short"],
                    help="default; paper (the paper's 18 frames); short (fewer frames, for slow cameras)")
    pt.add_argument("--motion-refs", type=int, default=None,
                    help="repeats of a phase-frame pair spread over the scan, to measure how far the subject moved "
                         "(default: 9 for default, 7 for short, 0 for paper; 0 = none)")
    pt.add_argument("--axes", default=None,
                    help="column, row or column,row (default: both, which work whatever side of the camera the "
                         "projector stands on; with --calibration, what that rig needs; the paper preset: column)")
    pt.add_argument("--calibration", help="pick the stripe axes this rig needs: columns for a projector beside "
                                          "the camera, rows above or below it, both diagonal")
    pt.set_defaults(func=cmd_patterns)

    r = sub.add_parser("reconstruct", help="decode + triangulate a capture to a PLY point cloud")
    r.add_argument("capture")
    r.add_argument("--calibration", required=True)
    r.add_argument("--out", required=True)
    r.set_defaults(func=cmd_reconstruct)

    c = sub.add_parser("calibrate", help="calibrate camera and projector")
    csub = c.add_subparsers(dest="calibrate_command", required=True)
    cp = csub.add_parser("points", help="the paper's two-step calibration from control points")
    cp.add_argument("--camera", required=True, help="CSV with columns X,Y,Z,u,v")
    cp.add_argument("--projector", required=True, help="CSV with columns X,Y,Z,u")
    cp.add_argument("--out", required=True)
    cp.add_argument("--camera-size", type=_size, default=(1600, 1200), help="camera resolution WxH")
    cp.add_argument("--projector-size", type=_size, default=(1024, 768), help="projector resolution WxH")
    cp.set_defaults(func=cmd_calibrate_points)
    cb = csub.add_parser("box", help="automatic calibration from a scan of the calibration box")
    cb.add_argument("capture")
    cb.add_argument("--out", required=True)
    cb.set_defaults(func=cmd_calibrate_box)
    cbo = csub.add_parser("board", help="camera and projector from Gray-code captures of a printed chessboard")
    cbo.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture folders (column and row patterns)")
    cbo.add_argument("--board", type=_size, required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x7")
    cbo.add_argument("--square", type=_positive_float, required=True, metavar="MM", help="square side, mm")
    cbo.add_argument("--distortion", default="k1k2",
                     help="free lens distortion terms: k1, k1k2 (default), k1k2p (+ tangential), full (+ k3), "
                          "for both devices or CAMERA/PROJECTOR such as k1/k1k2")
    cbo.add_argument("--out", required=True)
    cbo.set_defaults(func=cmd_calibrate_board)
    cl = csub.add_parser("level", help="the same calibration in the clinic's frame, from a scan of the level table")
    cl.add_argument("calibration", metavar="CAL.json")
    cl.add_argument("capture", metavar="TABLE_CAPTURE")
    cl.add_argument("--out", required=True)
    cl.set_defaults(func=cmd_calibrate_level)
    ci = csub.add_parser("import", help="an OpenCV FileStorage (XML/YAML) projector-camera calibration")
    ci.add_argument("file")
    ci.add_argument("--projector", type=_size, required=True, help="projector resolution WxH")
    ci.add_argument("--camera", type=_size, default=None, help="camera resolution WxH (if not in the file)")
    ci.add_argument("--unit", default="mm", choices=["mm", "cm", "m", "in"], help="the file's length unit")
    ci.add_argument("--out", required=True)
    ci.set_defaults(func=cmd_calibrate_import)
    ce = csub.add_parser("export", help="our calibration as an OpenCV FileStorage (.yml, .xml or .json)")
    ce.add_argument("calibration", metavar="CAL.json")
    ce.add_argument("--out", required=True)
    ce.set_defaults(func=cmd_calibrate_export)

    im = sub.add_parser("import", help="bring another tool's capture in as a capture")
    isub = im.add_subparsers(dest="import_command", required=True)
    io = isub.add_parser("opencv-graycode", help="OpenCV GrayCodePattern frames (procam-calibration's step)")
    io.add_argument("src", metavar="SRC", help="folder of the frames, in OpenCV's order by name")
    io.add_argument("--projector", type=_size, required=True, help="projector resolution WxH")
    io.add_argument("--step", type=_positive_int, default=1, help="projector pixels per code (graycode_step)")
    io.add_argument("--out", required=True)
    io.set_defaults(func=cmd_import_opencv_graycode)

    m = sub.add_parser("measure", help="reconstruct, find and label the 7 marks, compute the angles")
    m.add_argument("capture")
    m.add_argument("--calibration", required=True)
    m.add_argument("--mark-diameter", type=float, default=None, metavar="MM",
                   help="the marks' diameter in mm (default: measured from the capture)")
    m.add_argument("--out", required=True)
    m.add_argument("--motion-threshold", type=float, default=0.5,
                   help="flag the trial when the subject moved more than this during the scan, mm (default 0.5)")
    m.set_defaults(func=cmd_measure)

    a = sub.add_parser("angles", help="SPEC §3 angles from labelled marks (label,x,y,z)")
    a.add_argument("marks")
    a.add_argument("--sigma", type=_positive, default=0.2, help="mark position uncertainty, mm (default 0.2)")
    a.set_defaults(func=cmd_angles)
    return p


def _path_arguments(args) -> list[str]:
    """Every argument other than --out that names an existing file or folder: the inputs."""
    values = []
    for key, v in vars(args).items():
        if key == "out" or callable(v):
            continue
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(item, (str, os.PathLike)) and str(item) and os.path.lexists(item):
                values.append(item)
    return values


MAX_MESSAGE_CHARS = 400  # a message quoting a 5000-digit "number" must stay readable


def _one_line(text) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= MAX_MESSAGE_CHARS else line[:MAX_MESSAGE_CHARS - 1] + "…"


def _say(text: str) -> None:
    print(f"anklescan: {_one_line(text)}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args = parser.parse_args(argv or ["gui"])
    if args.func is cmd_gui:
        return args.func(args)
    from anklescan.core.errors import AnkleScanError

    set_verbose(getattr(args, "verbose", False))
    # OpenCV's own log lines ("[ WARN:0@...]") would add to the one error line; read when
    # cv2 is first imported, which the commands do lazily after this point
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    try:  # file names that are not valid UTF-8 print as their bytes, never crash a print
        sys.stdout.reconfigure(errors="surrogateescape")
    except (AttributeError, ValueError):
        pass
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
            return args.func(args)
    except AnkleScanError as exc:
        _say(f"error: {exc}")
        return EXIT_USER_ERROR
    except BrokenPipeError:
        # stdout closed early (``| head``): end quietly like other tools, and keep Python
        # from printing a second error when it flushes stdout at exit
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 128 + signal.SIGPIPE
    except (OSError, MemoryError) as exc:
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
