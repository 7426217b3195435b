"""Peak memory and time of building one person, stage by stage, against the number of photos.

    .venv/bin/python benchmarks/person_memory.py [--sizes 500 2000 5000] [--workers 2]

For each size a collection of that many distinct photos is made from george_w_bush in
../shared/data: the k-th copy of a photo is scaled by 1 + 0.02 k (so no two files are the same
and none is dropped as a duplicate), written as JPEG to a temporary folder. The person is then
built as a run builds a puppet: ingest and the per-photo chain, the mean face, the appearance
subspace, the collection flow, the 3D shape and the texture cache, each size in a process of
its own. During each of these steps the resident memory of the client process and of every
worker process is sampled (every 50 ms); printed per step: its time, the client's peak and the
largest worker's peak.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import psutil
import yaml

from ingest_throughput import SHARED, PeakMemory


class Sampler(PeakMemory):
    """The client's and the largest worker's resident memory, peaks per named phase."""

    def __init__(self, interval: float = 0.05):
        super().__init__(interval)
        self.phase, self.peaks = None, {}

    def _run(self):
        me = psutil.Process()
        while not self._stop.is_set():
            client = me.memory_info().rss
            workers = 0
            for child in me.children(recursive=True):
                try:
                    workers = max(workers, child.memory_info().rss)
                except psutil.Error:
                    pass
            if self.phase is not None:
                old = self.peaks.get(self.phase, (0, 0))
                self.peaks[self.phase] = (max(old[0], client), max(old[1], workers))
            time.sleep(self.interval)

    @contextmanager
    def during(self, phase: str, times: dict):
        self.phase = phase
        t0 = time.perf_counter()
        try:
            yield
        finally:
            times[phase] = time.perf_counter() - t0
            time.sleep(2 * self.interval)
            self.phase = None

def distinct_photos(size: int, folder: Path) -> Path:
    """``size`` distinct JPEGs from george_w_bush: copy k of each photo scaled by 1 + 0.02 k."""
    paths = sorted((SHARED / "george_w_bush").iterdir())
    out = folder / "photos"
    out.mkdir()
    for i in range(size):
        image = cv2.imread(str(paths[i % len(paths)]))
        k = i // len(paths)
        if k:
            image = cv2.resize(image, None, fx=1 + 0.02 * k, fy=1 + 0.02 * k, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / f"{i:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return out


def build(photos: Path, workers: int, tmp: Path) -> tuple[dict, dict, int]:
    """Build the person of the folder ``photos`` as a run builds a puppet, its store in ``tmp``; returns each
    step's seconds, each step's peaks (client, largest worker; bytes) and the number of accepted photos."""
    from persona.dag.collection import mean_face
    from persona.dag.executor import executor_for
    from persona.dag.graph import Target
    from persona.dag.inputs import resolve_inputs
    from persona.dag.runner import Runner
    from persona.dag.shape import run_alignment, run_shape, run_subspace
    from persona.dag.stages import STAGES, accepted
    from persona.dag.texture import run_texture
    from persona.dag.workflow import load_workflow

    wf = {"version": 1, "name": "memory", "store": str(tmp / "run.zarr"), "output": str(tmp / "out"),
          "puppet": {"photos": str(photos)},
          "cluster": {"scheduler": "local", "workers": workers}}
    (tmp / "wf.yaml").write_text(yaml.safe_dump(wf))
    workflow = load_workflow(tmp / "wf.yaml")
    times = {}
    with executor_for(workflow) as ex, Sampler() as memory:
        runner = Runner(workflow, ex, progress=False)
        target = Target("puppet")
        with memory.during("photos", times):
            coll, video = runner.collection("puppet", resolve_inputs(workflow)["puppet"])
            runner.run_photo_stages(coll, video)
        with memory.during("mean face", times):
            mean_face(runner, coll)
        with memory.during("subspace", times):
            run_subspace(runner, STAGES["subspace"], target)
        with memory.during("align", times):
            run_alignment(runner, STAGES["align"], target)
        with memory.during("shape", times):
            run_shape(runner, STAGES["shape"], target)
        with memory.during("texture", times):
            run_texture(runner, STAGES["texture"], target)
        return times, memory.peaks, int(accepted(coll).sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[500, 2000, 5000])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--one", action="store_true", help="measure the one size given, in this process")
    args = ap.parse_args()
    if not args.one:  # each size in a process of its own: a freed heap does not count for the next
        for size in args.sizes:
            subprocess.run([sys.executable, __file__, "--one", "--sizes", str(size), "--workers", str(args.workers)],
                           check=True)
        return
    for size in args.sizes:
        with tempfile.TemporaryDirectory() as tmp:
            times, peaks, accepted = build(distinct_photos(size, Path(tmp)), args.workers, Path(tmp))
        print(f"\n{size} photos ({accepted} accepted), {args.workers} workers:")
        print(f"  {'step':<10} {'seconds':>8} {'client peak GiB':>16} {'worker peak GiB':>16}")
        for phase, seconds in times.items():
            client, worker = peaks.get(phase, (0, 0))
            print(f"  {phase:<10} {seconds:8.1f} {client / 2**30:16.2f} {worker / 2**30:16.2f}", flush=True)


if __name__ == "__main__":
    main()
