"""Milliseconds per image pair and end-point error of every flow backend at the paper's face size.

    .venv/bin/python benchmarks/flow_speed.py [--runs 5] [--grey] [--backends liu,dis]

One thread (cv2.setNumThreads(1), NUMBA_NUM_THREADS=1), on the seeded textured 194 x 244 pair
of the conformance suite (persona.plugins.flow_conformance: a smooth affine + sinusoid warp,
|w| <= 3 px). Prints, per backend, the median wall and CPU milliseconds over --runs calls
(after one warm-up call, which for ``liu`` includes loading or compiling its numba kernels),
and the mean end-point error in the interior. ``liu`` is checked against the 0.5 s target.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import statistics
import time

LIU_TARGET_MS = 500.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--grey", action="store_true", help="grey pair instead of RGB")
    ap.add_argument("--backends", default="", help="comma-separated names (default: all)")
    args = ap.parse_args()

    import cv2

    cv2.setNumThreads(1)
    from persona.plugins.builtin.flow import BACKENDS
    from persona.plugins.flow_conformance import (
        FACE_SHAPE,
        end_point_error,
        warped_pair,
    )

    i0, i1, truth = warped_pair(FACE_SHAPE, seed=0, colour=not args.grey)
    wanted = {n.strip() for n in args.backends.split(",") if n.strip()}
    print(f"pair {FACE_SHAPE[1]}x{FACE_SHAPE[0]} (W x H), {'grey' if args.grey else 'RGB'}, "
          f"max |w| 3 px, median of {args.runs} runs, one thread")
    print(f"{'backend':10s} {'first ms':>9s} {'wall ms':>8s} {'cpu ms':>7s} {'EPE px':>7s}")
    for cls in BACKENDS:
        if wanted and cls.name not in wanted:
            continue
        backend = cls()
        t = time.perf_counter()
        flow = backend.flow(i0, i1)
        first = (time.perf_counter() - t) * 1000
        walls, cpus = [], []
        for _ in range(args.runs):
            t, c = time.perf_counter(), time.process_time()
            flow = backend.flow(i0, i1)
            walls.append((time.perf_counter() - t) * 1000)
            cpus.append((time.process_time() - c) * 1000)
        wall, cpu = statistics.median(walls), statistics.median(cpus)
        note = ""
        if cls.name == "liu":
            note = f"  target {LIU_TARGET_MS:.0f} ms: {'met' if wall <= LIU_TARGET_MS else 'MISSED'}"
        print(f"{cls.name:10s} {first:9.0f} {wall:8.0f} {cpu:7.0f} {end_point_error(flow, truth):7.3f}{note}")


if __name__ == "__main__":
    main()
