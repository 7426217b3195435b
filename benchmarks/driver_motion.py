"""How well the driver's per-frame meshes M_D^t follow the driver's real expressions (issue 6).

For a finished 3D run: the driver's mean fiducials are tracked through every frame's mesh (the
mesh's (x, y) at each fiducial's canonical position, rigid pose already removed), and the same
expression signals as ``persona evaluate`` (mouth opening, eye openness, brow height, over the
inter-ocular distance) are computed from those tracked points and from dlib's landmarks on the
frame itself; the same for the puppet's meshes M_P^t after the transfer, at the puppet's fiducials. Their Pearson correlation per signal says how much of the driver's expression the 3D
flow captured, before transfer, texture and rendering add their own errors.

    python benchmarks/driver_motion.py runs/powell_woman.zarr [runs/bush_obama.zarr ...]
"""

from __future__ import annotations

import argparse

import numpy as np

from persona.plugins.builtin import evaluate as ev
from persona.plugins.face.template import IDX49
from persona.stores.layout import OK, Collection, open_store


def tracked_landmarks(meshes: np.ndarray, fiducials: np.ndarray) -> np.ndarray:
    """(T, 68, 2) iBUG-indexed canonical positions of the 49 fiducials moved by each mesh (NaN elsewhere)."""
    cols, rows = np.round(fiducials).astype(int).T
    out = np.full((len(meshes), 68, 2), np.nan)
    out[:, list(IDX49)] = meshes[:, rows, cols, :2]
    return out


def correlations(store: str, meshes: str, fiducials: str) -> dict[str, float]:
    """Pearson r per expression signal between the fiducials ``fiducials`` moved by the per-frame
    meshes ``meshes`` and dlib's landmarks on the driver's frames."""
    root = open_store(store, mode="r")
    frames = Collection(root, "driver/frames")
    seen = frames.array("landmarks/points")[:].astype(np.float64)
    seen[frames.state("landmarks") != OK] = np.nan
    moved = tracked_landmarks(np.nan_to_num(root[meshes][...]), root[fiducials][...])
    ours, theirs = ev.expression_signals(moved), ev.expression_signals(seen)
    return {k: ev.pearson(ours[k], theirs[k]) for k in theirs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stores", nargs="+", help="stores of finished 3D runs")
    for store in parser.parse_args().stores:
        for name, meshes, fiducials in (("driver meshes M_D^t", "drive/motion/driver_mesh", "driver/aligned/mean_fiducials"),
                                        ("puppet meshes M_P^t", "drive/mesh", "puppet/aligned/mean_fiducials")):
            figures = correlations(store, meshes, fiducials)
            print(f"{store} {name}: " + ", ".join(f"{k} r = {v:.3f}" for k, v in figures.items()))


if __name__ == "__main__":
    main()
