"""3-D viewer speed on a 2-million-point cloud: load, redraw rate, pick latency.

    xvfb-run -a -s "-screen 0 1280x1024x24" /work/venv/bin/python benchmarks/bench_viewer.py \
        [--points 2000000] [--size 1000x750] [--seconds 3] [--repeats 3] [--path auto|splat|classic|both]

The cloud is the simulated rig's exact surface at full resolution (every camera pixel that
sees the scene: leg, table, floor, ~1.9 M) topped up to ``--points`` with jittered copies, with
a shaded white-frame colour. Needs a real X server with OpenGL (Xvfb + Mesa llvmpipe here).

``--path``: the viewer's render path (app/viewer.py): ``auto`` = what the viewer picks for
this context (the compute splat where GL 4.3 is available), ``both`` = splat, then classic.

Prints, per path: which render path is active and why; load = ``CloudViewer.set_cloud``
(shuffle, colours, GPU upload), the first frame after it, and when the background KD-tree for
snapping is ready; redraw = frames per second of back-to-back redraws while the view turns
(paint + compose, counted by ``frameSwapped``), at full density -- every point, every frame --
(median and range of ``--repeats`` runs) and, on the classic path, at the drag-time level of
detail; pick = depth-buffer read + gluUnProject + snap, at points of the cloud. The machine's
load average is printed with the figures: on a shared 2-core machine it moves them a lot.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("QT_QPA_PLATFORM", "xcb")

from PySide6.QtWidgets import QApplication  # noqa: E402

from anklescan.core.scan.pointcloud import PointCloud  # noqa: E402


def make_cloud(n: int) -> tuple[PointCloud, np.ndarray]:
    from anklescan.hardware.simrig import SimRig
    rig = SimRig(scale=1.0)
    truth = rig.truth()
    seen = truth.seen.reshape(-1)
    pts = truth.points.reshape(-1, 3)[seen]
    shade = np.clip(np.abs(truth.normals.reshape(-1, 3)[seen] @ [0.3, 0.5, 0.8]) * 230, 30, 255)
    rng = np.random.default_rng(0)
    extra = max(0, n - len(pts))
    idx = rng.integers(0, len(pts), extra)
    pts = np.r_[pts, pts[idx] + rng.normal(0, 0.2, (extra, 3))][:n].astype(np.float32)
    shade = np.r_[shade, shade[idx]][:n]
    colours = np.repeat(shade[:, None], 3, axis=1).astype(np.uint8)
    return PointCloud(pts, colours), rig.camera.center


def fps(app, viewer, seconds: float) -> float:
    """Frames per second of a render loop: each swapped frame asks for the next one, the
    event loop idles in between (a busy processEvents loop would steal a core from llvmpipe)."""
    from PySide6.QtCore import QEventLoop, QTimer
    frames = []

    def next_frame():
        frames.append(time.perf_counter())
        viewer.camera.orbit(1.0, 0.0)  # the view turns every frame, as while dragging
        viewer.update()

    viewer.frameSwapped.connect(next_frame)
    loop = QEventLoop()
    QTimer.singleShot(int(seconds * 1000), loop.quit)
    viewer.update()
    loop.exec()
    viewer.frameSwapped.disconnect(next_frame)
    if len(frames) < 3:
        return float("nan")
    return (len(frames) - 1) / (frames[-1] - frames[0])


def load_average() -> str:
    return "load average " + " ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--size", default="1000x750")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--repeats", type=int, default=3, help="full-density fps runs (median and range)")
    ap.add_argument("--path", choices=("auto", "splat", "classic", "both"), default="auto")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    app = QApplication(sys.argv)
    cloud, eye = make_cloud(args.points)
    paths = {"auto": [None], "both": ["splat", "classic"]}.get(args.path, [args.path])
    for i, path in enumerate(paths):
        if i:
            print()
        bench(app, cloud, eye, w, h, args, path)


def bench(app, cloud, eye, w, h, args, path) -> None:
    from OpenGL import GL

    from anklescan.app.viewer import RENDER_CLASSIC, CloudViewer

    load_before = load_average()
    viewer = CloudViewer(render_path=path)
    viewer.resize(w, h)
    viewer.show()
    for _ in range(20):
        app.processEvents()
        time.sleep(0.01)
    viewer.makeCurrent()
    renderer = GL.glGetString(GL.GL_RENDERER).decode()
    viewer.doneCurrent()

    t0 = time.perf_counter()
    viewer.set_cloud(cloud, scanner_eye=eye)
    t1 = time.perf_counter()
    viewer.grabFramebuffer()  # renders the first frame synchronously
    t2 = time.perf_counter()
    _ = viewer.snapper  # waits for the KD-tree built in the background
    t3 = time.perf_counter()

    full_runs = []
    for _ in range(max(1, args.repeats)):
        full_runs.append(fps(app, viewer, args.seconds))
        full_load = load_average()
    full = statistics.median(full_runs)
    lod = None
    if viewer.render_path == RENDER_CLASSIC:
        viewer._interacting = True  # what a mouse drag or wheel zoom draws
        lod = fps(app, viewer, args.seconds)
        viewer._interacting = False
    viewer.grabFramebuffer()

    pos = viewer.widget_pos_of(viewer.points[:: len(viewer.points) // 400].astype(np.float64))
    inside = (pos[:, 0] > 5) & (pos[:, 1] > 5) & (pos[:, 0] < w - 5) & (pos[:, 1] < h - 5)
    times = []
    for x, y, _ in pos[inside][:60]:
        t = time.perf_counter()
        r = viewer.pick(int(x), int(y))
        times.append((time.perf_counter() - t) * 1000)
        assert r is not None

    print(f"render path: {viewer.render_path} -- {viewer.render_path_info}")
    print(f"renderer: {renderer}; window {w}x{h}; {len(cloud):,} points; point size {viewer.effective_point_size():g} px; "
          f"before: {load_before}")
    print(f"load (set_cloud: shuffle, colours, GPU upload): {t1 - t0:.3f} s; + first frame on screen: {t2 - t0:.3f} s; "
          f"picking KD-tree ready (background thread): {t3 - t0:.3f} s")
    print(f"redraw, full density ({len(viewer.points):,} points every frame): {full:.1f} fps ({1000 / full:.0f} ms/frame); "
          f"{len(full_runs)} runs of {args.seconds:g} s: {min(full_runs):.1f}-{max(full_runs):.1f} fps; after: {full_load}")
    if lod is None:
        print("redraw while dragging: full density as well (the splat path has no level of detail)")
    else:
        print(f"redraw while dragging ({viewer.lod_points:,} points): {lod:.1f} fps")
    print(f"pick (depth read + gluUnProject + snap), {len(times)} clicks: median {statistics.median(times):.1f} ms, "
          f"max {max(times):.1f} ms")
    viewer.close()
    viewer.deleteLater()
    app.processEvents()


if __name__ == "__main__":
    main()
