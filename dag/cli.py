"""The ``persona`` command: a thin layer over :mod:`persona.dag.api`."""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from persona.plugins.base import Rejected
from persona.plugins.manager import PluginError
from persona.stores.errors import InputError, PersonaError
from persona.stores.layout import StoreUnreadable
from persona.stores.lock import StoreLocked
from persona.stores.output import OutputTaken
from persona.stores.paths import item


class Terminated(KeyboardInterrupt):
    """SIGTERM: what a batch system sends to cancel a job or at its time limit, as do `kill` and timeouts."""


@contextmanager
def _terminate_as_interrupt():
    """SIGTERM stops the run as Ctrl-C does, for as long as it runs: its batch jobs cancelled, its local
    workers stopped, the store's lock let go and the line to resume with printed. Python's default ends the
    process at once, and a SLURM run's worker jobs stayed in the queue, to start later with no scheduler."""
    if threading.current_thread() is not threading.main_thread():  # only the main thread takes signals
        yield
        return

    def stop(signum, frame):
        raise Terminated()

    before = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def _cmd_run(args) -> int:
    from . import api

    wf = api.workflow(args.workflow, args.set)
    if args.dry_run:
        print(_plan(wf))
        return 0
    try:
        with _terminate_as_interrupt():
            report = api.run(wf, scheduler=args.scheduler, workers=args.workers, progress=not args.quiet,
                             force=args.force)
    except KeyboardInterrupt as exc:
        _resume_hint(args)
        return 128 + signal.SIGTERM if isinstance(exc, Terminated) else 130
    except (InputError, Rejected, StoreLocked, OutputTaken, StoreUnreadable):  # running again cannot help: no hint
        raise
    except Exception:  # a full disk (api.run's StorageError), a lost cluster, ...: finished work is kept
        _resume_hint(args)
        raise
    _print_report(report)
    return 0


def _plan(wf, statuses: dict | None = None) -> str:
    """Every stage the workflow runs, in order, with its settings: each collection's, then each
    drive's, as the run's graph has them (:func:`persona.dag.graph.build`); with ``statuses``
    (:func:`persona.dag.graph.status`), each stage's status in the store too."""
    from .graph import build
    from .stages import STAGES

    graph = build(wf)

    def stages(target: str) -> list[str]:
        lines = []
        for node in graph.of(target):
            stage = STAGES[node.stage]
            state = f" [{statuses[node]}]" if statuses is not None else ""
            lines.append(f"    {stage.name:<14} {stage.makes} ({stage.runs}){state}")
            lines += [f"      {_setting(wf, kind)}" for kind in stage.settings]
        return lines

    lines = [f"workflow {wf.name}: store {wf.store}, output {wf.output}"]
    for plan in graph.collections:  # a video gives frames, not a 3D shape; a puppet's stages include the driver's
        lines.append(f"  {plan.path}: {plan.photos}")
        lines += stages(plan.path)
    for drive in graph.drives:
        c = drive.cast
        lines.append(f"  {c.drive}: {c.puppet} performing {c.frames} (driver model {c.driver}), frame by frame, "
                     f"into {drive.output}")
        lines += stages(c.drive)
    c = wf.cluster
    if c.kind == "local":
        lines.append(f"  cluster: {c.scheduler} (workers: {c.workers or 'one per core'})")
    else:
        lines.append(f"  cluster: {c.kind}, {c.jobs} job(s) of {c.cores} core(s) and {c.memory}, "
                     f"queue {c.queue or '(default)'}, walltime {c.walltime}")
    return "\n".join(lines)


def _cmd_plan(args) -> int:
    """The run's graph with each stage's status in the store: as text, JSON, or a picture (SVG, HTML)."""
    from persona.stores import media
    from persona.stores.layout import StoreError, open_store

    from . import api
    from .graph import build, status
    from .plan_view import page, svg

    wf = api.workflow(args.workflow, args.set)
    try:
        root = open_store(wf.store, mode="r")
    except StoreError:  # no store yet: every stage is to run
        root = None
    graph = build(wf)
    statuses = status(graph, root, wf)
    title = f"{wf.name}: {wf.store}"
    for file, text in ((args.html, page), (args.svg, svg)):
        if file:
            media.write_bytes(file, text(graph, statuses, title).encode())
            print(f"plan: {file}", file=sys.stderr)
    if args.json:
        print(json.dumps({"nodes": [{"stage": n.stage, "target": n.target, "status": statuses[n]} for n in graph.nodes],
                          "edges": [[str(a), str(b)] for a, b in graph.edges]}, indent=2))
    elif not (args.html or args.svg):
        print(_plan(wf, statuses))
    return 0


def _setting(wf, kind: str) -> str:
    """A stage kind's settings in the plan: its backend, if it has any, and its params."""
    from .workflow import BACKENDLESS

    if kind in BACKENDLESS:
        return f"{kind:<10} {json.dumps(wf.backendless(kind))}"
    if kind == "denoise" and kind not in wf.stages:
        return f"{kind:<10} (none: stages.denoise not set)"
    backend, params = wf.stage(kind)
    return f"{kind:<10} {backend} {json.dumps(params)}"


def _resolved_stages(wf) -> dict:
    """Every stage's settings with the defaults filled in: backend and params per backend kind, and
    the params of the stages without backends."""
    from persona.plugins.manager import default_registry

    from .workflow import BACKENDLESS

    stages = {name: {"params": wf.backendless(name)} for name in BACKENDLESS}
    for kind in default_registry().kinds():
        backend, params = wf.stage(kind)
        stages[kind] = {"backend": backend, "params": params}
    return stages


def _resume_hint(args) -> None:
    command = ["persona", "run", args.workflow, *sum((["--set", s] for s in args.set), [])]
    if args.scheduler:
        command += ["--scheduler", args.scheduler]
    if args.workers:
        command += ["--workers", str(args.workers)]
    print("\nThe run stopped. Finished work is kept in the store; resume with:\n  "
          + shlex.join(command), file=sys.stderr)


def _identity_line(ev: dict, key: str, of: str) -> str:
    """"B and not A" for the console, or why it is not judged (dlib sees B and A as one person: a
    self-reenactment), with the self-reenactment's PSNR where there is one."""
    from .report import identity_caveat

    if not identity_caveat(ev):
        return f"B and not A {ev['identity'][key]:.0%} {of}"
    own = ev.get("self_reenactment", {})
    psnr = (f"; self-reenactment {own['psnr_db_composite']:.1f} dB on the composite"
            if "psnr_db_composite" in own else "")
    why = "the puppet is the driver" if ev["identity"].get("judged") is False else "dlib sees B and A as one person"
    return f"B and not A: not judged ({why}){psnr}"


def _print_report(report: dict) -> None:
    for path, c in report["collections"].items():
        print(f"{path}: {c['accepted']} of {c['n_photos']} {item(path)}s aligned")
        for name, file in c["pictures"].items():
            print(f"  {name}: {file}")
    for name, file in report.get("videos", {}).items():
        print(f"{name} video: {file}")
    for name, d in report.get("drives", {}).items():  # a version-2 batch: a line per drive
        if "evaluation" not in d:
            print(f"{name}: failed: {d.get('error')}")
            continue
        ev = d["evaluation"]
        print(f"{name}: {_identity_line(ev, 'fraction_b_not_a_composite', 'of composite frames')}; gains "
              + ", ".join(f"{k.replace('_', ' ')} {a['gain']:.2f}" for k, a in ev["amplitude"].items())
              + f" — {d['report']}")
    if "evaluation" in report:
        ev = report["evaluation"]
        print(f"{_identity_line(ev, 'fraction_b_not_a', 'of frames')}; "
              f"mouth opening: correlation {ev['expression']['mouth_open']:.2f}, "
              f"gain {ev['amplitude']['mouth_open']['gain']:.2f} (1 = the driver's amplitude)")
    for warning in report.get("warnings", []):
        print(f"warning: {warning}")
    print(f"report: {report['report']}")


def _cmd_demo(args) -> int:
    from .demo import run_demo

    report = run_demo(Path(args.folder), n_photos=args.photos, n_frames=args.frames, workers=args.workers,
                      scheduler=args.scheduler, progress=not args.quiet)
    _print_report(report)
    return 0


def _cmd_evaluate(args) -> int:
    from persona.stores import lock
    from persona.stores.layout import open_store

    from .errors import RunError
    from .executor import executor_for
    from .runner import Runner
    from .workflow import load_workflow

    wf = load_workflow(args.workflow, args.set)
    if args.texture:
        return _evaluate_texture(wf, args)
    plans = wf.drive_plans()
    if not plans:
        raise RunError(f"{args.workflow} drives no puppet (no driver video): there is no output to evaluate")
    root = open_store(wf.store, mode="r")
    for plan in plans:
        drive = root.get(plan.cast.drive)
        if drive is None or drive.get("composite") is None:
            raise RunError(f"{wf.store} holds no composited output of {plan.cast.drive} yet: run "
                           f"`persona run {args.workflow}` first")
    results = {}
    with lock.writer(wf.store), executor_for(wf, args.scheduler, args.workers) as ex:  # it keeps the centroids
        runner = Runner(wf, ex, progress=False)
        for plan in plans:
            results[plan.name] = runner.evaluate(plan.cast)
            results[plan.name].pop("series")
            results[plan.name].pop("pictures", None)  # a self-reenactment's error map: a run's report shows it
    result = results.get("drive", {}) if wf.version == 1 else results  # version 2: by drive
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    _print_figures(result)
    return 0


def _print_figures(figures: dict, indent: str = "") -> None:
    for k, v in figures.items():
        if isinstance(v, dict):
            print(f"{indent}{k}:")
            _print_figures(v, indent + "  ")
        else:
            interval = isinstance(v, list) and v and all(isinstance(x, float) for x in v)
            shown = f"{v:.3f}" if isinstance(v, float) else " - ".join(f"{x:.3f}" for x in v) if interval else v
            print(f"{indent}{k:<24} {shown}")


def _refresh_report(wf) -> Path | str | None:
    """report.html made again with the texture evaluations now in the output folder, when the run
    left its metrics.json (and series.json, the plots) there; None when there is no run's report."""
    from persona.stores import storage
    from persona.stores.layout import open_store

    from .report import write_run_report

    metrics, series = storage.join(wf.output, "metrics.json"), storage.join(wf.output, "series.json")
    if not storage.isfile(metrics):
        return None
    series = json.loads(storage.read_text(series)) if storage.isfile(series) else None
    return write_run_report(wf, open_store(wf.store, mode="r"), json.loads(storage.read_text(metrics)), series)


def _texture_methods(value: str) -> tuple[str, ...]:
    from .texture_eval import METHODS

    names = tuple(v.strip() for v in value.split(",") if v.strip())
    unknown = [n for n in names if n not in METHODS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown texture method(s) {', '.join(unknown) or '(none)'}; "
                                         f"choose from {', '.join(METHODS)}")
    return tuple(m for m in METHODS if m in names)


def _evaluate_texture(wf, args) -> int:
    from persona.stores.layout import Collection, open_store

    from .errors import RunError
    from .executor import executor_for
    from .runner import Runner
    from .texture_eval import LABELS, evaluate_texture

    if not Collection(open_store(wf.store, mode="r"), args.collection).has("aligned/fiducials"):
        raise RunError(f"{wf.store} has no aligned faces in {args.collection!r}: run `persona run {args.workflow}` first")
    with executor_for(wf, args.scheduler, args.workers) as ex:
        result = evaluate_texture(Runner(wf, ex, progress=not args.json), args.collection, references=args.references,
                                  seed=args.seed, photos=args.photos, mode=args.mode,
                                  **({"methods": args.methods} if args.methods else {}))
    page = _refresh_report(wf)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{args.collection}: {len(result['references'])} held-out references, {result['collection_photos']} "
          f"photos, flow {result['methods'].get('multiscale', {}).get('flow', {}).get('backend', '-')}, target: "
          + ("each reference photo" if result["mode"] == "reference" else "each reference's fiducials"))
    print(f"  {'method':<16}{'alignment %IOD':>16}{'no face':>9}{'detail':>9}{'fidelity':>10}{'colour %':>10}")
    columns = (("alignment_median_pct_iod", 16, ".2f"), ("no_face_found", 9, "d"), ("detail_median", 9, ".3f"),
               ("fidelity_median", 10, ".3f"), ("colour_spread_pct", 10, ".2f"))
    for name, row in result["table"].items():
        cells = [format(row[key], f"{width}{fmt}") if row.get(key) is not None else f"{'-':>{width}}"
                 for key, width, fmt in columns]
        print(f"  {LABELS[name]:<16}" + "".join(cells))
    if result["paired_alignment"]:
        print("  alignment, ours minus the other on the same references (% IOD; negative: ours better)")
    for name, d in result["paired_alignment"].items():
        se = f" ± {d['standard_error']:.2f}" if d["standard_error"] is not None else ""
        print(f"  {LABELS[name]:<16}median {d['median']:+.2f}, mean {d['mean']:+.2f}{se}, "
              f"ours better on {d['ours_better']} of {d['references']}")
    if page is not None:
        print(f"report: {page}")
    print(f"  grid: {result['grid']}")
    return 0


def _cmd_validate(args) -> int:
    from .workflow import load_workflow

    from .inputs import resolve_inputs

    wf = load_workflow(args.workflow, args.set)
    counts = {path: len(sources) for path, sources in resolve_inputs(wf).items()}
    if args.json:
        print(json.dumps({"workflow": args.workflow, "valid": True, "counts": counts,
                          "resolved": {**wf.model_dump(mode="json"), "stages": _resolved_stages(wf)}}, indent=2))
        return 0
    print(f"{args.workflow}: valid; " + ", ".join(f"{path}: {n} {item(path)}s" for path, n in counts.items()))
    print(_plan(wf))
    return 0


def _cmd_schema(args) -> int:
    from .workflow import json_schema

    print(json.dumps(json_schema(), indent=2))
    return 0


def _default_params(registry, row: dict) -> dict:
    """A backend's default params for the text listing; a nested flow choice shows its backend."""
    try:
        values = registry.get(row["kind"], row["name"]).Params().model_dump(mode="json")
    except ValueError:  # a param without a default (a third-party backend's): the schema's defaults
        return {k: v.get("default") for k, v in row["params"].get("properties", {}).items()}
    return {k: v["backend"] if isinstance(v, dict) and "backend" in v else v for k, v in values.items()}


def _cmd_plugins(args) -> int:
    from persona.plugins.manager import default_registry

    registry = default_registry()
    rows = [info.describe() for info in registry.all()]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for kind in registry.kinds():
        print(f"{kind}:")
        for row in (r for r in rows if r["kind"] == kind):
            star = "*" if row["default"] else " "
            params = ", ".join(f"{k}={v!r}" for k, v in _default_params(registry, row).items())
            print(f"  {star} {row['name']:<12} {row['description']}  [{row['distribution']}]")
            if params:
                print(f"      params: {params}")
    for name, why in registry.broken.items():
        print(f"broken plugin {name}: {why}")
    print("(* = default)")
    return 0


def _cmd_inspect(args) -> int:
    from persona.stores.layout import StoreError, summarize

    if args.verify:
        return _verify(args)
    try:
        summary = summarize(args.store)
    except PersonaError:
        raise
    except Exception as exc:  # e.g. an array's zarr.json that is not JSON
        raise StoreError(f"{args.store} cannot be read whole ({type(exc).__name__}: {exc}): "
                         f"`persona inspect --verify {args.store}` names what is damaged") from exc
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"store {summary['store']}")
    for path, c in summary["collections"].items():
        print(f"\n{path}: {c['n_photos']} {item(path)}s — {c['accepted']} accepted, {c['rejected']} rejected"
              + (f", {c['pending']} pending" if c["pending"] else ""))
        for reason, count in c["rejected_by_reason"].items():
            print(f"  {count:5d} × {reason}")
        rejected = list(c["rejections"].items())
        for photo, reason in rejected[:20]:
            print(f"        {photo}: {reason}")
        if len(rejected) > 20:
            print(f"        ... and {len(rejected) - 20} more (--json lists all)")
        if c["attrs"]:
            print("  " + ", ".join(f"{k}: {v}" for k, v in c["attrs"].items()))
        if c["used_by"]:
            print(f"  used by: {', '.join(c['used_by'])}")
        print("  built: " + (", ".join(f"{stage} ({b['backend']})" if b["backend"] != "-" else stage
                                       for stage, b in c["built"].items()) or "nothing yet"))
        if c["unfinished"]:
            print(f"  unfinished (a run stopped while making them; the next run makes them again): "
                  f"{', '.join(c['unfinished'])}")
        for name, a in c["arrays"].items() if args.arrays else ():
            dims = ", ".join(f"{d}={s}" for d, s in zip(a["dims"], a["shape"]))
            print(f"    {name:<24} {a['dtype']:<10} ({dims})")
    return 0


def _verify(args) -> int:
    """``inspect --verify``: every chunk of every array read and its checksum checked; exit 1 when
    something is lost or damaged."""
    from dataclasses import asdict

    from persona.stores.layout import open_store
    from persona.stores.verify import affected, check

    root = open_store(args.store, mode="r")
    problems = check(root, read=True)
    stages = affected(root, problems)[1] if problems else []
    if args.json:
        print(json.dumps({"store": args.store, "problems": [asdict(p) for p in problems],
                          "would_recompute": stages}, indent=2))
        return 1 if problems else 0
    if not problems:
        print(f"store {args.store}: every chunk of every array is there and reads back intact")
        return 0
    print(f"store {args.store}: {len(problems)} problem{'s' * (len(problems) > 1)}")
    for p in problems:
        print(f"  {p}\n    file {args.store}/{p.chunk or p.array + '/zarr.json'}")
    print(f"would recompute: {', '.join(stages) or '(nothing done depends on them)'}")
    print("Run the workflow again: missing chunks are recomputed before the stages start, damaged ones when "
          "the run reads them. To recompute a damaged one for sure, delete its file first.")
    return 1


def _cmd_glb(args) -> int:
    """Every person's average face and every drive of a run as .glb files in ``--out``."""
    from persona.stores import storage

    from . import api

    run = api.open(args.source)
    chosen = set(args.only)
    unknown = chosen - set(run.people) - set(run.drives)
    if unknown:
        raise PersonaError(f"{', '.join(sorted(unknown))}: not a person or drive of {run.store}; its people: "
                           f"{', '.join(run.people) or '(none)'}; its drives: {', '.join(run.drives) or '(none)'}")
    out = args.out or (run.output or ".")
    for name, person in run.people.items():
        if (not chosen or name in chosen) and person.has_shape:
            path = person.glb(storage.join(out, f"{person.path.replace('/', '_')}_mesh.glb"))  # beside its OBJ
            print(f"{name}: {path} ({storage.stat(path)[0] / 2**20:.1f} MB)")
    for name, drive in run.drives.items():
        if not chosen or name in chosen:
            written = drive.glb(storage.join(out, f"{name}.glb"), step=args.step)
            print(f"{name}: {written['path']} ({written['frames']} frames at {written['fps']:g} fps, "
                  f"{written['vertices']} vertices, {written['bytes'] / 2**20:.1f} MB)")
    return 0


def _positive(value: str) -> int:
    if not value.isdigit() or int(value) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of 1 or more, got {value!r}")
    return int(value)


def _version() -> str:
    from .runner import persona_version

    return persona_version()


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Each option's default after its help (unless the help gives it, or there is none); the
    example in the epilog kept as written."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text or not action.option_strings or default is None or default is False
                or default == [] or default is argparse.SUPPRESS):
            return text
        return f"{text} (default: {action.default})"


def _docs() -> str:
    """The epilog's line on the documentation: README.md and docs/README.md (the index of every page)
    beside the source of an editable install, else their place in Persona's source (a wheel ships the
    code only)."""
    root = Path(__file__).resolve().parents[1]
    if (root / "docs" / "README.md").is_file():
        return f"Documentation: {root / 'README.md'}; every page, and who it is for: {root / 'docs' / 'README.md'}"
    return "Documentation: README.md and docs/README.md (every page, and who it is for) in Persona's source"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="persona", description=(
        "Build a controllable 3D face puppet from a photo collection and drive it with a video."),
        epilog="Start with: persona demo demo   (synthetic faces, every stage, a few minutes)\n"
               + _docs(),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, help: str, example: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".",
                              epilog=f"example:\n  {example}",
                              formatter_class=_HelpFormatter)

    def workflow(p):
        p.add_argument("workflow", help="the workflow YAML file (see workflows/ for examples)")

    def overrides(p):
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="override a workflow value, e.g. --set stages.landmarks.params.select=largest; "
                       "repeat for several")

    def common_run(p):
        p.add_argument("--scheduler", help='"local" (one worker per core on this machine), "sync" (in this '
                       "process) or a Dask scheduler address such as tcp://HOST:8786 (default: the "
                       "workflow's cluster; this replaces its scheduler and kind)")
        p.add_argument("--workers", type=int, help="local Dask workers (default: one per core)")
        p.add_argument("--quiet", action="store_true", help="no progress display")

    p = command("run", "run a workflow (resumes an interrupted run)", "persona run workflows/bush_driven_by_obama.yaml")
    workflow(p)
    overrides(p)
    p.add_argument("--dry-run", action="store_true", help="validate and print the plan, compute nothing")
    p.add_argument("--force", action="store_true", help="write into an output folder that holds files Persona "
                   "did not write (a run replaces metrics.json, report.html and the videos it makes)")
    common_run(p)
    p.set_defaults(func=_cmd_run)

    p = command("plan", "show the run's graph, every stage of every collection and drive and what each reads, "
                "with its status in the store (done, to run, failed); as a picture with --html or --svg",
                "persona plan workflows/fig8.yaml --html plan.html")
    workflow(p)
    overrides(p)
    p.add_argument("--html", metavar="FILE", help="write the graph as a self-contained HTML page")
    p.add_argument("--svg", metavar="FILE", help="write the graph as an SVG picture")
    p.add_argument("--json", action="store_true", help="print the nodes, their statuses and the edges as JSON")
    p.set_defaults(func=_cmd_plan)

    p = command("demo", "make synthetic faces and run every stage on them", "persona demo demo --photos 24")
    p.add_argument("folder", nargs="?", default="demo", help="where the demo data and results go")
    p.add_argument("--photos", type=int, default=24, help="photos per synthetic collection")
    p.add_argument("--frames", type=int, default=30, help="frames of the synthetic driving video")
    common_run(p)
    p.set_defaults(func=_cmd_demo)

    p = command("evaluate", "identity, expression and stability figures of a finished run; with --texture, "
                "leave-one-out scores of texture synthesis", "persona evaluate workflows/bush_driven_by_obama.yaml")
    workflow(p)
    p.add_argument("--texture", action="store_true", help="hold out reference photos and score every texture "
                   "method on them (paper Fig. 5): table and picture grid in the output folder")
    p.add_argument("--collection", default="puppet", help="--texture: the collection")
    p.add_argument("--references", type=int, default=40, help="--texture: held-out references")
    p.add_argument("--seed", type=int, default=0, help="--texture: seed of the references' draw")
    p.add_argument("--photos", type=int, help="--texture: synthesize from this many of the other photos, drawn at "
                   "random (default: all of them)")
    p.add_argument("--mode", choices=("reference", "fiducials"), default="reference", help="--texture: target the "
                   "reference photo itself (the paper's Fig. 5) or only its fiducials (as in puppetry)")
    p.add_argument("--methods", type=_texture_methods, default=None, help="--texture: comma-separated subset of "
                   "static,weighted,prewarped,multiscale (default: all four)")
    overrides(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    common_run(p)
    p.set_defaults(func=_cmd_evaluate)

    p = command("validate", "check a workflow without running it: its values, and every photo folder, video "
                "and frame range it names", "persona validate workflows/bush_driven_by_obama.yaml")
    workflow(p)
    overrides(p)
    p.add_argument("--json", action="store_true", help="print one JSON object: the workflow with every default "
                   "filled in, and the photos or frames of each collection")
    p.set_defaults(func=_cmd_validate)

    p = command("schema", "print the workflow JSON schema", "persona schema > workflow.schema.json")
    p.set_defaults(func=_cmd_schema)

    p = command("plugins", "list the installed backends", "persona plugins --json")
    p.add_argument("--json", action="store_true", help="print one JSON list, with each backend's params schema")
    p.set_defaults(func=_cmd_plugins)

    p = command("glb", "write each person's average face and each drive as glTF 2.0 binary files (.glb) that Blender "
                "and web viewers open: a drive moves frame by frame at the video's rate, its head posed",
                "persona glb workflows/fig8.yaml --only bush_obama_address")
    p.add_argument("source", help="the workflow YAML file, or the run's Zarr store")
    p.add_argument("--out", help="the folder for the .glb files (default: the workflow's output folder; with a store, "
                   "the current folder)")
    p.add_argument("--only", action="append", default=[], metavar="NAME",
                   help="only this person or drive (repeat for several); `persona inspect` lists them")
    p.add_argument("--step", type=_positive, default=2, help="a drive's mesh keeps every STEP-th point of the face's grid "
                   "across and down: 2 keeps a quarter (a 300-frame drive is about 17 MB), 1 every point (4 times "
                   "the size)")
    p.set_defaults(func=_cmd_glb)

    p = command("inspect", "summarise a store: each person, video and drive, its accepted and rejected photos, "
                "the stages that built it and the drives that use it; with --verify, check every chunk",
                "persona inspect runs/bush_obama.zarr")
    p.add_argument("store", help="the run's Zarr store (the workflow's store:)")
    p.add_argument("--verify", action="store_true", help="read every chunk of every array and check its checksum; "
                   "list what is missing or damaged (array, shard, photos) and the stages a run would "
                   "recompute; exit 1 when there is any")
    p.add_argument("--arrays", action="store_true", help="also list every array: name, dtype, dimensions")
    p.add_argument("--json", action="store_true", help="print one JSON object (arrays included)")
    p.set_defaults(func=_cmd_inspect)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (PersonaError, PluginError, Rejected) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `persona plugins | head`
        return 0


if __name__ == "__main__":
    sys.exit(main())
