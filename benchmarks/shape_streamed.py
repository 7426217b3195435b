"""The 3D shape's fit on a built person: time, peak memory and result, against another checkout's.

    .venv/bin/python benchmarks/shape_streamed.py STORE [--runs 3] [--reference DIR] [--set KEY=VALUE ...]

STORE is a run's store with an aligned collection ``puppet`` (``person_speed.py --keep DIR`` leaves one in
DIR/run.zarr). Each run calls the shape stage's task (``dag/shape.py: photometric_stereo``, the fit and
the integration, as a run does) in a process of its own, once with this checkout and, with
``--reference DIR`` (a folder holding ``persona/{dag,plugins,stores}`` of another checkout, say the
commit before a change), once with that one, the two alternating. The task writes the shape's arrays
into STORE, as a run would. Printed: for each checkout, the median wall and CPU seconds of the task
and its process's peak resident memory (the largest over the runs); the median of the per-run ratios
of this checkout's seconds to the reference's (both measured under the same load); and how far this
checkout's result is from the reference's: the normals' angle (median, 99th percentile, largest) and
the depth's difference (RMS and largest, canonical px) on the pixels both have, and the lights'.
``--set`` gives the shape stage a parameter (``--set max_images=0``), both checkouts alike.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def fit(store: str, params: dict, out: str) -> dict:
    """The shape task on ``store``'s puppet in this process; its arrays saved to ``out`` (npz)."""
    from persona.dag import stages as st
    from persona.dag.shape import photometric_stereo
    from persona.stores.layout import OK, Collection, open_store
    from persona.stores.provenance import Provenance

    coll = Collection(open_store(store), "puppet")
    ok = coll.state("align") == OK
    count = sum(coll.array("collection/mask")[a:b][ok[a:b]].sum(axis=0, dtype=np.int64)
                for a, b in coll.shard_ranges())
    prov = Provenance.make(stage="shape", backend="benchmark", backend_version="0", params=params,
                           inputs={}, persona_version="benchmark")
    default = st.default_registry()
    shape_params = default.get("shape", "ps_template").Params.model_validate(params).model_dump(mode="json")
    wall, cpu = time.perf_counter(), time.process_time()
    depth, mask = photometric_stereo(store, "puppet", count >= 0.3 * ok.sum(), prov, "ps_template", shape_params,
                                     "sparse_ls", {})
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    np.savez(out, depth=depth, mask=mask, normals=coll.array("shape/normals")[...],
             lighting=coll.array("shape/lighting")[...])
    return {"wall": wall, "cpu": cpu, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "photos": int(ok.sum()), "lit": int(np.isfinite(coll.array("shape/lighting")[...]).all(axis=1).sum())}


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Degrees between unit vectors, from their chord (exact to rounding at small angles, as arccos is not)."""
    return np.degrees(2 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=-1) / 2, 0.0, 1.0)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("store")
    ap.add_argument("--runs", type=int, default=3, help="runs of each checkout (>= 1)")
    ap.add_argument("--reference", type=Path, help="folder holding persona/ of the checkout to compare with")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a parameter of the shape stage (a YAML value), both checkouts alike")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # a fit in this process, saved to this npz
    args = ap.parse_args()
    import yaml

    params = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--set {item}: expected KEY=VALUE")
        params[key] = yaml.safe_load(value)
    if args.one:
        print(json.dumps(fit(args.store, params, args.one)))
        return
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    checkouts = {"this": None}
    if args.reference:
        checkouts["reference"] = args.reference
    figures = {name: [] for name in checkouts}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for name, path in checkouts.items():
                env = dict(os.environ)
                if path is not None:
                    env["PYTHONPATH"] = os.pathsep.join([str(path), env.get("PYTHONPATH", "")])
                out = str(Path(tmp) / f"{name}.npz")
                done = subprocess.run([sys.executable, __file__, args.store, "--one", out,
                                       *(f"--set={s}" for s in args.set)], env=env, capture_output=True, text=True)
                if done.returncode:
                    sys.exit(f"{name}, run {i + 1} failed:\n{done.stderr}")
                figures[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
                f = figures[name][-1]
                print(f"run {i + 1} {name}: {f['wall']:.1f} s wall, {f['cpu']:.1f} s CPU, "
                      f"peak {f['peak'] / 2**30:.2f} GiB", flush=True)
        results = {name: dict(np.load(Path(tmp) / f"{name}.npz")) for name in checkouts}
    this = figures["this"]
    print(f"\n{args.store}: {this[0]['photos']} photos accepted; {args.runs} runs; params {params or 'default'}")
    print(f"  {'checkout':<10} {'photos lit':>10} {'wall s':>7} {'CPU s':>7} {'peak GiB':>9}")
    for name, runs in figures.items():
        print(f"  {name:<10} {runs[0]['lit']:>10} {statistics.median(r['wall'] for r in runs):7.1f} "
              f"{statistics.median(r['cpu'] for r in runs):7.1f} {max(r['peak'] for r in runs) / 2**30:9.2f}")
    if "reference" not in figures:
        return
    ref = figures["reference"]
    for what in ("wall", "cpu"):
        ratio = statistics.median(a[what] / b[what] for a, b in zip(this, ref))
        print(f"  this / reference, {what}: {ratio:.2f} (median of the runs' ratios)")
    a, b = results["this"], results["reference"]
    both = a["mask"] & b["mask"]
    e = angle(a["normals"][both], b["normals"][both])
    dz = a["depth"][both] - b["depth"][both]
    lit = np.isfinite(a["lighting"]).all(axis=1) & np.isfinite(b["lighting"]).all(axis=1)
    print(f"  difference on {both.sum()} pixels (masks differ at {(a['mask'] != b['mask']).sum()}): normals "
          f"{np.median(e):.2e}° median, {np.percentile(e, 99):.2e}° 99th percentile, {e.max():.2e}° largest; "
          f"depth RMS {np.sqrt(np.mean(dz ** 2)):.2e} px, largest {np.abs(dz).max():.2e} px; "
          f"lights of the {lit.sum()} photos both lit: largest {np.abs(a['lighting'] - b['lighting'])[lit].max():.2e}")


if __name__ == "__main__":
    main()
