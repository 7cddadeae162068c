"""Set-ups that are not our default scene (hardware/sim_variety.py): other mark sizes, light
tables, cameras with a tone curve, the projector above the camera. Each case here failed before
the change its docstring names (docs/marks.md, "Beyond our own scene")."""

import numpy as np
import pytest

from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_fit import plane_from_pixels
from anklescan.core.scan.camera_response import GAMMA_GRID, response_gamma
from anklescan.core.vocabulary import MarkKind
from anklescan.hardware.sim_variety import DIAMETER_RANGE_MM, draw_variant, variant_rig


def _capture(rig):
    from anklescan.core.scan.capture import capture_from_images
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.core.scan.triangulate import scan_axes

    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=scan_axes(rig.true_calibration()))
    return capture_from_images(pset, rig.capture_many(render_all(pset)))


def _measured(rig):
    from anklescan.core.measure.pipeline import measure_capture

    return measure_capture(_capture(rig), rig.true_calibration()), rig.truth()


def _assert_within(res, truth, limit_mm=0.3):
    """Every labelled mark within ``limit_mm`` of the truth and within its SD (3.37: 1 % if exact)."""
    for k, m in res.marks.labelled.items():
        e = m.centre - truth.marks[k]
        assert np.linalg.norm(e) < limit_mm, (k, np.linalg.norm(e), m.sd)
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, (k, np.linalg.norm(e), m.sd)


def test_drawn_setups_are_reproducible_and_within_the_spec():
    a, b = draw_variant(5), draw_variant(5)
    assert a == b and a != draw_variant(6)
    for v in map(draw_variant, range(40)):
        assert DIAMETER_RANGE_MM[0] <= v.diameter <= DIAMETER_RANGE_MM[1]  # SPEC §2: 8-25 mm
        assert v.mark_type in ("plate", "sticker") and 1.0 <= v.scene["mark_thickness"] <= 3.0
    assert {v.layout for v in map(draw_variant, range(40))} == {"side", "diagonal", "above"}
    assert draw_variant(1, "plate", 8.0).diameter == 8.0
    # from HAND_PLACED_FROM_SEED on, lateral marks off the front marks' level; before it, level
    from anklescan.hardware.sim_variety import HAND_PLACED_FROM_SEED, LATERAL_OFFSET_RANGES_MM

    assert "lateral_mark_offsets" not in draw_variant(HAND_PLACED_FROM_SEED - 1).scene
    for v in map(draw_variant, range(HAND_PLACED_FROM_SEED, HAND_PLACED_FROM_SEED + 20)):
        for off, (lo, hi) in zip(v.scene["lateral_mark_offsets"], LATERAL_OFFSET_RANGES_MM, strict=False):
            assert lo <= off <= hi


def test_from_a_seed_on_the_camera_stands_elsewhere_and_still_sees_every_mark():
    """Camera round the leg, higher or lower, nearer or further, zoomed; the projector at another
    baseline. Every mark's centre stays inside both frames, facing the camera, in every posture."""
    from anklescan.hardware.sim_variety import VIEW_DRAWN_FROM_SEED, VIEW_RANGES

    assert not draw_variant(VIEW_DRAWN_FROM_SEED - 1).view and draw_variant(VIEW_DRAWN_FROM_SEED).view
    assert draw_variant(VIEW_DRAWN_FROM_SEED + 3) == draw_variant(VIEW_DRAWN_FROM_SEED + 3)
    for v in map(draw_variant, range(VIEW_DRAWN_FROM_SEED, VIEW_DRAWN_FROM_SEED + 24)):
        assert all(lo <= v.view[k] <= hi for k, (lo, hi) in VIEW_RANGES.items())
        for inv, pf in [(0, -20), (0, 20), (20, -20), (20, 20)]:
            rig = variant_rig(v, inv, pf, scale=0.25)
            for m in rig.scene.marks.values():
                for dev in (rig.camera, rig.projector):
                    u, w = dev.project(m.centre[None])[0]
                    assert 0 <= u < dev.width and 0 <= w < dev.height, (v.seed, inv, pf)
                assert m.normal @ (rig.camera.center - m.centre) > 0


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_camera_tone_curve_is_measured_from_the_capture(gamma):
    """A pattern and its inverse share the projector's light: frame + inverse = white + black in
    linear light, which holds for v^γ with the camera's own γ only."""
    rig = variant_rig(draw_variant(2), 10, 0, scale=0.4, optics={"camera_gamma": gamma})
    assert abs(response_gamma(_capture(rig)) - gamma) <= 0.1


def test_real_camera_measures_linear(tmp_path):
    """The real rig's camera (tests/data/procam-calibration) is linear: γ 1.0, the grid's floor."""
    from pathlib import Path

    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.opencv_graycode import import_opencv_graycode

    data = Path(__file__).resolve().parent / "data" / "procam-calibration" / "capture_1"
    import_opencv_graycode(data, tmp_path / "c", 2048, 1536, step=2)
    assert response_gamma(load_capture(tmp_path / "c")) == GAMMA_GRID[0] == 1.0


def test_a_plane_through_one_row_of_points_is_refused():
    """Seven top-face pixels of an 8 mm plate seen at 66°, all in one image row: a plane through
    them has RMS 0 and any tilt about their line (that plate went 3.7 mm off)."""
    t = np.linspace(0, 4, 7)
    row = np.stack([81.8 - 0.55 * t, 87.6 + 0.65 * t, 153.5 + 0.22 * t], axis=1)
    points = np.full((3, 10, 3), np.nan, np.float32)
    points[1, :7] = row
    uv = np.stack([np.arange(7), np.ones(7, int)], axis=1)
    assert plane_from_pixels(points, None, uv, np.array([0.0, 1000.0, 800.0])) is None
    points[0, :7] = row + [0.0, 0.0, 1.0]  # a second row 1 mm away: a plane again
    uv2 = np.concatenate([uv, np.stack([np.arange(7), np.zeros(7, int)], axis=1)])
    assert len(uv2) >= CONFIG.min_interior_points and plane_from_pixels(points, None, uv2, np.array([0.0, 1000.0, 800.0]))


# (variant, inversion, plantar flexion, type, diameter): the type and size drawn unless given
CASES = {
    # camera tone curve 2.2 and a light table (0.69 against marks of 0.87): the table marks
    # stood out by 26 % and the curve made that 11 %; with a 30 % contrast floor, 2 of 7 found
    "tone curve, light table": (1, 0, -20, None, None),
    # projector above the camera, 17.6 mm stickers on a 0.65 table: no table mark (30 % floor)
    "projector above": (3, 10, 0, None, None),
    # a 25 mm sticker across the front ankle's terminator: its outline on the dark side was the
    # terminator (edge RMS 2.8 mm) and it was refused; edges are now used only where decoded
    "25 mm sticker at the terminator": (2, 0, 20, "sticker", 25.0),
    # our default scene with 8 mm plates: the table plate 6, seen at 66°, had its top face's
    # pixels in one row, and a plane of any tilt through them put it 3.7 mm off
    "8 mm plates": (None, 0, -20, "plate", 8.0),
}


@pytest.mark.parametrize("case", list(CASES))
def test_marks_on_drawn_clinic_setups(case):
    """0.75 scale: all seven found and labelled, centres within 0.3 mm, angles within 0.2°."""
    from anklescan.hardware.sim_scene import leg_scene
    from anklescan.hardware.simrig import SimRig

    v, inv, pf, kind, diameter = CASES[case]
    rig = (SimRig(leg_scene(inv, pf, mark_type=kind, mark_radius=diameter / 2), scale=0.75, seed=0) if v is None
           else variant_rig(draw_variant(v, kind, diameter), inv, pf, scale=0.75, seed=v))
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    errors = {k: float(np.linalg.norm(m.centre - truth.marks[k])) for k, m in res.marks.labelled.items()}
    assert max(errors.values()) < 0.3, errors
    assert all(abs(a["value"] - truth.angles[k]) < 0.2 for k, a in res.angles.items())


def test_the_captures_common_kind_needs_three_marks_and_three_quarters():
    from anklescan.core.measure.marks import _common_kind

    assert _common_kind(["sticker"] * 6 + ["plate"]) == "sticker"
    assert _common_kind(["plate", "plate", "plate", "sticker"]) == "plate"
    assert _common_kind(["plate", "plate", "sticker", "sticker"]) is None
    assert _common_kind(["plate", "plate"]) is None


def test_the_captures_kind_is_voted_by_the_fits_whose_step_measures_it():
    """Drawn 1102 (harsh): five stickers with clear flush steps and two ankle stickers whose step
    nothing measured, fitted as plates because the plate is tried first. Those two are no
    evidence; the capture is one of stickers. Fewer than three measured steps: every fit votes."""
    from anklescan.core.measure.marks import Mark, _capture_kind

    def fit(kind, step_mm, step_sd=0.05):
        return Mark(np.zeros(3), np.array([0.0, 0.0, 1.0]), 7.5, 0.1, 0.1, np.eye(3) * 0.01, (0.0, 0.0), 40, 40,
                    kind=kind, step_mm=step_mm, step_sd=step_sd)

    flush = [fit(MarkKind.STICKER, s) for s in (0.06, 0.05, 0.21, -0.08, 0.0)]
    unmeasured = [fit(MarkKind.PLATE, None), fit(MarkKind.PLATE, None)]
    assert _capture_kind(flush + unmeasured) == MarkKind.STICKER
    assert _capture_kind(flush[:2] + unmeasured) is None  # two measured: every fit votes, 2 of 4
    assert _capture_kind(flush[:1] + unmeasured + unmeasured[:1]) == MarkKind.PLATE  # every fit: 3 of 4
    proud = [fit(MarkKind.PLATE, 1.5) for _ in range(3)]
    assert _capture_kind(proud + [fit(MarkKind.STICKER, None)]) == MarkKind.PLATE


def test_a_sticker_whose_step_cannot_be_measured_is_not_fitted_as_a_plate():
    """Variant 21 at 0/+20: the 12.5 mm front ankle sticker, lit at 80°, has too little decoded
    round it for a step; fitted as a plate it passed 0.56 mm off at 4 SD. Now only as a sticker
    (the capture's kind): not found rather than silently off."""
    rig = variant_rig(draw_variant(21), 0, 20, scale=0.75, seed=1)
    res, truth = _measured(rig)
    assert all(m.kind == "sticker" for m in res.marks.marks)
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_two_fits_of_one_disk_leave_one_mark():
    """A blob and its wider cut, or two blobs, on one disk: the fit with more edge points stays."""
    from anklescan.core.measure.marks import Mark, _distinct
    from anklescan.hardware.sim_scene import leg_scene
    from anklescan.hardware.simrig import SimRig

    cal = SimRig(leg_scene(0, 0), scale=0.5, seed=0).true_calibration()

    def mark(x, n_edge):
        c = np.array([x, 0.0, 150.0])
        return Mark(c, np.array([0.0, 0.0, 1.0]), 5.0, 0.05, 0.05, np.eye(3) * 0.01,
                    tuple(float(v) for v in cal.camera.project(c[None])[0]), n_edge, 100)

    a, b, far = mark(0.0, 20), mark(1.5, 30), mark(30.0, 10)
    kept = _distinct([a, b, far], cal, 5.0)
    assert [m is b or m is far for m in kept] == [True, True] and len(kept) == 2


def test_a_mark_lit_past_85_degrees_is_not_measured():
    """Variant 4 at 0/+20 (projector diagonal to the camera): the front knee sticker is lit at
    88°, 3.5 % of the light, and was fitted 0.45 mm off at 7 SD. It is refused, and says why."""
    rig = variant_rig(draw_variant(4), 0, 20, scale=0.75, seed=1)
    res, truth = _measured(rig)
    assert "1" not in res.marks.labelled
    assert all(m.light_deg <= 85.0 for m in res.marks.marks)
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_a_bright_patch_between_depth_steps_is_not_an_eighth_mark():
    """Variant 25 at 20/20, full resolution: a lit sliver of floor between the leg's shadows,
    its border 98 % undecoded, passed as a 17.5 mm sticker on 9 edge points; with eight marks
    the table triple was ambiguous and the trial lost 5-7. A sticker lies on the skin, so the
    skin round it is decoded (``MarkConfig.sticker_max_border_undecoded``)."""
    rig = variant_rig(draw_variant(25), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    assert not res.marks.unlabelled
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_a_rim_beside_a_darker_region_is_read_against_the_surface_next_to_it():
    """A disk at 240 on skin at 150, the background (10) 5 px past its rim on one side (a
    20 mm plate beside the leg's silhouette, variant 42 at 20/20): half-way to the darkest
    level (125) lies on the skin, and the edge was read at the silhouette (edge RMS 1.9 mm)."""
    import cv2

    from anklescan.core.measure.mark_edges import edge_profiles

    yy, xx = np.mgrid[0:100, 0:100].astype(np.float32)
    image = np.where(np.hypot(xx - 50, yy - 50) <= 20, 240.0, np.where(xx < 25, 10.0, 150.0)).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    pr = edge_profiles(image, {"centre": (50.0, 50.0), "axes": (20.0, 20.0), "angle": 0.0})
    r = np.hypot(*(pr.points() - 50.0).T)
    assert len(r) > 0.9 * len(pr.dirs)
    assert np.max(np.abs(r - 20.0)) < 0.6, r.max()


def test_a_clipped_rim_has_a_span_inwards_and_an_unclipped_one_none():
    """A disk twice as bright over its surround as the clip lets it read (400 on 100, clipped at
    250): half-way down from the clip is outside the true rim, and ``s_span`` reaches back over
    it; unclipped, no span."""
    import cv2

    from anklescan.core.measure.mark_edges import edge_profiles

    yy, xx = np.mgrid[0:100, 0:100].astype(np.float32)
    true = cv2.GaussianBlur(np.where(np.hypot(xx - 50.3, yy - 49.8) <= 20, 400.0, 100.0).astype(np.float32), (0, 0), 0.8)
    shape = {"centre": (50.0, 50.0), "axes": (20.0, 20.0), "angle": 0.0}
    pr = edge_profiles(np.minimum(true, 250.0), shape, clipped=true >= 250.0)
    r = np.hypot(*(pr.points() - [50.3, 49.8]).T)
    inner = np.hypot(*(pr.points(pr.s_edge - pr.s_span) - [50.3, 49.8]).T)
    assert np.mean(r) > 20.3  # read outside the rim ...
    assert np.mean(inner <= 20.05) > 0.5 and np.mean(inner) > 19.0  # ... and the span reaches back over it
    assert not np.any(edge_profiles(true, shape, clipped=np.zeros(true.shape, bool)).s_span)


def test_an_overexposed_mark_says_so_and_its_sd_covers_its_error():
    """Our default scene at 0/0 with the exposure at 1.25: the table-facing lateral knee plate,
    lit at 20°, saturates the camera, and its rim read half-way down from the clip is 0.3 mm
    off. It is flagged, its SD includes the rim's span, and the text says what to do."""
    from anklescan.hardware.sim_scene import leg_scene
    from anklescan.hardware.simrig import Optics, SimRig

    rig = SimRig(leg_scene(0, 0, mark_type="plate", mark_radius=7.5), scale=0.75, seed=0, optics=Optics(exposure=1.25))
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    over = [k for k, m in res.marks.labelled.items() if m.clipped]
    assert over and "overexposed" in res.format_text()
    for k, m in res.marks.labelled.items():
        e = m.centre - truth.marks[k]
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, (k, np.linalg.norm(e), m.sd)
    assert res.to_dict()["mark_details"][over[0]]["overexposed"] is True


def test_a_disk_beside_its_brighter_side_wall_is_found_by_its_outline():
    """The disk's outline slid over its surround stops over the disk, not on the bright
    crescent of side wall beside it that the blob cuts were (``disk_contrast_peak``); the fit
    then finds the rim from there."""
    import cv2

    from anklescan.core.measure.mark_candidates import disk_contrast_peak

    yy, xx = np.mgrid[0:120, 0:120].astype(np.float32)
    image = np.full((120, 120), 100.0, np.float32) + 0.5 * xx  # skin, lit more to the right
    face = ((xx - 60) / 12) ** 2 + ((yy - 58) / 7) ** 2 <= 1
    wall = (((xx - 57) / 12) ** 2 + ((yy - 58) / 7) ** 2 <= 1) & ~face
    image[face], image[wall] = 170.0, 400.0
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    mask = np.zeros((27, 27), np.uint8)
    cv2.ellipse(mask, (13, 13), (12, 7), 0, 0, 360, 1, -1)
    blob = disk_contrast_peak(image, {"mask": mask.astype(bool), "centre": (52, 58)})
    assert blob is not None
    covered = np.zeros(face.shape, bool)
    covered[blob["slice"]] = blob["region"]
    assert (covered & face).sum() >= 0.8 * face.sum() and np.hypot(blob["centre"][0] - 60, blob["centre"][1] - 58) <= 3.5


def test_a_dim_face_over_a_bright_wall_is_found_by_the_plate_outline():
    """A thick plate lit at a grazing angle: a dim face (a little over the surface) above a wall
    far brighter than both, as held-out variant 76's table plates at 0/-20. The disk's outline
    alone stands out most over the wall, below the face; the plate's outline (face and wall,
    ``predicted_disk`` with a thickness) stops with its face on the face."""
    import cv2

    from anklescan.core.measure.mark_candidates import disk_contrast_peak

    yy, xx = np.mgrid[0:120, 0:120].astype(np.float32)
    image = np.full((120, 120), 60.0, np.float32)
    face = ((xx - 60) / 11) ** 2 + ((yy - 55) / 4) ** 2 <= 1
    base = ((xx - 60) / 11) ** 2 + ((yy - 59) / 4) ** 2 <= 1
    wall = (base | ((np.abs(xx - 60) <= 11) & (yy >= 55) & (yy <= 59))) & ~face
    image[face], image[wall] = 100.0, 400.0
    image = cv2.GaussianBlur(image, (0, 0), 0.8)

    def outline(dy):  # the face's ellipse, and its base dy px lower, in a 31 x 31 frame
        m = np.zeros((31, 31), np.uint8)
        cv2.ellipse(m, (15, 15), (11, 4), 0, 0, 360, 1, -1)
        if dy:
            cv2.ellipse(m, (15, 15 + dy), (11, 4), 0, 0, 360, 1, -1)
            m[15:15 + dy + 1, 4:27] = 1
        return m.astype(bool)

    def found_centre(disk):  # where the face's centre (the frame's) stopped
        return np.array(disk_contrast_peak(image, disk)["centre"])

    alone = found_centre({"mask": outline(0), "centre": (60, 58)})
    plate = found_centre({"mask": outline(4), "face": outline(0), "centre": (60, 58)})
    assert abs(alone[1] - 55) >= 3  # the disk alone: over the wall
    assert np.hypot(plate[0] - 60, plate[1] - 55) <= 1.5


def test_a_thick_plate_whose_every_cut_is_its_side_wall_is_found():
    """Variant 28 at 10/0, full resolution: the 13.4 x 2 mm lateral ankle plate's lit side wall
    outshines its face, whose level the skin on that side shares; every blob cut was the wall's
    crescent and the mark was missing. The disk's predicted outline finds it (``_shape_look``)."""
    rig = variant_rig(draw_variant(28), 10, 0, scale=1.0, seed=2)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_large_plates_on_evenly_shaded_skin_are_cut_against_their_own_surround():
    """Held-out variant 55 at 0/-20, full resolution: 20.6 mm plates only 1.3x the skin's albedo.
    The first, any-size pass cut each blob over the opening's minimum, the skin's darkest side;
    the cut leaked into the lit skin on the other side, no blob was left, no size was measured,
    and 0 of 7 marks were found. Where that cut leaks, the first pass now cuts again over the
    decoded surface round the seed, as the later passes do (``candidate_blobs``' ring_background)."""
    rig = variant_rig(draw_variant(55), 0, -20, scale=1.0, seed=0)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    assert abs(res.marks.diameter[0] - 20.6) < 0.3
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_a_plate_partly_in_the_legs_shadow_is_fitted_on_its_rim_alone():
    """Held-out variant 138 at 20/+20, full resolution: table plate 5 (24.5 x 2.1 mm, seen at 30°,
    lit at 13°) lies a quarter in the leg's shadow, whose straight edge was that much of its
    outline: edge RMS 1.0 mm, every fit 1.1-1.6 mm off and refused, the table left unlabelled.
    A fit that scatters so is made again without the edges off the circle most of them lie on
    (``_without_stray_arc``). Marks 3 and 4 are lit at 90° (no light): the trial stays
    incomplete, but 5, 6 and 7 are found and labelled."""
    rig = variant_rig(draw_variant(138), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    found = res.marks.labelled
    assert {"5", "6", "7"} <= set(found), res.marks.message()
    for k in ("5", "6", "7"):
        e = found[k].centre - truth.marks[k]
        assert np.linalg.norm(e) < 0.15, (k, np.linalg.norm(e))
        assert float(np.sqrt(e @ np.linalg.solve(found[k].covariance, e))) < 3.37, k


def test_a_runaway_circle_fit_is_refused_not_a_crash():
    """Held-out variant 125 at 20/+20, full resolution (8.3 mm stickers): one candidate's first,
    free-radius plate fit ran away (its edges on a line) and the plate's second profiling drew
    the face of that circle, millions of pixels across: ``measure`` died asking for 163 GiB.
    Such a fit is now refused by its checks without a second profiling, and profiles are not
    drawn across an outline larger than the image."""
    from anklescan.core.measure.mark_edges import edge_profiles

    image = np.zeros((100, 100), np.float32)
    huge = edge_profiles(image, {"centre": (50.0, 50.0), "axes": (4.0, 4.6e7), "angle": 10.0})
    assert len(huge.rows) == 0 and len(huge.points()) == 0
    rig = variant_rig(draw_variant(125), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_a_grazing_plate_is_centred_between_its_two_profile_origins():
    """Held-out variant 50 at 0/-20, full resolution: 14.2 x 2.1 mm table plates seen at ~70° and
    lit at ~67°. The blob found is mostly the plate's lit side wall; the edge profiles drawn from
    it ended short of the face's far rim, 8 edges were clean and table plate 5 was 0.93 mm off.
    The plate is now fitted again on profiles across the image of the face the first fit found,
    and centred between the two fits, their half-distance in its covariance
    (``_with_face_profiles``): 0.38 mm, 0.6 SD."""
    rig = variant_rig(draw_variant(50), 0, -20, scale=1.0, seed=0)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    for k, m in res.marks.labelled.items():
        e = m.centre - truth.marks[k]
        assert np.linalg.norm(e) < 0.5, (k, np.linalg.norm(e))
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, k


def test_thick_table_plates_under_a_grazing_light_are_found_and_covered_by_their_sd():
    """Held-out variant 76 at 0/-20, full resolution: 13.2 x 2.9 mm table plates seen at 68-71°
    and lit at 65-68°, their side walls lit almost head-on and far brighter than their faces.
    - Only the far side of such a rim is clean, and there an edge level a quarter of a pixel off
      moves the centre by 1/cos(view) times as much in the face's plane: a plate found was
      0.72 mm off with an SD of 0.10 mm (over 4 SD). The edge level's error is now carried to
      the centre (``_edge_level_covariance``).
    - Every cut of plates 5 and 7 was the wall, and the last look's disk stood out most over the
      wall too, 3.7 px below the face: both were missing and the trial incomplete. The last look
      now slides the plate's face and side wall together (``predicted_disk`` with the capture's
      thickness) and fits the face: 0.11-0.23 mm off."""
    rig = variant_rig(draw_variant(76), 0, -20, scale=1.0, seed=0)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    grazing = 0
    for k, m in res.marks.labelled.items():
        e = m.centre - truth.marks[k]
        assert np.linalg.norm(e) < 0.3, (k, np.linalg.norm(e), m.sd)
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, (k, np.linalg.norm(e), m.sd)
        grazing += m.view_deg > 65
    assert grazing >= 3


def test_a_doubtful_wider_fit_with_clean_edges_completes_the_set():
    """Held-out variant 92 at 0/+20, full resolution: the 10 mm front ankle plate, lit at 79°, is
    found only by the last looks, with a free radius of 4.63 ± 0.05 mm against the set's 4.99
    (doubtful) but clean edges (RMS 0.14 mm), 0.17 mm off. It was refused and the trial left
    incomplete; it is now kept, as a doubtful mark restored after the second look is, with the
    radius's disagreement in its SD."""
    rig = variant_rig(draw_variant(92), 0, 20, scale=1.0, seed=1)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    _assert_within(res, truth)


def test_a_bright_table_past_the_foots_silhouette_is_no_sticker():
    """Held-out variant 168 at 20/+20, full resolution (9.2 mm stickers): the front ankle sticker
    is lit at 86° (out of reach), and the bright table seen past the foot's outline passed as a
    sticker on the shading-corrected image, SD 1.6 mm; the lit image's edges there lie on a line.
    It took label 4, the true lateral mark label 2, and the trial said complete with the leg's
    angles 5° and 14° off. Such a fit is refused: the trial is incomplete, and what is labelled
    is right."""
    rig = variant_rig(draw_variant(168), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert not res.complete and "2" not in res.marks.labelled, res.marks.message()
    assert set(res.marks.labelled) == {"1", "3", "4", "5", "6", "7"}, res.marks.message()
    for k, m in res.marks.labelled.items():
        assert np.linalg.norm(m.centre - truth.marks[k]) < 0.3, k


def test_a_sticker_lit_past_75_degrees_is_not_refused_for_its_lit_edges_on_a_line():
    """Held-out variant 36 at 0/+20, full resolution (24.9 mm stickers): the front ankle sticker,
    lit at 77°, is fitted 0.06 mm off on the shading-corrected image's edges (51 of them, radius
    within 0.1 mm of the size), but its lit image keeps only the near rim, whose fit runs away
    like the table's edge above, and it was refused: the trial was incomplete. The lit image's
    edges now count only where the disk is lit at up to 75°, as for the lit shift."""
    rig = variant_rig(draw_variant(36), 0, 20, scale=1.0, seed=1)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    _assert_within(res, truth)


def test_a_sticker_on_a_surface_the_quadric_misfits_is_not_taken_for_a_plate():
    """Held-out variant 151 at 20/-20, full resolution: the 14.4 mm lateral ankle sticker, near the
    leg's silhouette, stood 0.60 ± 0.02 mm over a quadric that fits the skin round it to 0.19 mm
    RMS; that clear 'step' made it a plate, fitted 0.69 mm off at 7 SD. The step's SD now holds
    the fit's RMS (a 3-SD bound), the step is unclear, and the capture's kind decides."""
    rig = variant_rig(draw_variant(151), 20, -20, scale=1.0, seed=3)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    assert res.marks.labelled["4"].kind == "sticker"
    for k, m in res.marks.labelled.items():
        e = m.centre - truth.marks[k]
        assert np.linalg.norm(e) < 0.3, k
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, k


def test_a_plate_on_the_legs_outline_against_a_bright_table_is_cut_by_depth():
    """Held-out variant 160 at 20/+20, full resolution: the 19.1 x 2.3 mm lateral ankle plate,
    seen at 70° on the leg's outline, images against the table far behind, about as bright as
    its face: every brightness cut leaked into the table and no blob was left. Cut again without
    the pixels at a depth step (``_depth_cut``), it is found, within its SD. Variant 187 at
    20/+20: a first version, a window in depth round the seed, cut bands out of the receding
    floor that passed as two more marks; a cut must be bounded by a depth step."""
    for variant, seed, limit in ((160, 4, 0.4), (187, 4, 0.3)):
        rig = variant_rig(draw_variant(variant), 20, 20, scale=1.0, seed=seed)
        res, truth = _measured(rig)
        assert res.complete and len(res.marks.marks) == 7, (variant, res.marks.message())
        for k, m in res.marks.labelled.items():
            e = m.centre - truth.marks[k]
            assert np.linalg.norm(e) < limit, (variant, k)
            assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, (variant, k)


def test_a_sticker_the_lit_image_places_elsewhere_is_refused():
    """Held-out variant 195 at 0/+20, full resolution (8.7 mm plates): a shadow edge on the leg,
    seen at 77°, passed as a sticker on the shading-corrected image (SD 1.5 mm); the same fit on
    the lit image put its centre 5.2 mm (1.2 radii) away. That fifth leg mark left the leg
    unlabelled in a trial where all seven true marks were found. It is refused now: the trial is
    complete, and every mark within its SD."""
    rig = variant_rig(draw_variant(195), 0, 20, scale=1.0, seed=1)
    res, truth = _measured(rig)
    assert res.complete and len(res.marks.marks) == 7, res.marks.message()
    _assert_within(res, truth)


@pytest.mark.parametrize("variant, inv, pf, seed", [(155, 0, 20, 1), (177, 0, -20, 0)])
def test_a_click_on_a_sticker_the_search_refused_snaps_to_its_centre(variant, inv, pf, seed):
    """Manual placement where the automatic search fails, full resolution. Variant 155 at 0/+20:
    a 23 mm front ankle sticker stands out only in the shading-corrected image, and its edges
    scatter 0.35 mm; variant 177 at 0/-20: a 24.4 mm one the foot partly hides, edges 0.39 mm.
    Both were refused by the search, and a click beside either was kept as it was, 3 mm off.
    The snap now looks in both images, takes a blob that reaches the click, and lets a clicked
    disk's edges scatter more: within 0.35 mm, and within its SD."""
    from anklescan.core.measure.mark_candidates import points_image
    from anklescan.core.measure.marks import snap_to_disk
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.lit_image import averaged_lit, clipped_white

    rig = variant_rig(draw_variant(variant), inv, pf, scale=1.0, seed=seed)
    cap = _capture(rig)
    res = measure_capture(cap, rig.true_calibration())
    truth = rig.truth()
    if "2" in res.marks.labelled:  # the search finds it now (its image fitted as a whole): right
        assert np.linalg.norm(res.marks.labelled["2"].centre - truth.marks["2"]) < 0.35
    lit = averaged_lit(cap)
    n = truth.mark_normals["2"]
    off = np.cross(n, [0.0, 0.0, 1.0])
    for sign in (1.0, -1.0):
        click = truth.marks["2"] + sign * 3.0 * off / np.linalg.norm(off)
        m = snap_to_disk(click, lit, points_image(res.cloud, lit.shape), rig.true_calibration(),
                         mark_diameter_mm=res.marks.diameter[0], clipped=clipped_white(cap))
        assert m is not None, sign
        e = m.centre - truth.marks["2"]
        assert np.linalg.norm(e) < 0.35, sign
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, sign


def test_a_disk_with_an_outline_through_its_face_is_refused():
    """Held-out variant 234 at 20/+20, full resolution (15.4 mm plates): where the bright table's
    edge stands over the dark floor 105 mm below, a 'sticker' was fitted across the edge, 63 % of
    its face on the floor, and made the trial 'found 8' with all seven true marks found. A disk's
    face is one surface, so such a fit is refused: the trial is complete, every mark within its
    SD."""
    rig = variant_rig(draw_variant(234), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete and len(res.marks.marks) == 7, res.marks.message()
    _assert_within(res, truth)


def test_a_thick_plate_on_the_outline_is_found_by_its_predicted_outline():
    """Held-out variant 221 at 20/+20, full resolution (15.7 x 2.8 mm plates): the lateral ankle
    plate, seen at 74° on the leg's outline, images as its lit side wall over a dim face; the
    cut blob is mostly the wall and its fit a fifth too small. The shape look's predicted
    outline (face and wall) was refused as 'not elliptical': a disk 7 px across rasterises to a
    solidity of 0.87. A predicted outline is now taken as the ellipse it is: the trial is
    complete, every mark within 0.3 mm and its SD."""
    rig = variant_rig(draw_variant(221), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    _assert_within(res, truth)


def test_a_large_plates_predicted_outline_is_judged_by_its_radius_sd_against_its_size():
    """Held-out variant 120 at 20/+20, full resolution (23.6 x 2.7 mm plates): the lateral ankle
    plate, seen at 73° on the leg's outline, is found only by the shape look's predicted disk,
    fitted on 30 edges with radius 11.59 +- 0.32 mm, 0.12 mm off, and was refused for an SD over
    0.3 mm. On a large mark that SD is 2.8 % of the size: the bound is now 4 % of the size where
    that exceeds 0.3 mm, and the trial is complete, every mark within 0.3 mm and its SD."""
    rig = variant_rig(draw_variant(120), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    _assert_within(res, truth)


def test_two_blobs_of_one_disk_in_the_second_look_leave_one_mark():
    """Held-out variant 287 at 20/+20, full resolution (10.9 mm stickers): two blobs of the
    shading-corrected image, 16 px apart, both fitted the front knee sticker, 0.01 mm apart. The
    second look checked where each blob lies, not where its fit lands, and kept both: 'seven'
    marks, so the later looks never searched for the missing front ankle sticker, and the leg
    went unlabelled. One disk is one mark now, and the trial is complete, every mark within
    0.3 mm and its SD."""
    rig = variant_rig(draw_variant(287), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    _assert_within(res, truth)


def test_a_click_is_not_moved_onto_a_doubtful_fit():
    """Held-out variant 173 at 20/+20, full resolution (11.3 mm plates): the front ankle plate,
    lit at 77°, is missed by the search. A click 3 mm beside it was snapped onto a fit of its lit
    side wall (clean edges, radius 7 % short of the size), 2.7 mm off along the view at an SD of
    0.24 mm: a confident wrong place. A fit whose radius disagrees with the size is passed
    over now, and the click is kept as it was."""
    from anklescan.core.measure.mark_candidates import points_image
    from anklescan.core.measure.marks import snap_to_disk
    from anklescan.core.measure.pipeline import measure_capture
    from anklescan.core.scan.lit_image import averaged_lit, clipped_white

    rig = variant_rig(draw_variant(173), 20, 20, scale=1.0, seed=4)
    cap = _capture(rig)
    res = measure_capture(cap, rig.true_calibration())
    assert "2" not in res.marks.labelled
    truth = rig.truth()
    lit = averaged_lit(cap)
    n = truth.mark_normals["2"]
    off = np.cross(n, [0.0, 0.0, 1.0])
    click = truth.marks["2"] + 3.0 * off / np.linalg.norm(off)
    m = snap_to_disk(click, lit, points_image(res.cloud, lit.shape), rig.true_calibration(),
                     mark_diameter_mm=res.marks.diameter[0], clipped=clipped_white(cap))
    if m is not None:  # a snap, if any, must be where the mark is, within its SD
        e = m.centre - truth.marks["2"]
        assert np.linalg.norm(e) < 0.35 and float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37


def test_a_table_sticker_half_in_the_legs_shadow_is_not_kept():
    """Held-out variant 297 at 20/+20, full resolution (14 mm stickers): the first table sticker,
    lit at 12°, lies half under the leg's cast shadow. Its bright sliver, 0.18 of the disk, was
    fitted as a plate 0.84 mm off at 9.3 SD, and tilted the table's angles by 0.26°. A face lit
    that squarely is bright all across; a blob of so little of it is a disk partly hidden, and
    is refused. Every mark kept is where a true mark is, within its SD."""
    rig = variant_rig(draw_variant(297), 20, 20, scale=1.0, seed=4)
    res, truth = _measured(rig)
    for m in res.marks.marks:
        e = min((m.centre - t for t in truth.marks.values()), key=np.linalg.norm)
        assert float(np.sqrt(e @ np.linalg.solve(m.covariance, e))) < 3.37, (m.label, np.linalg.norm(e), m.sd)
    assert all(np.linalg.norm(m.centre - truth.marks["5"]) > 5.0 for m in res.marks.marks)


def test_a_doubtful_fit_beside_seven_sure_marks_is_not_an_eighth():
    """Held-out variant 344 at 20/-20, the camera 42° round and 38° up (VIEW_DRAWN_FROM_SEED):
    the second look fitted skin by the leg's outline, near the lateral ankle plate, as a plate of
    6.3 mm radius against the marks' 7.15 (doubtful). Restored beside the seven true marks, it made
    five leg marks and the trial unlabelled; now seven sure marks leave no place for it."""
    rig = variant_rig(draw_variant(344), 20, -20, scale=1.0, seed=3)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    assert len(res.marks.marks) == 7
    _assert_within(res, truth)


def test_a_bright_patch_of_skin_is_not_kept_as_a_sticker_among_plates():
    """Held-out variant 378 at 0/+20 (9.6 x 2.1 mm plates): the second look kept a patch of skin
    by the leg's outline as a sticker (step -0.03 mm, edge RMS 0.22 mm) beside the lateral ankle
    plate, the true lateral mark was labelled the front one and the leg's angles were 8° off,
    said complete. A later look's fit whose step clearly says the other kind than the capture's
    marks is refused; the front ankle plate it stood in for is then found."""
    rig = variant_rig(draw_variant(378), 0, 20, scale=1.0, seed=1)
    res, truth = _measured(rig)
    assert res.complete, res.marks.message()
    assert {m.kind for m in res.marks.marks} == {"plate"}
    _assert_within(res, truth)
