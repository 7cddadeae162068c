"""Labelling the marks 1-7 (SPEC §2): the table triple (5, 6, 7 in a rule of their own layout),
knee above ankle, front vs lateral by the normal round the leg. docs/marks.md, "Labels".
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_types import Mark, MarkSet
from anklescan.core.measure.marks_surface import local_frame
from anklescan.core.vocabulary import LABEL_KEYS as LABELS  # the detector keys marks by the labels' text form
from anklescan.core.vocabulary import TABLE_LABEL_KEYS as TABLE_LABELS


def label_marks(ms: MarkSet) -> None:
    """Label in place (SPEC §2). Unresolvable parts stay unlabelled, with a message."""
    for m in ms.marks:
        m.label = None
    marks = ms.marks
    if len(marks) > len(LABELS):  # fewer: the message's "found N" and "missing labels" say it
        ms.problems.append(f"{len(marks)} marks where {len(LABELS)} are expected")
    table = _table_triple(marks, ms.problems)
    if table is not None:
        for lab, m in zip(TABLE_LABELS, _table_order([marks[i] for i in table]), strict=True):
            m.label = lab
        # a leg mark faces sideways: a bright patch on the floor or the foot's top that passed
        # as a mark must not take a leg label (as the lateral ankle mark it turns the true one
        # into the front, and the leg's angles go several degrees off)
        leg = [m for i, m in enumerate(marks) if i not in table and abs(m.normal[2]) < CONFIG.leg_normal_max_z]
        if len(leg) <= 4:
            _label_leg(leg, ms.problems, _table_plane([marks[i] for i in table]))
        else:
            ms.problems.append(f"{len(leg)} leg marks (expected 4): leg marks not labelled")
    else:
        # No table triple: the leg plates still label themselves if exactly four plates face
        # sideways (leg plates' normals are perpendicular to the near-vertical leg axis; the
        # table plates' are within ~30° of +z), so a lost table plate does not cost the leg.
        leg = [m for m in marks if abs(m.normal[2]) < CONFIG.leg_normal_max_z]
        if len(leg) == 4:
            _label_leg(leg, ms.problems)
    order = {lab: i for i, lab in enumerate(LABELS)}
    ms.marks.sort(key=lambda m: (m.label is None, order.get(m.label or "", 99), m.pixel[1], m.pixel[0]))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(abs(a @ b), -1.0, 1.0))))


def _triple_score(ms: list[Mark]) -> float:
    """Worst disagreement (deg) among the three plate normals and the plane through the centres."""
    P = np.array([m.centre for m in ms])
    n = np.cross(P[1] - P[0], P[2] - P[0])
    if np.linalg.norm(n) < 1e-9:
        return 180.0
    n /= np.linalg.norm(n)
    return max([_angle_deg(m.normal, n) for m in ms]
               + [_angle_deg(a.normal, b.normal) for a, b in itertools.combinations(ms, 2)])


def _table_triple(marks: list[Mark], problems: list[str]) -> set[int] | None:
    """Indices of the table marks: the only triple whose plates all lie in one plane, flat on it.

    Leg marks come in pairs along a generator (front, lateral) whose normals are ~90° apart,
    so any triple other than the table's has a large normal spread. Ties are ambiguous.
    """
    if len(marks) < 3:
        problems.append("fewer than 3 marks: cannot find the table marks")
        return None
    scored = sorted((_triple_score([marks[i] for i in t]), t) for t in itertools.combinations(range(len(marks)), 3))
    best, t = scored[0]
    if best > CONFIG.table_normal_spread_deg:
        facing_up = sum(bool(abs(m.normal[2]) >= CONFIG.leg_normal_max_z) for m in marks)
        if facing_up < 3:  # the usual cause, said plainly: the table marks were not found
            what = ("no mark found faces" if not facing_up
                    else f"only {facing_up} mark{'s' * (facing_up > 1)} found face{'s' * (facing_up == 1)}")
            problems.append(f"{what} up as table marks do (3 expected): table marks not identified")
        else:
            problems.append(f"no three marks lie flat in one plane (best {best:.1f}°): table marks not identified")
        return None
    if len(scored) > 1 and scored[1][0] - best < CONFIG.ambiguity_margin_deg:
        problems.append(f"two candidate sets of table marks ({best:.1f}° vs {scored[1][0]:.1f}°): ambiguous")
        return None
    return set(t)


def _table_order(ms: list[Mark]) -> list[Mark]:
    """5, 6, 7: counter-clockwise seen from above (about +z) around their centroid, starting
    after the widest angular gap (for the default layout: lateral-posterior, lateral-anterior,
    medial)."""
    P = np.array([m.centre for m in ms])
    n = _table_plane(ms)[1]
    B = local_frame(P.mean(axis=0), n)[:2]
    if np.cross(B[0], B[1]) @ n < 0:
        B = B[::-1]
    q = (P - P.mean(axis=0)) @ B.T
    ang = np.arctan2(q[:, 1], q[:, 0])
    order = np.argsort(ang)
    gaps = np.diff(np.r_[ang[order], ang[order[0]] + 2 * math.pi])
    start = (int(np.argmax(gaps)) + 1) % 3
    return [ms[i] for i in np.roll(order, -start)]


def _table_plane(table: list[Mark]) -> tuple[np.ndarray, np.ndarray]:
    """(point, upward unit normal) of the table top through its three marks."""
    P = np.array([m.centre for m in table])
    n = np.cross(P[1] - P[0], P[2] - P[0])
    n = n / np.linalg.norm(n)
    return P.mean(axis=0), n if n[2] >= 0 else -n


def _label_leg(leg: list[Mark], problems: list[str], table: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Knee pair above the ankle pair (along the leg axis, i.e. z); within a pair the front
    plate faces anterior (+y) more than lateral (+x), the lateral one the other way round.

    With only two or three leg plates found, what the geometry still decides is labelled: the
    knee/ankle split is the widest gap in height (it must be clear: ≥ 100 mm), a lone plate in
    its group is front or lateral by its normal's nearness to the other group's labelled pair
    (or, without one, by which way round the leg its normal points).
    """
    if len(leg) < 2:
        if len(leg) == 1 and table is not None:
            _label_lone_mark(leg[0], table, problems)
        return
    z = np.array([m.centre[2] for m in leg])
    idx = np.argsort(z)
    if len(leg) == 4:
        ankle, knee = [leg[i] for i in idx[:2]], [leg[i] for i in idx[2:]]
        axis = np.mean([m.centre for m in knee], axis=0) - np.mean([m.centre for m in ankle], axis=0)
        gap = (z[idx[2]] - z[idx[1]])
        if gap < 0.25 * np.linalg.norm(axis):
            problems.append("knee and ankle marks are not clearly separated in height")
            return
    else:
        gaps = np.diff(z[idx])
        k = int(np.argmax(gaps))
        if gaps[k] < CONFIG.partial_leg_gap_mm:
            if len(leg) == 2 and table is not None:
                _label_lone_pair(leg, table, problems)
                return
            problems.append("knee and ankle marks are not clearly separated in height")
            return
        ankle, knee = [leg[i] for i in idx[: k + 1]], [leg[i] for i in idx[k + 1:]]
        if len(ankle) > 2 or len(knee) > 2:
            problems.append("more than two leg marks at one height")
            return
        axis = np.mean([m.centre for m in knee], axis=0) - np.mean([m.centre for m in ankle], axis=0)
    length = float(np.linalg.norm(axis))
    axis /= length
    for pair, where in ((knee, "knee"), (ankle, "ankle")):
        spread = abs(float((pair[0].centre - pair[-1].centre) @ axis))
        if spread > CONFIG.pair_max_spread * length:
            problems.append(f"the two {where} marks are {spread:.0f} mm apart along the leg (one level expected): "
                            "one of them may not be a mark; leg marks not labelled")
            return
    groups = ((knee, ("1", "3"), "knee"), (ankle, ("2", "4"), "ankle"))
    for pair, (front, lateral), where in groups:
        if len(pair) == 2:
            _label_pair(pair, axis, front, lateral, where, problems)
    if not _pairs_agree(knee, ankle, axis, problems):
        for m in leg:
            m.label = None
        return
    for (pair, (front, lateral), where), (other, _, _) in zip(groups, groups[::-1], strict=True):
        if len(pair) == 1:
            label = _lone_label(pair[0], other, axis, front, lateral)
            if label is None:
                problems.append(f"cannot tell whether the {where} mark is the front or the lateral one")
            pair[0].label = label


def _pairs_agree(knee: list[Mark], ankle: list[Mark], axis: np.ndarray, problems: list[str]) -> bool:
    """False (with a message) if a mark of one labelled pair faces round the leg clearly nearer
    the other role's mark of the other pair than its own role's (``CONFIG.cross_pair_margin_deg``)."""
    marks = knee + ankle
    if len(marks) != 4 or any(m.label is None for m in marks):
        return True
    az = {m.label: _azimuth_about(m.normal, axis) for m in marks}
    # (same role, other role); the ankle's first: a patch on the foot is likelier there
    partner = {"2": ("1", "3"), "4": ("3", "1"), "1": ("2", "4"), "3": ("4", "2")}
    for lab, (same, other) in partner.items():
        d_same, d_other = (abs(_wrap_deg(az[lab] - az[k])) for k in (same, other))
        if d_other + CONFIG.cross_pair_margin_deg < d_same:
            where = "knee" if lab in ("1", "3") else "ankle"
            role = "front" if lab in ("1", "2") else "lateral"
            problems.append(f"the {where}'s {role} mark faces round the leg {d_other:.0f}° from the other pair's "
                            f"{'lateral' if role == 'front' else 'front'} mark and {d_same:.0f}° from its "
                            f"{role} one: one of the leg marks may not be a mark; leg marks not labelled")
            return False
    return True


def _label_lone_pair(pair: list[Mark], table: tuple[np.ndarray, np.ndarray], problems: list[str]) -> None:
    """Two leg plates at one height, the other pair lost: knee or ankle by their height over
    the table top (``CONFIG.knee_min_height_mm``), front or lateral by which way round the leg their
    normals point (about z: the leg stands, SPEC §1)."""
    (front, lateral), where = _by_height(pair, table)
    _label_pair(pair, np.array([0.0, 0.0, 1.0]), front, lateral, where, problems)


def _label_lone_mark(m: Mark, table: tuple[np.ndarray, np.ndarray], problems: list[str]) -> None:
    """The only leg plate found: knee or ankle by its height over the table top, front or
    lateral by which way round the leg its normal points (as a lone plate without the other
    pair, ``_lone_label``)."""
    (front, lateral), where = _by_height([m], table)
    m.label = _lone_label(m, [], np.array([0.0, 0.0, 1.0]), front, lateral)
    if m.label is None:
        problems.append(f"cannot tell whether the {where} mark is the front or the lateral one")


def _by_height(marks: list[Mark], table: tuple[np.ndarray, np.ndarray]) -> tuple[tuple[str, str], str]:
    """((front, lateral) labels, "knee"/"ankle") of leg marks by their mean height over the table top."""
    point, up = table
    height = float(np.mean([(m.centre - point) @ up for m in marks]))
    return (("1", "3"), "knee") if height >= CONFIG.knee_min_height_mm else (("2", "4"), "ankle")


def _label_pair(pair: list[Mark], axis: np.ndarray, front: str, lateral: str, where: str, problems: list[str]) -> None:
    """Front and lateral of one pair by which way round ``axis`` their normals point."""
    a = [_azimuth_about(m.normal, axis) for m in pair]
    if abs(_wrap_deg(a[0] - a[1])) < CONFIG.side_margin_deg:  # 50-90° apart; a tie means no decision
        problems.append(f"cannot tell the front from the lateral {where} mark")
        return
    f, lat = (pair[0], pair[1]) if _wrap_deg(a[0] - a[1]) > 0 else (pair[1], pair[0])
    f.label, lat.label = front, lateral


def _lone_label(m: Mark, other: list[Mark], axis: np.ndarray, front: str, lateral: str) -> str | None:
    """A lone knee (ankle) plate is front or lateral by which plate of the labelled ankle
    (knee) pair its normal is nearer to, around the leg axis: the leg carries both pairs,
    wherever round its side the marks were stuck. Without that pair, by which side of
    ``CONFIG.lone_split_deg`` its normal points round the leg (front marks face 90°, lateral ones
    0-40°: docs/marks.md), at least half the margin clear of it."""
    if len(other) == 2 and all(o.label is not None for o in other):
        ref = sorted(other, key=lambda o: o.label or "")  # front ("1"/"2") before lateral ("3"/"4")
        d = [abs(_wrap_deg(_azimuth_about(m.normal, axis) - _azimuth_about(o.normal, axis))) for o in ref]
        if abs(d[0] - d[1]) >= CONFIG.side_margin_deg:
            return front if d[0] < d[1] else lateral
        return None
    a = _azimuth_about(m.normal, axis)
    if a >= CONFIG.lone_split_deg + CONFIG.side_margin_deg / 2:
        return front
    if a <= CONFIG.lone_split_deg - CONFIG.side_margin_deg / 2:
        return lateral
    return None


def _azimuth_about(n: np.ndarray, axis: np.ndarray) -> float:
    """Direction (deg) of a normal round the leg, seen down its axis: 0 lateral (+x), 90 front (+y)."""
    p = n - (n @ axis) * axis
    return math.degrees(math.atan2(p[1], p[0]))


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0

