"""A stage's work as Dask tasks, with the lifecycle hooks and the progress display: the per-photo
chain's tasks over the shards of a collection not done yet, a function mapped over every shard, and a
stage over a whole collection as one step.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

from persona.stores.layout import OK, PENDING, REJECTED, Collection
from persona.stores.paths import item

from . import stages as st
from .executor import Executor
from .progress import progress


class Tasks:
    """Runs a run's tasks on its ``executor`` for the store at ``store``, telling the plugin manager
    ``pm``'s lifecycle hooks and showing progress (hidden when not ``shown``)."""

    def __init__(self, store: str, executor: Executor, pm, shown: bool = True):
        self.store, self.executor, self.pm, self.shown = store, executor, pm, shown

    def run_stage_tasks(self, coll: Collection, steps: list[tuple[str, str, dict]]) -> None:
        """The chain of ``steps`` on every shard where one of them is not done yet."""
        states = [coll.state(name) for name, _, _ in steps]
        pending = [(s, e) for s, e in coll.shard_ranges() if any((state[s:e] == PENDING).any() for state in states)]
        tasks = [(self.store, coll.path, s, e, steps) for s, e in pending]
        self.run_tasks(coll, steps, tasks, st.run_chain)

    @contextmanager
    def step(self, stage: str, collection: str):
        """A collection-level step (shape, texture, motion, ...) as the lifecycle hooks and the
        timing table see a stage: before, after (with its wall time) or error; and as progress, one
        step that starts and ends (a log gets a line each, with the time taken). ``stage`` is one
        of :data:`persona.dag.stages.STAGES`."""
        if stage not in st.STAGES:
            raise KeyError(f"{stage!r} is not in persona.dag.stages.STAGES, which the plan shows")
        self.pm.hook.persona_before_stage(stage=stage, collection=collection, info={})
        start = time.perf_counter()
        try:
            with self.progress_bar(f"{collection:>13} {stage:<10}", 1, unit="step") as bar:
                yield
                bar.update()
        except BaseException as exc:
            self.pm.hook.persona_stage_error(stage=stage, collection=collection, error=exc)
            raise
        self.pm.hook.persona_after_stage(stage=stage, collection=collection,
                                         summary={"seconds": time.perf_counter() - start})

    def progress_bar(self, what: str, total: int, unit: str = "frame", initial: int = 0):
        """A progress bar (hidden with --quiet): :func:`progress`."""
        return progress(what, total, unit, initial=initial, enabled=self.shown)

    def map_shards(self, coll: Collection, label: str, fn, *args) -> dict[int, object]:
        """``fn(store, path, start, stop, *args)`` on every shard of ``coll`` as tasks on the cluster
        (:func:`persona.dag.stages.on_shard`), with a progress bar; returns each shard's result by
        its first frame."""
        return {start: result for start, result in self._shard_results(coll, label, fn, *args)}

    def fold_shards(self, coll: Collection, label: str, fn, combine, *args):
        """:meth:`map_shards`, the shards' results (None: nothing to add) folded with
        ``combine(a, b)`` in the order of the shards as they arrive: only the results that come
        before their turn are held, and the fold is the same to the bit whichever task ends first."""
        starts = [s for s, _ in coll.shard_ranges()]
        early, total, turn = {}, None, 0
        for start, result in self._shard_results(coll, label, fn, *args):
            early[start] = result
            while turn < len(starts) and starts[turn] in early:
                result = early.pop(starts[turn])
                turn += 1
                if result is not None:
                    total = result if total is None else combine(total, result)
        return total

    def _shard_results(self, coll: Collection, label: str, fn, *args):
        """(first frame, result) of each shard's task as it ends, with a progress bar."""
        tasks = [(fn, self.store, coll.path, s, e, *args) for s, e in coll.shard_ranges()]
        with self.progress_bar(f"{coll.path:>13} {label:<10}", coll.n, item(coll.path)) as bar:
            for start, stop, result in self.executor.run(st.on_shard, tasks):
                bar.update(stop - start)
                yield start, result

    def run_tasks(self, coll, steps, tasks, fn):
        """``fn(*task)`` for each of ``tasks``, the per-photo ``steps`` they run timed, hooked and shown."""
        names = [name for name, _, _ in steps]
        done = {name: int((coll.state(name) != PENDING).sum()) for name in names}
        counts = {name: {"n_done": 0, "n_skipped": done[name], "seconds": 0.0} for name in names}
        for name, backend, params in steps:
            self.pm.hook.persona_before_stage(stage=name, collection=coll.path,
                                              info={"backend": backend, "params": params, "n_items": coll.n})
        bars = {name: self.progress_bar(f"{coll.path:>13} {name:<10}", coll.n, item(coll.path), initial=done[name])
                for name in names}
        try:
            for result in self.executor.run(fn, tasks):
                for name, summary in result.items():
                    if not summary.get("skipped"):
                        counts[name]["n_done"] += summary["n"]
                        counts[name]["seconds"] += summary["seconds"]
                        bars[name].update(summary["n"])
            for name in names:  # shards a task finished before its worker died: its next attempt found them done
                lost = int((coll.state(name) != PENDING).sum()) - done[name] - counts[name]["n_done"]
                if lost > 0:
                    counts[name]["n_done"] += lost
                    bars[name].update(lost)
        except BaseException as exc:
            for name in names:
                self.pm.hook.persona_stage_error(stage=name, collection=coll.path, error=exc)
            raise
        finally:
            for bar in bars.values():
                bar.close()
        for name in names:
            state = coll.state(name)
            self.pm.hook.persona_after_stage(stage=name, collection=coll.path, summary={
                **counts[name], "n_ok": int((state == OK).sum()), "n_rejected": int((state == REJECTED).sum())})
