"""Time and peak memory of building one person end to end, step by step, median of several runs.

    .venv/bin/python benchmarks/person_speed.py [--photos 1000] [--runs 3] [--workers 2] [--keep DIR]

The photos are ``--photos`` distinct JPEGs made from george_w_bush in ../shared/data as
``person_memory.py`` makes them (Bush's 530, then the k-th copy of each scaled by 1 + 0.02 k), once,
into a temporary folder shared by the runs. Each run builds the person as a run builds a puppet
(ingest and the per-photo chain, mean face, appearance subspace, collection flow, 3D shape, texture
cache; ``person_memory.build``) in a process of its own, on ``--workers`` local workers, with the
resident memory of the client and of every worker sampled every 50 ms.

Printed per step: the median seconds over the runs and their spread (min-max), the step's share of
the whole, its ratio to the per-photo chain's seconds in the same run (a reference the shape and
the subspace do not touch: a busier machine slows both), and the largest peak over the runs of the
client and of any one worker. ``--keep DIR`` keeps the last run's store and photos in DIR (for
``shape_streamed.py``); ``--folder`` builds from a folder's photos as they are. To measure another
checkout of Persona (say the commit before a change), put a folder holding ``persona/{dag,plugins,stores}``
of it first on PYTHONPATH: the runs and their workers import it instead.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

STEPS = ("photos", "mean face", "subspace", "align", "shape", "texture")


def one_run(photos: Path, workers: int, keep: Path | None) -> dict:
    from person_memory import build

    with tempfile.TemporaryDirectory() as tmp:
        times, peaks, accepted = build(photos, workers, Path(tmp))
        if keep is not None:
            shutil.rmtree(keep, ignore_errors=True)
            shutil.copytree(tmp, keep, symlinks=True)
    return {"times": times, "peaks": peaks, "accepted": accepted}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", type=int, default=1000, help="how many distinct photos (>= 1)")
    ap.add_argument("--runs", type=int, default=3, help="how many builds (>= 1); figures are their median")
    ap.add_argument("--workers", type=int, default=2, help="local Dask workers (>= 1)")
    ap.add_argument("--keep", type=Path, help="keep the last run's store and output in this folder")
    ap.add_argument("--folder", type=Path, help="build from the photos of this folder as they are (e.g. "
                    "../shared/data/collections/george_w_bush) instead of --photos distinct ones")
    ap.add_argument("--one", type=Path, help=argparse.SUPPRESS)  # a run in this process, on these photos
    args = ap.parse_args()
    if min(args.photos, args.runs, args.workers) < 1:
        ap.error("--photos, --runs and --workers must be at least 1")
    if args.one:
        print(json.dumps(one_run(args.one, args.workers, args.keep)))
        return
    import persona.dag

    from person_memory import distinct_photos

    print(f"persona from {Path(persona.dag.__file__).parent.parent}", flush=True)  # PYTHONPATH may name another checkout
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        photos = args.folder or distinct_photos(args.photos, Path(tmp))
        for i in range(args.runs):  # each run in a process of its own: a freed heap does not count for the next
            keep = ["--keep", str(args.keep)] if args.keep and i == args.runs - 1 else []
            done = subprocess.run([sys.executable, __file__, "--one", str(photos), "--workers", str(args.workers),
                                   *keep], capture_output=True, text=True)
            if done.returncode:
                sys.exit(f"run {i + 1} failed:\n{done.stderr}")
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
            total = sum(runs[-1]["times"].values())
            print(f"run {i + 1}: {total:.1f} s ({runs[-1]['accepted']} photos accepted)", flush=True)
    totals = [sum(r["times"].values()) for r in runs]
    print(f"\n{args.folder or f'{args.photos} photos'}, {args.workers} workers, {args.runs} runs: whole person "
          f"{statistics.median(totals):.1f} s (median; {min(totals):.1f}-{max(totals):.1f})")
    print(f"  {'step':<10} {'seconds':>8} {'spread':>13} {'share':>6} {'/ photos':>9} {'client GiB':>11} "
          f"{'worker GiB':>11}")
    for step in STEPS:
        seconds = [r["times"][step] for r in runs]
        ratio = [r["times"][step] / r["times"]["photos"] for r in runs]
        client = max(r["peaks"].get(step, (0, 0))[0] for r in runs) / 2**30
        worker = max(r["peaks"].get(step, (0, 0))[1] for r in runs) / 2**30
        print(f"  {step:<10} {statistics.median(seconds):8.1f} {min(seconds):6.1f}-{max(seconds):<6.1f} "
              f"{statistics.median(seconds) / statistics.median(totals):6.0%} {statistics.median(ratio):9.2f} "
              f"{client:11.2f} {worker:11.2f}", flush=True)


if __name__ == "__main__":
    main()
