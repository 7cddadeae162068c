"""The projector-lit image averaged over the Gray-code pairs (anklescan.core.scan.lit_image)."""

import numpy as np
import pytest

from anklescan.core.scan.capture import capture_from_images
from anklescan.core.scan.lit_image import averaged_lit, lit_from_frames
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.hardware.sim_scene import leg_scene
from anklescan.hardware.simrig import SimRig


@pytest.fixture(scope="module")
def rig_and_set():
    rig = SimRig(leg_scene(10, 0), scale=0.3, seed=3)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height)
    return rig, pset


def _frames(rig, pset, **kw):
    return np.stack([rig.capture(img, **kw) for img in render_all(pset)])


def test_averaging_cuts_the_noise_of_white_minus_black(rig_and_set):
    rig, pset = rig_and_set
    clean = _frames(rig, pset, noise=False)
    noisy = _frames(rig, pset)
    truth = clean[pset.index("white")].astype(np.float32) - clean[pset.index("black")]
    lit = averaged_lit(capture_from_images(pset, list(noisy)))
    plain = noisy[pset.index("white")].astype(np.float32) - noisy[pset.index("black")]
    well_lit = truth > 40
    err_avg = np.std((lit - truth)[well_lit])
    err_plain = np.std((plain - truth)[well_lit])
    # ~8 of 10 pairs decisive at a typical pixel: the noise falls by ~3 (sqrt 9), quantisation aside
    assert err_avg < 0.5 * err_plain, (err_avg, err_plain)
    assert abs(np.mean((lit - truth)[well_lit])) < 0.5  # unbiased where lit


def test_a_camera_tone_curve_leaves_no_stripe_edges(rig_and_set):
    """max − min of a decisive pair is white − black whatever the camera's response; pixels on
    a stripe edge (where frame + inverse would not add up) are left out, not averaged in."""
    rig, pset = rig_and_set
    linear = _frames(rig, pset, noise=False).astype(np.float64)
    toned = np.round(255.0 * (linear / 255.0) ** (1 / 2.2)).astype(np.uint8)
    lit = lit_from_frames(toned, pset)
    plain = toned[pset.index("white")].astype(np.float32) - toned[pset.index("black")]
    # within the 8-bit rounding of the frames (a straddling pixel with every pair partial was 38 off)
    assert np.abs(lit - plain).max() <= 4.0


@pytest.mark.parametrize("preset,axes", [("paper", ("column",)), ("default", ("column", "row"))])
def test_other_pattern_sets_and_float_frames(rig_and_set, preset, axes):
    """The paper's 8 bits, and a set with rows too (the calibration box's): every axis's pairs."""
    rig, _ = rig_and_set
    pset = make_pattern_set(preset, rig.projector.width, rig.projector.height, axes=axes)
    frames = np.stack([rig.capture(img, noise=False) for img in render_all(pset)]).astype(np.float32)
    lit = lit_from_frames(frames, pset)
    plain = frames[pset.index("white")] - frames[pset.index("black")]
    assert lit.dtype == np.float32 and lit.shape == plain.shape
    d = np.abs(lit - plain)
    assert np.percentile(d, 99) <= 1.5 and d.max() <= 4.0  # noiseless: rounding, and a few straddling pixels


def test_sixteen_bit_frames_scale_with_the_frames(rig_and_set):
    rig, pset = rig_and_set
    frames8 = _frames(rig, pset, noise=False)
    lit8 = lit_from_frames(frames8, pset)
    lit16 = lit_from_frames(frames8.astype(np.uint16) * 257, pset)
    assert np.allclose(lit16, 257 * lit8, atol=257 * 0.5)
