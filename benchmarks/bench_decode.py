"""Decode speed on a synthetic 1600x1200 capture (image loading excluded), and the marks' lit image.

    /work/venv/bin/python benchmarks/bench_decode.py [--runs 7] [--width 1600 --height 1200]

The capture is synthetic: a smooth, slightly curved column map (about 0.6 projector
columns per camera pixel, like the paper's 1024-column projector seen by a 1600-px camera)
pushed through the patterns with projector gamma 2.2, Gaussian blur 1 px and noise
sigma 2/255, quantised to 8 bits.  Prints the median decode time, the peak memory that
decode allocates (tracemalloc) and the process' peak RSS, plus the accuracy it reached.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anklescan.core.scan.decode import decode  # noqa: E402
from anklescan.core.scan.lit_image import lit_from_frames  # noqa: E402
from anklescan.core.scan.patterns import make_pattern_set, simulate_frames  # noqa: E402


def column_map(h: int, w: int, proj_width: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    scale = (proj_width - 40) / w
    return 20 + xx * scale + 6 * np.sin(yy / 90) + 4e-5 * (xx - w / 2) ** 2


def bench(preset: str, h: int, w: int, runs: int, dtype) -> dict:
    pset = make_pattern_set(preset, 1024, 768)
    truth = column_map(h, w, 1024)
    frames = simulate_frames(pset, truth, blur=1.0, noise=2 / 255, gamma=2.2, dtype=dtype)
    decode(frames, pset)  # warm-up: first-call allocations, OpenCV thread pool
    lit_from_frames(frames, pset)
    times, lit_times = [], []
    for _ in range(runs):
        t0 = time.perf_counter()
        res = decode(frames, pset)
        times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        lit_from_frames(frames, pset)  # the marks' image, averaged over the Gray pairs
        lit_times.append(time.perf_counter() - t0)
    tracemalloc.start()
    decode(frames, pset)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # paper decodes 4-column stripe centres: expect ~4/sqrt(12) = 1.15 px rms
    # only pixels the projector covers: beyond its last column the synthetic camera still sees
    # the continued cosine, light no real projector sends, which the Gray code cannot unwrap
    covered = (truth > -0.5) & (truth < pset.width - 0.5)
    err = (res.column - truth)[res.valid & covered]
    return {"preset": preset, "frames": len(pset.frames), "dtype": np.dtype(dtype).name,
            "median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times),
            "lit_ms": 1e3 * statistics.median(lit_times),
            "decode_peak_mb": peak / 2 ** 20, "input_mb": frames.nbytes / 2 ** 20,
            "valid": float(res.valid.mean()), "rms_px": float(np.sqrt(np.mean(err ** 2)))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1200)
    ap.add_argument("--16bit", dest="bit16", action="store_true", help="also time uint16")
    args = ap.parse_args(argv)
    cases = [("default", np.uint8), ("paper", np.uint8)]
    if args.bit16:
        cases.append(("default", np.uint16))
    print(f"camera {args.width}x{args.height}, projector 1024x768, {args.runs} runs")
    for preset, dtype in cases:
        r = bench(preset, args.height, args.width, args.runs, dtype)
        print(f"{r['preset']:8s} {r['frames']:2d} frames {r['dtype']:6s}  "
              f"median {r['median_ms']:6.1f} ms (min {r['min_ms']:.1f})  "
              f"decode peak {r['decode_peak_mb']:.0f} MB (input {r['input_mb']:.0f} MB)  "
              f"valid {100 * r['valid']:.1f}%  rms {r['rms_px']:.4f} px  "
              f"lit image (anklescan.core.scan.lit_image) {r['lit_ms']:.1f} ms")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"process peak RSS {rss:.0f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
