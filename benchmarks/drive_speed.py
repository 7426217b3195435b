"""Milliseconds per driver frame of the baseline puppet, per stage.

    .venv/bin/python benchmarks/drive_speed.py [--frames 300] [--runs 3]

Runs the Bush-driven-by-Obama workflow on the first --frames frames of the Obama address
into a temporary store (2 local workers) and prints, per stage, the compute time per
driver frame on one worker (task seconds / frames) and the wall time per frame. Then
times the render backend alone in this process (one core, median of --runs passes over
100 frames). The paper's full method needs 540 ms per frame on one core.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import yaml

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
PAPER_MS = 540.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    from persona.dag.runner import run_workflow
    from persona.dag.workflow import load_workflow

    with tempfile.TemporaryDirectory() as tmp:
        wf = {"version": 1, "name": "speed", "store": f"{tmp}/run.zarr", "output": f"{tmp}/out",
              "puppet": {"photos": str(SHARED / "collections" / "george_w_bush")},
              "driver": {"photos": str(SHARED / "collections" / "barack_obama"),
                         "video": {"video": str(SHARED / "videos" / "obama_address.mov"), "stop": args.frames}},
              "cluster": {"scheduler": "local", "workers": 2}}
        path = Path(tmp) / "wf.yaml"
        path.write_text(yaml.safe_dump(wf))
        report = run_workflow(load_workflow(path), progress=False)
        n = args.frames
        print(f"{n} driver frames (obama_address.mov, 256x256), puppet george_w_bush, 2 workers")
        for r in report["stages"]:
            if r["collection"] in ("driver/frames", "drive"):
                print(f"  {r['collection']:>13} {r['stage']:<10} {1000 * r['task_seconds'] / n:7.1f} ms/frame on one worker")
        speed = report["speed"]
        print(f"  retarget + render wall: {speed['ms_per_driver_frame']:.1f} ms/frame (2 workers); "
              f"evaluation {1000 * speed['evaluate_seconds'] / n:.1f} ms/frame")
        times = render_alone(Path(tmp) / "run.zarr", args.runs)
        median = statistics.median(times)
        print(f"render alone, one core: {median:.1f} ms/frame (median of {args.runs}: "
              f"{', '.join(f'{t:.1f}' for t in times)}); paper's full method {PAPER_MS:.0f} ms/frame "
              f"-> {PAPER_MS / median:.0f}x below")


def render_alone(store: Path, runs: int, frames: int = 100) -> list[float]:
    import zarr

    from persona.plugins.builtin.render import Tps2dRender
    from persona.plugins.kinds import Pose, Puppet

    root = zarr.open_group(str(store), mode="r")
    aligned = root["puppet/aligned"]
    puppet = Puppet(aligned["mean"][...], aligned["coverage"][...], aligned["mean_fiducials"][...].astype(float))
    targets = root["drive/target"][:frames].astype(float)
    poses = [Pose.from_vector(v) for v in root["drive/pose"][:frames]]
    images = root["driver/frames/photos/rgb"][:frames]
    backend = Tps2dRender()
    backend.render(puppet, targets[0], poses[0], images[0])  # warm up (template, ray-casting scene)
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        for i in range(len(targets)):
            backend.render(puppet, targets[i], poses[i], images[i])
        out.append(1000 * (time.perf_counter() - t0) / len(targets))
    return out


if __name__ == "__main__":
    main()
