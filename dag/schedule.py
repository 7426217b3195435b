"""A version-2 run's schedule: every person and video built once, ``cluster.builds`` at a time in threads of
this process whose tasks share the cluster, and every drive as soon as its people and video are built.
A person or a video that cannot be built fails the drives that use it; a drive that fails fails alone.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor

from persona.stores import media, storage
from persona.stores.errors import InputError, PersonaError

from .context import RunContext
from .errors import RunError
from .executor import stops_the_run
from .outputs import write_json, write_outputs
from .report import write_batch_page

log = logging.getLogger(__name__)


def run_batch(runner: RunContext, inputs: dict, report: dict) -> dict:
    """A version-2 workflow: every person and video once, then every drive, each drive's outputs
    in its own folder and the batch page over them. A person or a video that cannot be built
    fails the drives that use it, a drive that fails fails alone; the run then raises a
    :class:`RunError` naming each failed drive, after the others are done.

    People and videos are built ``cluster.builds`` at a time, in threads of this process whose
    tasks share the cluster; the drives run one after another in this thread, each as soon as
    its puppet, driver and video are built, while the others' builds go on."""
    plans = runner.wf.collections()
    for plan in plans:  # every group (and its parents) made here, before the threads write in them
        if not isinstance(inputs[plan.path], InputError):
            runner.root.require_group(plan.path)
    # built in the order the drives need them, so that the first drive starts as soon as it can
    needed = [p for d in runner.wf.drive_plans() for p in (d.cast.puppet, d.cast.driver, d.cast.frames)]
    first_use = {path: i for i, path in reversed(list(enumerate(needed)))}
    pool = (_OneByOne() if runner.executor.client is None or runner.wf.cluster.builds == 1
            else ThreadPoolExecutor(runner.wf.cluster.builds, thread_name_prefix="persona-build"))
    try:
        builds = {plan.path: pool.submit(_build, runner, plan, inputs[plan.path], report)
                  for plan in sorted(plans, key=lambda plan: first_use.get(plan.path, len(needed)))}
        failed = _run_drives(runner, report, builds)
        pool.shutdown()  # the people and videos no drive uses
        for build in builds.values():
            built(build)  # a damaged chunk met there is recovered as anywhere
    except BaseException as exc:
        # a damaged chunk (run() recovers and starts again) or an error: no build may go on writing
        # meanwhile. Ctrl-C does not wait: closing the cluster then ends the builds' tasks
        pool.shutdown(wait=not isinstance(exc, KeyboardInterrupt), cancel_futures=True)
        raise
    ended = report["collections"]  # in the order the builds ended: the workflow's order
    report["collections"] = {plan.path: ended[plan.path] for plan in plans if plan.path in ended}
    write_json(storage.join(runner.wf.output, "metrics.json"), report)
    write_batch_page(runner.wf, report)
    if failed:
        raise RunError(f"{len(failed)} of {len(report['drives'])} drives failed: "
                       + "; ".join(f"{name}: {why}" for name, why in failed.items())
                       + f". The others are done (in {runner.wf.output}); fix the cause and run again: "
                       "what is done is not redone")
    return report


def _build(runner: RunContext, plan, sources: list[media.Source] | InputError, report: dict) -> None:
    """:meth:`build_collection` in a build thread, its result into ``report``; an error is logged
    here, when it happens, and raised to the drives that wait for it."""
    try:
        if isinstance(sources, InputError):
            raise sources
        report["collections"][plan.path] = runner.build_collection(plan, sources, report)
    except Exception as exc:
        if not stops_the_run(exc):  # that one is said where the run stops
            log.error("%s: %s", plan.path, _why(exc))
        raise


def _run_drives(runner: RunContext, report: dict, builds: dict[str, Future]) -> dict[str, str]:
    """Every drive of a version-2 workflow, each once its collections' ``builds`` are done, into
    ``report``; returns why each drive that failed did."""
    report["stages"] = runner.timer.records
    report["report"] = str(storage.join(runner.wf.output, "index.html"))
    report["drives"], failed = {}, {}
    for plan in runner.wf.drive_plans():
        try:
            cause = [f"{p}: {why}" for p in dict.fromkeys((plan.cast.puppet, plan.cast.driver, plan.cast.frames))
                     if (why := built(builds[p])) is not None]
            if cause:
                raise RunError("; ".join(cause))
            part = runner.drive(plan)
        except Exception as exc:  # one drive that fails does not take the others down
            if stops_the_run(exc):
                raise
            failed[plan.name] = _why(exc)
            log.error("drive %s failed: %s", plan.name, failed[plan.name])
            report["drives"][plan.name] = {"output": str(plan.output), "error": failed[plan.name]}
            continue
        own = {"workflow": f"{runner.wf.name}: {plan.name}", "store": runner.wf.store, "drive": plan.name,
               "collections": {p: report["collections"][p] for p in (plan.cast.puppet, plan.cast.driver,
                                                                       plan.cast.frames)},
               **{k: v for k, v in part.items() if k != "series"},
               "stages": [r for r in runner.timer.records if r["collection"] in (plan.cast.drive, plan.cast.puppet)],
               "report": str(storage.join(plan.output, "report.html"))}
        write_outputs(runner, plan.output, own, part["series"], plan.cast)
        report["drives"][plan.name] = {"output": str(plan.output), "report": own["report"],
                                       "evaluation": own["evaluation"]}
    return failed


class _OneByOne:
    """The builds of :func:`run_batch` one after another in this thread, as a pool of one
    thread would run them (the scheduler "sync", or ``cluster.builds`` 1)."""

    @staticmethod
    def submit(fn, *args) -> Future:
        future = Future()
        try:
            future.set_result(fn(*args))
        except Exception as exc:  # raised where the drives wait for it (built)
            if stops_the_run(exc):  # at once, as a thread's would stop the run
                raise
            future.set_exception(exc)
        return future

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        pass


def built(build: Future) -> str | None:
    """Waits for a collection's build (:func:`_build`): None when it is built, else why not. A
    damaged chunk met there is raised, for :meth:`Runner.run` to recover, and so are a full disk and a lost
    cluster (:func:`stops_the_run`)."""
    exc = build.exception()
    if exc is not None and (not isinstance(exc, Exception) or stops_the_run(exc)):
        raise exc
    return None if exc is None else _why(exc)


def _why(exc: Exception) -> str:
    """A failure's reason in a line: a Persona error's own message, else the exception's type too."""
    return str(exc) if isinstance(exc, PersonaError) else f"{type(exc).__name__}: {exc}"
