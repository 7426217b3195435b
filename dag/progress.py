"""What a run shows and records of its stages: the progress display (a bar on a terminal, timestamped
lines in a log) and the stage timer, a built-in plugin of the lifecycle hooks.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

from persona.plugins.hookspecs import hookimpl


@dataclass
class StageTimer:
    """A built-in plugin that records every stage's times and counts.

    ``wall_seconds``: from the stage's start to its end (per-photo stages run fused per
    shard, so they share one wall time); ``task_seconds``: the stage's own compute time
    summed over all tasks and workers.
    """

    records: list = field(default_factory=list)
    _start: dict = field(default_factory=dict)

    @hookimpl
    def persona_before_stage(self, stage, collection, info):
        self._start[(stage, collection)] = time.perf_counter()

    @hookimpl
    def persona_after_stage(self, stage, collection, summary):
        seconds = time.perf_counter() - self._start.pop((stage, collection), time.perf_counter())
        self.records.append({"stage": stage, "collection": collection, "wall_seconds": round(seconds, 3),
                             "task_seconds": round(summary.get("seconds", 0.0), 3),
                             **{k: v for k, v in summary.items() if k != "seconds"}})


class _Lines:
    """Progress for a log file or a batch job: one timestamped line when a step starts and one when
    it ends, instead of a bar redrawn with carriage returns."""

    def __init__(self, what: str, total: int, unit: str, initial: int):
        self.what, self.total, self.unit, self.done = " ".join(what.split()), total, unit, initial
        self.start = time.monotonic()
        self._say(f"started: {total} {self.units}" + (f", {initial} done before" if initial else ""))

    @property
    def units(self) -> str:
        return self.unit if self.total == 1 else f"{self.unit}s"

    def _say(self, text: str) -> None:
        print(f"{time.strftime('%H:%M:%S')} {self.what}: {text}", file=sys.stderr, flush=True)

    def update(self, n: int = 1) -> None:
        self.done += n

    def close(self) -> None:
        """The step's last line: "done" when every item is counted, "stopped" when the run stopped
        before (an error, a kill of the scheduler, Ctrl-C)."""
        if self.start is not None:
            word = "done" if self.done >= self.total else "stopped"
            self._say(f"{word}: {self.done} of {self.total} {self.units} in {time.monotonic() - self.start:.1f} s")
            self.start = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress(what: str, total: int, unit: str = "frame", *, initial: int = 0, enabled: bool = True):
    """A progress display with ``update(n)`` and ``close()`` (also a context manager): a tqdm bar on a
    terminal, :class:`_Lines` when stderr is a file or pipe, nothing when not ``enabled``."""
    from tqdm.auto import tqdm

    if enabled and not sys.stderr.isatty():
        return _Lines(what, total, unit, initial)
    return tqdm(total=total, initial=initial, desc=what, unit=unit, disable=not enabled, leave=True,
                dynamic_ncols=True)
