import pytest

from persona.dag.workflow import WorkflowError, load_workflow, parse_workflow


def write(tmp_path, text, name="wf.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD = """
version: 1
name: t
store: out/run.zarr
output: out
puppet: {photos: photos}
stages:
  landmarks: {backend: dlib, params: {select: largest}}
"""


def test_relative_paths_resolve_against_the_workflow_folder(tmp_path):
    (tmp_path / "sub").mkdir()
    wf = load_workflow(write(tmp_path / "sub", GOOD))
    assert wf.store == str((tmp_path / "sub" / "out" / "run.zarr").resolve())
    assert wf.puppet.photos == str((tmp_path / "sub" / "photos").resolve())
    name, params = wf.stage("landmarks")
    assert name == "dlib" and params["select"] == "largest"
    assert params["upsample"] == 0  # defaults filled in
    assert wf.stage("pose")[0] == "pnp"


def test_every_error_reported_at_once_with_paths_and_suggestions(tmp_path):
    text = """
version: 1
name: t
stor: x.zarr
output: out
puppet: {photos: p, vidoe: v.mp4}
stages:
  landmarks: {backend: dlb}
  pose: {params: {focal_factr: 1.0}}
  frontalise: {}
cluster: {scheduler: nowhere}
"""
    with pytest.raises(WorkflowError) as info:
        load_workflow(write(tmp_path, text))
    errors = dict(info.value.errors)
    assert 'Did you mean "store"' in errors["stor"]
    assert "store" in errors  # missing required key
    assert 'Did you mean "video"' in errors["puppet.vidoe"]
    assert 'Did you mean "dlib"' in errors["stages.landmarks.backend"]
    assert 'Did you mean "focal_factor"' in errors["stages.pose.params.focal_factr"]
    assert 'Did you mean "frontalize"' in errors["stages.frontalise"]
    assert "cluster.scheduler" in errors
    message = str(info.value)
    assert message.count("\n") >= 7  # one line per error


def test_invalid_yaml_names_line_and_column(tmp_path):
    with pytest.raises(WorkflowError, match=r"invalid YAML at line 3, column 8: mapping values"):
        load_workflow(write(tmp_path, "version: 1\nname: t\n  store: x\n"))


@pytest.mark.parametrize("text, expected", [
    ("", "empty"),
    ("- a\n- b\n", "mapping"),
])
def test_not_a_workflow(tmp_path, text, expected):
    with pytest.raises(WorkflowError, match=expected):
        load_workflow(write(tmp_path, text))


def test_missing_file(tmp_path):
    with pytest.raises(WorkflowError, match="no such file"):
        load_workflow(tmp_path / "nope.yaml")


def test_overrides(tmp_path):
    wf = load_workflow(write(tmp_path, GOOD), ["cluster.workers=3", "stages.landmarks.params.upsample=2"])
    assert wf.cluster.workers == 3
    assert wf.stage("landmarks")[1]["upsample"] == 2
    with pytest.raises(WorkflowError, match="upsample"):
        load_workflow(write(tmp_path, GOOD), ["stages.landmarks.params.upsample=9"])


def test_ingest_takes_params_but_no_backend():
    base = {"version": 1, "name": "t", "store": "s", "output": "o", "puppet": {"photos": "p"}}
    wf = parse_workflow({**base, "stages": {"ingest": {"params": {"max_side": 800}}}})
    assert wf.stages["ingest"].params == {"max_side": 800}
    with pytest.raises(WorkflowError, match="no backends"):
        parse_workflow({**base, "stages": {"ingest": {"backend": "x"}}})
    with pytest.raises(WorkflowError, match='Did you mean "max_side"'):
        parse_workflow({**base, "stages": {"ingest": {"params": {"max_sid": 800}}}})


def test_the_transfers_params_where_they_were_are_the_transfer_kinds():
    """``stages.motion.params.transfer`` is still read: as ``stages.transfer.params`` (the transfer kind's, its
    default backend's), once; given in both places it is an error."""
    base = {"version": 1, "name": "t", "store": "s", "output": "o", "puppet": {"photos": "p"}}
    data = {**base, "stages": {"motion": {"params": {"pose_sigma": 1.0, "transfer": {"fiducial_sigma": 2.0}}}}}
    wf = parse_workflow(data)
    assert wf.stage("transfer") == parse_workflow({**base, "stages": {"transfer": {"params": {
        "fiducial_sigma": 2.0}}}}).stage("transfer")
    assert wf.stage("transfer")[0] == "deformation" and wf.backendless("motion")["pose_sigma"] == 1.0
    assert "transfer" in data["stages"]["motion"]["params"]  # the caller's data as it was
    with pytest.raises(WorkflowError, match="give it once"):
        parse_workflow({**base, "stages": {"transfer": {"params": {"fiducials": 0.5}},
                                           "motion": {"params": {"transfer": {"fiducials": 0.0}}}}})


def test_video_range_and_lists():
    base = {"version": 1, "name": "t", "store": "s", "output": "o"}
    wf = parse_workflow({**base, "puppet": {"photos": {"video": "v.mov", "stop": 900}},
                         "driver": {"photos": ["a.jpg", "b.jpg"], "video": {"video": "v.mov", "start": 900}}},
                        base_dir="/data")
    assert wf.puppet.photos.video == "/data/v.mov" and wf.puppet.photos.stop == 900
    assert wf.driver.photos == ["/data/a.jpg", "/data/b.jpg"]
    assert wf.driver.video.start == 900


def test_shipped_workflows_validate():
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "workflows"
    files = sorted(folder.glob("*.yaml"))
    assert len(files) >= 2
    for path in files:
        load_workflow(path)


def test_misspelt_key_inside_a_stage_gets_a_suggestion():
    base = {"version": 1, "name": "t", "store": "s", "output": "o", "puppet": {"photos": "p"}}
    with pytest.raises(WorkflowError) as info:
        parse_workflow({**base, "stages": {"landmarks": {"bakend": "dlib"}}, "cluster": {"schedular": "x"}})
    errors = dict(info.value.errors)
    assert 'Did you mean "backend"' in errors["stages.landmarks.bakend"]
    assert 'Did you mean "scheduler"' in errors["cluster.schedular"]


def test_storage_options_are_validated_and_their_secrets_never_printed():
    from persona.stores import storage

    base = {"version": 1, "name": "t", "store": "s3://bucket/run.zarr", "output": "s3://bucket/out",
            "puppet": {"photos": "s3://bucket/photos/*.jpg"}}
    with pytest.raises(WorkflowError) as err:
        parse_workflow({**base, "storage_options": {"endpoint_url": "127.0.0.1:9000", "secert": "s"}})
    assert "storage_options.endpoint_url: Value error" in str(err.value) and "http://" in str(err.value)
    assert 'storage_options.secert: unknown key "secert". Did you mean "secret"?' in str(err.value)
    wf = parse_workflow({**base, "storage_options": {"endpoint_url": "http://127.0.0.1:9000", "key": "AKIA1",
                                                     "secret": "shh", "region": "eu-central-1"}})
    assert wf.store == "s3://bucket/run.zarr" and wf.puppet.photos == "s3://bucket/photos/*.jpg"  # URLs as given
    printed = f"{wf!r} {wf.model_dump(mode='json')} {wf.model_dump_json()}"
    assert "AKIA1" not in printed and "shh" not in printed
    assert storage.options("s3://bucket/x") == {"endpoint_url": "http://127.0.0.1:9000", "key": "AKIA1", "secret": "shh",
                                                "client_kwargs": {"region_name": "eu-central-1"}}
    assert storage.options("/local/path") == {} and storage.options("gs://b/x") == {}
    parse_workflow(base)  # none given: the environment's (AWS_* variables)
    assert storage.options("s3://bucket/x") == {}
