"""Peak memory of the subspace step against the size of the collection.

    .venv/bin/python benchmarks/subspace_memory.py [--sizes 530 2000]
    .venv/bin/python benchmarks/subspace_memory.py --random [--sizes 500 2000 5000] [--shard 16]

For each size, george_w_bush repeated through symbolic links goes through ingest ->
frontalize (2 local workers); then the rank-4 subspace (randomised SVD over shards) runs
alone while the summed resident memory of this process and its workers is sampled.
Printed: the peak during the subspace step, the memory just before it (the baseline of
the processes), and the step's time.

``--random``: the streamed SVD alone (``streamed_svd``, as the subspace step calls it, a
seventh of the rows left out) on that many random rows of a face's size (244 × 194 × 3) in
chunks of ``--shard`` rows, made chunk by chunk on 2 local workers (one thread each); printed:
the largest worker's resident memory before and at its peak, and the time.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import yaml

from ingest_throughput import SHARED, PeakMemory


def random_rows(size: int, shard: int) -> None:
    import dask.array as da
    import numpy as np
    from dask.distributed import Client, LocalCluster

    from person_memory import Sampler
    from persona.plugins.face.subspace import streamed_svd
    from persona.plugins.face.template import CANONICAL_HEIGHT, CANONICAL_WIDTH

    times = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster, \
            Client(cluster) as client, Sampler() as memory:
        face = CANONICAL_HEIGHT * CANONICAL_WIDTH * 3
        rows = da.random.RandomState(0).random_sample((size, face), chunks=(shard, -1)).astype(np.float32)
        with memory.during("before", times):
            time.sleep(1.0)
        with memory.during("svd", times):
            streamed_svd(rows, 4, lambda *arrays: client.gather(client.compute(list(arrays))),
                         keep=np.arange(size) % 7 != 0)
    print(f"{size} random rows in chunks of {shard}: largest worker {memory.peaks['before'][1] / 2**30:.2f} GiB "
          f"before, peak {memory.peaks['svd'][1] / 2**30:.2f} GiB; {times['svd']:.1f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[530, 2000])
    ap.add_argument("--random", action="store_true", help="the streamed SVD alone, on random rows")
    ap.add_argument("--shard", type=int, default=16, help="--random: rows per chunk")
    args = ap.parse_args()
    if args.random:
        for size in args.sizes:
            random_rows(size, args.shard)
        return
    from persona.dag.collection import mean_face
    from persona.dag.executor import executor_for
    from persona.dag.inputs import resolve_inputs
    from persona.dag.runner import Runner
    from persona.dag.shape import compute_subspace
    from persona.dag.workflow import load_workflow

    paths = sorted((SHARED / "george_w_bush").iterdir())
    for size in args.sizes:
        with tempfile.TemporaryDirectory() as tmp:
            links = Path(tmp) / "photos"
            links.mkdir()
            for i in range(size):
                (links / f"{i:05d}_{paths[i % len(paths)].name}").symlink_to(paths[i % len(paths)])
            wf = {"version": 1, "name": "mem", "store": f"{tmp}/run.zarr", "output": f"{tmp}/out",
                  "puppet": {"photos": str(links)}, "cluster": {"scheduler": "local", "workers": 2}}
            (Path(tmp) / "wf.yaml").write_text(yaml.safe_dump(wf))
            workflow = load_workflow(Path(tmp) / "wf.yaml")
            with executor_for(workflow) as ex:
                runner = Runner(workflow, ex, progress=False)
                coll, video = runner.collection("puppet", resolve_inputs(workflow)["puppet"])
                runner.run_photo_stages(coll, video)
                mean_face(runner, coll)
                with PeakMemory(interval=0.05) as before:
                    time.sleep(1.0)
                t0 = time.perf_counter()
                with PeakMemory(interval=0.05) as during:
                    compute_subspace(runner, coll, source="aligned", state="frontalize", rank=4,
                                     tps_lambda=10.0, upstream="benchmark")
                seconds = time.perf_counter() - t0
            print(f"{size} photos: subspace {seconds:.1f} s; resident memory of all processes: "
                  f"{before.peak / 2**30:.2f} GiB before, peak {during.peak / 2**30:.2f} GiB during "
                  f"(+{(during.peak - before.peak) / 2**20:.0f} MiB)")


if __name__ == "__main__":
    main()
