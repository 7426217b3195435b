"""The seam of the composite on a finished run: a plain paste, multi-band blending alone, and
multi-band blending after B's face is matched to A's light at its edge (``lighting`` 1, the default).

For every ``--every``-th output frame of a run's store, the render is composited into the
driver's frame each way and the seam along the face's edge measured
(:func:`persona.plugins.face.composite.seam`: colour step beyond the frame's own, grey levels;
gradient energy over the frame's). Prints the medians, and the milliseconds per frame of each
composite at the video's size. The same figures as ``persona evaluate``'s ``composite`` for the
code at hand, without recomputing the rest of the evaluation.

    python benchmarks/composite_seam.py workflows/bush_driven_by_obama.yaml --every 4
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from persona.dag.stages import render_alpha
from persona.dag.workflow import load_workflow
from persona.plugins.face import composite
from persona.stores.layout import Collection, open_store


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflow")
    parser.add_argument("--every", type=int, default=4)
    args = parser.parse_args()
    wf = load_workflow(args.workflow)
    root = open_store(wf.store, mode="r")
    drive, frames = Collection(root, "drive"), Collection(root, "driver/frames")
    ways = {"paste": composite.paste, "multiband": composite.multiband, "blend (lighting 1)": composite.blend}
    found = {name: [] for name in ways}
    seconds = {name: [] for name in ways}
    for t in range(0, drive.n, args.every):
        face, alpha = drive.array("render/rgb")[t], render_alpha(drive.array("render/mask")[t])
        frame = frames.array("photos/rgb")[t][:face.shape[0], :face.shape[1]]
        for name, way in ways.items():
            start = time.perf_counter()
            image = way(face, frame, alpha)
            seconds[name].append(time.perf_counter() - start)
            f = composite.seam(image, frame, alpha)
            if f is not None:
                found[name].append((f["colour_step"], f["gradient_ratio"]))
    print(f"{wf.name}: {len(found['paste'])} frames (every {args.every}th), {face.shape[1]}x{face.shape[0]}")
    print("| composite | colour step (grey levels) | gradient ratio | ms / frame |")
    print("|---|---|---|---|")
    for name, rows in found.items():
        a = np.array(rows)
        ms = 1000 * np.median(seconds[name])
        print(f"| {name} | {np.median(a[:, 0]):.1f} | {np.median(a[:, 1]):.2f} | {ms:.1f} |")


if __name__ == "__main__":
    main()
