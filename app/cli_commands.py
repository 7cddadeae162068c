"""The ``anklescan`` sub-commands' implementations (app.cli holds the parser and the guards
every command gets from ``main``). Imports are made inside the commands so that ``anklescan gui``
starts without loading the reconstruction stack and ``--help`` is instant."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

_VERBOSE = False  # set by app.cli.main from -v (set_verbose)


class Progress:
    """Step messages: on stderr when it is a terminal (or with -v), else on stdout, so that a
    script or log capturing stderr sees exactly one line when a command fails."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.stream = sys.stderr if (_VERBOSE or sys.stderr.isatty()) else sys.stdout
        self.t0 = time.perf_counter()

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=self.stream, flush=True)


def set_verbose(verbose: bool) -> None:
    """-v: progress messages on stderr even when it is not a terminal."""
    global _VERBOSE
    _VERBOSE = bool(verbose)


def cmd_gui(args: argparse.Namespace) -> int:
    from anklescan.app.main_window import run_gui

    return run_gui(args.qt_args)


def cmd_patterns(args: argparse.Namespace) -> int:
    from anklescan.core.scan.patterns import make_pattern_set, write_patterns
    from anklescan.core.vocabulary import Axis

    args.projector_default = args.projector is None
    width, height = args.projector or (1024, 768)
    if args.axes:
        axes, why = tuple(a.strip() for a in args.axes.split(",")), "as asked"
    elif args.calibration:
        from anklescan.core.calibration.model.file import load_calibration
        from anklescan.core.scan.triangulate import scan_axes

        cal = load_calibration(args.calibration)
        if (cal.projector.width, cal.projector.height) != (width, height) and args.projector_default:
            width, height = cal.projector.width, cal.projector.height
        from anklescan.core.scan.triangulate import check_geometry

        axes, why = scan_axes(cal), f"what the rig of {Path(args.calibration).name} needs"
        check_geometry(cal, axes)
    elif args.preset == "paper":
        axes, why = (Axis.COLUMN,), "the paper's 18 sheets; --axes column,row for a projector above the camera"
    else:
        axes, why = (Axis.COLUMN, Axis.ROW), "for a projector on any side of the camera; --calibration picks fewer"
    from anklescan.core.scan.motion import default_motion_refs

    refs = default_motion_refs(args.preset) if args.motion_refs is None else args.motion_refs
    pset = make_pattern_set(args.preset, width, height, axes=axes, motion_refs=refs)
    out = write_patterns(pset, args.out)
    print(f"wrote {len(pset.frames)} frames ({args.preset}, {width}x{height}, {' + '.join(axes)} stripes: {why}) "
          f"and manifest.json to {out}")
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from anklescan.core.calibration.model.file import load_calibration
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.pointcloud import write_ply
    from anklescan.core.scan.reconstruct import reconstruct
    from anklescan.core.scan.triangulate import prepare

    progress = Progress(args.quiet)
    cal = load_calibration(args.calibration)
    progress(f"loading capture {args.capture}")
    # A plain executor, not app.background: there is no Qt event loop here, and it only overlaps
    # two steps of this one command (the calibration's grids are built while the frames are
    # read; PNG decoding leaves the cores part idle), joined before the command goes on.
    with ThreadPoolExecutor(max_workers=1) as pool:
        ready = pool.submit(prepare, cal)
        capture = load_capture(args.capture)
        ready.result()
    progress("decoding and triangulating")
    cloud = reconstruct(capture, cal)
    if len(cloud) == 0:
        from anklescan.core.errors import AnkleScanError

        raise AnkleScanError(f"no surface points could be decoded from {args.capture} "
                             f"({cloud.meta.get('summary', 'nothing decoded')}); nothing written")
    progress(f"writing {len(cloud)} points")
    write_ply(args.out, cloud, comments=[f"capture {Path(args.capture).name}"])
    print(f"wrote {len(cloud)} points to {args.out} ({cloud.meta.get('summary', '')})")
    return 0


def cmd_calibrate_points(args: argparse.Namespace) -> int:
    from anklescan.core.calibration.procedures.calibrate import run_calibrate_points

    report = run_calibrate_points(args.camera, args.projector, args.out,
                                  camera_size=args.camera_size, projector_size=args.projector_size)
    print(report.format_text())
    from anklescan.core.calibration.model.file import load_calibration, volume_text
    print(volume_text(load_calibration(args.out)))
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_calibrate_box(args: argparse.Namespace) -> int:
    from anklescan.core.calibration.model.file import save_calibration
    from anklescan.core.calibration.procedures.box import calibrate_from_box_captures, position_summary

    Progress(args.quiet)(f"reading {len(args.captures)} box capture(s)")
    cal, report, positions = calibrate_from_box_captures(args.captures)
    save_calibration(cal, args.out)
    print(report.format_text())
    from anklescan.core.calibration.model.file import volume_text
    print(volume_text(cal))
    for line in position_summary(positions):
        print(line)
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_import_opencv_graycode(args: argparse.Namespace) -> int:
    from anklescan.core.scan.opencv_graycode import import_opencv_graycode
    from anklescan.core.vocabulary import Axis

    width, height = args.projector
    pset = import_opencv_graycode(args.src, args.out, width, height, args.step)
    ac, ar = pset.code(Axis.COLUMN), pset.code(Axis.ROW)  # an OpenCV Gray-code set always has both
    print(f"imported {len(pset.frames)} frames ({ac.bits} column bits, {ar.bits} row bits, step {args.step}) "
          f"as a capture in {args.out}")
    return 0


def cmd_calibrate_import(args: argparse.Namespace) -> int:
    import numpy as np

    from anklescan.core.calibration.model.file import save_calibration
    from anklescan.core.calibration.procedures.opencv_calibration import import_opencv_calibration

    cal = import_opencv_calibration(args.file, args.projector, args.camera, args.unit)
    save_calibration(cal, args.out)
    b = cal.projector.center - cal.camera.center
    print(f"imported {args.file}: camera {cal.camera.width}x{cal.camera.height}, projector "
          f"{cal.projector.width}x{cal.projector.height}, baseline {np.linalg.norm(b):.1f} mm "
          f"(projector at {b[0]:+.1f}, {b[1]:+.1f}, {b[2]:+.1f} mm in the camera's frame)")
    print("world frame = the camera's: run 'anklescan calibrate level' before measuring angles")
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_calibrate_export(args: argparse.Namespace) -> int:
    from anklescan.core.calibration.model.file import load_calibration
    from anklescan.core.calibration.procedures.opencv_calibration import export_opencv_calibration

    export_opencv_calibration(load_calibration(args.calibration), args.out)
    print(f"wrote OpenCV FileStorage {args.out} (K1 D1 camera, K2 D2 projector, R T camera -> projector, mm)")
    return 0


def cmd_calibrate_board(args: argparse.Namespace) -> int:
    from anklescan.core.calibration.model.file import save_calibration
    from anklescan.core.calibration.procedures.board import calibrate_from_board_captures

    cols, rows = args.board
    progress = Progress(args.quiet)
    progress(f"reading {len(args.captures)} board capture(s)")
    result = calibrate_from_board_captures(args.captures, cols, rows, args.square, args.distortion)
    save_calibration(result.calibration, args.out)
    print(result.report.format_text())
    from anklescan.core.calibration.model.file import volume_text
    print(volume_text(result.calibration))
    print(f"world frame: the board of {Path(args.captures[0]).name} (z its normal, origin its corner grid's centre); "
          f"unless it lay flat on the level table, run 'anklescan calibrate level' before measuring angles")
    print(f"wrote calibration to {args.out}")
    return 0


def cmd_calibrate_level(args: argparse.Namespace) -> int:
    from anklescan.core.calibration.model.file import load_calibration, save_calibration
    from anklescan.core.calibration.procedures.levelling import (
        DEFAULT_TABLE,
        TableSizeError,
        level_calibration,
        parse_table_size,
    )
    from anklescan.core.scan.capture import load_capture

    table = DEFAULT_TABLE if args.table_size is None else parse_table_size(args.table_size)
    cal = load_calibration(args.calibration)
    capture = load_capture(args.capture)
    try:
        new, top = level_calibration(cal, capture, table)
    except TableSizeError as e:
        raise TableSizeError(f"{e} (--table-size LxW)") from None
    save_calibration(new, args.out)
    print(f"table top found: {top.describe()} (the reference table: {table.describe()})")
    print(f"wrote levelled calibration to {args.out}")
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from anklescan.core.errors import AnkleScanError
    from anklescan.core.scan.capture import load_capture

    if not (args.motion_threshold > 0 and args.motion_threshold < float("inf")):
        raise AnkleScanError(f"--motion-threshold must be a positive number of mm, not {args.motion_threshold}")
    # the frames are read (PNG decoding releases the GIL) while the measure stage's modules
    # import; run_measure takes the capture when it needs it, after checking its other inputs
    with ThreadPoolExecutor(max_workers=1) as pool:
        loading = pool.submit(load_capture, args.capture)
        from anklescan.core.measure.pipeline import run_measure

        result = run_measure(args.capture, args.calibration, args.out, args.mark_diameter,
                             motion_threshold_mm=args.motion_threshold, loading=loading)
    print(result.format_text())
    return 0


EXIT_CHECK_FAILED = 3  # SPEC §6: the daily check ran and the rig has drifted


def cmd_check(args: argparse.Namespace) -> int:
    from anklescan.core.atomic import write_json_atomic
    from anklescan.core.calibration.model.file import load_calibration
    from anklescan.core.calibration.procedures.daily_check import CheckSettings, run_check
    from anklescan.core.scan.capture import load_capture

    progress = Progress(args.quiet)
    cal = load_calibration(args.calibration)
    progress(f"loading capture {args.capture}")
    capture = load_capture(args.capture)
    progress("measuring the object's top")
    settings = CheckSettings(args.tolerance, args.flatness, args.min_area * 100.0)
    result = run_check(capture, cal, args.inversion, args.plantar_flexion, settings)
    if args.out is not None:
        write_json_atomic(args.out, {**result.to_json(), "capture": Path(args.capture).name,
                                     "calibration": Path(args.calibration).name})
    if not result.passed:
        print(f"anklescan: {result.summary()}", file=sys.stderr, flush=True)
        return EXIT_CHECK_FAILED
    print(result.summary())
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0


def cmd_angles(args: argparse.Namespace) -> int:
    from anklescan.core.limits import require_finite
    from anklescan.core.measure.angles import compute_angles, format_angles, read_marks_csv

    marks = read_marks_csv(args.marks)
    angles = compute_angles(marks, sigma_mm=args.sigma)
    if not angles:  # SPEC: never an empty result with exit 0
        from anklescan.core.errors import AnkleScanError

        raise AnkleScanError(f"{args.marks}: no angle can be computed; {angles.missing_message()}")
    require_finite(angles.to_json(), "angle")  # coordinates out of range give nan, never print it
    print(format_angles(angles))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from anklescan.app.demo import DEMO_SCALE, run_demo

    if not (0 <= args.sway < 50):
        from anklescan.core.errors import AnkleScanError
        raise AnkleScanError(f"--sway must be 0 to 50 mm, not {args.sway}")
    if getattr(args, "study", False):
        from anklescan.app.demo import run_study_demo
        from anklescan.core.errors import AnkleScanError

        if args.quick:
            raise AnkleScanError("--quick and --study cannot be combined: --study is the whole cohort")

        return run_study_demo(Path(args.out), progress=Progress(args.quiet),
                              scale=1.0 if args.full_resolution else DEMO_SCALE)
    return run_demo(Path(args.out), quick=args.quick, progress=Progress(args.quiet),
                    scale=1.0 if args.full_resolution else DEMO_SCALE, sway_mm=args.sway, camera=args.camera)
