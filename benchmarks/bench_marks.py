"""Mark centres and angles against the simulated rig's truth over the table settings.

    /work/venv/bin/python benchmarks/bench_marks.py [--scale 1.0] [--quick] [--jobs 2]
        [--postures 20/20,10/20] [--seed N | --seeds i,31,32] [--camera-blur PX] [--projector-blur PX] [--noise SIGMA]
        [--types plate,sticker] [--diameters 10,15,20] [--size unknown,given] [--variants 1,2,3] [--preset paper]
        [--ambient FRACTION]
    /work/venv/bin/python benchmarks/bench_marks.py --cases tests/data/mark_cases.csv [--only NAME,NAME] [--suite]
    /work/venv/bin/python benchmarks/bench_marks.py --draw 20 [--draw-from 1000] [--harsh] [--scale 0.75] [--rows]

Every posture with each mark type and diameter; each rendered capture is measured once per
``--size`` mode (the diameter measured from the capture, and given as the true one).

Prints, per trial, each labelled mark's centre error (mm), the four angle errors (deg),
whether all seven were found and labelled, and which true marks were not found (each plate
found is matched to the nearest true centre); then the worst cases and the counts.

``--variants`` replaces our default scene with drawn clinic-like set-ups
(``hardware/sim_variety.py``: leg, marks of 8-25 mm, plate thickness, albedos, gamma, tone
curve, specular, rig layout); each variant draws its own mark type and diameter unless
``--types`` / ``--diameters`` are given.

``--cases FILE`` runs a table of cases (hardware/sim_mark_cases.py; tests/data/mark_cases.csv,
whose ``suite`` rows tests/test_mark_cases.py runs): one line per case with its worst centre and
angle errors and PASS/FAIL against the row's expectation (``right``: all seven found, labelled
right, centres within 0.3 mm, angles within 0.2 deg; ``right_or_refused``: that, or a refusal
in one line, never a wrong answer), then found-right / refused / wrong per group. ``--draw N``
runs N drawn combinations of every effect at once (seeds from ``--draw-from``: a variant's leg,
marks, optics and camera with the table's posture, read noise, blur and ambient light in the
contract's ranges, or ``--harsh``'s, adjacent ankle disks, a table seen at 72-80 deg, the size
given or measured: ``sim_variety.draw_conditions``); ``--rows`` prints each as a CSV row for
the table.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anklescan.core.measure.mark_fit import view_deg  # noqa: E402
from anklescan.core.measure.marks import LABELS  # noqa: E402
from anklescan.core.measure.pipeline import measure_capture  # noqa: E402
from anklescan.core.scan.capture import capture_from_images  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, render_all  # noqa: E402
from anklescan.core.scan.triangulate import scan_axes  # noqa: E402
from anklescan.hardware.sim_mark_cases import Case, case_row, load_cases, run_case, summary  # noqa: E402
from anklescan.hardware.sim_scene import leg_scene  # noqa: E402
from anklescan.hardware.sim_variety import draw_variant, variant_rig  # noqa: E402
from anklescan.hardware.simrig import Optics, SimRig  # noqa: E402

PRESET = ["default"]  # the pattern set (--preset); a list so that forked workers see main's choice
THICKNESS = [1.5]  # the default scene's plates (--thickness)
SETTINGS = [(inv, pf) for inv in (0, 10, 20) for pf in (-20, -10, 0, 10, 20)]
QUICK = [(0, 0), (20, 20), (10, -20), (20, -20)]


def trial(inv, pf, scale, seed, optics=None, mark_type="plate", diameter=15.0, modes=("unknown",), variant=None):
    if variant is None:
        rig = SimRig(leg_scene(inv, pf, mark_type=mark_type, mark_radius=diameter / 2, mark_thickness=THICKNESS[0]),
                     scale=scale, seed=seed, optics=optics)
    else:
        rig = variant_rig(variant, inv, pf, scale=scale, seed=seed, optics=optics)
    cap = captured(rig, PRESET[0])
    return [_measured(rig, cap, None if mode == "unknown" else diameter) for mode in modes]


def captured(rig, preset="default"):
    """The rig's capture of the pattern set ``preset``, along the stripe axes its calibration scans."""
    pset = make_pattern_set(preset, rig.projector.width, rig.projector.height, axes=scan_axes(rig.true_calibration()))
    return capture_from_images(pset, rig.capture_many(render_all(pset)))


def _measured(rig, cap, given):
    t = time.perf_counter()
    res = measure_capture(cap, rig.true_calibration(), given)
    dt = time.perf_counter() - t
    tr = rig.mark_truth()
    mark_err = {k: float(np.linalg.norm(m.centre - tr.marks[k])) for k, m in res.marks.labelled.items()}
    ang_err = {k: float(v.value - tr.angles[k]) for k, v in res.angles.items()}
    nearest = {}
    for m in res.marks.marks:
        k = min(tr.marks, key=lambda k: np.linalg.norm(tr.marks[k] - m.centre))
        nearest[k] = m.label
    res.found_truth = nearest  # true label -> label given (None: found, not labelled)
    res.truth_marks = tr.marks
    res.truth_angles = {k: (view_deg(rig.camera.center, tr.marks[k], tr.mark_normals[k]),
                            view_deg(rig.projector.center, tr.marks[k], tr.mark_normals[k])) for k in tr.marks}
    return res, mark_err, ang_err, dt


# A mark the camera sees beyond this, or the projector lights beyond that, is out of any method's
# reach: its face images a sliver, or gets cos(80°) = 17 % of the light (a clinic re-sticks it or
# turns the rig); the summary counts trials with every mark within both apart.
REACH_VIEW_DEG, REACH_LIGHT_DEG = 75.0, 80.0
FAKE_MM = 3.0  # a mark kept this far from every true mark is a false one
WIDE_SD_MM = 0.5  # a mark kept with a centre SD over this is named in the trial's lines
Z_1PCT = 3.37  # error / SD (Mahalanobis, 3 dof) past which 1 % of exact SDs lie: named in the trial's lines


def _run(job):
    """One trial in a worker process; only the figures travel back. A trial that raises is
    reported as a crash, and the sweep goes on (variant 125's MemoryError had ended one)."""
    try:
        return _trial_figures(job)
    except Exception as exc:  # noqa: BLE001 (any crash is a finding to print, not a reason to stop)
        inv, pf, _, seed, _, _, _, _, variant = job
        return [{"crash": f"{type(exc).__name__}: {exc}"[:300], "inv": inv, "pf": pf, "seed": seed,
                 "variant": None if variant is None else variant.describe()}]


def _trial_figures(job):
    inv, pf, scale, seed, optics, mtype, diam, modes, variant = job
    if variant is not None:
        mtype, diam = variant.mark_type, variant.diameter
    overrides = optics or {}
    optics = Optics(**overrides) if overrides and variant is None else (overrides or None)
    out = []
    for mode, (res, me, ae, dt) in zip(modes, trial(inv, pf, scale, seed, optics, mtype, diam, modes, variant), strict=False):
        z_by = {k: float(np.sqrt(e @ np.linalg.solve(m.covariance, e)))
                for k, m in res.marks.labelled.items() for e in [m.centre - res.truth_marks[k]]}
        z = list(z_by.values())
        d = res.marks.diameter
        # every mark kept, labelled or not: its centre SD, and whether it is one of the true marks
        sds = [(float(m.sd), min(np.linalg.norm(m.centre - t) for t in res.truth_marks.values()) < FAKE_MM,
                f"{m.label or '?'} {m.kind} seen at {m.view_deg:.0f}°, lit at {m.light_deg:.0f}°")
               for m in res.marks.marks]
        # the doubtful fits kept (free radius far from the size, ``Mark.doubtful``): how far off
        doubtful = [(k, float(np.linalg.norm(e)), float(np.sqrt(e @ np.linalg.solve(m.covariance, e))))
                    for k, m in res.marks.labelled.items() if m.doubtful for e in [m.centre - res.truth_marks[k]]]
        past_sd = [(k, me[k], zk) for k, zk in z_by.items() if zk > Z_1PCT]  # printed, so a sweep says which
        out.append(
            {
                "sds": sds,
                "doubtful": doubtful,
                "past_sd": past_sd,
                "inv": inv,
                "pf": pf,
                "seed": seed,
                "complete": res.complete,
                "found": res.found_truth,
                "marks": me,
                "angles": ae,
                "dt": dt,
                "z": z,
                "message": "" if res.complete else res.marks.message(),
                "type": mtype,
                "diameter": diam,
                "mode": mode,
                "measured": None if d is None or mode == "given" else d,
                "variant": None if variant is None else variant.describe(),
                "geometry": res.truth_angles,
            }
        )
    return out


def _jobs(a, optics):
    settings = QUICK if a.quick else SETTINGS
    if a.postures:
        settings = [tuple(int(v) for v in p.split("/")) for p in a.postures.split(",")]
    seeds = a.seeds.split(",") if a.seeds else ["i" if a.seed is None else str(a.seed)]
    modes = tuple(a.size.split(","))
    if a.variants:
        types = a.types.split(",") if a.types else [None]
        diameters = [float(d) for d in a.diameters.split(",")] if a.diameters else [None]
        return [(inv, pf, a.scale, i if s == "i" else int(s), optics, None, None, modes, draw_variant(int(v), t, d))
                for v in a.variants.split(",") for t in types for d in diameters
                for s in seeds for i, (inv, pf) in enumerate(settings)]
    return [(inv, pf, a.scale, i if s == "i" else int(s), optics, t, float(d), modes, None)
            for t in (a.types or "plate").split(",") for d in (a.diameters or "15").split(",")
            for s in seeds for i, (inv, pf) in enumerate(settings)]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--postures", help="inversion/plantar flexion pairs, e.g. 20/20,0/-20 (default: all 15)")
    ap.add_argument("--seed", type=int, help="one seed for every trial (default: the trial's index)")
    ap.add_argument("--seeds", help="every posture with each of these seeds, 'i' meaning its index, e.g. i,31,32")
    ap.add_argument("--jobs", type=int, default=1, help="trials run in parallel (processes)")
    ap.add_argument("--camera-blur", type=float, help="px (rig default 0.6)")
    ap.add_argument("--projector-blur", type=float, help="projector px (rig default 0.8)")
    ap.add_argument("--noise", type=float, help="read noise, fraction of full scale (rig default 2/255)")
    ap.add_argument("--types", help="mark types: plate,sticker (default: plate; with --variants: drawn)")
    ap.add_argument("--diameters", help="mark diameters in mm, e.g. 10,15,20 (default: 15; with --variants: drawn)")
    ap.add_argument("--preset", default="default", help="pattern set: default, paper (8 Gray bits, no phase) or short")
    ap.add_argument("--thickness", type=float, default=1.5, help="plates' thickness in the default scene, mm "
                                                                     "(SPEC §2: up to 3)")
    ap.add_argument("--variants", help="drawn set-ups (hardware/sim_variety.py) by seed, e.g. 1,2,3, instead of "
                                       "the default scene")
    ap.add_argument("--size", default="unknown", help="unknown (measured), given, or both: unknown,given")
    ap.add_argument("--ambient", type=float, help="ambient light, fraction of the projector's white (rig default 0.04)")
    ap.add_argument("--cases", help="a table of cases (CSV, hardware/sim_mark_cases.py), e.g. tests/data/mark_cases.csv")
    ap.add_argument("--only", help="with --cases: these cases by name, comma-separated")
    ap.add_argument("--suite", action="store_true", help="with --cases: the rows the test suite runs")
    ap.add_argument("--draw", type=int, help="N drawn combinations of every effect (sim_variety.draw_conditions)")
    ap.add_argument("--draw-from", type=int, default=1000, help="with --draw: the first seed (default 1000)")
    ap.add_argument("--harsh", action="store_true", help="with --draw: the harsh ranges (noise to 6/255, blur to "
                                                         "1.5 px, ambient to 0.2), expecting right or refused")
    ap.add_argument("--rows", action="store_true", help="with --draw: print each drawn case as a CSV row")
    a = ap.parse_args(argv)
    if a.cases or a.draw:
        return run_cases(a)
    overrides = {k: v for k, v in (("camera_blur_px", a.camera_blur), ("projector_blur_px", a.projector_blur),
                                   ("noise_sigma", a.noise), ("ambient", a.ambient)) if v is not None}
    PRESET[0], THICKNESS[0] = a.preset, a.thickness
    jobs = _jobs(a, overrides)
    failures, n_found, n_right, errors, angle_errors, z, n_trials, size_err = 0, 0, 0, [], [], [], 0, []
    wrong_complete, crashes, true_sd, fake_sd, doubtful = 0, 0, [], [], []
    reach = {"trials": 0, "incomplete": 0, "errors": [], "angles": []}
    with multiprocessing.Pool(a.jobs) if a.jobs > 1 else contextlib.nullcontext() as pool:
        for r in (r for rs in (pool.imap(_run, jobs) if pool else map(_run, jobs)) for r in rs):
            n_trials += 1
            if "crash" in r:
                crashes += 1
                failures += 1
                if r["variant"]:
                    print(r["variant"], flush=True)
                print(f"CRASH inv {r['inv']:3d} pf {r['pf']:4d} seed {r['seed']:3d}  {r['crash']}", flush=True)
                continue
            if r["measured"] is not None:
                size_err.append((r["measured"][0] - r["diameter"], r["measured"][1]))
            failures += not r["complete"]
            in_reach = all(v <= REACH_VIEW_DEG and li <= REACH_LIGHT_DEG for v, li in r["geometry"].values())
            if in_reach:
                reach["trials"] += 1
                reach["incomplete"] += not r["complete"]
                reach["errors"] += r["marks"].values()
                reach["angles"] += map(abs, r["angles"].values())
            n_found += len(r["found"])
            # the worst outcome: a trial that says it is complete with a mark mislabelled. Judged by
            # each label's own error too: "found" keeps one mark per nearest true mark, so a false
            # mark nearest the same true one as a mislabelled mark hid it (variant 378 at 0/+20)
            wrong_complete += r["complete"] and (any(k != lab for k, lab in r["found"].items())
                                                 or any(e > FAKE_MM for e in r["marks"].values()))
            n_right += sum(k == lab for k, lab in r["found"].items())
            errors += r["marks"].values()
            angle_errors += map(abs, r["angles"].values())
            z += r["z"]
            true_sd += [sd for sd, true, _ in r["sds"] if true]
            fake_sd += [sd for sd, true, _ in r["sds"] if not true]
            doubtful += r["doubtful"]
            marks = " ".join(f"{k}:{v:.2f}" for k, v in sorted(r["marks"].items()))
            angles = " ".join(f"{k.replace('_', ' ')[:10]}:{v:+.3f}" for k, v in r["angles"].items())
            size = (f"{r['type']:7s} {r['diameter']:4.1f} mm {r['mode']:7s}"
                    + (f" (measured {r['measured'][0]:.2f} ± {r['measured'][1]:.2f})" if r["measured"] else ""))
            if r["variant"]:
                print(r["variant"], flush=True)
            state = '7/7' if r['complete'] else 'INCOMPLETE' + ' IN REACH' * in_reach
            print(f"{size} inv {r['inv']:3d} pf {r['pf']:4d} seed {r['seed']:3d}  {state}  "
                  f"marks(mm) {marks}  angles(deg) {angles}  [{r['dt']:.1f} s]", flush=True)
            for sd, true, what in r["sds"]:
                if sd > WIDE_SD_MM or not true:
                    print(f"    {'a true' if true else 'A FALSE'} mark, SD {sd:.2f} mm: {what}", flush=True)
            for k, err, zk in r["doubtful"]:
                print(f"    a doubtful fit kept: {k}, {err:.2f} mm off, {zk:.1f} SD", flush=True)
            for k, err, zk in r["past_sd"]:
                print(f"    past its SD: {k}, {err:.2f} mm off, {zk:.1f} SD (seen at {r['geometry'][k][0]:.0f}°, lit at "
                      f"{r['geometry'][k][1]:.0f}°)", flush=True)
            if not r["complete"]:
                print("    " + r["message"], flush=True)
                lost = sorted(set(LABELS) - set(r["found"]))
                print("    true marks not found: " + (", ".join(f"{k} (seen at {r['geometry'][k][0]:.0f}°, lit at "
                                                                 f"{r['geometry'][k][1]:.0f}°)" for k in lost) or "none"),
                      flush=True)
    e = np.array(errors) if errors else np.zeros(1)
    angle_errors = angle_errors or [0.0]
    z = z or [0.0]
    print(f"worst mark error {e.max():.3f} mm, worst angle error {max(angle_errors):.3f} deg, incomplete trials "
          f"{failures} of {n_trials}; marks found {n_found}/{7 * n_trials}, correctly labelled {n_right}/{7 * n_trials}")
    print(f"complete trials with a wrong label (wrong angles, no warning): {wrong_complete}")
    if crashes:
        print(f"CRASHED trials (an exception, counted as incomplete above): {crashes}")
    if reach["trials"] < n_trials:
        print(f"in reach (every mark seen <= {REACH_VIEW_DEG:.0f}°, lit <= {REACH_LIGHT_DEG:.0f}°): {reach['trials']} of "
              f"{n_trials} trials, incomplete {reach['incomplete']}, worst mark error "
              f"{max(reach['errors'] or [0]):.3f} mm, worst angle error {max(reach['angles'] or [0]):.3f} deg")
    if size_err:
        de = np.array(size_err)
        print(f"measured diameter - true: worst {np.abs(de[:, 0]).max():.3f} mm, RMS {np.sqrt(np.mean(de[:, 0] ** 2)):.3f} mm; "
              f"|error| / SD median {np.median(np.abs(de[:, 0]) / np.maximum(de[:, 1], 1e-9)):.2f}, "
              f"worst {np.max(np.abs(de[:, 0]) / np.maximum(de[:, 1], 1e-9)):.2f}")
    print(f"centre errors: RMS {np.sqrt(np.mean(e ** 2)):.3f} mm, 95th percentile {np.percentile(e, 95):.3f} mm, "
          f"over 0.25 mm {int((e > 0.25).sum())}; error / SD (Mahalanobis) median {np.median(z):.2f} (1.54 ideal), "
          f"over 3.37 (1 % if exact) {int((np.array(z) > Z_1PCT).sum())} of {len(z)}, worst {max(z):.1f}")
    if true_sd:
        print(f"centre SD of the true marks kept: median {np.median(true_sd):.3f} mm, 99th percentile "
              f"{np.percentile(true_sd, 99):.3f} mm, largest {max(true_sd):.3f} mm; false marks kept: {len(fake_sd)}"
              + (f", SDs {', '.join(f'{s:.2f}' for s in sorted(fake_sd))} mm" if fake_sd else ""))
    if doubtful:
        de = np.array([(err, zk) for _, err, zk in doubtful])
        print(f"doubtful fits kept (radius far from the size): {len(doubtful)}, worst {de[:, 0].max():.3f} mm off, "
              f"worst {de[:, 1].max():.1f} SD")


def run_cases(a: argparse.Namespace) -> int:
    """``--cases`` / ``--draw``: one line per case, then the summary per group; exit 1 on a FAIL."""
    if a.cases:
        try:
            cases = load_cases(a.cases)
        except (OSError, ValueError) as exc:
            print(f"bench_marks: {exc}", file=sys.stderr)
            return 2
        if a.suite:
            cases = [c for c in cases if c.suite]
        if a.only:
            wanted = set(a.only.split(","))
            cases = [c for c in cases if c.name in wanted]
    else:
        cases = [Case.drawn(s, a.harsh, a.scale) for s in range(a.draw_from, a.draw_from + a.draw)]
    results = []
    with multiprocessing.Pool(a.jobs) if a.jobs > 1 else contextlib.nullcontext() as pool:
        for r in (pool.imap(run_case, cases) if pool else map(run_case, cases)):
            results.append(r)
            print(r.line() + (f"  (xfail: {r.case.xfail})" if r.case.xfail else ""), flush=True)
            if a.rows:
                print("    " + case_row(r.case), flush=True)
    for line in summary(results):
        print(line)
    return 0 if all(r.passed for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
