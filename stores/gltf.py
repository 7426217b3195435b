"""glTF 2.0 binary files (.glb), which Blender and the web viewers built on three.js or Babylon.js open.

Two kinds, written from arrays (this module knows the format, not the face):

- :func:`write_mesh_glb`: a textured triangle mesh (a person's average face), float positions and
  normals, a matte material;
- :func:`write_animated_glb`: a mesh that moves frame by frame (a drive): the rest shape plus one
  morph target per frame, an animation that gives each frame's target the weight 1 at its time (the
  weights in between blend two neighbouring frames), and the rotation and translation of the node
  above the mesh per frame (the head's pose). The material is unlit: its texture is a photograph, its
  light already in it, and the morph targets carry no normals (they would double the file).

Size: positions are 16-bit integers (the ``KHR_mesh_quantization`` extension, which three.js, Blender and
the Khronos validator know), one quantum for the whole file, of at most a 32767th of the largest
coordinate (about 4 µm for a face), undone by the scale of the mesh's node. A vertex of a frame costs 8
bytes (6, padded to 4-byte alignment as glTF requires), so 300 frames of 7,000 vertices are 17 MB.
The weights animation is a sparse accessor: one 1 per frame, the rest zeros that are not stored.

Layout of the file (glTF 2.0 §4.4): a 12-byte header ("glTF", version 2, length), a JSON chunk padded
with spaces and a binary chunk padded with zeros, each to 4 bytes; every buffer view starts on a 4-byte
boundary. The file is written atomically.

This module imports neither ``persona.plugins`` nor ``persona.dag``.
"""

from __future__ import annotations

import io
import json
import struct

import numpy as np

from .media import png_bytes, write_bytes

__all__ = ["write_animated_glb", "write_mesh_glb"]

# glTF's numbers for component types, buffer targets and sampler settings
BYTE, UNSIGNED_BYTE, SHORT, UNSIGNED_SHORT, UNSIGNED_INT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, CLAMP_TO_EDGE = 9729, 33071
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}
_COMPONENT = {np.dtype(np.int8): BYTE, np.dtype(np.uint8): UNSIGNED_BYTE, np.dtype(np.int16): SHORT,
              np.dtype(np.uint16): UNSIGNED_SHORT, np.dtype(np.uint32): UNSIGNED_INT, np.dtype(np.float32): FLOAT}
#: the largest 16-bit coordinate a quantized position takes
QUANTA = 32767


class _Builder:
    """The JSON document and the binary buffer of one file, filled view by view."""

    def __init__(self, generator: str, extras: dict | None):
        self.doc: dict = {"asset": {"version": "2.0", "generator": generator, **({"extras": extras} if extras else {})},
                          "buffers": [{"byteLength": 0}], "bufferViews": [], "accessors": []}
        self.blob = io.BytesIO()

    def view(self, data: bytes, *, target: int | None = None, stride: int | None = None) -> int:
        """A buffer view of ``data``, starting on a 4-byte boundary; its index."""
        self.blob.write(b"\0" * (-self.blob.tell() % 4))
        view = {"buffer": 0, "byteOffset": self.blob.tell(), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        if stride is not None:
            view["byteStride"] = stride
        self.blob.write(data)
        self.doc["bufferViews"].append(view)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, view: int | None, array: np.ndarray, *, offset: int = 0, bounds: bool = False,
                 count: int | None = None, extra: dict | None = None) -> int:
        """An accessor of ``array`` (n, k) or (n,) in ``view`` at ``offset``; ``bounds``: with its min and max
        (glTF requires them for positions and animation times); its index."""
        a = np.asarray(array)
        width = 1 if a.ndim == 1 else a.shape[1]
        acc = {"componentType": _COMPONENT[a.dtype], "count": int(len(a) if count is None else count),
               "type": _TYPES[width]}
        if view is not None:
            acc["bufferView"] = view
            if offset:
                acc["byteOffset"] = offset
        if bounds:
            flat = a.reshape(len(a), width)
            cast = float if a.dtype.kind == "f" else int
            acc["min"] = [cast(x) for x in flat.min(axis=0)]
            acc["max"] = [cast(x) for x in flat.max(axis=0)]
        acc.update(extra or {})
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def data(self, array: np.ndarray, *, target: int | None = None, bounds: bool = False) -> int:
        """A tightly packed array in a view of its own, and its accessor."""
        a = np.ascontiguousarray(array)
        return self.accessor(self.view(a.tobytes(), target=target), a, bounds=bounds)

    def texture(self, image: np.ndarray) -> dict:
        """The image as an embedded PNG, and the material's texture reference to it."""
        rgb = np.asarray(image)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"a texture must be an (h, w, 3) uint8 RGB image, got {rgb.dtype} {rgb.shape}")
        self.doc["images"] = [{"bufferView": self.view(png_bytes(rgb, "the texture")), "mimeType": "image/png"}]
        self.doc["samplers"] = [{"magFilter": LINEAR, "minFilter": LINEAR, "wrapS": CLAMP_TO_EDGE,
                                 "wrapT": CLAMP_TO_EDGE}]
        self.doc["textures"] = [{"sampler": 0, "source": 0}]
        return {"index": 0}

    def material(self, name: str, texture: np.ndarray, *, unlit: bool = False) -> None:
        """The file's one material: matte, double-sided, coloured by ``texture``; ``unlit``: shown as the
        texture is, without the viewer's lights (``KHR_materials_unlit``)."""
        material = {"name": name, "doubleSided": True,
                    "pbrMetallicRoughness": {"baseColorTexture": self.texture(texture), "metallicFactor": 0.0,
                                             "roughnessFactor": 1.0}}
        if unlit:
            material["extensions"] = {"KHR_materials_unlit": {}}
        self.doc["materials"] = [material]

    def write(self, path) -> int:
        """The file at ``path``, atomically; its size in bytes."""
        blob = self.blob.getvalue() + b"\0" * (-self.blob.tell() % 4)
        self.doc["buffers"][0]["byteLength"] = len(blob)
        text = json.dumps(self.doc, separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        total = 12 + 8 + len(text) + 8 + len(blob)
        write_bytes(path, b"".join([struct.pack("<4sII", b"glTF", 2, total),
                                    struct.pack("<I4s", len(text), b"JSON"), text,
                                    struct.pack("<I4s", len(blob), b"BIN\0"), blob]))
        return total


def _check(vertices: np.ndarray, triangles: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.asarray(vertices, np.float32)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or not len(v):
        raise ValueError(f"vertices must be (n, 3) with n > 0, got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or not len(t) or t.min() < 0 or t.max() >= len(v):
        raise ValueError(f"triangles must be (m, 3) indices into the {len(v)} vertices")
    if np.shape(uvs) != (len(v), 2):
        raise ValueError(f"uvs must be ({len(v)}, 2), got {np.shape(uvs)}")
    return v, t.astype(np.uint16 if len(v) <= 65535 else np.uint32).ravel(), np.asarray(uvs, np.float32)


def write_mesh_glb(path, *, vertices: np.ndarray, triangles: np.ndarray, uvs: np.ndarray, texture: np.ndarray,
                   normals: np.ndarray | None = None, name: str = "face", extras: dict | None = None) -> None:
    """A textured mesh: ``vertices`` (n, 3) in metres, ``triangles`` (m, 3) counter-clockwise seen from the
    front, ``uvs`` (n, 2) with (0, 0) the texture's top-left corner, ``texture`` (h, w, 3) uint8 RGB,
    ``normals`` (n, 3) or None (viewers then shade each triangle flat); ``extras``: notes for the asset
    (units, axes)."""
    v, indices, uv = _check(vertices, triangles, uvs)
    g = _Builder("Persona", extras)
    attributes = {"POSITION": g.data(v, target=ARRAY_BUFFER, bounds=True),
                  "TEXCOORD_0": g.data(uv, target=ARRAY_BUFFER)}
    if normals is not None:
        attributes["NORMAL"] = g.data(np.asarray(normals, np.float32), target=ARRAY_BUFFER)
    g.material(name, texture)
    g.doc.update(meshes=[{"name": name, "primitives": [
        {"attributes": attributes, "indices": g.data(indices, target=ELEMENT_ARRAY_BUFFER), "material": 0}]}],
        nodes=[{"name": name, "mesh": 0}], scenes=[{"nodes": [0]}], scene=0)
    g.write(path)


def write_animated_glb(path, *, rest: np.ndarray, frames: np.ndarray, triangles: np.ndarray, uvs: np.ndarray,
                       texture: np.ndarray, fps: float, rotations: np.ndarray, translations: np.ndarray,
                       name: str = "puppet", extras: dict | None = None) -> dict:
    """A mesh moving frame by frame (module docstring): ``rest`` (n, 3) the shape shown without animation,
    ``frames`` (T, n, 3) the vertices of every frame, both in metres; ``rotations`` (T, 4) quaternions
    (x, y, z, w) and ``translations`` (T, 3) metres of the node above the mesh (the head); ``fps`` the
    frames' rate. Returns the quantum (metres) and the file's size in bytes."""
    v, indices, uv = _check(rest, triangles, uvs)
    f = np.asarray(frames, np.float32)
    count = len(f)
    if f.ndim != 3 or f.shape[1:] != v.shape or not count:
        raise ValueError(f"frames must be (T, {len(v)}, 3) with T > 0, got {f.shape}")
    if np.shape(rotations) != (count, 4) or np.shape(translations) != (count, 3):
        raise ValueError(f"rotations must be ({count}, 4) and translations ({count}, 3)")
    if not (np.isfinite(f).all() and np.isfinite(v).all()):
        raise ValueError("the rest shape and every frame must be finite")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    g = _Builder("Persona", extras)
    # one quantum for the file: the rest shape, every frame and every frame's difference from the rest fit
    quantum = max(float(np.abs(v).max()), float(np.abs(f).max()), float(np.abs(f - v).max()), 1e-9) / QUANTA
    rest_q = np.round(v / quantum).astype(np.int16)
    deltas = np.round(f / quantum).astype(np.int32) - rest_q  # within ±2 quanta of (f - v) / quantum
    deltas = np.clip(deltas, -QUANTA, QUANTA).astype(np.int16)

    def padded(a: np.ndarray) -> np.ndarray:  # (…, n, 3) int16 as (…, n, 4): 8 bytes a vertex, 4-aligned
        return np.concatenate([a, np.zeros(a.shape[:-1] + (1,), np.int16)], axis=-1)

    position = g.accessor(g.view(padded(rest_q).tobytes(), target=ARRAY_BUFFER, stride=8), rest_q, bounds=True)
    morphs = g.view(padded(deltas).tobytes(), target=ARRAY_BUFFER, stride=8)
    targets = [{"POSITION": g.accessor(morphs, deltas[t], offset=t * len(v) * 8, bounds=True)} for t in range(count)]
    primitive = {"attributes": {"POSITION": position, "TEXCOORD_0": g.data(uv, target=ARRAY_BUFFER)},
                 "indices": g.data(indices, target=ELEMENT_ARRAY_BUFFER), "material": 0, "targets": targets}
    g.material(name, texture, unlit=True)
    times = g.data(np.arange(count, dtype=np.float32) / np.float32(fps), bounds=True)
    ones = np.arange(count, dtype=np.uint32) * (count + 1)  # frame t's own target, in the T x T weights
    weights = g.accessor(None, np.zeros(1, np.float32), count=count * count, extra={"sparse": {
        "count": count, "indices": {"bufferView": g.view(ones.tobytes()), "componentType": UNSIGNED_INT},
        "values": {"bufferView": g.view(np.ones(count, np.float32).tobytes())}}})
    samplers = [{"input": times, "output": g.data(np.asarray(rotations, np.float32)), "interpolation": "LINEAR"},
                {"input": times, "output": g.data(np.asarray(translations, np.float32)), "interpolation": "LINEAR"},
                {"input": times, "output": weights, "interpolation": "LINEAR"}]
    g.doc.update(
        extensionsUsed=["KHR_mesh_quantization", "KHR_materials_unlit"], extensionsRequired=["KHR_mesh_quantization"],
        meshes=[{"name": name, "primitives": [primitive], "weights": [0.0] * count,
                 "extras": {"targetNames": [f"frame_{t:05d}" for t in range(count)]}}],
        # the head (posed per frame) holds the face, whose scale turns the 16-bit positions into metres
        nodes=[{"name": "head", "children": [1]}, {"name": name, "mesh": 0, "scale": [quantum] * 3}],
        scenes=[{"nodes": [0]}], scene=0,
        animations=[{"name": "drive", "samplers": samplers, "channels": [
            {"sampler": 0, "target": {"node": 0, "path": "rotation"}},
            {"sampler": 1, "target": {"node": 0, "path": "translation"}},
            {"sampler": 2, "target": {"node": 1, "path": "weights"}}]}])
    return {"quantum_m": quantum, "bytes": g.write(path)}
