"""Peak memory of the subspace step against the size of the collection.

    .venv/bin/python benchmarks/subspace_memory.py [--sizes 530 2000]

For each size, george_w_bush repeated through symbolic links goes through ingest ->
frontalize (2 local workers); then the rank-4 subspace (randomised SVD over shards) runs
alone while the summed resident memory of this process and its workers is sampled.
Printed: the peak during the subspace step, the memory just before it (the baseline of
the processes), and the step's time.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import yaml

from ingest_throughput import SHARED, PeakMemory


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[530, 2000])
    args = ap.parse_args()
    from persona.dag.runner import Runner, executor_for, resolve_inputs
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
                runner.mean_face(coll)
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
