"""The person's average 3D face from the photo collection (paper §4 with [14], [15]).

1. ``subspace``: the rank-k appearance basis of the frontalized faces, by a randomised
   SVD over shards (dask.array; memory bounded by a shard, not by the collection);
2. ``align`` (Dask tasks over shards): collection flow — each photo TPS-warped to the
   mean fiducials, then flowed to its own rank-k projection, the raw photo sampled once;
3. ``shape``: photometric stereo over the aligned collection, integrated to a depth map,
   and the mesh with its texture and shaded previews in the output folder.
"""

from __future__ import annotations

import numpy as np

from persona.plugins.face.template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W
from persona.stores.layout import OK, Collection
from persona.stores.provenance import Provenance

from . import stages as st


def compute_subspace(runner, coll: Collection, *, source: str, state: str, rank: int, tps_lambda: float,
                     upstream: str) -> Provenance:
    """The rank-k basis of ``source``/rgb over accepted photos -> ``subspace/basis`` (k, H, W, 3)."""
    import dask.array as da

    prov = Provenance.make(stage="subspace", backend="svd_compressed", backend_version="1",
                           params={"rank": rank, "source": source, "tps_lambda": tps_lambda},
                           inputs={"photos": upstream}, persona_version=runner.version)
    current = coll.provenance("subspace/basis")
    if current is not None and current.key == prov.key:
        return prov
    ok = np.flatnonzero(coll.state(state) == OK)
    chunks = coll.shard
    rgb = da.from_zarr(coll.array(f"{source}/rgb"), chunks=(chunks, H, W, 3))
    mask = da.from_zarr(coll.array(f"{source}/mask"), chunks=(chunks, H, W))
    mean = coll.array("aligned/mean")[...].astype(np.float32) / 255
    # pixels a photo does not see take the collection's mean (its unseen parts carry no light)
    rows = da.where(mask[..., None], rgb.astype(np.float32) / 255, mean)[ok].reshape(len(ok), H * W * 3)
    _, singular, basis = da.linalg.svd_compressed(rows.rechunk((chunks, -1)), k=rank, n_power_iter=2, seed=0)
    singular, basis = runner.executor.compute(singular, basis)
    basis = np.asarray(basis, np.float32).reshape(rank, H, W, 3)
    if basis[0].sum() < 0:  # the first component is the average face: keep it positive
        basis[0] *= -1
    coll.create_single("subspace/basis", basis, ("component", "y", "x", "channel"), prov)
    coll.create_single("subspace/singular_values", np.asarray(singular, np.float64), ("component",), prov)
    coll.root[f"{coll.path}/subspace"].attrs.update({"rank": rank, "tps_lambda": tps_lambda})
    return prov


def run_alignment(runner, coll: Collection) -> None:
    """Subspace of the frontalized faces, then collection flow of every photo."""
    config = runner.align_params()
    frontalized = coll.provenance("status/frontalize/state")
    sub = compute_subspace(runner, coll, source="aligned", state="frontalize", rank=config["rank"],
                           tps_lambda=config["tps_lambda"], upstream=frontalized.key)
    align = runner.prepare_stage(coll, st.ALIGN, {"frontalize": frontalized.key, "subspace": sub.key})
    runner.run_stage_tasks(coll, [("align", align.backend, align.params)])
