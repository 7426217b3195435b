"""How far each accepted photo's pose-corrected fiducials lie from its collection's median shape.

For every collection of the given workflows' stores (run them first), prints the photos
accepted, the largest distance of an accepted photo (RMS over its visible fiducials, the
screen's measure, canonical px; one inter-ocular distance is 64) and its 99th percentile, the
largest distance of any one fiducial, the photos with NaN (not visible) points, and what the
screen rejected. Stores written before the screen existed are read as they are
(every frontalized photo counts as accepted), so the same script gives "before" and "after".

    python benchmarks/fiducial_screen.py workflows/bush_driven_by_obama.yaml ...
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from persona.dag.workflow import load_workflow
from persona.plugins.face.fiducials import median_shape, shape_distance
from persona.stores.layout import OK, REJECTED, collections, open_store


def rows(store: str):
    root = open_store(store, mode="r")
    for coll in collections(root):
        if not coll.has("aligned/fiducials"):
            continue
        screened = coll.has("status/screen/state")
        ok = coll.state("screen" if screened else "frontalize") == OK
        fiducials = coll.array("aligned/fiducials")[:].astype(np.float64)
        median = median_shape(fiducials[ok])
        distance = shape_distance(fiducials, median)
        worst = int(np.flatnonzero(ok)[np.nanargmax(distance[ok])])
        point = np.full(coll.n, np.nan)  # each accepted photo's farthest visible fiducial
        point[ok] = np.nanmax(np.linalg.norm(fiducials[ok] - median, axis=-1), axis=1)
        far = int(np.flatnonzero(ok)[np.nanargmax(point[ok])])
        rejected = int((coll.state("screen") == REJECTED).sum()) if screened else 0
        ids = coll.array("photos/ids")
        yield (coll.path, int(ok.sum()), coll.n, float(distance[worst]), Path(str(ids[worst])).name,
               float(np.nanpercentile(distance[ok], 99)), float(point[far]), Path(str(ids[far])).name,
               int(np.isnan(fiducials[ok]).any(axis=(1, 2)).sum()), rejected)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflows", nargs="+")
    args = parser.parse_args()
    print("| workflow | collection | accepted | largest RMS distance px (photo) | 99th pct px "
          "| largest point distance px (photo) | photos with NaN points | screened out |")
    print("|---|---|---|---|---|---|---|---|")
    for path in args.workflows:
        wf = load_workflow(path)
        for coll, ok, n, worst, photo, p99, point, far, nan, rejected in rows(wf.store):
            print(f"| {wf.name} | {coll} | {ok}/{n} | {worst:.1f} ({photo}) | {p99:.1f} | {point:.1f} ({far}) "
                  f"| {nan} | {rejected} |")


if __name__ == "__main__":
    main()
