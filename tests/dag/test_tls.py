"""A scheduler that speaks TLS: a run with the workflow's certificates gets in and gives the store
a run in one process gives; without them it is refused, with a message that says what to give."""

import pytest
import yaml

from persona.dag.cli import main as cli
from persona.dag.errors import RunError
from persona.dag.runner import run_workflow
from persona.dag.workflow import WorkflowError, load_workflow
from pipeline import assert_same_store, make_certificates, write_photos, write_workflow


def test_a_tls_scheduler_runs_the_workflow_with_its_certificates_only(tmp_path, synthetic_photos, tls_cluster):
    address, files = tls_cluster
    photos = write_photos(tmp_path / "photos", synthetic_photos[:8])
    remote, local = tmp_path / "remote", tmp_path / "local"
    for folder in (remote, local):
        folder.mkdir()
    write_workflow(remote, str(photos), cluster={"scheduler": address, "tls": files})
    write_workflow(local, str(photos))
    assert cli(["run", str(remote / "wf.yaml"), "--quiet"]) == 0
    run_workflow(load_workflow(local / "wf.yaml"), scheduler="sync", progress=False)
    assert_same_store(remote / "run.zarr", local / "run.zarr")

    with pytest.raises(RunError, match=r"speaks TLS: give this machine's certificate as cluster\.tls"):
        run_workflow(load_workflow(local / "wf.yaml"), scheduler=address, progress=False)  # none at all
    stranger = make_certificates(tmp_path / "another CA")  # a certificate the cluster's CA did not sign
    write_workflow(remote, str(photos), cluster={"scheduler": address, "tls": stranger})
    with pytest.raises(RunError, match=r"cannot reach the Dask scheduler at tls://.*cluster\.tls"):
        run_workflow(load_workflow(remote / "wf.yaml"), progress=False)


def test_tls_settings_are_checked_before_anything_runs(tmp_path):
    path = write_workflow(tmp_path, "photos", cluster={"scheduler": "tls://127.0.0.1:8786"})
    with pytest.raises(WorkflowError, match=r"speaks TLS: give this machine's certificate as cluster\.tls"):
        load_workflow(path)
    files = {"ca_file": "ca.pem", "cert": "cert.pem", "key": "key.pem"}
    (tmp_path / "ca.pem").write_text("")
    (tmp_path / "key.pem").write_text("")
    wf = yaml.safe_load(path.read_text())
    wf["cluster"]["tls"] = files
    path.write_text(yaml.safe_dump(wf))
    with pytest.raises(WorkflowError, match=r"cluster\.tls\.cert: .*cert\.pem is not a file"):
        load_workflow(path)
    wf["cluster"]["scheduler"] = "tcp://127.0.0.1:8786"
    path.write_text(yaml.safe_dump(wf))
    with pytest.raises(WorkflowError, match=r"tls is for a scheduler address of tls://"):
        load_workflow(path)
