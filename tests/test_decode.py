import numpy as np
import pytest

from anklescan.core.errors import CaptureError
from anklescan.core.scan.capture import capture_from_images
from anklescan.core.scan.decode import INCONSISTENT, LOW_CONTRAST, OUTSIDE, SATURATED, SHADOW, VALID, decode, estimate_sigma
from anklescan.core.scan.patterns import make_pattern_set, render_all, simulate_frames

H, W = 120, 160
NOISE = 2 / 255


def identity(ps):
    """Camera image = projector image (no optics)."""
    return np.stack(render_all(ps))


def smooth_map(proj_width=128):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    return 4 + xx * (proj_width - 12) / W + 3 * np.sin(yy / 17) + 5e-4 * (xx - 80) ** 2


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_every_column_round_trips_identity_camera(preset):
    ps = make_pattern_set(preset, 1024, 4)
    # saturation above 255: an identity camera's white is at the dtype maximum
    res = decode(identity(ps), ps, saturation=256)
    assert res.valid.all()
    c = np.arange(1024)
    expect = c if preset == "default" else (c // 4) * 4 + 1.5
    assert np.abs(res.column - expect).max() < 1e-3
    assert res.row is None and res.column.dtype == np.float32


def test_rows_round_trip():
    ps = make_pattern_set("default", 128, 64, axes=("column", "row"))
    res = decode(identity(ps), ps, saturation=256)
    assert res.valid.all()
    assert np.abs(res.row - np.arange(64)[:, None]).max() < 1e-3
    assert np.abs(res.column - np.arange(128)[None, :]).max() < 1e-3


def test_non_power_of_two_projector():
    ps = make_pattern_set("default", 100, 4)
    res = decode(identity(ps), ps, saturation=256)
    assert res.valid.all() and np.abs(res.column - np.arange(100)).max() < 1e-3


def test_default_subpixel_accuracy_with_blur_noise_gamma():
    ps = make_pattern_set("default", 128, 96)
    truth = smooth_map()
    frames = simulate_frames(ps, truth, blur=1.0, noise=NOISE, gamma=2.2)
    res = decode(frames, ps)
    assert res.valid.mean() > 0.99
    err = (res.column - truth)[res.valid]
    assert np.sqrt(np.mean(err ** 2)) < 0.05
    assert np.abs(err).max() < 0.3
    # the noise estimate adapts to the data: true sigma 2 (+ quantisation)
    assert 1.6 < res.thresholds["sigma"] < 2.6


def test_16bit_decodes_like_8bit():
    ps = make_pattern_set("default", 128, 96)
    truth = smooth_map()
    frames = simulate_frames(ps, truth, blur=1.0, noise=NOISE, gamma=2.2, dtype=np.uint16)
    res = decode(capture_from_images(ps, list(frames)))
    err = (res.column - truth)[res.valid]
    assert res.valid.mean() > 0.99 and np.sqrt(np.mean(err ** 2)) < 0.05
    assert 400 < res.thresholds["sigma"] < 680  # 2/255 of 65535 = 514


def test_paper_preset_gives_stripe_centres():
    ps = make_pattern_set("paper", 1024, 768)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    truth = 100 + xx * 5.0 + 0.0 * yy  # 5 projector columns per camera pixel
    frames = simulate_frames(ps, truth, blur=0.7, noise=NOISE)
    res = decode(frames, ps)
    assert res.valid.mean() > 0.99
    col = res.column[res.valid]
    assert np.all((col - 1.5) % 4 == 0)  # always a stripe centre
    assert np.abs(res.column - truth)[res.valid].max() <= 2.5 + 1.0


def test_shadow_region_is_masked_as_shadow():
    ps = make_pattern_set("default", 128, 96)
    albedo = np.full((H, W), 0.8, np.float32)
    albedo[20:50, 30:70] = 0.0  # projector light never reaches it: white == black
    frames = simulate_frames(ps, smooth_map(), albedo=albedo, noise=NOISE)
    res = decode(frames, ps)
    assert np.all(res.reason[22:48, 32:68] == SHADOW)
    assert np.all(np.isnan(res.column[22:48, 32:68]))
    assert not res.valid[22:48, 32:68].any()
    assert res.valid[70:, 90:].all()
    assert res.stats()["reasons"]["shadow"] >= 26 * 36


def test_a_clipped_white_keeps_its_phase():
    # a white plate lit head-on: the white and the bright phase samples clip
    ps = make_pattern_set("default", 128, 96)
    truth = smooth_map()
    albedo = np.full((H, W), 0.8, np.float32)
    albedo[20:60, 30:90] = 1.4  # up to 3 of the 8 phase samples clip
    # projector gamma: the clipped waveform is not a clipped sinusoid, only an even one
    frames = simulate_frames(ps, truth, albedo=albedo, noise=NOISE, gamma=2.2)
    ac = ps.axis_code("column")
    clipped = (frames[list(ac.phase)] == 255).sum(axis=0)
    region = (slice(20, 60), slice(30, 90))
    assert (frames[ps.index("white")][region] == 255).all()
    assert clipped[region].max() >= 3 and clipped[region].min() >= 1
    res = decode(frames, ps)
    assert res.valid[region].all()
    err = res.column[region] - truth[region]
    plain = res.column[70:110, 30:90] - truth[70:110, 30:90]
    # as exact as the unclipped surface beside it (which has the lower albedo and noise)
    assert np.sqrt(np.mean(err ** 2)) < 0.05 and np.abs(err).max() < 0.2
    assert np.sqrt(np.mean(err ** 2)) < 1.5 * np.sqrt(np.mean(plain ** 2)) + 0.01


def test_clipping_error_stays_within_the_bound():
    # every phase (columns) at every over-exposure up to 6x (rows), projector gamma, no noise
    ps = make_pattern_set("default", 128, 96)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    truth = 4 + xx * 0.7 + 0.01 * yy
    albedo = 0.9 + 5.0 * yy / (H - 1)
    frames = simulate_frames(ps, truth, albedo=albedo, ambient=0.03, gamma=2.2)
    ac = ps.axis_code("column")
    clipped = (frames[list(ac.phase)] == 255).sum(axis=0)
    res = decode(frames, ps, sigma=0.5)
    assert np.all(res.reason[clipped > 4] == SATURATED)
    ok = res.valid & (clipped >= 1)
    assert ok.sum() > 0.3 * ok.size
    assert np.abs(res.column[ok] - truth[ok]).max() < 0.12  # the N-step phase's bound, 4 of 8 clipped


def test_saturated_region_is_masked_as_saturated():
    ps = make_pattern_set("default", 128, 96)
    frames = simulate_frames(ps, smooth_map(), noise=NOISE)
    phase = [i for i, f in enumerate(ps.frames) if f.kind in ("phase", "white")]
    bright = frames[phase, 60:90, 100:140].astype(int) * 3
    frames[phase, 60:90, 100:140] = np.clip(bright, 0, 255)  # a specular highlight
    res = decode(frames, ps)
    region = res.reason[60:90, 100:140]
    ac = ps.axis_code("column")
    unclipped = (frames[list(ac.phase), 60:90, 100:140] < 255).sum(axis=0)
    # more than half the phase samples clipped: saturated
    assert np.all(region[unclipped < 4] == SATURATED)
    assert (unclipped < 4).mean() > 0.5
    # the rest of the highlight decodes, to the right column
    ok = unclipped >= 4
    assert ok.any() and np.all(region[ok] != SATURATED)
    good = res.valid[60:90, 100:140] & ok
    assert np.abs(res.column[60:90, 100:140][good] - smooth_map()[60:90, 100:140][good]).max() < 0.3
    assert res.valid[:50].all()


def test_paper_preset_still_masks_a_clipped_white():
    ps = make_pattern_set("paper", 128, 96)
    albedo = np.full((H, W), 0.8, np.float32)
    albedo[20:60, 30:90] = 1.4
    res = decode(simulate_frames(ps, smooth_map(), albedo=albedo, noise=NOISE), ps)
    assert np.all(res.reason[20:60, 30:90] == SATURATED)


def test_scrambled_code_is_inconsistent():
    ps = make_pattern_set("default", 128, 96, period=16)  # the reasoning below is for P = 16
    truth = smooth_map()
    frames = simulate_frames(ps, truth, noise=NOISE)
    ac = ps.axis_code("column")
    # a wrong coarse bit (e.g. motion between frames): swap bit 1 and its inverse
    i, j = ac.gray[1], ac.gray_inv[1]
    frames[[i, j], 10:110, 20:140] = frames[[j, i], 10:110, 20:140]
    res = decode(frames, ps)
    region = res.reason[10:110, 20:140]
    # the flip turns the binary low bits x into 15 - x: a phase/Gray disagreement of
    # 15 - 2x (mod 16), i.e. |d| in {1, 3, 5, 7}; |d| > P/4 = 4 catches half of it
    assert (region == INCONSISTENT).mean() > 0.45
    x = np.round(truth[10:110, 20:140]) % 8
    caught = (x >= 2) & (x <= 5)
    assert np.all(region[caught] == INCONSISTENT)
    assert res.valid[:8].all()


def test_random_codes_and_low_contrast():
    ps = make_pattern_set("default", 128, 96)
    frames = simulate_frames(ps, smooth_map(), noise=NOISE)
    rng = np.random.default_rng(3)
    # a surface that washes out the stripes: every pattern frame ~ half of white
    gray_phase = [i for i, f in enumerate(ps.frames) if f.kind in ("gray", "phase")]
    white = frames[ps.index("white")].astype(float)
    black = frames[ps.index("black")].astype(float)
    for i in gray_phase:
        noise = rng.normal(0, 2, (40, 40))
        frames[i, 70:110, 10:50] = np.clip((white + black)[70:110, 10:50] / 2 + noise, 0, 255)
    res = decode(frames, ps)
    assert np.all(res.reason[70:110, 10:50] == LOW_CONTRAST)


def test_column_outside_projector():
    ps = make_pattern_set("default", 128, 96, period=16)  # the reasoning below is for P = 16
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    truth = xx * 0.9 - 10  # left part of the image lies left of the projector
    frames = simulate_frames(ps, truth, noise=NOISE)
    res = decode(frames, ps)
    assert np.all(res.reason[truth < -0.5] != VALID)
    # just left of the edge the phase continues below -0.5 while the Gray code says 0
    near = (truth < -0.7) & (truth > -3.5)
    assert near.any() and np.all(res.reason[near] == OUTSIDE)
    # further out the phase wraps and contradicts the Gray code
    assert np.all(res.reason[truth < -4.5] == INCONSISTENT)
    assert res.valid[:, 20:150].all()


def test_thresholds_and_stats_are_reported():
    ps = make_pattern_set("default", 128, 96, period=16)  # the reasoning below is for P = 16
    res = decode(simulate_frames(ps, smooth_map(), noise=NOISE), ps)
    t = res.thresholds
    assert t["shadow"] == pytest.approx(t["k_shadow"] * t["sigma"])
    assert t["column_phase_tolerance"] == 4.0 and t["column_coarse_bits"] == [0, 1, 2, 3]
    s = res.stats()
    assert s["pixels"] == H * W and sum(s["reasons"].values()) == H * W
    assert s["valid"] == int(res.valid.sum())
    assert res.white.dtype == np.float32 and res.white.shape == (H, W)
    assert (res.white >= res.black).mean() > 0.99


def test_noise_estimate_tracks_true_noise():
    rng = np.random.default_rng(0)
    base = rng.uniform(100, 200, (H, W))
    for sigma in (1.0, 4.0):
        # a lit frame and a dark inverse, each with independent noise
        w = base + rng.normal(0, sigma, (H, W))
        f = base + rng.normal(0, sigma, (H, W))
        b = np.full((H, W), 20.0) + rng.normal(0, sigma, (H, W))
        inv = np.full((H, W), 20.0) + rng.normal(0, sigma, (H, W))
        est = estimate_sigma(w.astype(np.float32), b.astype(np.float32),
                             f.astype(np.float32), inv.astype(np.float32), 255.0)
        assert est == pytest.approx(sigma, rel=0.15)


def test_bad_inputs():
    ps = make_pattern_set("default", 128, 96)
    frames = identity(ps)
    with pytest.raises(CaptureError, match="pattern set"):
        decode(frames)
    with pytest.raises(CaptureError, match=f"got {len(ps.frames) - 1} frames"):
        decode(frames[:-1], ps)
    with pytest.raises(CaptureError, match="float64"):
        decode(frames.astype(np.float64), ps)


def test_strips_match_whole_image():
    ps = make_pattern_set("default", 128, 96, axes=("column", "row"))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = simulate_frames(ps, smooth_map(), yy * 0.7 + 5, blur=1.0, noise=NOISE)
    whole = decode(frames, ps, strip_pixels=0)
    strips = decode(frames, ps, strip_pixels=1000)  # 8-row strips, last one partial
    assert np.array_equal(whole.reason, strips.reason)
    assert np.array_equal(whole.column, strips.column, equal_nan=True)
    assert np.array_equal(whole.row, strips.row, equal_nan=True)
    assert whole.valid.mean() > 0.95


def test_the_same_capture_decodes_to_the_same_bits():
    """Phase SDs (and the weak-modulation test they share a magnitude with) do not depend on
    where the decoder's arrays happen to lie in memory: a capture decoded again, whole or in
    strips of any size, gives the same bits, so a cloud's checksum identifies its capture."""
    ps = make_pattern_set("default", 128, 96, axes=("column", "row"))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = simulate_frames(ps, smooth_map(), yy * 0.7 + 5, blur=1.0, noise=NOISE)
    first = decode(frames, ps, strip_pixels=0)
    for strip in (0, 1000, 1000, 2 * W + 3 * 8, 5000, 0):
        again = decode(frames, ps, strip_pixels=strip)
        for axis in ("column", "row"):
            assert np.array_equal(getattr(again, f"{axis}_sigma"), getattr(first, f"{axis}_sigma"), equal_nan=True)
            assert np.array_equal(getattr(again, axis), getattr(first, axis), equal_nan=True)
        assert np.array_equal(again.reason, first.reason)
