import json
import subprocess
import sys
from pathlib import Path

import pytest

from persona.dag.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]


def test_plugins_json_lists_backends_with_schema_and_distribution(capsys):
    assert cli(["plugins", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    by_name = {(r["kind"], r["name"]): r for r in rows}
    for key in [("landmarks", "dlib"), ("landmarks", "sidecar"), ("pose", "pnp"), ("frontalize", "template")]:
        row = by_name[key]
        assert {"kind", "name", "description", "params", "distribution"} <= set(row)
        assert row["params"]["type"] == "object"
        assert row["distribution"].startswith("persona")
    assert by_name[("landmarks", "dlib")]["params"]["properties"]["select"]["default"] == "center"


def test_plugins_text(capsys):
    assert cli(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "landmarks:" in out and "* dlib" in out
    assert "flow='varref'" in out  # a nested flow choice shows its backend


def test_schema_is_json_schema(capsys):
    assert cli(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert {"store", "puppet", "stages", "cluster"} <= set(schema["properties"])
    motion = schema["x-stage-params"]["motion"]  # the params of the stages without backends, documented
    assert {"dynamics", "flow", "correspondence", "transfer"} <= set(motion["properties"])
    assert "landmark_guide" in motion["$defs"]["DynamicsParams"]["properties"]


def test_validate_reports_errors_and_exit_code(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\nstore: s\noutput: o\npupet: {photos: p}\n")
    assert cli(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert 'pupet: unknown key "pupet". Did you mean "puppet"?' in err
    # a flow chosen inside a stage's params: errors at their own path, with a suggestion
    bad.write_text("version: 1\nname: x\nstore: s\noutput: o\npuppet: {photos: p}\nstages:\n"
                   "  texture: {params: {flow: {backend: varef}}}\n"
                   "  motion: {params: {correspondence: {backend: liu, params: {alpha: -1}}}}\n")
    assert cli(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert 'stages.texture.params.flow.backend: Value error, unknown flow backend "varef". Did you mean "varref"?' in err
    assert "stages.motion.params.correspondence.params: Value error, alpha: Input should be greater than 0" in err
    assert cli(["validate", str(ROOT / "workflows" / "bush_driven_by_obama.yaml")]) == 0
    assert "landmarks  dlib" in capsys.readouterr().out


def test_console_script_is_installed():
    exe = Path(sys.executable).with_name("persona")
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, check=True).stdout
    assert "run" in out and "inspect" in out


@pytest.mark.slow
def test_a_normal_install_puts_only_the_persona_package_in_site_packages(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                    "--target", str(tmp_path), str(ROOT)], check=True, capture_output=True)
    top = sorted(p.name for p in tmp_path.iterdir() if not p.name.endswith(".dist-info"))
    assert top == ["bin", "persona"] or top == ["persona"], top
    assert sorted(p.name for p in (tmp_path / "persona").iterdir() if p.is_dir() and p.name != "__pycache__") == [
        "dag", "plugins", "stores"]
    assert (tmp_path / "persona" / "plugins" / "builtin" / "landmarks.py").is_file()
