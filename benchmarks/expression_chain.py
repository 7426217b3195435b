"""Where does the driver's expression amplitude go? The gain of each step of the 3D drive.

On a finished 3D run's store, for every expression signal (mouth opening, mouth width, the mouth
corners' height, eye openness, brow height; dlib's landmarks on A's frames are the reference), prints the gain
(slope on the driver's signal), the correlation and the ranges of:

- A's per-frame meshes M_D^t (A's mean fiducials moved by them): what the dynamics kept;
- B's meshes M_P^t after the transfer (B's mean fiducials moved): what the transfer kept;
- the same seen at each frame's pose, as the renderer draws them: what a perfect reader of the
  rendered face would find;
- B's meshes transferred again here, as the run's transfer backend prepares them (``default``: the
  run's own, which the row above must match) and with variants of it (``--variants``), on every
  ``--every``-th frame, to locate the loss inside the transfer;
- the rendered output (dlib's landmarks on the output frames), read from the run's
  ``metrics.json`` when its evaluation is there;
- with ``--worst N``, for each signal the N frames whose output falls furthest from the driver's
  along the output's fitted line, each step's value there, and the gain without them: whether a loss
  is spread over the drive or sits in a few frames, and at which step.

    python benchmarks/expression_chain.py workflows/obama_self_reenactment.yaml --every 4
    python benchmarks/expression_chain.py workflows/obama_driven_by_mead_happy.yaml --variants default --worst 6
    python benchmarks/expression_chain.py workflows/hd_gaze_drives.yaml --drive frontal_fringe_woman_gaze_fringe_400-end

A workflow with several drives (version 2) names one with ``--drive`` (its name, as its output folder is
called); without it, the first.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from persona.dag.evaluate import driver_frame_landmarks, expression_gains, mesh_landmarks
from persona.dag.motion import prepared_transfer
from persona.dag.workflow import load_workflow
from persona.plugins.builtin import evaluate as ev
from persona.stores.layout import Collection, open_store

SIGNALS = ("mouth_open", "mouth_width", "mouth_corners", "eye_open", "brow_height")


def gains(landmarks: np.ndarray, driver: dict) -> dict:
    ours = ev.expression_signals(landmarks)
    return {k: ev.amplitude(driver[k], ours[k]) for k in SIGNALS}


def row(name: str, figures: dict) -> str:
    cells = [f"{figures[k]['gain']:.2f} / {figures[k]['r']:.2f}" for k in SIGNALS]
    return f"| {name} | " + " | ".join(cells) + " |"


def worst(root, cast, driver: dict, output: dict, count: int) -> None:
    """For each signal, the ``count`` frames furthest from the output's least-squares line on the
    driver's (the output's ``series.json``), with each step of the chain there, and the gain without them."""
    steps = {"A's meshes": (f"{cast.drive}/motion/driver_mesh", cast.driver, False),
             "B's meshes": (f"{cast.drive}/mesh", cast.puppet, False),
             "as drawn": (f"{cast.drive}/mesh", cast.puppet, True)}
    fiducials = {actor: root[f"{actor}/aligned/mean_fiducials"][...] for actor in (cast.driver, cast.puppet)}
    poses = root[f"{cast.drive}/pose"]
    for k in SIGNALS:
        ours = np.asarray(output[f"output_{k}"], np.float64)
        ok = np.isfinite(driver[k]) & np.isfinite(ours)
        slope, offset = np.polyfit(driver[k][ok], ours[ok], 1)
        off = np.where(ok, np.abs(ours - (slope * driver[k] + offset)), -1.0)
        frames = np.sort(np.argsort(-off)[:count])
        kept = ok.copy()
        kept[frames] = False
        without = ev.amplitude(driver[k][kept], ours[kept])
        print(f"\n{k}: gain {ev.amplitude(driver[k], ours)['gain']:.2f}, without frames {frames.tolist()} "
              f"{without['gain']:.2f} (r {without['r']:.2f})")
        print("| frame | driver | " + " | ".join(steps) + " | output |")
        print("|---|---|" + "---|" * len(steps) + "---|")
        for t in frames:
            cells = []
            for meshes, actor, drawn in steps.values():
                mesh = root[meshes][int(t):int(t) + 1]
                moved = (ev.posed_landmarks(mesh, fiducials[actor], poses[int(t):int(t) + 1]) if drawn
                         else ev.moved_landmarks(mesh, fiducials[actor]))
                cells.append(f"{ev.expression_signals(moved)[k][0]:.3f}")
            print(f"| {t} | {driver[k][t]:.3f} | " + " | ".join(cells) + f" | {ours[t]:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflow")
    parser.add_argument("--every", type=int, default=4, help="re-transfer every n-th frame (variants)")
    parser.add_argument("--variants", default="default,none,naive,normal",
                        help="comma-separated: default (the run's), none (no denoising), naive, normal, "
                        "tv=W (Huber-ROF with TV weight W)")
    parser.add_argument("--worst", type=int, default=0, help="list the N frames furthest from the output's "
                        "line on the driver's, each step there (needs the run's series.json)")
    parser.add_argument("--drive", help="which drive of a version-2 workflow, by name (as its output folder is "
                        "called); default: the first")
    args = parser.parse_args()
    wf = load_workflow(args.workflow)
    plans = {plan.name: plan for plan in wf.drive_plans()}
    if not plans:
        parser.error(f"{args.workflow} has no drive")
    if args.drive is not None and args.drive not in plans:
        parser.error(f"{args.workflow} has no drive {args.drive!r}; its drives: {', '.join(plans)}")
    plan = plans[args.drive] if args.drive is not None else next(iter(plans.values()))
    cast = plan.cast
    root = open_store(wf.store, mode="r")
    drive = Collection(root, cast.drive)
    landmarks = driver_frame_landmarks(root, cast.frames)
    driver = ev.expression_signals(landmarks)
    print(f"{wf.name}, {cast.drive}: {drive.n} frames; driver ranges (5-95 %, / IOD): "
          + ", ".join(f"{k} {np.subtract(*np.nanpercentile(driver[k], [95, 5])):.3f}" for k in SIGNALS))
    print("| step | " + " | ".join(f"{k} gain / r" for k in SIGNALS) + " |")
    print("|---|" + "---|" * len(SIGNALS))
    print(row("A's meshes", expression_gains(landmarks, mesh_landmarks(root, f"{cast.drive}/motion/driver_mesh",
                                                                      cast.driver)[0])))
    moved, posed = mesh_landmarks(root, f"{cast.drive}/mesh", cast.puppet, poses=drive.array("pose")[:])
    print(row("B's meshes (the run)", expression_gains(landmarks, moved)))
    print(row("B's meshes at the frames' poses", expression_gains(landmarks, posed)))

    chosen = np.arange(0, drive.n, args.every)
    sub = {k: v[chosen] for k, v in driver.items()}
    source = drive.array("motion/driver_mesh")
    a_meshes = [source[int(t)] for t in chosen]
    puppet = Collection(root, cast.puppet)
    fiducials = puppet.array("aligned/mean_fiducials")[...]
    transfer = wf.stage("transfer")
    run_denoise = wf.stage("denoise") if "denoise" in wf.stages else None
    for variant in args.variants.split(","):
        (name, params), denoise = transfer, run_denoise
        if variant in ("naive", "normal"):
            params = {**params, "method": variant}
        elif variant == "none":
            denoise = ("none", {})
        elif variant.startswith("tv="):
            denoise = ("huber_rof", {"weight": float(variant[3:]), "outside": "exclude"})
        mesh, _ = prepared_transfer(root, drive, puppet, (name, params), denoise)  # as the run's motion stage
        meshes = np.stack([mesh(int(t), m) for t, m in zip(chosen, a_meshes)])
        moved = ev.moved_landmarks(meshes, fiducials)
        print(row(f"B's meshes, transfer {variant} (every {args.every}th frame)", gains(moved, sub)))
    metrics = Path(plan.output) / "metrics.json"
    if metrics.is_file():
        amp = json.loads(metrics.read_text()).get("evaluation", {}).get("amplitude")
        if amp:
            print(row("output (the run's evaluation)", amp))
    series = Path(plan.output) / "series.json"
    if args.worst and series.is_file():
        worst(root, cast, driver, json.loads(series.read_text()), args.worst)


if __name__ == "__main__":
    main()
