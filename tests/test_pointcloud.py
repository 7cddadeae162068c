"""Binary PLY: our own round trip, the header other tools read, and ASCII PLY from elsewhere."""

import numpy as np
import pytest

from anklescan.core.errors import AnkleScanError
from anklescan.core.scan.pointcloud import PointCloud, read_ply, write_ply


def _cloud(n=1000, seed=0):
    rng = np.random.default_rng(seed)
    return PointCloud(rng.normal(0, 200, (n, 3)).astype(np.float32), rng.integers(0, 256, (n, 3), dtype=np.uint8),
                      rng.integers(0, 1600, (n, 2)).astype(np.uint16), rng.random(n).astype(np.float32),
                      rng.random(n).astype(np.float32))


def test_round_trip(tmp_path):
    c = _cloud()
    write_ply(tmp_path / "c.ply", c)
    r = read_ply(tmp_path / "c.ply")
    for name in ("points", "colors", "pixels", "quality", "sigma"):
        assert np.array_equal(getattr(r, name), getattr(c, name)), name
    assert not list(tmp_path.glob(".*tmp"))


def test_header_is_standard(tmp_path):
    write_ply(tmp_path / "c.ply", _cloud(5))
    head = (tmp_path / "c.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert head.startswith("ply\nformat binary_little_endian 1.0\n")
    assert "element vertex 5" in head
    for prop in ("float x", "float y", "float z", "uchar red", "uchar green", "uchar blue"):
        assert f"property {prop}\n" in head
    size = 5 * (3 * 4 + 3 + 2 * 2 + 4 + 4)
    assert len((tmp_path / "c.ply").read_bytes()) == len(head) + len("end_header\n") + size


def test_reads_ascii_ply_with_faces(tmp_path):
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\ncomment from elsewhere\nelement vertex 2\n"
                                    "property float x\nproperty float y\nproperty float z\n"
                                    "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
                                    "1 2 3\n4 5 6\n")
    r = read_ply(tmp_path / "a.ply")
    assert r.points.tolist() == [[1, 2, 3], [4, 5, 6]] and r.colors is None


def test_bad_files(tmp_path):
    (tmp_path / "x.ply").write_text("not a ply")
    with pytest.raises(AnkleScanError, match="not a PLY"):
        read_ply(tmp_path / "x.ply")
    write_ply(tmp_path / "t.ply", _cloud(100))
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-50])
    with pytest.raises(AnkleScanError, match="truncated"):
        read_ply(tmp_path / "t.ply")


def test_a_failed_write_leaves_the_old_file(tmp_path):
    write_ply(tmp_path / "c.ply", _cloud(10))
    before = (tmp_path / "c.ply").read_bytes()
    broken = _cloud(10)
    broken.colors = np.zeros((3, 3), np.uint8)  # wrong length: the write fails part-way
    with pytest.raises(ValueError):
        write_ply(tmp_path / "c.ply", broken)
    assert (tmp_path / "c.ply").read_bytes() == before
    assert not list(tmp_path.glob(".*tmp"))
