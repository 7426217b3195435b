"""How far each accepted photo's pose-corrected fiducials lie from its collection's median shape.

For every collection of the given workflows' stores (run them first), prints the photos
accepted, the largest distance (RMS over the visible fiducials, canonical px; one inter-ocular
distance is 64) and its photo, the 99th percentile, the photos with NaN (not visible) points,
and what the screen rejected. Stores written before the screen existed are read as they are
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
        distance = shape_distance(fiducials, median_shape(fiducials[ok]))
        worst = int(np.flatnonzero(ok)[np.nanargmax(distance[ok])])
        rejected = int((coll.state("screen") == REJECTED).sum()) if screened else 0
        yield (coll.path, int(ok.sum()), coll.n, float(distance[worst]), Path(str(coll.array("photos/ids")[worst])).name,
               float(np.nanpercentile(distance[ok], 99)), int(np.isnan(fiducials[ok]).any(axis=(1, 2)).sum()), rejected)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflows", nargs="+")
    args = parser.parse_args()
    print("| workflow | collection | accepted | worst photo | distance px | 99th pct px | photos with NaN points | screened out |")
    print("|---|---|---|---|---|---|---|---|")
    for path in args.workflows:
        wf = load_workflow(path)
        for coll, ok, n, worst, photo, p99, nan, rejected in rows(wf.store):
            print(f"| {wf.name} | {coll} | {ok}/{n} | {photo} | {worst:.1f} | {p99:.1f} | {nan} | {rejected} |")


if __name__ == "__main__":
    main()
