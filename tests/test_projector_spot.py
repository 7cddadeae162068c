"""Refining a steered projector spot to the camera's control point (anklescan.core.calibration.procedures.projector_spot)."""

import cv2
import numpy as np
import pytest

from anklescan.core.calibration.procedures import projector_spot as ps

PROJECTOR = (320, 240)
CAMERA = (200, 160)
# camera (x, y) -> projector (column, row): oblique, with perspective
H = np.array([[0.62, 0.21, 95.0], [-0.08, 0.55, 60.0], [2e-4, -4e-4, 1.0]])
CORNER = np.array([101.3, 77.6])  # camera px: a marker corner, printed black to its lower right


def _truth():
    p = H @ [*CORNER, 1.0]
    return p[:2] / p[2]


def _shoot(projector_image, rng, ss=4):
    """Camera image of a projector frame on a surface with a black quadrant at CORNER:
    4x4 supersampled, ambient, blur, noise."""
    w, h = CAMERA
    ys, xs = np.mgrid[0:h * ss, 0:w * ss]
    cx, cy = (xs + 0.5) / ss - 0.5, (ys + 0.5) / ss - 0.5
    q = np.tensordot(H, np.stack([cx, cy, np.ones_like(cx)]), axes=1)
    light = cv2.remap(projector_image.astype(np.float32) / 255, (q[0] / q[2]).astype(np.float32),
                      (q[1] / q[2]).astype(np.float32), cv2.INTER_LINEAR, borderValue=0)
    albedo = np.where((cx > CORNER[0]) & (cy > CORNER[1]), 0.05, 0.85)
    img = cv2.resize((albedo * (0.04 + light)).astype(np.float32), CAMERA, interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.7) * 255 + rng.normal(0, 2, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_edge_frames_are_exact_edges_with_inverses():
    frames = ps.refinement_frames(PROJECTOR, (150.4, 100.6))
    edges = ps.refinement_edges((150.4, 100.6))
    assert len(frames) == len(edges) == 8
    for k in range(0, 8, 2):
        lit, inv = frames[k].astype(int), frames[k + 1].astype(int)
        assert not np.any(lit & inv) and np.any(lit) and np.any(inv)  # complementary in the window
    assert [e.at for e in edges[::2]] == [147.5, 152.5, 98.5, 103.5]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_refines_half_a_pixel_to_a_few_hundredths(seed):
    rng = np.random.default_rng(seed)
    truth = _truth()
    steered = tuple(truth + rng.normal(0, 0.5, 2))
    white = _shoot(np.full(PROJECTOR[::-1], 255, np.uint8), rng)
    images = [_shoot(f, rng) for f in ps.refinement_frames(PROJECTOR, steered)]
    result = ps.refine_spot(images, CORNER, steered, white=white)
    assert result.ok, result.message
    assert np.abs(np.array(result.position) - truth).max() < 0.1


def test_refuses_a_spot_steered_onto_another_point():
    rng = np.random.default_rng(0)
    steered = tuple(_truth() + [2.9, 2.9])  # edges still in view, but the answer is 4 px away
    images = [_shoot(f, rng) for f in ps.refinement_frames(PROJECTOR, steered)]
    result = ps.refine_spot(images, CORNER, steered, _shoot(np.full(PROJECTOR[::-1], 255, np.uint8), rng),
                            radius_px=30)
    assert not result.ok and "steer it onto the point" in result.message
    assert result.shift == (0.0, 0.0)


def test_refuses_when_the_edges_are_not_seen():
    rng = np.random.default_rng(0)
    steered = tuple(_truth() + [40.0, 0.0])  # the window lights somewhere else entirely
    images = [_shoot(f, rng) for f in ps.refinement_frames(PROJECTOR, steered)]
    result = ps.refine_spot(images, CORNER, steered, _shoot(np.full(PROJECTOR[::-1], 255, np.uint8), rng))
    assert not result.ok and "is the spot on it" in result.message


def test_wrong_number_of_images_is_a_clear_error():
    with pytest.raises(ValueError, match="expected 8 images"):
        ps.refine_spot([np.zeros((10, 10))] * 3, (5, 5), (5.0, 5.0), np.zeros((10, 10)))
