"""For the tests of .glb files: the Khronos glTF validator's verdict, and a file read back as JSON and arrays.

The validator is the npm package ``gltf-validator``, which ``bash setup.sh test`` installs into
``.venv/node``; run by Node with tests/validate_gltf.js. Without Node or the package the tests that need
it skip, saying how to get it.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

MODULES = Path(sys.prefix) / "node" / "node_modules"
SCRIPT = Path(__file__).with_name("validate_gltf.js")


def validate(*files) -> dict[str, dict]:
    """The validator's report for each file: numErrors, numWarnings, messages, info."""
    node = shutil.which("node")
    if node is None or not (MODULES / "gltf-validator").is_dir():
        pytest.skip(f"the glTF validator is not installed ({MODULES}/gltf-validator, and node): bash setup.sh test "
                    "installs it")
    done = subprocess.run([node, str(SCRIPT), *map(str, files)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "NODE_PATH": str(MODULES)})
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def read_glb(path) -> tuple[dict, bytes]:
    """The JSON document and the binary chunk of a .glb."""
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    size, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    doc = json.loads(data[20:20 + size])
    size2, kind2 = struct.unpack_from("<I4s", data, 20 + size)
    assert kind2 == b"BIN\0"
    return doc, data[28 + size:28 + size + size2]


def accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An accessor's values (count, width), strides and sparse values applied."""
    a = doc["accessors"][index]
    dtype, width = np.dtype(_DTYPES[a["componentType"]]), _WIDTH[a["type"]]
    out = np.zeros((a["count"], width), dtype)
    if "bufferView" in a:
        view = doc["bufferViews"][a["bufferView"]]
        stride = view.get("byteStride", dtype.itemsize * width)
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        per = stride // dtype.itemsize  # components from one element to the next
        flat = np.frombuffer(blob, dtype, (a["count"] - 1) * per + width, start)
        out[:] = np.lib.stride_tricks.as_strided(flat, (a["count"], width), (stride, dtype.itemsize))
    if "sparse" in a:
        s = a["sparse"]
        iv, vv = doc["bufferViews"][s["indices"]["bufferView"]], doc["bufferViews"][s["values"]["bufferView"]]
        where = np.frombuffer(blob, _DTYPES[s["indices"]["componentType"]], s["count"], iv.get("byteOffset", 0))
        out[where] = np.frombuffer(blob, dtype, s["count"] * width, vv.get("byteOffset", 0)).reshape(-1, width)
    return out


def trimesh_scene(path):
    """The file as trimesh reads it (a Scene), or the test skips without trimesh."""
    trimesh = pytest.importorskip("trimesh")
    with warnings.catch_warnings():  # trimesh's own deprecations are not ours to fail on
        warnings.simplefilter("ignore")
        return trimesh.load(path)
