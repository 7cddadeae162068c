"""The ``anklescan`` command line (SPEC §6).

Every command turns a user's mistake into one line on stderr and exit code 2, and never leaves
a partly written output file (outputs are written to a temporary sibling and renamed).
Imports are made inside the commands so that ``anklescan gui`` starts without loading the
reconstruction stack and ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

EXIT_USER_ERROR = 2
EXIT_INTERNAL = 1


class Progress:
    """Step messages on stderr, so stdout stays machine-readable."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.t0 = time.perf_counter()

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=sys.stderr, flush=True)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        w, h = int(w), int(h)
        if w <= 0 or h <= 0:
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1024x768, not {text!r}") from None


# ---------------------------------------------------------------------------- commands
def cmd_gui(args) -> int:
    from app.main_window import run_gui

    return run_gui(args.qt_args)


def cmd_patterns(args) -> int:
    from core.patterns import make_pattern_set, write_patterns

    width, height = args.projector
    from core.motion import default_motion_refs

    refs = default_motion_refs(args.preset) if args.motion_refs is None else args.motion_refs
    pset = make_pattern_set(args.preset, width, height, axes=tuple(args.axes.split(",")), motion_refs=refs)
    out = write_patterns(pset, args.out)
    print(f"wrote {len(pset.frames)} frames ({args.preset}, {width}x{height}) and manifest.json to {out}")
    return 0


def cmd_reconstruct(args) -> int:
    from core.calibration_file import load_calibration
    from core.capture import load_capture
    from core.pointcloud import write_ply
    from core.reconstruct import reconstruct

    progress = Progress(args.quiet)
    cal = load_calibration(args.calibration)
    progress(f"loading capture {args.capture}")
    capture = load_capture(args.capture)
    progress("decoding and triangulating")
    cloud = reconstruct(capture, cal)
    progress(f"writing {len(cloud)} points")
    write_ply(args.out, cloud, comments=[f"capture {Path(args.capture).name}"])
    print(f"wrote {len(cloud)} points to {args.out} ({cloud.meta.get('summary', '')})")
    return 0


def cmd_calibrate_points(args) -> int:
    from core.calibrate import run_calibrate_points

    report = run_calibrate_points(args.camera, args.projector, args.out,
                                  camera_size=args.camera_size, projector_size=args.projector_size)
    print(report.format_text())
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_calibrate_box(args) -> int:
    from core.calibration_box import calibrate_from_box_capture
    from core.calibration_file import save_calibration

    cal, report = calibrate_from_box_capture(args.capture)
    save_calibration(cal, args.out)
    print(report.format_text())
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_measure(args) -> int:
    from core.errors import AnkleScanError
    from core.measure import run_measure

    if not (args.motion_threshold > 0 and args.motion_threshold < float("inf")):
        raise AnkleScanError(f"--motion-threshold must be a positive number of mm, not {args.motion_threshold}")
    result = run_measure(args.capture, args.calibration, args.out, motion_threshold_mm=args.motion_threshold)
    print(result.format_text())
    return 0


def cmd_angles(args) -> int:
    from core.angles import compute_angles, format_angles, read_marks_csv

    marks = read_marks_csv(args.marks)
    print(format_angles(compute_angles(marks, sigma_mm=args.sigma)))
    return 0


def cmd_demo(args) -> int:
    from app.demo import run_demo

    from app.demo import DEMO_SCALE

    if not (0 <= args.sway < 50):
        from core.errors import AnkleScanError
        raise AnkleScanError(f"--sway must be 0 to 50 mm, not {args.sway}")
    return run_demo(Path(args.out), quick=args.quick, progress=Progress(args.quiet),
                    scale=1.0 if args.full_resolution else DEMO_SCALE, sway_mm=args.sway, camera=args.camera)


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="anklescan", description="Structured-light 3-D scanner for ankle posture.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    sub = p.add_subparsers(dest="command")

    g = sub.add_parser("gui", help="the desktop application (default)")
    g.add_argument("qt_args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    g.set_defaults(func=cmd_gui)

    d = sub.add_parser("demo", help="a whole clinical session on the built-in simulated rig")
    d.add_argument("--out", required=True, help="output folder")
    d.add_argument("--quick", action="store_true", help="one condition, four settings (a quick look)")
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
    pt.add_argument("--projector", type=_size, default=(1024, 768), help="projector resolution WxH")
    pt.add_argument("--preset", default="default", choices=["default", "paper", "short"],
                    help="default; paper (the paper's 18 frames); short (fewer frames, for slow cameras)")
    pt.add_argument("--motion-refs", type=int, default=None,
                    help="repeats of a phase-frame pair spread over the scan, to measure how far the subject moved "
                         "(default: 3 for default, 2 for short, 0 for paper; 0 = none)")
    pt.add_argument("--axes", default="column", help="column, or column,row for calibration scans")
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

    m = sub.add_parser("measure", help="reconstruct, find and label the 7 marks, compute the angles")
    m.add_argument("capture")
    m.add_argument("--calibration", required=True)
    m.add_argument("--out", required=True)
    m.add_argument("--motion-threshold", type=float, default=0.5,
                   help="flag the trial when the subject moved more than this during the scan, mm (default 0.5)")
    m.set_defaults(func=cmd_measure)

    a = sub.add_parser("angles", help="SPEC §3 angles from labelled marks (label,x,y,z)")
    a.add_argument("marks")
    a.add_argument("--sigma", type=float, default=0.2, help="mark position uncertainty, mm (default 0.2)")
    a.set_defaults(func=cmd_angles)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args = parser.parse_args(argv or ["gui"])
    from core.errors import AnkleScanError

    try:
        return args.func(args)
    except AnkleScanError as exc:
        print(f"anklescan: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except (OSError, MemoryError) as exc:
        # Disk full, permissions, a vanished file: the user's environment, not a bug.
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        print(f"anklescan: error: {getattr(exc, 'strerror', None) or exc}{where}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("anklescan: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last line of defence: one line, never a traceback
        if os.environ.get("ANKLESCAN_DEBUG"):
            raise
        print(f"anklescan: internal error: {type(exc).__name__}: {exc} (set ANKLESCAN_DEBUG=1 for details)",
              file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
