"""Does the reconstructed 3D shape capture identity? Two random halves of Bush against Powell.

    .venv/bin/python benchmarks/shape_identity.py [--seed 0] [--keep DIR] [--flow NAME]

Reconstructs george_w_bush from two random halves of its photos and colin_powell from all
of its photos (default backends, 2 local workers), aligns each pair of depth maps by a
least-squares scale and offset on their common mask, and prints the mean absolute depth
difference (canonical px) of each pair, the ratio halves / (Bush vs Powell) (the issue
asks for < 0.5), and the wall time of each run. Shaded previews of the three meshes are
left in --keep (default: a temporary folder that is printed).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "collections"


def reconstruct(name: str, photos, folder: Path, flow: str | None) -> tuple[np.ndarray, np.ndarray, float]:
    from persona.dag.runner import run_workflow
    from persona.dag.workflow import load_workflow
    from persona.stores.layout import Collection, open_store

    wf = {"version": 1, "name": name, "store": str(folder / f"{name}.zarr"), "output": str(folder / name),
          "puppet": {"photos": photos}, "cluster": {"scheduler": "local", "workers": 2}}
    if flow:
        wf["stages"] = {"flow": {"backend": flow}}
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(wf))
    t0 = time.perf_counter()
    run_workflow(load_workflow(path), progress=False)
    seconds = time.perf_counter() - t0
    coll = Collection(open_store(wf["store"], mode="r"), "puppet")
    return coll.array("shape/depth")[...], coll.array("shape/mask")[...], seconds


def difference(a, mask_a, b, mask_b) -> float:
    """Mean |a - (s b + t)| over the common mask, s and t by least squares."""
    common = mask_a & mask_b
    x, y = b[common], a[common]
    s, t = np.linalg.lstsq(np.c_[x, np.ones_like(x)], y, rcond=None)[0]
    return float(np.mean(np.abs(y - (s * x + t))))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path)
    ap.add_argument("--flow", help="the collection flow's backend (default: the workflow default)")
    args = ap.parse_args()
    folder = args.keep or Path(tempfile.mkdtemp(prefix="shape_identity_"))
    folder.mkdir(parents=True, exist_ok=True)
    bush = sorted(str(p) for p in (SHARED / "george_w_bush").iterdir())
    order = np.random.default_rng(args.seed).permutation(len(bush))
    halves = [sorted(bush[i] for i in order[: len(bush) // 2]), sorted(bush[i] for i in order[len(bush) // 2:])]
    results = {}
    for name, photos in (("bush_a", halves[0]), ("bush_b", halves[1]), ("powell", str(SHARED / "colin_powell"))):
        results[name] = reconstruct(name, photos, folder, args.flow)
        print(f"{name}: {len(photos) if isinstance(photos, list) else 'all'} photos, {results[name][2]:.1f} s")
    d = {pair: difference(*results[pair[0]][:2], *results[pair[1]][:2])
         for pair in (("bush_a", "bush_b"), ("bush_a", "powell"), ("bush_b", "powell"))}
    for (a, b), v in d.items():
        print(f"mean |depth difference| {a} vs {b}: {v:.3f} px")
    cross = (d[("bush_a", "powell")] + d[("bush_b", "powell")]) / 2
    print(f"halves / Bush-vs-Powell = {d[('bush_a', 'bush_b')] / cross:.2f} (asked: < 0.5)")
    print(f"previews: {folder}/*/puppet_mesh_previews.png")


if __name__ == "__main__":
    main()
