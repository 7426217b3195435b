"""How much of the driver's expression a drive's frame textures already draw, in what should be B's neutral geometry.

    .venv/bin/python benchmarks/texture_leak.py WORKFLOW [--drive NAME] [--every 1]

A drive's frame texture keeps B's neutral geometry (the photos are aligned to B's mean fiducials) with the detail
of the photos whose expression is the frame's; the mesh then moves B's fiducials onto the frame's targets. Where
the aligned photos still show their own expression (a squint's narrowed lids, an open mouth), the texture moves
part of the way by itself, and the mesh moves it again. For every drive of WORKFLOW (finished, rendered in 3D: its
store holds ``texture/rgb``), this fits dlib's 68 points on each frame texture (upsampled 3x, in the box of B's mean
fiducials) and prints, per expression signal (evaluate.expression_signals), the slope of the texture's signal on
the target's (0: the texture holds still, as it should; 1: it moves as far as the target), its correlation, and the
slope of B's meshes' fiducials on the targets (1: the mesh lands on them). Texture plus mesh is what the render
draws: a texture slope of 0.5 with a mesh slope of 1 draws the lids half as far again as the target moves them.
"""

from __future__ import annotations

import argparse

import numpy as np

#: how much the canonical textures (244 x 194) are enlarged before dlib fits its points: its predictor is made
#: for faces of 100-300 px
UPSAMPLE = 3


def slopes(root, cast, every: int = 1) -> dict[str, dict] | None:
    """Per expression signal of the drive of ``cast`` in the store ``root``: the target's 5-95 % range (IOD), and
    the (slope, r) on the target's of the frame textures' (dlib's points on them) and of B's meshes' fiducials,
    every ``every``-th frame; None for a drive without frame textures and meshes (not run, or rendered in 2D)."""
    import cv2
    import dlib

    from persona.plugins.builtin.evaluate import amplitude, expression_signals, moved_landmarks
    from persona.plugins.builtin.landmarks import dlib_models
    from persona.plugins.face.template import IDX49
    from persona.stores.layout import Collection

    drive = Collection(root, cast.drive)
    if not drive.has("texture/rgb") or not drive.has("mesh"):
        return None
    rows = np.arange(0, drive.n, every)
    neutral = root[f"{cast.puppet}/aligned/mean_fiducials"][...].astype(np.float64)
    targets = np.full((len(rows), 68, 2), np.nan)
    targets[:, list(IDX49)] = drive.array("target")[:][rows]
    (x0, y0), (x1, y1) = neutral.min(axis=0) - (25, 30), neutral.max(axis=0) + (25, 45)
    box = dlib.rectangle(*(int(round(UPSAMPLE * v)) for v in (x0, y0, x1, y1)))
    predictor, fitted = dlib_models()[1], []
    for texture in drive.rows("texture/rgb", rows):
        big = cv2.resize(np.asarray(texture, np.uint8), None, fx=UPSAMPLE, fy=UPSAMPLE, interpolation=cv2.INTER_CUBIC)
        fitted.append([[p.x, p.y] for p in predictor(big, box).parts()])
    signals = {who: expression_signals(points) for who, points in
               (("target", targets), ("texture", np.array(fitted, np.float64) / UPSAMPLE),
                ("mesh", moved_landmarks(drive.rows("mesh", rows), neutral)))}
    out = {}
    for name, target in signals["target"].items():
        fits = {who: amplitude(target, signals[who][name]) for who in ("texture", "mesh")}  # gain = the slope
        out[name] = {"range": fits["mesh"]["driver_range"],
                     **{who: None if np.isnan(fit["gain"]) else (fit["gain"], fit["r"]) for who, fit in fits.items()}}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workflow")
    ap.add_argument("--drive", help="only the drive of this name (default: every drive)")
    ap.add_argument("--every", type=int, default=1, help="every how many frames (default: all)")
    args = ap.parse_args(argv)

    from persona.dag.workflow import load_workflow
    from persona.stores.layout import open_store

    wf = load_workflow(args.workflow)
    root = open_store(wf.store, mode="r")
    for plan in wf.drive_plans():
        if args.drive and plan.name != args.drive:
            continue
        found = slopes(root, plan.cast, args.every)
        if found is None:
            print(f"{plan.name}: no frame textures and meshes in the store (not run, or not rendered in 3D)")
            continue
        print(f"{plan.name}: every {args.every} frame(s)")
        for name, figures in found.items():
            line = f"  {name:14s} target's range {figures['range']:.3f} IOD"
            for who in ("texture", "mesh"):
                fit = figures[who]
                line += f";  {who}: too few frames" if fit is None else \
                    f";  {who} on target {fit[0]:5.2f} (r {fit[1]:.2f})"
            print(line, flush=True)


if __name__ == "__main__":
    main()
