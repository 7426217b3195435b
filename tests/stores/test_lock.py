"""One writer per store: a second run stops at once naming the first; a lock left by a killed run is
taken over; the same in object storage (a moto S3 server on loopback)."""

import json
import logging
import socket
import subprocess
import sys
import time

import pytest

from persona.stores import lock, storage

from pipeline import write_workflow


def _leave(url, **fields) -> None:
    """A lock file as a run leaves it, with ``fields`` over a live one of this process."""
    held = {"host": socket.gethostname(), "pid": 1, "token": "other", "since": "2026-12-02T04:00:00+00:00",
            "renewed": time.time(), **fields}
    with storage.open_file(storage.join(url, lock.NAME), "w") as f:
        f.write(json.dumps(held))


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid  # ended and reaped: no process has it (for a while)


def test_a_second_writer_stops_at_once_naming_the_first(tmp_path):
    url = str(tmp_path / "run.zarr")
    with lock.writer(url) as me:
        with pytest.raises(lock.StoreLocked, match=rf"process {me['pid']} on {socket.gethostname()}, since "):
            with lock.writer(url):
                pass
        assert lock.holder(url)["token"] == me["token"]  # the refused run did not touch it
    assert lock.holder(url) is None  # given back at the end


def test_the_lock_is_given_back_when_the_run_fails(tmp_path):
    url = str(tmp_path / "run.zarr")
    with pytest.raises(RuntimeError), lock.writer(url):
        raise RuntimeError("a stage failed")
    assert lock.holder(url) is None


@pytest.mark.parametrize("written", [0.5, 1.0])
def test_a_stop_while_the_lock_is_taken_gives_it_back(tmp_path, monkeypatch, written):
    """A SIGTERM or Ctrl-C in the moment the lock is written (cut short half way) or read back leaves no lock."""
    url = str(tmp_path / "run.zarr")

    def write_then_stop(url, held):
        text = json.dumps(held)
        with storage.open_file(storage.join(url, lock.NAME), "w") as f:
            f.write(text[: int(len(text) * written)])
        raise KeyboardInterrupt

    monkeypatch.setattr(lock, "_write", write_then_stop)
    with pytest.raises(KeyboardInterrupt), lock.writer(url):
        pass
    assert not (tmp_path / "run.zarr" / lock.NAME).exists()


def test_a_lock_file_cut_short_by_a_kill_is_taken_over(tmp_path, caplog):
    url = str(tmp_path / "run.zarr")
    tmp_path.joinpath("run.zarr").mkdir()
    tmp_path.joinpath("run.zarr", lock.NAME).write_text('{"host": "')
    with caplog.at_level(logging.WARNING, logger="persona.stores.lock"), lock.writer(url) as me:
        assert lock.holder(url)["token"] == me["token"]
    assert "a lock file cut short" in caplog.text and lock.holder(url) is None


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path, caplog):
    """A process of this machine that is gone, at once; another machine's, once it has not renewed its lock
    for ``STALE`` seconds, and not before."""
    url = str(tmp_path / "run.zarr")
    tmp_path.joinpath("run.zarr").mkdir()
    _leave(url, pid=_dead_pid())
    with caplog.at_level(logging.WARNING, logger="persona.stores.lock"), lock.writer(url) as me:
        assert lock.holder(url)["token"] == me["token"]
    assert "no longer runs" in caplog.text
    _leave(url, host="elsewhere", renewed=time.time() - 10)
    with pytest.raises(lock.StoreLocked, match="on elsewhere"), lock.writer(url):
        pass
    _leave(url, host="elsewhere", renewed=time.time() - lock.STALE - 1)
    with lock.writer(url):
        pass


def test_persona_run_on_a_locked_store_stops_before_any_work(tmp_path, capsys):
    from persona.dag.cli import main

    tmp_path.joinpath("photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes(b"")
    path = write_workflow(tmp_path, "photos")
    url = str(tmp_path / "run.zarr")
    with lock.writer(url):
        assert main(["run", str(path), "--scheduler", "sync", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "is being written by another run" in err and "resume with" not in err
    assert sorted(p.name for p in (tmp_path / "run.zarr").iterdir()) == []  # nothing created in it


def test_one_writer_in_object_storage(s3_bucket):
    url = f"s3://{s3_bucket[0]}/run.zarr"
    with lock.writer(url) as me:
        assert lock.holder(url)["token"] == me["token"]
        with pytest.raises(lock.StoreLocked), lock.writer(url):
            pass
    assert lock.holder(url) is None
