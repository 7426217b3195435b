"""The run's graph (persona.dag.graph): its nodes and edges for a workflow, each node's status in a
store, the picture `persona plan` draws, and a stage added to the list that the run then runs."""

import contextlib
import io
import shutil
import xml.etree.ElementTree as ET

import pytest
import yaml

from example_stage import BRIGHTNESS
from persona.dag import stages as st
from persona.dag.cli import main as cli
from persona.dag.demo import make_demo_data
from persona.dag.graph import DONE, TO_RUN, Node, build, status
from persona.dag.plan_view import page, svg
from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow
from persona.stores.layout import open_store


@contextlib.contextmanager
def added(stage: st.Stage, before: str):
    """``stage`` in the list of stages, just before the stage ``before``, for the time of the block."""
    saved = dict(st.STAGES)
    st.STAGES.clear()
    for name, each in saved.items():
        if name == before:
            st.STAGES[stage.name] = stage
        st.STAGES[name] = each
    try:
        yield
    finally:
        st.STAGES.clear()
        st.STAGES.update(saved)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A small 2D drive of synthetic faces, run with the example stage ``brightness`` in the list."""
    folder = tmp_path_factory.mktemp("plan")
    path = make_demo_data(folder, n_photos=10, n_frames=8)
    wf = yaml.safe_load(path.read_text())
    wf["photos_per_shard"] = 4
    wf.setdefault("stages", {})["render"] = {"backend": "tps2d"}
    path.write_text(yaml.safe_dump(wf))
    with added(BRIGHTNESS, before="videos"), contextlib.redirect_stderr(io.StringIO()):
        run_workflow(load_workflow(path), scheduler="sync", progress=False)
    return folder, path


def test_the_graph_has_every_person_video_and_drive_and_what_each_stage_reads(tmp_path):
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump({
        "version": 2, "name": "two", "store": "s.zarr", "output": "out",
        "people": {"ann": {"photos": "ann"}, "bob": {"photos": "bob"}},
        "drives": [{"puppet": ["ann", "bob"], "driver": "bob", "video": "clip.mp4"}],
        "stages": {"render": {"backend": "tps2d"}}}))
    wf = load_workflow(path)
    graph = build(wf)
    assert list(dict.fromkeys(n.target for n in graph.nodes)) == [
        "people/ann", "people/bob", "videos/clip", "drives/ann_bob_clip", "drives/bob_bob_clip"]
    assert [n.stage for n in graph.of("videos/clip")] == ["ingest", "landmarks", "pose", "frontalize", "screen", "mean"]
    assert "texture" in {n.stage for n in graph.of("people/ann")}  # a puppet
    assert not {"dynamics", "motion", "mouth", "teeth"} & {n.stage for n in graph.nodes}  # a 2D render
    edges = set(graph.edges)
    drive = "drives/ann_bob_clip"
    assert (Node("screen", "videos/clip"), Node("retarget", drive)) in edges
    assert (Node("mean", "people/ann"), Node("retarget", drive)) in edges
    assert (Node("texture", "people/ann"), Node("frame textures", drive)) in edges
    assert (Node("render", drive), Node("light", drive)) in edges
    order = {node: i for i, node in enumerate(graph.nodes)}
    assert all(order[a] < order[b] for a, b in graph.edges)  # the run's order follows every edge
    assert {n.stage for n in build(wf.model_copy(update={"stages": {}})).nodes} >= {"dynamics", "motion", "mouth"}


def test_a_stage_added_to_the_list_runs_once_and_then_is_done(small_run):
    folder, path = small_run
    drive = open_store(str(folder / "run.zarr"), mode="r")["drive"]
    made = drive["example/brightness"].attrs["provenance"]
    assert made["stage"] == "brightness" and drive["example/brightness"].shape == (8,)
    with added(BRIGHTNESS, before="videos"), contextlib.redirect_stderr(io.StringIO()):
        assert Node("brightness", "drive") in build(load_workflow(path)).nodes
        run_workflow(load_workflow(path), scheduler="sync", progress=False)
    again = open_store(str(folder / "run.zarr"), mode="r")["drive/example/brightness"].attrs["provenance"]
    assert again["created"] == made["created"]  # done: not made again


def test_the_plan_reads_each_stages_status_from_the_store_and_draws_one_node_each(small_run, tmp_path, capsys):
    folder, path = small_run
    wf = load_workflow(path)
    graph = build(wf)
    statuses = status(graph, open_store(wf.store, mode="r"), wf)
    assert set(statuses.values()) == {DONE}
    # a copy of the store whose light planes were lost: the light and all after it are to run again
    copy = tmp_path / "copy.zarr"
    shutil.copytree(folder / "run.zarr", copy)
    root = open_store(str(copy))
    del root["drive/composite/light"].attrs["provenance"]
    wf = load_workflow(path, [f"store={copy}"])
    statuses = status(graph, open_store(str(copy), mode="r"), wf)
    assert {n.stage for n, s in statuses.items() if s == TO_RUN} == {"light", "composite", "videos", "evaluate"}
    picture = ET.fromstring(svg(graph, statuses, "small"))
    nodes = [g for g in picture.iter("{http://www.w3.org/2000/svg}g") if g.get("class") == "node"]
    assert len(nodes) == len(graph.nodes)
    assert {(g.get("data-stage"), g.get("data-target"), g.get("data-status")) for g in nodes} == {
        (n.stage, n.target, s) for n, s in statuses.items()}
    edges = [p for p in picture.iter("{http://www.w3.org/2000/svg}path") if p.get("class") == "edge"]
    assert len(edges) == len(graph.edges)
    assert "http" not in page(graph, statuses, "small").replace("http://www.w3.org/2000/svg", "")  # nothing fetched
    out = tmp_path / "plan.html"
    assert cli(["plan", str(path), "--set", f"store={copy}", "--html", str(out)]) == 0
    assert out.read_text().count('class="node"') == len(graph.nodes)
    assert cli(["plan", str(path), "--set", f"store={copy}"]) == 0
    assert "    light" in capsys.readouterr().out
