import json
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from persona.dag.cli import main as cli
from persona.dag.runner import persona_version

from pipeline import write_workflow

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
    assert {"dynamics", "flow", "correspondence"} <= set(motion["properties"])
    assert "transfer" not in motion["properties"]  # the transfer kind's backend's params (persona plugins)
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
    if (ROOT.parent / "shared" / "data").is_dir():  # the example's photos are there to count
        assert cli(["validate", str(ROOT / "workflows" / "bush_driven_by_obama.yaml")]) == 0
        out = capsys.readouterr().out
        assert "landmarks  dlib" in out and "puppet: 530 photos" in out and "driver/frames: 1169 frames" in out


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


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        cli(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"persona {persona_version()}"


@pytest.mark.parametrize("case", ["missing folder", "empty folder", "missing video", "text named .mp4",
                                  "photo as video"])
def test_bad_inputs_stop_the_run_before_any_work(tmp_path, capsys, case):
    """Each bad input is a one-line error naming it, from `validate` and from `run`, within seconds,
    with no store or output created and no advice to resume (running again cannot help)."""
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), np.zeros((64, 64, 3), np.uint8))
    (tmp_path / "empty").mkdir()
    (tmp_path / "clip.mp4").write_text("not a video\n")
    puppet, video, named = {"missing folder": ("nowhere", "clip.mp4", "nowhere"),
                            "empty folder": ("empty", "clip.mp4", "empty"),
                            "missing video": ("photos", "gone.mp4", "gone.mp4"),
                            "text named .mp4": ("photos", "clip.mp4", "clip.mp4"),
                            "photo as video": ("photos", "photos/a.png", "a.png")}[case]
    workflow = tmp_path / "w.yaml"
    workflow.write_text(f"version: 1\nname: x\nstore: s.zarr\noutput: out\npuppet: {{photos: {puppet}}}\n"
                        f"driver: {{photos: photos, video: {video}}}\n")
    for command in (["validate", str(workflow)], ["run", str(workflow), "--quiet"]):
        start = time.perf_counter()
        assert cli(command) == 2
        seconds = time.perf_counter() - start
        err = capsys.readouterr().err
        assert err.startswith("error: ") and named in err and "Traceback" not in err, err
        assert "resume" not in err and "Errno" not in err, err
        assert seconds < 5, seconds
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "empty", "photos", "w.yaml"]


def test_too_few_photos_for_a_3d_puppet_is_a_message_that_says_what_to_do(tmp_path, capsys):
    """Three photos per person: no traceback (the subspace used to fail reshaping an array), but
    a one-line error that says how many photos were usable, how many are needed, and the 2D way
    out; the same run with the 2D renderer finishes."""
    from persona.dag.demo import make_demo_data

    workflow = make_demo_data(tmp_path, n_photos=3, n_frames=4)
    assert cli(["run", str(workflow), "--quiet", "--scheduler", "sync"]) == 2
    err = capsys.readouterr().err
    assert err.count("error: ") == 1 and "Traceback" not in err and "resume" not in err, err
    assert re.search(r"[0-3] usable photos of 3", err) and "needs at least 5" in err and "tps2d" in err, err
    assert cli(["run", str(workflow), "--quiet", "--scheduler", "sync",
                "--set", "stages.render.backend=tps2d"]) == 0


def test_every_command_explains_its_arguments_with_defaults_and_an_example(capsys):
    """`persona COMMAND --help`: every positional and option has a help text, options with a default
    show it, and an example closes the page."""
    from persona.dag.cli import build_parser

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices  # argparse keeps them there
    for name, sub in commands.items():
        for action in sub._actions:
            assert action.help, (name, action.dest)
        with pytest.raises(SystemExit):
            cli([name, "--help"])
        page = capsys.readouterr().out
        assert "example:\n  persona " + name in page, name
    with pytest.raises(SystemExit):
        cli(["evaluate", "--help"])
    page = capsys.readouterr().out
    assert "(default: 40)" in page and "(default: 0)" in page


def test_validate_json_gives_the_resolved_workflow_and_the_counts(tmp_path, capsys):
    (tmp_path / "p").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "p" / f"{i}.png"), np.zeros((64, 64, 3), np.uint8))
    workflow = tmp_path / "w.yaml"
    workflow.write_text("version: 1\nname: x\nstore: s.zarr\noutput: out\npuppet: {photos: p}\n")
    assert cli(["validate", str(workflow), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["valid"] and out["counts"] == {"puppet": 3}
    assert out["resolved"]["stages"]["landmarks"]["backend"] == "dlib"  # defaults filled in


def test_a_store_whose_root_is_damaged_stops_with_what_to_do_and_no_resume_advice(tmp_path, capsys):
    """A run cannot mend a store whose root zarr.json is not JSON: the message says what will (restore it, or
    move the store aside), and the "resume with" advice, which would fail the same way, is not given."""
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes(b"")
    (tmp_path / "run.zarr").mkdir()
    (tmp_path / "run.zarr" / "zarr.json").write_text("{ not json")
    assert cli(["run", str(write_workflow(tmp_path, "photos")), "--scheduler", "sync", "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "move the store aside" in captured.err and "resume with" not in captured.out + captured.err


def test_the_console_does_not_judge_identity_where_dlib_sees_one_person():
    """A self-reenactment's summary line gives its PSNR, not "B and not A 0%", which would read as a failure."""
    from persona.dag.cli import _identity_line

    same = {"identity": {"mean_distance_to_a": 0.39, "mean_distance_to_b": 0.39, "fraction_b_not_a": 0.0},
            "self_reenactment": {"psnr_db_composite": 26.78}}
    line = _identity_line(same, "fraction_b_not_a", "of frames")
    assert "not judged" in line and "26.8 dB" in line and "0%" not in line
    apart = {"identity": {"mean_distance_to_a": 0.8, "mean_distance_to_b": 0.4, "fraction_b_not_a": 1.0}}
    assert _identity_line(apart, "fraction_b_not_a", "of frames") == "B and not A 100% of frames"
