"""Seconds per output frame of the evaluation of a finished drive, and its share of the drive's own time.

    .venv/bin/python benchmarks/evaluation_speed.py WORKFLOW [--runs 3] [--set KEY=VALUE ...] [--workers N]

Evaluates every drive of WORKFLOW (already run: its store holds the composited output) --runs times, as
`persona evaluate` does (the workflow's executor, or --scheduler / --workers; each pass over the drives
with one runner, which describes a person's photos once for all its drives), reading the store only,
and prints per drive the median wall time per output frame and its share of the drive's own wall time
per frame (``speed.ms_per_driver_frame`` of the drive's metrics.json in the workflow's output folder,
or --metrics). Issue 58 asks for a share of at most 25 %. With ``--scheduler sync`` the CPU time of
this process, also printed, is all of the evaluation's work: the figure to compare on a shared machine. ``--set store=...`` evaluates a copy of the
store (the figures and the frames are the same; the drive's time is still read from metrics.json).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path


def drive_ms_per_frame(wf, plan, metrics: Path | None) -> float | None:
    """The drive's own ms per driver frame from its metrics.json (None when not timed there)."""
    from persona.stores import storage

    if metrics is None:
        folder = wf.output if wf.version == 1 else storage.join(wf.output, plan.name)
        metrics = Path(storage.join(folder, "metrics.json"))
    if not metrics.is_file():
        return None
    report = json.loads(metrics.read_text())
    report = report.get("drives", {}).get(plan.name, report) if "speed" not in report else report
    return report.get("speed", {}).get("ms_per_driver_frame")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workflow")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a workflow value")
    ap.add_argument("--scheduler", help="as `persona evaluate --scheduler` (default: the workflow's cluster)")
    ap.add_argument("--workers", type=int, help="local Dask workers (default: one per core)")
    ap.add_argument("--metrics", type=Path, help="the drive's metrics.json (default: in the workflow's output)")
    args = ap.parse_args()

    from persona.dag.executor import executor_for
    from persona.dag.runner import Runner
    from persona.dag.workflow import load_workflow

    wf = load_workflow(args.workflow, args.set)
    plans = wf.drive_plans()
    seconds, cpu, frames = {p.name: [] for p in plans}, {p.name: [] for p in plans}, {}
    with executor_for(wf, args.scheduler, args.workers) as ex:
        for run in range(args.runs):
            runner = Runner(wf, ex, progress=False)  # one per pass over the drives, as `persona evaluate`'s
            for plan in plans:
                t0, c0 = time.perf_counter(), time.process_time()
                frames[plan.name] = runner.evaluate(plan.cast)["frames"]
                seconds[plan.name].append(time.perf_counter() - t0)
                cpu[plan.name].append(time.process_time() - c0)
                print(f"{plan.name}: run {run + 1}: {seconds[plan.name][-1]:.1f} s for {frames[plan.name]} frames",
                      flush=True)
    for plan in plans:
        per_frame = statistics.median(seconds[plan.name]) / frames[plan.name]
        drive_ms = drive_ms_per_frame(wf, plan, args.metrics)
        share = f"{100 * per_frame * 1000 / drive_ms:.0f} % of the drive's {drive_ms:.0f} ms/frame" \
            if drive_ms else "the drive's time is not in its metrics.json"
        print(f"{plan.name}: evaluation {per_frame:.3f} s/frame (median of {args.runs}; "
              f"{', '.join(f'{s:.1f}' for s in seconds[plan.name])} s), {share}; CPU in this process "
              f"{statistics.median(cpu[plan.name]) / frames[plan.name]:.3f} s/frame (all of the work with "
              f"--scheduler sync: steadier than the wall time on a busy machine)", flush=True)


if __name__ == "__main__":
    main()
