"""Folds in B's meshes below the mouth: where the lower lip drops further than the skin under it.

A mesh that folds has texels drawn over others in the same column; the renderer shows the overlap as
a ragged edge under the lower lip and along the chin. On each finished 3D run's store given, prints,
over every ``--every``-th frame of the drive, the share of B's face below the mouth's middle that lies
more than ``--over`` canonical px above a texel over it (``transfer.fold_depths``; mean and 95th
percentile over the frames) and the deepest fold of each frame (median, 95th percentile and max, px).
``transfer.unfold`` (the default) leaves none; a store made with it off, or before it, shows them.
Beside them, how much taller than its target B's lower lip is drawn (iBUG 66 to 57 on the meshes less
the same on the frame's target fiducials, canonical px; median, 95th percentile and max): unfolding by
pushing the lip's outer edge down with the chin drew it up to 5 px taller; since the lip's body is
squeezed over its edge instead, it stays within about a pixel.

    python benchmarks/mesh_folds.py runs/powell_woman.zarr runs/bush_glasses.zarr
"""

from __future__ import annotations

import argparse

import numpy as np

from persona.plugins.builtin.evaluate import moved_landmarks
from persona.plugins.face.template import IDX49
from persona.plugins.face.transfer import below_mouth, fold_depths
from persona.stores.layout import Cast, Collection, open_store


def folds(store: str, every: int, over: float) -> dict:
    root = open_store(store, mode="r")
    cast = Cast.of(root, "drive")
    puppet, drive = Collection(root, cast.puppet), Collection(root, cast.drive)
    fiducials = puppet.array("aligned/mean_fiducials")[...]
    below = below_mouth(puppet.array("shape/mask")[...], fiducials)
    meshes, targets = drive.array("mesh"), drive.array("target")
    inner, outer = IDX49.index(66), IDX49.index(57)
    share, deepest, taller = [], [], []
    for t in range(0, meshes.shape[0], every):
        depth = fold_depths(meshes[t], below)
        share.append(float((depth[below] > over).mean()))
        deepest.append(float(depth[below].max()))
        drawn, target = moved_landmarks(meshes[t:t + 1], fiducials)[0], targets[t]
        taller.append(float((drawn[57, 1] - drawn[66, 1]) - (target[outer, 1] - target[inner, 1])))
    return {"share": np.array(share), "deepest": np.array(deepest), "taller": np.array(taller)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stores", nargs="+", help="stores of finished 3D runs")
    parser.add_argument("--every", type=int, default=2, help="every n-th frame (default 2)")
    parser.add_argument("--over", type=float, default=0.5, help="canonical px above which a texel counts as "
                        "folded (default 0.5: the float32 meshes' own rounding stays under it)")
    args = parser.parse_args()
    width = max(len(store) for store in args.stores)
    print(f"{'store':{width}s} {'folded share: mean':>19s} {'p95':>7s} {'deepest px: median':>19s} {'p95':>6s} "
          f"{'max':>6s} {'lip taller px: median':>22s} {'p95':>6s} {'max':>6s}")
    for store in args.stores:
        f = folds(store, args.every, args.over)
        print(f"{store:{width}s} {f['share'].mean():19.4f} {np.percentile(f['share'], 95):7.4f} "
              f"{np.median(f['deepest']):19.2f} {np.percentile(f['deepest'], 95):6.2f} {f['deepest'].max():6.2f} "
              f"{np.nanmedian(f['taller']):22.2f} {np.nanpercentile(f['taller'], 95):6.2f} {np.nanmax(f['taller']):6.2f}")


if __name__ == "__main__":
    main()
