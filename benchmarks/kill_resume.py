"""SIGKILL a real run at points spread over its stages, re-run it each time, and compare the final store
with an uninterrupted run's, array by array.

    .venv/bin/python benchmarks/kill_resume.py workflows/powell_driven_by_woman.yaml --reference STORE [--workers 2]

Without --reference, the workflow is first run uninterrupted into a temporary store. Then one
store is built by a sequence of runs: attempt k waits until its run prints the k-th trigger line
(a stage starting or finishing, see ``TRIGGERS``), waits a few seconds more so that the stage is
busy writing, and SIGKILLs the whole process group (the client and its local Dask workers, as a
power cut or an out-of-memory killer would). A final run completes the store. Every array of both
stores is compared: shape, dtype, and values (NaN equal to NaN). Prints one line per kill (when,
where, the last line the run printed; each run's whole output is in the folder, ``kill_<k>.log``)
and the comparison; exit status 1 when an array differs or a run failed.

The default triggers fit the example workflows, version 1 (collections ``puppet``, ``driver``,
``driver/frames`` and ``drive``) and version 2 (``people/<name>``, ``videos/<name>``,
``drives/<name>``; the first person, video and drive to print the step): per-photo stages, the
collection-level shape and texture cache, the video's frames, the drive's per-frame textures,
dynamics, transfer, render, composite, videos and the evaluation.
"""

from __future__ import annotations

import argparse
import os
import re
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr

#: The collection a line is about, in a version-1 or a version-2 workflow.
PERSON, VIDEO, DRIVE = r"(puppet|people/\S+)", r"(driver/frames|videos/\S+)", r"(drive|drives/\S+)"

#: (pattern of a line the run prints, seconds to wait after it before the SIGKILL)
TRIGGERS = [
    (rf"{PERSON} ingest: started", 4),           # photos: ingest, landmarks, pose, frontalize
    (rf"{PERSON} align: started", 6),            # the collection flow, per photo
    (rf"{PERSON} shape: started", 8),            # the puppet's subspace and shape
    (rf"{PERSON} tex. cache: started", 6),       # the puppet's texture cache
    (rf"{VIDEO} landmarks: started", 1),         # the driver's frames, per frame
    (rf"{DRIVE} texture: started", 1),           # the per-frame textures
    (rf"{DRIVE} dynamics: started", 3),          # the driver's 3D flow
    (rf"{DRIVE} transfer: started", 1),          # the deformation transfer
    (rf"{DRIVE} render3d: started", 1),          # the render
    (rf"{DRIVE} composite: started", 2),         # the composite
    (rf"{DRIVE} videos: started", 2),            # the videos
    (rf"{DRIVE} analyse: started", 10),          # the evaluation
]


def run(workflow: str, store: Path, output: Path, workers: int, trigger=None, env=None, log: Path | None = None):
    """One ``persona run``; with ``trigger`` (pattern, delay), SIGKILLed ``delay`` s after the first
    line matching it; the lines it prints go to the file ``log`` too. Returns (return code or
    "killed", seconds, the last line printed)."""
    command = [sys.executable, "-m", "persona.dag.cli", "run", workflow, "--workers", str(workers),
               "--set", f"store={store}", "--set", f"output={output}"]
    start = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env=env)
    selector = selectors.DefaultSelector()
    selector.register(proc.stdout, selectors.EVENT_READ)
    last, deadline = "", None
    with open(log or os.devnull, "w", buffering=1) as out:  # line by line: a run that hangs shows where
        while True:
            if deadline is not None and time.perf_counter() >= deadline:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                return "killed", time.perf_counter() - start, last
            if selector.select(timeout=0.2):
                line = proc.stdout.readline()
                if not line:
                    break
                last = line.rstrip()[:120] or last
                out.write(line)
                if trigger and deadline is None and re.search(trigger[0], line):
                    deadline = time.perf_counter() + trigger[1]
    proc.wait()
    return proc.returncode, time.perf_counter() - start, last


def arrays(group) -> dict:
    """{path: array} of every array under a Zarr group."""
    return {path: item for path, item in group.members(max_depth=None) if isinstance(item, zarr.Array)}


def compare(reference: Path, test: Path) -> list[str]:
    """Paths of the arrays that differ (or exist in only one store), with how."""
    ref, got = arrays(zarr.open_group(str(reference), mode="r")), arrays(zarr.open_group(str(test), mode="r"))
    problems = [f"{p}: only in the reference" for p in sorted(set(ref) - set(got))]
    problems += [f"{p}: only in the killed run" for p in sorted(set(got) - set(ref))]
    for path in sorted(set(ref) & set(got)):
        a, b = ref[path], got[path]
        if a.shape != b.shape or a.dtype != b.dtype:
            problems.append(f"{path}: {a.shape} {a.dtype} against {b.shape} {b.dtype}")
            continue
        x, y = a[...], b[...]
        same = np.array_equal(x, y, equal_nan=x.dtype.kind in "fc")
        if not same:
            diff = (np.nanmax(np.abs(x.astype(np.float64) - y.astype(np.float64)))
                    if x.dtype.kind in "fiub" else "n/a")
            problems.append(f"{path}: values differ (max |difference| {diff})")
    print(f"{len(set(ref) & set(got))} arrays compared, {len(problems)} differ")
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workflow")
    parser.add_argument("--reference", type=Path, help="the store of an uninterrupted run of the same code")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--folder", type=Path, help="where the killed run's store goes (default: a temporary folder)")
    args = parser.parse_args()
    folder = args.folder or Path(tempfile.mkdtemp(prefix="persona-kill-"))
    folder.mkdir(parents=True, exist_ok=True)
    workflow = str(Path(args.workflow).resolve())
    reference = args.reference
    if reference is None:
        reference = folder / "reference.zarr"
        rc, seconds, last = run(workflow, reference, folder / "reference", args.workers, log=folder / "reference.log")
        print(f"uninterrupted run: rc {rc}, {seconds:.0f} s")
        if rc != 0:
            print(last)
            return 1
    store, output = folder / "killed.zarr", folder / "killed"
    for k, trigger in enumerate(TRIGGERS, 1):
        rc, seconds, last = run(workflow, store, output, args.workers, trigger, log=folder / f"kill_{k:02d}.log")
        print(f"kill {k:2d} ({trigger[0]} + {trigger[1]} s): {rc} after {seconds:.0f} s; last line: {last}")
    rc, seconds, last = run(workflow, store, output, args.workers, log=folder / "final.log")
    print(f"final run: rc {rc}, {seconds:.0f} s; last line: {last}")
    problems = compare(reference, store)
    for p in problems:
        print("  " + p)
    return int(rc != 0 or bool(problems))


if __name__ == "__main__":
    sys.exit(main())
