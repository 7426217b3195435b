"""Simulated makespan of a batch (puppets x drivers) on N workers, from one real run's measured
task durations.

    .venv/bin/python benchmarks/batch_makespan.py runs/powell_woman/metrics.json [--puppets 100]
        [--drivers 10] [--workers 8 32 128]

The run's ``stages`` table (metrics.json) gives each step's task seconds on this machine: the
per-photo stages as a total over the collection (split evenly into its shards of
``photos_per_shard``), the collection-level steps (shape, texture, frame textures, motion,
videos) as one task each. A batch of P puppets and D drivers is built as a task graph from them,
two ways:

* ``shared``: every person's collection and shape is built once and used by all its drives (P
  puppets, D drivers, P x D drives), every step a task on the cluster;
* ``per drive``: one workflow per drive, as ``persona run`` does today: each drive builds its own
  puppet and driver (P x D of each).

Each graph is scheduled on N identical workers by list scheduling (a free worker takes the ready
task with the longest path to the end). Printed per N: the makespan, the ideal (total work / N),
the critical path, and the efficiency (ideal / makespan). Communication is not modelled, and the
scheduler's own cost only as a bound (``--overhead`` seconds a task, one task at a time): the
figures say what the task graph allows, not what a cluster achieves.
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
from collections import defaultdict


class Graph:
    def __init__(self):
        self.seconds: list[float] = []
        self.after: list[list[int]] = []  # the tasks each task waits for

    def task(self, seconds: float, after=()) -> int:
        self.seconds.append(seconds)
        self.after.append(list(after))
        return len(self.seconds) - 1

    def stage(self, seconds: float, shards: int, after=()) -> list[int]:
        """A per-photo stage: ``shards`` tasks sharing ``seconds``, each after all of ``after``."""
        return [self.task(seconds / shards, after) for _ in range(shards)]


def collection(g: Graph, steps: dict, name: str, n: int, per_shard: int) -> list[int]:
    """The per-photo stages of one collection (ingest to align, in order; screen needs all of the
    first chain), then its collection-level shape (and texture for a puppet). Returns the last tasks."""
    shards = max(1, math.ceil(n / per_shard))
    chain = sum(steps.get((s, name), 0.0) for s in ("ingest", "landmarks", "pose", "frontalize"))
    last = g.stage(chain, shards)
    for stage in ("screen", "align"):
        if (stage, name) in steps:
            last = g.stage(steps[(stage, name)], shards, last)
    for stage in ("shape", "texture", "mouth"):
        if (stage, name) in steps:
            last = [g.task(steps[(stage, name)], last)]
    return last


def drive(g: Graph, steps: dict, frames: int, per_shard: int, puppet, driver, driver_frames) -> None:
    shards = max(1, math.ceil(frames / per_shard))
    textures = g.task(steps.get(("frame textures", "drive"), 0.0), puppet + driver_frames)
    dynamics = g.stage(steps.get(("dynamics", "drive"), 0.0), shards, driver + driver_frames + [textures])
    motion = g.task(steps.get(("motion", "drive"), 0.0), dynamics + puppet)
    render = g.stage(sum(steps.get((s, "drive"), 0.0) for s in ("render3d", "render")), shards, [motion])
    g.task(steps.get(("videos", "drive"), 0.0), render)


def batch(steps: dict, sizes: dict, per_shard: int, puppets: int, drivers: int, shared: bool) -> Graph:
    g = Graph()

    def person(name):
        return collection(g, steps, name, sizes[name], per_shard)

    def actor():
        return person("driver"), person("driver/frames")

    if shared:
        built_puppets = [person("puppet") for _ in range(puppets)]
        built_drivers = [actor() for _ in range(drivers)]
        for p in built_puppets:
            for d, frames in built_drivers:
                drive(g, steps, sizes["driver/frames"], per_shard, p, d, frames)
    else:
        for _ in range(puppets * drivers):
            d, frames = actor()
            drive(g, steps, sizes["driver/frames"], per_shard, person("puppet"), d, frames)
    return g


def schedule(g: Graph, workers: int) -> tuple[float, float]:
    """(makespan, critical path) of list scheduling, longest path to the end first."""
    n = len(g.seconds)
    waiting = [len(a) for a in g.after]
    children = defaultdict(list)
    for t, parents in enumerate(g.after):
        for p in parents:
            children[p].append(t)
    rank = list(g.seconds)  # longest path from each task to the end (tasks are created in order)
    for t in range(n - 1, -1, -1):
        rank[t] = g.seconds[t] + max((rank[c] for c in children[t]), default=0.0)
    ready = [(-rank[t], t) for t in range(n) if waiting[t] == 0]
    heapq.heapify(ready)
    running: list[tuple[float, int]] = []
    now, free = 0.0, workers
    while ready or running:
        while free and ready:
            _, t = heapq.heappop(ready)
            heapq.heappush(running, (now + g.seconds[t], t))
            free -= 1
        now, t = heapq.heappop(running)
        free += 1
        for c in children[t]:
            waiting[c] -= 1
            if waiting[c] == 0:
                heapq.heappush(ready, (-rank[c], c))
    return now, max(rank)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("metrics")
    parser.add_argument("--puppets", type=int, default=100)
    parser.add_argument("--drivers", type=int, default=10)
    parser.add_argument("--workers", type=int, nargs="+", default=[8, 32, 128])
    parser.add_argument("--photos-per-shard", type=int, default=4)
    parser.add_argument("--overhead", type=float, default=0.001, help="the scheduler's seconds per task (Dask's "
                        "documentation: about 1 ms), a bound printed beside the makespans")
    args = parser.parse_args()
    m = json.load(open(args.metrics))
    steps = {(r["stage"], r["collection"]): r["task_seconds"] for r in m["stages"]}
    sizes = {name: c["n_photos"] for name, c in m["collections"].items()}
    print(f"from {args.metrics}: puppet {sizes['puppet']} photos, driver {sizes['driver']} photos, "
          f"{sizes['driver/frames']} frames; {args.puppets} puppets x {args.drivers} drivers")
    for shared in (True, False):
        g = batch(steps, sizes, args.photos_per_shard, args.puppets, args.drivers, shared)
        work = sum(g.seconds)
        print(f"\n{'shared' if shared else 'per drive'}: {len(g.seconds)} tasks, {work / 3600:.0f} h of work; "
              f"a scheduler spending {args.overhead * 1000:g} ms on each task needs {len(g.seconds) * args.overhead / 3600:.2f} h")
        print("workers | makespan h | ideal h | critical path h | efficiency")
        for w in args.workers:
            makespan, critical = schedule(g, w)
            print(f"{w:7d} | {makespan / 3600:10.2f} | {work / w / 3600:7.2f} | {critical / 3600:15.2f} | "
                  f"{work / w / makespan:.2f}")


if __name__ == "__main__":
    main()
