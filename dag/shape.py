"""The person's average 3D face from the photo collection (paper §4 with [14], [15]).

1. ``subspace``: the rank-k appearance basis of the frontalized faces, by a randomised
   SVD over shards (dask.array; memory bounded by a shard, not by the collection);
2. ``align`` (Dask tasks over shards): collection flow — each photo TPS-warped to the
   mean fiducials, then flowed to its own rank-k projection, the raw photo sampled once;
3. ``shape``: photometric stereo over the aligned collection, integrated to a depth map,
   and the mesh with its texture and shaded previews in the output folder.
"""

from __future__ import annotations

import logging

import numpy as np

from persona.plugins.base import Rejected
from persona.plugins.builtin.shape import lighting_variety
from persona.plugins.face.subspace import streamed_svd
from persona.plugins.face.template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W
from persona.stores import storage
from persona.stores.layout import OK, Collection, open_store
from persona.stores.provenance import Provenance

from . import stages as st
from .context import RunContext
from .graph import Target

log = logging.getLogger(__name__)


def compute_subspace(runner: RunContext, coll: Collection, *, source: str, state: str, rank: int,
                     tps_lambda: float, upstream: str) -> Provenance:
    """The rank-k basis of ``source``/rgb over accepted photos -> ``subspace/basis`` (k, H, W, 3)."""
    import dask.array as da

    prov = st.provenance("subspace", backend="svd_compressed",
                         params={"rank": rank, "source": source, "tps_lambda": tps_lambda},
                         inputs={"photos": upstream}, persona_version=runner.version)
    if st.is_done(coll, prov, *st.STAGES["subspace"].done):
        return prov
    keep = coll.state(state) == OK
    if keep.sum() <= rank:
        raise Rejected(f"{keep.sum()} usable photos of {coll.n}, and the rank-{rank} appearance subspace needs at "
                       f"least {rank + 1} (the 3D shape needs 8 or more): add photos of the same person; "
                       "`persona inspect` says why the others were rejected")
    chunks = coll.shard
    rgb = da.from_zarr(coll.array(f"{source}/rgb"), chunks=(chunks, H, W, 3))
    mask = da.from_zarr(coll.array(f"{source}/mask"), chunks=(chunks, H, W))
    mean = coll.array("aligned/mean")[...].astype(np.float32) / 255
    # pixels a photo does not see take the collection's mean (its unseen parts carry no light)
    rows = da.where(mask[..., None], rgb.astype(np.float32) / 255, mean).reshape(coll.n, H * W * 3)
    singular, basis = streamed_svd(rows, rank, runner.executor.compute, keep=keep)  # a shard's rows per chunk
    basis = basis.astype(np.float32).reshape(rank, H, W, 3)
    if basis[0].sum() < 0:  # the first component is the average face: keep it positive
        basis[0] *= -1
    # the basis last: its provenance marks the step done, so what defines it is written before it
    coll.create_single("subspace/singular_values", np.asarray(singular, np.float64), ("component",), prov)
    coll.root[f"{coll.path}/subspace"].attrs.update({"rank": rank, "tps_lambda": tps_lambda})
    coll.create_single("subspace/basis", basis, ("component", "y", "x", "channel"), prov)
    return prov


def run_subspace(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``subspace``: the rank-k appearance basis of the collection's screened frontalized faces."""
    config = runner.align_params()
    coll = Collection(runner.root, target.path)
    target.made[stage.name] = compute_subspace(
        runner, coll, source="aligned", state="screen", rank=config["rank"], tps_lambda=config["tps_lambda"],
        upstream=coll.provenance("status/screen/state").key)


def run_alignment(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``align``: collection flow of every photo to its projection on the subspace (Dask tasks over shards)."""
    coll = Collection(runner.root, target.path)
    align = runner.prepare_stage(coll, st.ALIGN, {"screen": coll.provenance("status/screen/state").key,
                                                  "subspace": target.made["subspace"].key})
    runner.tasks.run_stage_tasks(coll, [("align", align.backend, align.params)])
    target.made[stage.name] = align


def run_shape(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """Photometric stereo over the aligned collection -> normals, albedo, lighting, depth;
    the textured mesh (PLY, OBJ) and shaded previews into the output folder (their paths into
    ``target.pictures``). The collection's
    mean (the mesh's texture) is a sum over shards; the rest is one task on a worker
    (:func:`photometric_stereo`), which streams the collection's grey faces through the backend."""
    coll, aligned = Collection(runner.root, target.path), target.made["align"]
    shape_name, shape_params = runner.wf.stage("shape")
    integrate_name, integrate_params = runner.wf.stage("integrate")
    registry = st.default_registry()
    prov = st.provenance(stage.name, backend=f"{shape_name}+{integrate_name}",
                         backend_version=registry.get("shape", shape_name).version,
                         params={"shape": shape_params, "integrate": integrate_params},
                         inputs={"align": aligned.key}, persona_version=runner.version)
    files = mesh_files(runner.wf.output, coll)
    target.made[stage.name] = prov
    if st.is_done(coll, prov, *stage.done):  # done: only the files, should they be missing
        if not all(storage.isfile(f) for f in files.values()):  # e.g. a new output folder
            export(coll, runner.wf.output, *(coll.array(name)[...] for name in ("shape/depth", "shape/mask", "shape/texture")))
        target.pictures.update({k: str(v) for k, v in files.items()})
        return
    ok = coll.state("align") == OK
    sums = runner.tasks.fold_shards(coll, "mean", st.aligned_sum, st.add_sums, "collection", "align")
    count = sums["count"]
    texture = (sums["sum"] / np.maximum(count, 1)[..., None]).clip(0, 255).astype(np.uint8)
    (depth, mask), = runner.executor.run(photometric_stereo, [(runner.wf.store, coll.path, count >= 0.3 * ok.sum(),
                                                              prov, shape_name, shape_params, integrate_name,
                                                              integrate_params)])
    full = shape_params.get("full_variety", 0)
    variety = lighting_variety(coll.array("shape/lighting")[:])  # NaN for the photos it did not take
    if variety < full:  # the user should know the shape is mostly the template's, and why
        log.warning("%s shape: lighting variety %.2f, under %.2f: the normals %.0f %% the photos', the rest the "
                 "template's (photos under more kinds of light give a shape of its own; docs/shape.md)",
                 coll.path, variety, full, 100 * variety / full)
    # the mesh files here: pymeshlab, which cleans them, corrupts the heap of a worker (its task thread)
    export(coll, runner.wf.output, depth, mask, texture)
    coll.create_single("shape/texture", texture, ("y", "x", "channel"), prov)
    # shape/depth last: its provenance marks the step done (files above, arrays it depends on before it)
    coll.create_single("shape/depth", depth, ("y", "x"), prov)
    target.pictures.update({k: str(v) for k, v in files.items()})


def photometric_stereo(url: str, path: str, seen: np.ndarray, prov: Provenance,
                       shape_name: str, shape_params: dict, integrate_name: str,
                       integrate_params: dict) -> tuple[np.ndarray, np.ndarray]:
    """:func:`run_shape`'s task on a worker: the shape backend over the aligned collection (its
    accepted photos, grey, or those of them it takes: ``images_for``), on the template's mask where at
    least 30 % of them see (``seen``), then the integrate backend where the backend gave a normal. The photos
    go to the backend a shard at a time (``reconstruct_chunks``): this task holds no more of them than the
    backend does. Stores normals, albedo, mask and lights, and returns (depth, mask)."""
    from persona.plugins.builtin.shape import as_grey
    from persona.plugins.face.template import generic_template

    coll = Collection(open_store(url), path)
    registry = st.default_registry()
    backend = registry.get("shape", shape_name)(shape_params)
    accepted = np.flatnonzero(coll.state("align") == OK)
    ok = np.zeros(coll.n, bool)
    ok[accepted[backend.images_for(len(accepted))]] = True  # all, or as many as the backend takes
    template = generic_template()
    mask = template.mask & seen

    def shards():  # the aligned collection, grey (m x H x W), and where each photo sees, a shard at a time
        for start, stop in coll.shard_ranges():
            keep = ok[start:stop]
            if keep.any():
                yield (as_grey(coll.array("collection/rgb")[start:stop][keep].astype(np.float32) / 255),
                       coll.array("collection/mask")[start:stop][keep])

    result = backend.reconstruct_chunks(shards(), mask, template.normals, template.depth)
    # the face is where the backend gave a normal: not at its edge where too few photos see, but in a hole it
    # encloses (the backend's docs)
    mask = np.isfinite(result.normals).all(axis=-1)
    depth = registry.get("integrate", integrate_name)(integrate_params).integrate(
        result.normals, mask, reference=template.depth)
    lighting = np.full((coll.n, result.lighting.shape[1]), np.nan)
    lighting[ok] = result.lighting
    for name, value, dims in (("shape/normals", result.normals, ("y", "x", "xyz")),
                              ("shape/albedo", result.albedo, ("y", "x")), ("shape/mask", mask, ("y", "x")),
                              ("shape/lighting", lighting, ("photo", "sh"))):
        coll.create_single(name, np.asarray(value), dims, prov)
    return np.asarray(depth), mask


def mesh_name(coll: Collection) -> str:
    """The file name, without extension, of a collection's average mesh: ``puppet_mesh``."""
    return f"{coll.path.replace('/', '_')}_mesh"


def mesh_files(out, coll: Collection) -> dict:
    """Where :func:`export` writes a collection's mesh (PLY, OBJ) and its previews in the folder ``out``."""
    name = mesh_name(coll)
    return {"mesh_ply": storage.join(out, f"{name}.ply"), "mesh_obj": storage.join(out, f"{name}.obj"),
            "mesh_previews": storage.join(out, f"{name}_previews.png")}


def export(coll: Collection, out, depth: np.ndarray, mask: np.ndarray, texture: np.ndarray) -> None:
    """The collection's average mesh (PLY, and OBJ with its texture, in metres) and its shaded
    previews into the folder ``out`` (:func:`mesh_files`), from its depth, mask and texture."""
    from persona.plugins.face.meshing import METRIC_UNITS, depth_to_mesh, metric_frame, shaded_previews
    from persona.stores import media
    from persona.stores.meshes import clean_mesh, write_mesh

    mesh = clean_mesh(depth_to_mesh(depth, mask, texture))
    origin, scale = metric_frame(coll.array("aligned/mean_fiducials")[...], depth, mask)
    write_mesh(out, mesh_name(coll), mesh, texture, y_up=True, origin=origin, scale=scale, units=METRIC_UNITS)
    media.write_png(mesh_files(out, coll)["mesh_previews"], np.concatenate(shaded_previews(depth, mask), axis=1))
