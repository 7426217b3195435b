"""Chaos (issue 59): a version-2 batch (two puppets, one driver, two drives, small collections) run as a user
runs it, `persona run` in its own process group with its own two local Dask workers, and SIGKILLed at ten
points spread over its run, either one worker process or the whole run (the client, its scheduler and
its workers); a last run must finish and leave every array as an uninterrupted run leaves it. And the
same batch on a disk that fills up part way: a clear message, and with space again a clean resume.

The points come from a seeded generator, a new seed each session: PERSONA_CHAOS_SEED=<seed> replays the
points and kinds of a failure (every assertion's message gives the seed; where a point lands varies a
little with the machine's load), and each run's output is kept in the test's folder when it fails
(``chaos_<n>.log``).

The batch and its uninterrupted run are conftest.py's ``batch``, shared with the other tests that run it.
"""

import json
import os
import re
import secrets
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from persona.dag.cli import main as cli
from persona.stores.lock import NAME as LOCK

from pipeline import Run, assert_same_store, events

SEED = int(os.environ.get("PERSONA_CHAOS_SEED") or secrets.randbelow(2**31))
KILLS = 10
#: of which the whole run (the others: one worker). A whole-run kill costs most: the next run's start, the
#: lines of what is done again and the work the kill lost (10 to 15 s here); a worker's costs its new one's start
RUN_KILLS = 4
#: the kill points: fractions of the uninterrupted run's time (from its first progress line to its end),
#: one drawn in each tenth of this span; none in its last seconds (the second drive's videos and evaluation),
#: so that the last point comes before the run ends
SPAN = (0.03, 0.85)
#: seconds a run may take before the test gives up on it (a hang is a failure too)
TIMEOUT = 600
#: the runs' environment: up to 4 of the 6 worker kills can land in one long task (a 3D shape, an
#: evaluation); Dask gives a task up after 4 workers died under it (its allowed-failures, 3), a stop the
#: run makes clear (test_runner.py) and that would be a failure here
ENV = {**os.environ, "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": str(KILLS)}


def _why(where: str) -> str:
    return f"(seed {SEED}: PERSONA_CHAOS_SEED={SEED} replays it) {where}"


def _run(workflow: Path, store: Path, output: Path, log: Path) -> Run:
    """A run of the batch as the chaos test makes them: Dask's allowed failures raised (ENV), and the seed
    in the message of a failure."""
    return Run(workflow, store, output, log, env=ENV, note=_why(""))


def _same_store(store: Path, reference: Path) -> None:
    try:
        assert_same_store(store, reference)
    except AssertionError as exc:
        raise AssertionError(_why(f"{store} is not the uninterrupted run's store: {exc}")) from None


class Progress:
    """How far a sequence of runs got on the uninterrupted run's timeline: as far on it as the number of
    its progress lines they printed between them (each counted once and in any order: two people are built
    at once, not always in the same order), plus the seconds since the last of them that was new (a long
    step prints nothing until it ends). A run after a kill prints the lines of what is done again, then
    does the work the kill lost: it counts from its first new line."""

    def __init__(self, timeline: dict[str, float]):
        self.timeline, self.offsets = timeline, sorted(timeline.values())
        self.seen: set[str] = set()
        self.since = None

    def saw(self, event: str, when: float) -> None:
        if event in self.timeline and event not in self.seen:
            self.seen.add(event)
            self.since = when

    def pause(self) -> None:
        self.since = None

    def at(self, now: float) -> float:
        return float("-inf") if self.since is None else self.offsets[len(self.seen) - 1] + now - self.since


def _kill_on_points(run: Run, progress: Progress, points: list, kinds: list, kills: list, rng) -> bool:
    """Follow ``run`` on the uninterrupted run's timeline and, each time the runs reach the next of
    ``points`` (half a second at least after the last kill), SIGKILL one of its workers or all of it, as
    ``kinds`` says; each kill is added to ``kills``. Returns once the run has ended: True when it was killed."""
    seen = 0
    progress.pause()
    while run.proc.poll() is None:
        now = time.monotonic()
        new, seen = run.lines[seen:], seen + len(run.lines[seen:])
        for when, line in new:
            for event in events(line):
                run.working = run.working or when
                progress.saw(event, when)
        if now - run.start > TIMEOUT:
            pytest.fail(_why(f"a run did not end within {TIMEOUT} s ({len(kills)} kills before):\n{run.tail()}"))
        k = len(kills)
        if k == len(points) or progress.at(now) < points[k] or (kills and now - kills[-1]["when"] < 0.5):
            time.sleep(0.05)
            continue
        kill = {"kind": kinds[k], "point": points[k], "at": progress.at(now), "when": now,
                "in_run": now - run.start, "last": run.last_step(), "run": run}
        if kinds[k] == "worker":
            workers = run.workers()
            if not workers:  # between a killed worker and its nanny's new one: a moment later
                time.sleep(0.05)
                continue
            os.kill(int(rng.choice(workers)), signal.SIGKILL)
            kills.append(kill)
        else:
            run.kill()
            kills.append(kill)
            return True
    return False


@pytest.mark.slow  # 1.5 minutes on 2 cores (2.5 on a busy machine), the uninterrupted run (shared) not counted
def test_a_batch_killed_at_ten_points_ends_as_an_uninterrupted_run(batch, tmp_path):
    """Ten SIGKILLs at seeded points, of one worker or of the whole run; every run after a whole-run kill
    takes the dead run's lock over at once and resumes, no run stops with an error of its own, and the last
    one exits 0 with a store whose every array is the uninterrupted run's and that verifies."""
    folder, workflow, timeline, end = batch
    rng = np.random.default_rng(SEED)
    low, high = SPAN
    points = [end * (low + (high - low) * (k + rng.random()) / KILLS) for k in range(KILLS)]
    kinds = list(rng.permutation(["worker"] * (KILLS - RUN_KILLS) + ["run"] * RUN_KILLS))
    print(f"seed {SEED}: kills at " + ", ".join(f"{p:.1f} s ({kind})" for p, kind in zip(points, kinds)))

    store, output = tmp_path / "chaos.zarr", tmp_path / "chaos"
    kills, runs, progress = [], [], Progress(timeline)
    started, killed = time.monotonic(), True
    try:
        while killed:  # the first run, and a run after each whole-run kill
            runs.append(_run(workflow, store, output, tmp_path / f"chaos_{len(runs) + 1}.log"))
            killed = _kill_on_points(runs[-1], progress, points, kinds, kills, rng)
        rc = runs[-1].wait(TIMEOUT)
    finally:
        for run in runs:  # a test that failed half-way leaves no run behind
            if run.proc.poll() is None:
                run.kill()
    assert rc == 0, _why(f"run {len(runs)} stopped with exit status {rc} (kills so far: "
                         f"{[(k['kind'], round(k['at'], 1)) for k in kills]}):\n{runs[-1].tail()}")
    seconds = time.monotonic() - started

    report = "\n".join(f"  kill {i + 1:2d}: {k['kind']:<6} at {k['at']:5.1f} s of {end:.0f} (point {k['point']:.1f}), "
                       f"run {runs.index(k['run']) + 1} after {k['in_run']:.1f} s; last line: {k['last'].strip()}"
                       for i, k in enumerate(kills))
    starts = ", ".join(f"{r.working - r.start:.1f}" for r in runs if r.working)
    print(f"{len(runs)} runs, {seconds:.0f} s (from each start to its first progress line: {starts} s):\n{report}")
    assert len(kills) == KILLS, _why(f"the last run ended before kill {len(kills) + 1} of {KILLS} "
                                     f"({points[len(kills)]:.1f} s of the uninterrupted run's {end:.0f}):\n{report}")

    # every run after a whole-run kill took the dead run's lock over and went on; no run said it failed
    for i, run in enumerate(runs):
        text = run.text()
        assert "Traceback" not in text and "Compute Failed" not in text, _why(f"run {i + 1}:\n{text}")
        # (a step that "stopped" in a run that went on: a worker's lost task, done again, counted as undone)
        errors = [line for _, line in run.lines
                  if line.startswith("error:") or "failed:" in line or ": stopped: " in line]
        assert not errors, _why(f"run {i + 1} reported an error: {errors}")
        if i:
            killed = runs[i - 1].proc.pid
            assert re.search(rf"the store's lock was left by a run that no longer runs \(process {killed} on "
                             r".*\): taken over", text), _why(f"run {i + 1} did not take over the lock of the "
                                                              f"killed run {i} (process {killed}):\n{run.tail()}")
    assert not (store / LOCK).exists(), _why("the last run left its lock in the store")
    leftovers = [str(p.relative_to(store)) for p in store.rglob("*.partial")]  # writes a kill cut short
    assert not leftovers, _why(f"the store keeps unfinished writes of killed runs: {leftovers}")

    _same_store(store, folder / "reference.zarr")
    assert cli(["inspect", "--verify", str(store)]) == 0, _why("the store does not verify")
    for drive in ("bea_al_al", "cy_al_al"):  # the outputs of both drives are there
        assert (output / drive / "composite.mp4").is_file(), _why(drive)
        metrics = json.loads((output / drive / "metrics.json").read_text())
        assert metrics["drive"] == drive and "evaluation" in metrics, _why(drive)


@pytest.fixture
def small_disk(batch, tmp_path):
    """A tmpfs at tmp_path/disk (root only) a seeded fraction of the reference store's size, so that
    it fills up part way through the batch; resized with ``resize(mebibytes)``."""
    folder = batch[0]
    used = sum(f.stat().st_blocks * 512 for f in (folder / "reference.zarr").rglob("*") if f.is_file()) / 2**20
    fraction = np.random.default_rng([SEED, 1]).uniform(0.2, 0.7)
    size = max(1, int(used * fraction))
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}m", "tmpfs", str(disk)],
                      capture_output=True).returncode:
        pytest.skip("mounting a tmpfs needs root")

    def resize(mebibytes):
        subprocess.run(["mount", "-o", f"remount,size={mebibytes}m", str(disk)], check=True)

    print(f"\nseed {SEED}: a disk of {size} MiB, {fraction:.0%} of the store's {used:.0f} MiB")
    yield disk, resize, int(used)
    subprocess.run(["umount", str(disk)], check=False)


@pytest.mark.slow  # about a minute (1.5 on a busy machine): a run to the full disk, and the rest
def test_a_batch_on_a_disk_that_fills_up_stops_clearly_and_resumes(batch, small_disk, tmp_path):
    """The store's disk fills up part way through the batch: the run stops with exit status 2 and one line
    that says so and what to do, no traceback (not the workers' either) and no drive reported failed as if
    the others were done; with space again the same command finishes with the uninterrupted run's store."""
    folder, workflow, _, _ = batch
    disk, resize, used = small_disk
    store, output = disk / "run.zarr", tmp_path / "out"
    start = time.monotonic()
    run = _run(workflow, store, output, tmp_path / "full.log")
    rc = run.wait()
    text = run.text()
    assert rc == 2, _why(f"exit status {rc} on a full disk:\n{text}")
    assert "error: the disk is full (No space left on device) writing " in text and "run again" in text, _why(text)
    assert "Traceback" not in text and "Compute Failed" not in text, _why(text)
    assert "drives failed" not in text and "failed:" not in text, _why(text)
    full = time.monotonic() - start
    assert any(" done: " in line for _, line in run.lines), _why(f"the disk was full before any work:\n{text}")

    resize(2 * used + 16)
    again = _run(workflow, store, output, tmp_path / "again.log")
    assert again.wait() == 0, _why(f"the run did not resume with space again:\n{again.tail()}")
    text = again.text()
    assert "Traceback" not in text and "error:" not in text, _why(text)
    assert "done before" in text, _why(f"the run after the full disk did not resume:\n{text}")
    assert "taken over" not in text, _why(f"the run that met the full disk left its lock:\n{text}")
    print(f"full disk after {full:.0f} s, then the resumed run {time.monotonic() - start - full:.0f} s; "
          f"last line before: {run.last_step().strip()}")
    _same_store(store, folder / "reference.zarr")
    assert cli(["inspect", "--verify", str(store)]) == 0, _why("the store does not verify")
