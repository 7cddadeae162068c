"""SPEC §3 angles against constructed geometry, uncertainty against Monte-Carlo."""

import json
import math

import numpy as np
import pytest

from anklescan.core.errors import AnkleScanError, GeometryError
from anklescan.core.measure.angles import (
    compute_angles,
    leg_inversion,
    leg_plantar_flexion,
    mismatch,
    read_marks_csv,
    table_angles,
    table_normal,
)
from anklescan.core.vocabulary import Angle


def rot_y(deg):
    """Rotation about +y: takes +z towards +x (knee tilted to the patient's right)."""
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def rot_x(deg):
    """Rotation about +x: takes +z towards −y; we use −deg to tilt +z to anterior."""
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def table_marks(inv_deg, pf_deg, centre=(80.0, 250.0, 60.0)):
    """Three marks on a plane whose sections have the given slopes.

    Lateral (+x) edge down by inv_deg and toes (+y) down by pf_deg: z falls along +x and +y.
    """
    c = np.array(centre)
    sx, sy = math.tan(math.radians(inv_deg)), math.tan(math.radians(pf_deg))
    pts = [(-40.0, -60.0), (45.0, -50.0), (5.0, 90.0)]
    return [c + np.array([u, v, -sx * u - sy * v]) for u, v in pts]


def leg_marks(inv_deg, pf_deg):
    """Knee 400 mm above the ankle, leg line tilted by the given projected angles."""
    ankle_front, ankle_lat = np.array([0.0, 40.0, 80.0]), np.array([35.0, 0.0, 85.0])
    d = np.array([math.tan(math.radians(inv_deg)), math.tan(math.radians(pf_deg)), 1.0])
    d = d / np.linalg.norm(d) * 400.0
    return {1: ankle_front + d, 2: ankle_front, 3: ankle_lat + d, 4: ankle_lat}


def all_marks(leg_inv=7.0, leg_pf=-12.0, tab_inv=15.0, tab_pf=20.0):
    m = leg_marks(leg_inv, leg_pf)
    m.update(dict(zip((5, 6, 7), table_marks(tab_inv, tab_pf), strict=False)))
    return m


# ----------------------------------------------------------------- definitions

@pytest.mark.parametrize("deg", [-25.0, 0.0, 10.0, 33.0])
def test_leg_inversion_from_rotated_leg(deg):
    knee = rot_y(deg) @ np.array([0, 0, 420.0])
    assert leg_inversion(knee, [0, 0, 0]) == pytest.approx(deg, abs=1e-9)
    # Knee to the patient's right (+x) of the ankle is positive.
    assert math.copysign(1, leg_inversion([10, 0, 400], [0, 0, 0])) == 1


@pytest.mark.parametrize("deg", [-20.0, 0.0, 15.0])
def test_leg_plantar_flexion_from_rotated_leg(deg):
    knee = rot_x(-deg) @ np.array([0, 0, 400.0])   # tilt +z towards +y (anterior)
    assert leg_plantar_flexion(knee, [0, 0, 0]) == pytest.approx(deg, abs=1e-9)


def test_projection_ignores_out_of_plane_component():
    # θ1 only looks at x and z: a large y offset must not change it.
    assert leg_inversion([50, 300, 400], [0, 0, 0]) == pytest.approx(math.degrees(math.atan2(50, 400)))


@pytest.mark.parametrize("inv,pf", [(0, 0), (20, 0), (0, 20), (-10, 25), (15, -5)])
def test_table_angles_known_plane(inv, pf):
    assert table_angles(*table_marks(inv, pf)) == pytest.approx((inv, pf), abs=1e-9)


def test_table_sign_conventions_and_orientation():
    # Lateral edge (+x) lower than medial edge → positive inversion.
    p = [[0, 0, 10], [100, 0, 0], [0, 100, 10]]
    inv, pf = table_angles(*p)
    assert inv > 0 and pf == pytest.approx(0, abs=1e-12)
    # Toes (+y) down → positive plantar flexion.
    inv, pf = table_angles([0, 0, 10], [100, 0, 10], [0, 100, 0])
    assert pf > 0 and inv == pytest.approx(0, abs=1e-12)
    # Mark order must not flip the normal (n_z > 0 always).
    assert table_normal(p[0], p[2], p[1])[2] > 0
    assert table_angles(p[0], p[2], p[1]) == pytest.approx(table_angles(*p))


def test_table_rotated_normal():
    n = rot_y(12) @ rot_x(-8) @ np.array([0, 0, 1.0])
    # Build the plane from the normal: two in-plane vectors.
    u = np.cross(n, [0, 1, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    c = np.array([10.0, 20.0, 30.0])
    inv, pf = table_angles(c, c + 80 * u, c + 60 * v + 10 * u)
    assert inv == pytest.approx(math.degrees(math.atan2(n[0], n[2])), abs=1e-9)
    assert pf == pytest.approx(math.degrees(math.atan2(n[1], n[2])), abs=1e-9)


# ------------------------------------------------------------------- degenerate

@pytest.mark.parametrize("pts,msg", [
    (([0, 0, 0], [0, 0, 0], [1, 1, 0]), "coincident"),
    (([0, 0, 0], [10, 10, 1], [20, 20, 2]), "collinear"),
    (([0, 0, 0], [10, 0, 0], [0, 0, 10]), "vertical"),
])
def test_table_degenerate(pts, msg):
    with pytest.raises(GeometryError, match=msg):
        table_angles(*pts)


def test_leg_degenerate():
    with pytest.raises(GeometryError, match="1–2"):
        leg_inversion([0, 5, 0], [0, -5, 0])   # only a y extent: no x–z projection
    with pytest.raises(GeometryError, match="3–4"):
        leg_plantar_flexion([3, 0, 0], [0, 0, 0])
    with pytest.raises(GeometryError, match="non-finite"):
        leg_inversion([np.nan, 0, 1], [0, 0, 0])


# ----------------------------------------------------------------- compute_angles

def test_compute_angles_values_and_json():
    r = compute_angles(all_marks(), sigma_mm=0.3)
    expect = {"leg_inversion": 7, "leg_plantar_flexion": -12, "table_inversion": 15,
              "table_plantar_flexion": 20}
    assert set(r) == set(expect) and r.missing == {}
    for k, v in expect.items():
        assert r[k].value == pytest.approx(v, abs=1e-9)
        assert r[k].sd > 0
    doc = json.loads(json.dumps(r.to_json()))  # RESULT.json's form (SPEC §3)
    assert doc == {k: {"value": a.value, "sd": a.sd} for k, a in r.items()}


def test_compute_angles_string_labels_and_missing():
    m = {str(k): v for k, v in all_marks().items() if k not in (3, 6)}
    r = compute_angles(m)
    assert set(r) == {"leg_inversion"}
    assert r.missing == {"leg_plantar_flexion": [3], "table_inversion": [6],
                         "table_plantar_flexion": [6]}
    assert r.missing_marks == [3, 6]
    assert "leg_plantar_flexion (needs mark 3)" in r.missing_message()


def test_compute_angles_bad_labels():
    with pytest.raises(AnkleScanError, match="out of range"):
        compute_angles({8: [0, 0, 0]})
    with pytest.raises(AnkleScanError, match="twice"):
        compute_angles({1: [0, 0, 1], "1": [0, 0, 2]})


def _monte_carlo_sd(marks, covs, n=4000, seed=1):
    # The plain angle functions (no Jacobian) keep 4000 draws well under a second.
    rng = np.random.default_rng(seed)
    d = {k: rng.multivariate_normal(np.asarray(p), covs[k], size=n) for k, p in marks.items()}
    samples = np.array([
        (leg_inversion(d[1][i], d[2][i]), leg_plantar_flexion(d[3][i], d[4][i]),
         *table_angles(d[5][i], d[6][i], d[7][i]))
        for i in range(n)])
    names = ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion")
    return dict(zip(names, samples.std(axis=0, ddof=1), strict=False))


def test_sd_matches_monte_carlo_isotropic():
    marks, sigma = all_marks(), 1.5
    r = compute_angles(marks, sigma_mm=sigma)
    mc = _monte_carlo_sd(marks, {k: np.eye(3) * sigma**2 for k in marks})
    for k, sd in mc.items():
        assert r[k].sd == pytest.approx(sd, rel=0.10), k


def test_sd_matches_monte_carlo_per_mark_covariance():
    marks = all_marks(leg_inv=-5, tab_inv=-8, tab_pf=10)
    rng = np.random.default_rng(7)
    covs = {}
    for k in marks:
        a = rng.normal(size=(3, 3))
        covs[k] = a @ a.T * 0.5 + np.eye(3) * 0.1
    r = compute_angles(marks, sigma_mm=covs)
    mc = _monte_carlo_sd(marks, covs, seed=3)
    for k, sd in mc.items():
        assert r[k].sd == pytest.approx(sd, rel=0.10), k


def test_bad_covariance_rejected():
    with pytest.raises(AnkleScanError, match="3x3"):
        compute_angles({1: [0, 0, 400], 2: [0, 0, 0]}, sigma_mm={1: np.eye(2), 2: 0.1})
    with pytest.raises(AnkleScanError, match="non-negative"):
        compute_angles({1: [0, 0, 400], 2: [0, 0, 0]}, sigma_mm=-1)


# -------------------------------------------------------------------- mismatch

def test_mismatch_value_and_sd():
    adj = compute_angles(all_marks(tab_inv=13, tab_pf=22), sigma_mm=0.5)
    m = mismatch(adj, {"inversion": 15.0, "plantar_flexion": Angle(20.0, 0.3)})
    assert m["inversion"].value == pytest.approx(-2.0, abs=1e-9)
    assert m["plantar_flexion"].value == pytest.approx(2.0, abs=1e-9)
    assert m["inversion"].sd == pytest.approx(adj["table_inversion"].sd)
    assert m["plantar_flexion"].sd == pytest.approx(
        math.hypot(adj["table_plantar_flexion"].sd, 0.3))


def test_mismatch_missing_axis():
    with pytest.raises(AnkleScanError, match="plantar_flexion"):
        mismatch({"inversion": 1.0}, {"inversion": 0.0, "plantar_flexion": 0.0})


# ------------------------------------------------------------------------ CSV

def _write(tmp_path, text):
    p = tmp_path / "marks.csv"
    p.write_text(text)
    return p


def test_read_marks_csv_round_trip(tmp_path):
    marks = all_marks()
    body = "label,x,y,z\n" + "".join(f"{k},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}\n" for k, p in marks.items())
    got = read_marks_csv(_write(tmp_path, body))
    assert sorted(got) == list(range(1, 8))
    for k in marks:
        np.testing.assert_array_equal(got[k], marks[k])


def test_read_marks_csv_column_order_and_bom(tmp_path):
    got = read_marks_csv(_write(tmp_path, "\ufeffZ, Y ,x,Label\n3,2,1,5\n"))
    np.testing.assert_array_equal(got[5], [1, 2, 3])


@pytest.mark.parametrize("text,msg", [
    ("", "empty"),
    ("1,0,0,0\n", "header"),
    ("label,x,y\n1,0,0\n", "header"),
    ("label,x,y,z\n1,0,0\n", "fields"),
    ("label,x,y,z\n,0,0,0\n", "missing mark label"),
    ("label,x,y,z\n1,0,abc,0\n", "not a number"),
    ("label,x,y,z\n1,0,nan,0\n", "finite"),
    ("label,x,y,z\n1,0,0,0\n1,1,1,1\n", "duplicate"),
    ("label,x,y,z\n9,0,0,0\n", "out of range"),
    ("label,x,y,z\n", "no marks"),
])
def test_read_marks_csv_errors(tmp_path, text, msg):
    with pytest.raises(AnkleScanError, match=msg) as e:
        read_marks_csv(_write(tmp_path, text))
    assert "\n" not in str(e.value)


def test_read_marks_csv_missing_file(tmp_path):
    with pytest.raises(AnkleScanError, match="cannot read"):
        read_marks_csv(tmp_path / "nope.csv")
