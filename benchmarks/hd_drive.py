"""A drive by a 1080p clip: the output's size and the time of each step, on real data.

    .venv/bin/python benchmarks/hd_drive.py [--frames 150] [--runs 2] [--workers 2] [--keep FOLDER]

Makes a 1920x1080 clip of the first --frames frames of woman_expressions.mp4 (each 512² frame
enlarged twice, her face about 640 px, on her own background colour), then runs Colin Powell's
collection driven by it (--workers local workers). Prints the size of the driver's frames and of
composite.mp4's (an HD clip should stay HD), and for each of --runs runs the wall time of the drive's
frames from ingest to the evaluation per frame, and each per-frame step's compute per frame on one
worker. The people are made once (kept in --keep, or a temporary folder) and reused; each run makes
the driver's frames and the drive again.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import yaml

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def make_clip(path: Path, frames: int) -> None:
    """The 1080p clip: woman_expressions.mp4's frames enlarged twice on a 1920x1080 canvas."""
    import cv2
    import numpy as np

    from persona.stores import media

    def enlarged():
        with media.VideoReader(SHARED / "videos" / "woman_expressions.mp4") as reader:
            for i, frame in reader.frames(0, frames):
                big = cv2.resize(frame, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
                canvas = np.empty((1080, 1920, 3), np.uint8)
                canvas[:] = frame[5, 5]
                canvas[28:1052, 700:1724] = big[:1024]
                yield canvas

    media.write_video_mp4(path, enlarged(), fps=30)


def video_size(path: Path) -> tuple[int, int]:
    from persona.stores import media

    with media.VideoReader(path) as reader:
        return reader.width, reader.height


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="keep the run here (default: a temporary folder); the people of a "
                    "kept run are reused")
    args = ap.parse_args()
    from persona.dag.runner import run_workflow
    from persona.dag.workflow import load_workflow

    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        clip = folder / "woman_1080p.mp4"
        if not clip.exists():
            make_clip(clip, args.frames)
        wf = {"version": 1, "name": "hd", "store": f"{folder}/run.zarr", "output": f"{folder}/out",
              "puppet": {"photos": str(SHARED / "collections" / "colin_powell")},
              "driver": {"photos": {"video": str(clip), "step": 10}, "video": str(clip)},
              "cluster": {"scheduler": "local", "workers": args.workers}}
        path = folder / "wf.yaml"
        path.write_text(yaml.safe_dump(wf))
        run_workflow(load_workflow(path), progress=False)  # the people (reused from a kept run)
        walls, steps = [], {}
        for _ in range(args.runs):
            for group in ("drive", "driver/frames"):
                shutil.rmtree(folder / "run.zarr" / group, ignore_errors=True)
            start = time.perf_counter()
            report = run_workflow(load_workflow(path), progress=False)
            walls.append(1000 * (time.perf_counter() - start) / args.frames)
            for r in report["stages"]:
                if r["collection"] in ("driver/frames", "drive"):
                    steps.setdefault(f"{r['collection']} {r['stage']}", []).append(
                        1000 * r["task_seconds"] / args.frames)
        print(f"{args.frames} frames of a 1080p clip, puppet colin_powell, {args.workers} workers, {args.runs} runs")
        print("  driver clip: %dx%d; composite.mp4: %dx%d" % (*video_size(clip), *video_size(folder / "out" /
                                                                                              "composite.mp4")))
        print(f"  the drive's frames, ingest to evaluation: {statistics.median(walls):.1f} ms/frame wall "
              f"(median; runs {', '.join(f'{w:.1f}' for w in walls)})")
        for name, times in steps.items():
            print(f"  {name:<28} {statistics.median(times):7.1f} ms/frame on one worker "
                  f"(runs {', '.join(f'{t:.1f}' for t in times)})")


if __name__ == "__main__":
    main()
