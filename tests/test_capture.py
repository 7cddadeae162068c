import json
import os

import cv2
import numpy as np
import pytest

import anklescan.core.scan.capture as capture_mod
from anklescan.core.errors import CaptureError
from anklescan.core.scan.capture import CaptureWriter, capture_from_images, load_capture, save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all

H, W = 30, 40


@pytest.fixture
def pset():
    return make_pattern_set("paper", 64, 32)  # 14 frames


def _images(pset, dtype=np.uint8, color=False):
    full = 255 if dtype == np.uint8 else 65535
    rng = np.random.default_rng(1)
    imgs = []
    for _ in pset.frames:
        shape = (H, W, 3) if color else (H, W)
        imgs.append(rng.integers(0, full + 1, shape, dtype=np.int64).astype(dtype))
    return imgs


def _saved(tmp_path, pset, **kw):
    imgs = _images(pset, **kw)
    return save_capture(tmp_path / "cap", pset, imgs, {"device": "sim"}), imgs


def _one_line(exc):
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_round_trip_8bit_gray(tmp_path, pset):
    folder, imgs = _saved(tmp_path, pset)
    cap = load_capture(folder)
    assert cap.frames.dtype == np.uint8 and cap.frames.shape == (len(pset.frames), H, W)
    assert cap.max_value == 255 and cap.shape == (H, W)
    assert np.array_equal(cap.frames, np.stack(imgs))
    assert cap.white_color is None
    assert cap.pattern_set.frames == pset.frames
    assert cap.metadata == {"device": "sim"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


def test_round_trip_16bit(tmp_path, pset):
    folder, imgs = _saved(tmp_path, pset, dtype=np.uint16)
    cap = load_capture(folder)
    assert cap.frames.dtype == np.uint16 and cap.max_value == 65535
    assert np.array_equal(cap.frames, np.stack(imgs))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_colour_frames(tmp_path, pset, dtype):
    folder, imgs = _saved(tmp_path, pset, dtype=dtype, color=True)
    cap = load_capture(folder)
    assert np.array_equal(cap.frames[3], cv2.cvtColor(imgs[3], cv2.COLOR_BGR2GRAY))
    assert cap.white_color.shape == (H, W, 3) and cap.white_color.dtype == np.uint8
    white = imgs[pset.index("white")]
    expect = white if dtype == np.uint8 else (white >> 8).astype(np.uint8)
    assert np.array_equal(cap.white_color, expect)


def test_missing_frame_is_named(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    os.remove(folder / pset.files[5])
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    assert pset.files[5] in _one_line(exc)


def test_extra_image_is_named_and_other_files_ignored(tmp_path, pset):
    folder, imgs = _saved(tmp_path, pset)
    (folder / "notes.txt").write_text("operator notes")
    load_capture(folder)
    cv2.imwrite(str(folder / "stray.png"), imgs[0])
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    assert "stray.png" in _one_line(exc)


def test_different_sizes_name_file_and_sizes(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    cv2.imwrite(str(folder / pset.files[4]), np.zeros((H + 2, W), np.uint8))
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    msg = _one_line(exc)
    assert pset.files[4] in msg and f"{W}x{H + 2}" in msg and f"{W}x{H}" in msg


def test_unreadable_image_is_named(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    (folder / pset.files[6]).write_bytes(b"\x89PNG not really")
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    assert pset.files[6] in _one_line(exc)


def test_mixed_bit_depth(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    cv2.imwrite(str(folder / pset.files[7]), np.zeros((H, W), np.uint16))
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    msg = _one_line(exc)
    assert pset.files[7] in msg and "bit" in msg


def test_malformed_manifest_json(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    (folder / "manifest.json").write_text('{"format": "anklescan-patterns", ')
    with pytest.raises(CaptureError) as exc:
        load_capture(folder)
    msg = _one_line(exc)
    assert "manifest.json" in msg and "JSON" in msg


def test_invalid_manifest_content(tmp_path, pset):
    folder, _ = _saved(tmp_path, pset)
    m = json.loads((folder / "manifest.json").read_text())
    m["frames"][3]["kind"] = "mystery"
    (folder / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(CaptureError, match="mystery"):
        load_capture(folder)


def test_missing_folder_and_manifest(tmp_path, pset):
    with pytest.raises(CaptureError, match="not found"):
        load_capture(tmp_path / "nope")
    folder, _ = _saved(tmp_path, pset)
    os.remove(folder / "manifest.json")
    with pytest.raises(CaptureError, match="manifest.json"):
        load_capture(folder)


def test_in_memory_capture_checks(pset):
    imgs = _images(pset)
    cap = capture_from_images(pset, imgs)
    assert cap.frames.shape == (len(imgs), H, W)
    imgs[2] = imgs[2][:-1]
    with pytest.raises(CaptureError, match=pset.files[2]):
        capture_from_images(pset, imgs)


def test_save_capture_is_atomic(tmp_path, pset, monkeypatch):
    calls = {"n": 0}
    real = capture_mod.imwrite_checked

    def flaky(path, image):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full")
        real(path, image)

    monkeypatch.setattr(capture_mod, "imwrite_checked", flaky)
    with pytest.raises(OSError):
        save_capture(tmp_path / "cap", pset, _images(pset))
    assert list(tmp_path.iterdir()) == []


def test_writer_keeps_frames_written_before_a_crash(tmp_path, pset, monkeypatch):
    imgs = _images(pset)
    folder = tmp_path / "cap"
    writer = CaptureWriter(folder, pset, {"device": "sim", "exposure_ms": 20})
    for name, img in list(zip(pset.files, imgs, strict=False))[:5]:
        writer.add(name, img)
    # the sixth frame dies half-way through writing
    real = capture_mod.imwrite_checked

    def dying(path, image):
        real(path, image)
        raise KeyboardInterrupt

    monkeypatch.setattr(capture_mod, "imwrite_checked", dying)
    with pytest.raises(KeyboardInterrupt):
        writer.add(pset.files[5], imgs[5])
    del writer  # crash: finish() never runs
    names = sorted(p.name for p in folder.iterdir())
    assert names == sorted(pset.files[:5])  # no manifest, no temporaries
    for name, img in list(zip(pset.files, imgs, strict=False))[:5]:
        assert np.array_equal(cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED), img)


def test_writer_finish_writes_manifest_last(tmp_path, pset):
    imgs = _images(pset)
    folder = tmp_path / "cap"
    writer = CaptureWriter(folder, pset, {"device": "sim"})
    for name, img in zip(pset.files[:-1], imgs[:-1], strict=False):
        writer.add(name, img)
    with pytest.raises(CaptureError, match=pset.files[-1]):
        writer.finish()
    assert not (folder / "manifest.json").exists()
    with pytest.raises(CaptureError, match="bogus.png"):
        writer.add("bogus.png", imgs[0])
    writer.add(pset.files[-1], imgs[-1])
    writer.finish()
    cap = load_capture(folder)
    assert np.array_equal(cap.frames, np.stack(imgs))
    assert cap.metadata["device"] == "sim"
    assert set(cap.metadata["frame_times"]) == set(pset.files)
    assert "started" in cap.metadata and "finished" in cap.metadata
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]


def test_writer_rejects_size_change(tmp_path, pset):
    writer = CaptureWriter(tmp_path / "cap", pset)
    writer.add(pset.files[0], np.zeros((H, W), np.uint8))
    with pytest.raises(CaptureError) as exc:
        writer.add(pset.files[1], np.zeros((H, W + 1), np.uint8))
    assert pset.files[1] in _one_line(exc)


def test_pattern_folder_photographed_is_a_capture(tmp_path):
    """SPEC 5: a camera that photographs the pattern folder file by file makes a capture."""
    from anklescan.core.scan.patterns import write_patterns
    ps = make_pattern_set("default", 64, 16)
    folder = write_patterns(ps, tmp_path / "pat")
    cap = load_capture(folder)
    assert np.array_equal(cap.frames, np.stack(render_all(ps)))
