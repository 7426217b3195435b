"""Helpers for pipeline tests: synthetic collections on disk, workflows, store comparison."""

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml

from persona.dag.demo import write_collection
from persona.stores.layout import open_store

PERSONA = str(Path(sys.executable).with_name("persona"))
#: a progress line (persona.dag.progress._Lines): "12:00:01 people/bea landmarks: started: 8 photos"; two build threads can
#: print on one line, so they are found anywhere in it
EVENT = re.compile(r"\d\d:\d\d:\d\d (\S+) ([a-z0-9. ]+?): (started|done|stopped)\b")


def write_photos(folder: Path, photos) -> Path:
    """Synthetic photos as PNGs with their ground-truth landmark sidecars, as the demo writes them."""
    write_collection(folder, photos)
    return folder


def write_quick_people(data: Path, people: dict[str, tuple[int, int]], video: str, frames: int) -> None:
    """Synthetic photo collections in ``data``, ``people`` by folder name (name -> (photos, seed)), and a driving
    video ``data/<video>.mp4`` of ``frames`` frames (seed 2, the demo driver's identity), all drawn without
    antialiasing: 2.5 times faster, and dlib finds them as well."""
    from persona.dag.demo import driver_identity
    from persona.plugins.face import synthetic
    from persona.stores import media

    for name, (n, seed) in people.items():
        write_collection(data / name, synthetic.make_collection(n, seed=seed, supersample=1))
    clip = synthetic.make_driver_video(frames, seed=2, identity=driver_identity(0), supersample=1)
    media.write_video_mp4(data / f"{video}.mp4", (frame.image for frame in clip), fps=25)


def write_workflow(folder: Path, photos: str, **extra) -> Path:
    wf = {"version": 1, "name": folder.name, "store": "run.zarr", "output": "out",
          "puppet": {"photos": photos}, "photos_per_shard": 4, **extra}
    path = folder / "wf.yaml"
    path.write_text(yaml.safe_dump(wf))
    return path


def store_arrays(url) -> dict[str, np.ndarray]:
    """Every array of a store by path (attrs ignored: they carry creation times)."""
    out = {}

    def walk(group, prefix):
        for name, arr in group.arrays():
            out[prefix + name] = arr[...]
        for name, child in group.groups():
            walk(child, prefix + name + "/")

    walk(open_store(url, mode="r"), "")
    return out


def assert_same_store(a, b, within: tuple[str, ...] = ()):
    """Store ``a`` has every array of store ``b`` and no other, each equal (float ones to 1e-6). ``within``:
    only the arrays of ``b`` under these groups (``a`` made only some of what ``b`` holds)."""
    left, right = store_arrays(a), store_arrays(b)
    if within:
        right = {name: array for name, array in right.items() if name.startswith(tuple(f"{g}/" for g in within))}
    assert sorted(left) == sorted(right)
    for name in left:
        x, y = left[name], right[name]
        if name.endswith("photos/source"):
            continue  # absolute paths differ between the two runs' folders
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6, equal_nan=True, err_msg=name)
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)


def make_certificates(folder: Path) -> dict[str, str]:
    """A CA made with openssl, and one certificate it signs: {ca_file, cert, key} (PEM files)."""
    folder.mkdir(parents=True)
    files = {"ca_file": folder / "ca.pem", "cert": folder / "cert.pem", "key": folder / "key.pem"}

    def openssl(*args):
        subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=persona test CA",
            "-keyout", folder / "ca-key.pem", "-out", files["ca_file"])
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1", "-keyout", files["key"],
            "-out", folder / "cert.csr")
    openssl("x509", "-req", "-in", folder / "cert.csr", "-CA", files["ca_file"], "-CAkey", folder / "ca-key.pem",
            "-CAcreateserial", "-days", "1", "-out", files["cert"])
    return {k: str(v) for k, v in files.items()}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def local_cluster(folder: Path, protocol: str = "tcp", tls: list[str] = (), security=None):
    """A real dask scheduler and two workers on 127.0.0.1, as separate processes; yields the address."""
    port = free_port()
    address = f"{protocol}://127.0.0.1:{port}"
    dask = str(Path(sys.executable).with_name("dask"))
    # the workers sample no profile, as a run's do (persona.dag.executor.no_profile: CPython 3.11.7 can deadlock in
    # it); and a busy machine gets two minutes to answer, not one (a CI run once timed out here)
    env = {**os.environ, "PERSONA_PLUGINS": "", "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False"}
    procs = [subprocess.Popen([dask, "scheduler", "--protocol", protocol, "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard", *tls], env=env, cwd=folder,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    for _ in range(2):
        procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard",
                                       "--host", "127.0.0.1", *tls], env=env, cwd=folder,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        from distributed import Client

        with Client(address, timeout="120s", security=security) as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def events(line: str) -> list[str]:
    """The progress events of a line, as "people/bea landmarks: started"."""
    return [f"{m[1]} {m[2].strip()}: {m[3]}" for m in EVENT.finditer(line)]


class Run:
    """One ``persona run`` of the workflow into ``store`` and ``output`` (``args``: more of its options), as a
    process group of its own; every line it prints read as it comes, with the time it came (and written to
    ``log``). ``note`` begins the message of a failure (e.g. the seed that replays it)."""

    def __init__(self, workflow: Path, store: Path, output: Path, log: Path, args=(), env=None, note: str = ""):
        self.log, self.note = log, note
        self.proc = subprocess.Popen([PERSONA, "run", str(workflow), "--set", f"store={store}", "--set",
                                      f"output={output}", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, start_new_session=True, env=env)
        self.start = time.monotonic()
        self.working = None  # when its first progress line came
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        with self.proc.stdout, open(self.log, "w") as log:
            for line in self.proc.stdout:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                log.write(line)
                log.flush()

    def wait(self, timeout: float = 600) -> int:
        """The run's exit status once it ended; a test failure (the run killed) when it runs for longer than
        ``timeout`` seconds from its start (a hang is a failure too)."""
        try:
            self.proc.wait(timeout=max(1.0, timeout - (time.monotonic() - self.start)))
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"{self.note}the run did not end within {timeout} s:\n{self.tail()}")
        self._reader.join(timeout=30)
        return self.proc.returncode

    def kill(self) -> None:
        """SIGKILL the whole run: every process of its group."""
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        self._reader.join(timeout=30)

    def workers(self) -> list[int]:
        """The process ids of the Dask workers of the run's own local cluster: processes its nannies spawned
        that listen for their peers (the process that cleans a mesh for a build thread is spawned too, and
        listens to none)."""
        try:
            children = psutil.Process(self.proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []
        found = []
        for child in children:
            try:
                if "spawn_main" in " ".join(child.cmdline()) and any(
                        c.status == psutil.CONN_LISTEN for c in child.net_connections("tcp")):
                    found.append(child.pid)
            except psutil.Error:
                continue
        return sorted(found)

    def seen(self, text: str) -> bool:
        """Whether a line it printed so far holds ``text``."""
        return any(text in line for _, line in self.lines)

    def text(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def tail(self, n: int = 40) -> str:
        return "\n".join(line for _, line in self.lines[-n:])

    def last_step(self) -> str:
        steps = [line for _, line in self.lines if EVENT.search(line)]
        return steps[-1] if steps else "(no progress line yet)"
