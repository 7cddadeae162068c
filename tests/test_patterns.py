import copy
import json
import time

import cv2
import numpy as np
import pytest

import anklescan.core.scan.patterns as patterns
from anklescan.core.errors import AnkleScanError, CaptureError
from anklescan.core.scan.patterns import PatternSet, gray_profile, make_pattern_set, render_all, render_frame, write_patterns


def test_paper_preset_is_the_papers_18_frames():
    ps = make_pattern_set("paper", 1024, 768)
    assert len(ps.frames) == 18
    assert [f.kind for f in ps.frames[:2]] == ["white", "black"]
    gray = ps.frames[2:]
    assert [(f.bit, f.inverse) for f in gray] == [(b, inv) for b in range(8)
                                                 for inv in (False, True)]
    assert {f.stripe for f in gray} == {4} and {f.bits for f in gray} == {8}
    assert ps.files[:4] == ["00_white.png", "01_black.png", "02_col_gray_b00.png",
                            "03_col_gray_b00_inv.png"]


def test_default_preset_layout_and_names():
    ps = make_pattern_set("default", 1024, 768)
    kinds = [f.kind for f in ps.frames]
    assert kinds.count("gray") == 20 and kinds.count("phase") == 8 and len(kinds) == 30
    assert ps.files[22] == "22_col_phase_p8_s0.png"
    assert ps.files[-1] == "29_col_phase_p8_s7.png"
    ac = ps.axis_code("column")
    assert (ac.bits, ac.stripe, ac.period, ac.steps) == (10, 1, 8.0, 8)
    both = make_pattern_set("default", 1024, 768, axes=("column", "row"))
    assert both.axis_code("row").bits == 10 and len(both.frames) == 2 + 2 * (20 + 8)
    assert any("row_gray_b09_inv" in f for f in both.files)


def test_gray_code_changes_one_bit_between_neighbours():
    bits = np.stack([gray_profile(1024, b, 10, 1) for b in range(10)])
    assert np.all(np.abs(np.diff(bits.astype(int), axis=1)).sum(axis=0) == 1)
    codes = {tuple(c) for c in bits.T}
    assert len(codes) == 1024


def test_render_values_and_inverse():
    ps = make_pattern_set("default", 128, 16)
    imgs = dict(zip(ps.files, render_all(ps), strict=False))
    g, gi = imgs["02_col_gray_b00.png"], imgs["03_col_gray_b00_inv.png"]
    assert g.shape == (16, 128) and g.dtype == np.uint8
    assert set(np.unique(g)) == {0, 255}
    assert np.array_equal(gi, 255 - g)
    assert np.all(g[:, :64] == 0) and np.all(g[:, 64:] == 255)  # MSB
    ph = [f for f in ps.frames if f.kind == "phase"]
    p0 = render_frame(ps, ph[0])
    assert p0[0, 0] == 255 and p0[0, 4] == 0 and p0[0, 8] == 255  # phase 0 at column 0, P = 8
    p1 = render_frame(ps, ph[1])  # shifted by P/N = 1 column
    assert p1[0, 1] == 255 and np.array_equal(p1[:, 1:], p0[:, :-1])
    rows = make_pattern_set("paper", 64, 32, axes=("row",))
    r = render_frame(rows, rows.frames[2])
    assert np.all(r[:16] == 0) and np.all(r[16:] == 255) and np.all(r == r[:, :1])


@pytest.mark.timing
def test_render_full_set_is_fast():
    ps = make_pattern_set("default", 1024, 768)
    t0 = time.perf_counter()
    render_all(ps)
    assert time.perf_counter() - t0 < 1.0


@pytest.mark.parametrize("axes", [("column",), ("column", "row"), ("row",)])
@pytest.mark.parametrize("preset", ["default", "paper"])
def test_manifest_round_trip(preset, axes):
    ps = make_pattern_set(preset, 800, 600, axes=axes)
    m = json.loads(json.dumps(ps.to_manifest()))
    for key in ("format", "version", "preset", "projector", "axes", "frames"):
        assert key in m
    back = PatternSet.from_manifest(m)
    assert back.frames == ps.frames and back.axes == ps.axes
    assert (back.width, back.height, back.preset) == (800, 600, preset)
    assert back.axis_code(axes[0]) == ps.axis_code(axes[0])


def _good():
    return make_pattern_set("default", 128, 64).to_manifest()


def _drop_frame(m, pred):
    m["frames"] = [f for f in m["frames"] if not pred(f)]
    return m


def _set_frame(m, i, **kw):
    m["frames"][i].update(kw)
    return m


MALFORMED = {
    "missing format": lambda m: m.pop("format") and m,
    "missing frames": lambda m: m.pop("frames") and m,
    "missing projector": lambda m: m.pop("projector") and m,
    "bad version": lambda m: m.update(version=99) or m,
    "wrong format": lambda m: m.update(format="other") or m,
    "zero width": lambda m: m.update(projector={"width": 0, "height": 64}) or m,
    "string height": lambda m: m.update(projector={"width": 128, "height": "64"}) or m,
    "unknown axis": lambda m: m.update(axes=["diagonal"]) or m,
    "empty frames": lambda m: m.update(frames=[]) or m,
    "unknown kind": lambda m: _set_frame(m, 3, kind="checkerboard"),
    "duplicate file": lambda m: _set_frame(m, 3, file=m["frames"][2]["file"]),
    "path in file name": lambda m: _set_frame(m, 3, file="../evil.png"),
    "frame without file": lambda m: m["frames"][2].pop("file") and m,
    "gray without bit": lambda m: m["frames"][2].pop("bit") and m,
    "bit out of range": lambda m: _set_frame(m, 2, bit=12),
    "missing bit": lambda m: _drop_frame(m, lambda f: f.get("bit") == 3 and not f["inverse"]),
    "missing inverse": lambda m: _drop_frame(m, lambda f: f.get("bit") == 0 and f.get("inverse")),
    "no white": lambda m: _drop_frame(m, lambda f: f["kind"] == "white"),
    "two blacks": lambda m: _set_frame(m, 0, kind="black"),
    "too few bits": lambda m: m.update(projector={"width": 4096, "height": 64}) or m,
    "missing phase step": lambda m: _drop_frame(m, lambda f: f.get("shift") == 5),
    "bad phase steps": lambda m: _set_frame(m, -1, steps=0),
    "phase axis not listed": lambda m: _set_frame(m, -1, axis="row"),
    "frame not an object": lambda m: m.update(frames=m["frames"][:-1] + ["x"]) or m,
    "not an object": lambda m: [m],
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_manifest_raises_capture_error(case):
    m = MALFORMED[case](copy.deepcopy(_good()))
    with pytest.raises(CaptureError) as exc:
        PatternSet.from_manifest(m, "manifest.json")
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("manifest.json")
    assert isinstance(exc.value, AnkleScanError)


def test_unknown_preset_and_bad_size():
    with pytest.raises(CaptureError, match="preset"):
        make_pattern_set("fancy")
    with pytest.raises(CaptureError, match="0x768"):
        make_pattern_set("default", 0, 768)


def test_write_patterns_files_and_manifest(tmp_path):
    ps = make_pattern_set("default", 128, 32)
    out = write_patterns(ps, tmp_path / "pat")
    m = json.loads((out / "manifest.json").read_text())
    assert [f["file"] for f in m["frames"]] == ps.files
    assert m["projector"] == {"width": 128, "height": 32} and m["axes"] == ["column"]
    for f in ps.frames:
        img = cv2.imread(str(out / f.file), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint8 and img.ndim == 2
        assert np.array_equal(img, render_frame(ps, f))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pat"]  # no temporaries left
    # overwriting replaces the whole set
    write_patterns(make_pattern_set("paper", 128, 32), out)
    assert len(list(out.glob("*.png"))) == 2 + 2 * 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pat"]


def test_write_patterns_is_atomic_on_crash(tmp_path, monkeypatch):
    ps = make_pattern_set("paper", 64, 16)
    calls = {"n": 0}
    real = patterns.imwrite_checked

    def flaky(path, image):
        calls["n"] += 1
        if calls["n"] == 5:
            raise OSError("disk full")
        real(path, image)

    monkeypatch.setattr(patterns, "imwrite_checked", flaky)
    with pytest.raises(OSError):
        write_patterns(ps, tmp_path / "pat")
    assert list(tmp_path.iterdir()) == []
