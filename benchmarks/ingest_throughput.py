"""Throughput of ingest -> frontalize on a real collection, against dlib detection alone.

    .venv/bin/python benchmarks/ingest_throughput.py [--collection george_w_bush] [--runs 3] [--big 2000]

Prints photos per second of the per-photo stages (ingest -> landmarks -> pose ->
frontalize) with 1 and 2 workers, median of --runs runs, on warm workers (dlib's models
and the template loaded, as the floor's processes are) and including the cluster's start;
the floor (dlib's HOG detector alone, upsample 1, on the decoded photos, in the same
number of warm processes); their ratio; and the peak resident memory of the whole
process tree (this process + Dask workers) on a --big photo list (the collection
repeated through symbolic links).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import psutil
import yaml

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "collections"


def detect_only(paths: list[str]) -> int:
    import cv2
    import dlib

    detector = dlib.get_frontal_face_detector()
    found = 0
    for p in paths:
        image = cv2.cvtColor(cv2.imread(p), cv2.COLOR_BGR2RGB)
        found += len(detector(image, 1)) > 0
    return found


def floor(paths: list[str], workers: int) -> float:
    """Photos per second of detection alone, the photos split over ``workers`` processes."""
    parts = [paths[i::workers] for i in range(workers)]
    with ProcessPoolExecutor(workers) as pool:
        list(pool.map(detect_only, [p[:2] for p in parts]))  # warm up: imports
        t0 = time.perf_counter()
        list(pool.map(detect_only, parts))
        return len(paths) / (time.perf_counter() - t0)


class PeakMemory:
    """Samples the summed RSS of this process and its children."""

    def __init__(self, interval=0.1):
        self.interval, self.peak, self._stop = interval, 0, threading.Event()

    def _run(self):
        me = psutil.Process()
        while not self._stop.is_set():
            total = 0
            for p in [me, *me.children(recursive=True)]:
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    pass
            self.peak = max(self.peak, total)
            time.sleep(self.interval)

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def warm_up() -> None:
    """What a worker loads once: dlib's models, the template and its ray-casting scene."""
    from persona.plugins.builtin.frontalize import template_scene
    from persona.plugins.builtin.landmarks import dlib_models

    dlib_models()
    template_scene()


def pipeline(photos, workers: int, folder: Path) -> tuple[float, float, dict]:
    """Seconds of ingest -> frontalize on warm workers, seconds including the cluster's
    start and warm-up, and the stage records."""
    from persona.dag.executor import executor_for
    from persona.dag.inputs import resolve_inputs
    from persona.dag.runner import Runner
    from persona.dag.stages import accepted
    from persona.dag.workflow import load_workflow

    wf = {"version": 1, "name": "bench", "store": str(folder / "run.zarr"), "output": str(folder / "out"),
          "puppet": {"photos": photos}, "cluster": {"scheduler": "local", "workers": workers}}
    path = folder / "wf.yaml"
    path.write_text(yaml.safe_dump(wf))
    workflow = load_workflow(path)
    t_start = time.perf_counter()
    with executor_for(workflow) as ex:
        ex.client.run(warm_up)
        runner = Runner(workflow, ex, progress=False)
        t0 = time.perf_counter()
        coll, video = runner.collection("puppet", resolve_inputs(workflow)["puppet"])
        runner.run_photo_stages(coll, video)
        t1 = time.perf_counter()
    return t1 - t0, t1 - t_start, {"stages": runner.timer.records, "accepted": int(accepted(coll).sum())}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--collection", default="george_w_bush")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--big", type=int, default=2000)
    args = ap.parse_args()
    folder = SHARED / args.collection
    paths = sorted(str(p) for p in folder.iterdir())
    n = len(paths)
    print(f"{args.collection}: {n} photos; {psutil.cpu_count()} cores")
    for workers in (1, 2):
        runs, cold, floors = [], [], []
        for _ in range(args.runs):
            with tempfile.TemporaryDirectory() as tmp:
                seconds, with_start, report = pipeline(str(folder), workers, Path(tmp))
            runs.append(n / seconds)
            cold.append(n / with_start)
            floors.append(floor(paths, workers))
        stages = {r["stage"]: r["task_seconds"] for r in report["stages"]}
        p, c, f = statistics.median(runs), statistics.median(cold), statistics.median(floors)
        print(f"workers={workers}: ingest->frontalize {p:6.1f} photos/s on warm workers, {c:6.1f} with the "
              f"cluster's start (medians of {args.runs}); detector floor {f:6.1f} photos/s (warm); "
              f"floor/pipeline = {f / p:.2f}x (with start {f / c:.2f}x); "
              f"last run, task seconds per stage {stages}")
    if args.big:
        with tempfile.TemporaryDirectory() as tmp:
            links = Path(tmp) / "photos"
            links.mkdir()
            for i in range(args.big):
                (links / f"{i:05d}_{Path(paths[i % n]).name}").symlink_to(paths[i % n])
            with PeakMemory() as mem:
                seconds, with_start, report = pipeline(str(links), 2, Path(tmp))
            print(f"{args.big} photos, 2 workers: {args.big / seconds:.1f} photos/s on warm workers "
                  f"({args.big / with_start:.1f} with the cluster's start), {report['accepted']} aligned, "
                  f"peak resident memory (all processes) {mem.peak / 2**30:.2f} GiB")


if __name__ == "__main__":
    main()
