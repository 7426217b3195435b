"""The driver's motion on the puppet's face (paper §4): what 3D renderers draw.

1. ``dynamics`` (Dask tasks over shards of frames): each frame's 3D flow of the driver's
   average face, before temporal smoothing (:mod:`persona.plugins.face.dynamics`);
2. Dask tasks over shards: the flows and depth changes smoothed over time (a halo of
   ``time_radius`` frames each side), the driver's meshes M_D^t; their mean M̄_D from the shards' sums;
3. the correspondence φ puppet -> driver (ALGORITHMS §7.3): the puppet's 2D average projected
   onto the driver's rank-4 appearance subspace, then a flow between the two (by default started
   from the TPS of the two faces' mean fiducials, and pinned to them afterwards;
   ``motion.correspondence`` in the workflow);
4. the motion transfer of every frame by the ``transfer`` backend (by default the magnitude-adjusted
   deformation transfer, :mod:`persona.plugins.builtin.transfer`: B's meshes M_P^t = M_P + Δ̂ f*, then moved
   so that their fiducials land on the retargeted ones); Dask tasks over shards, each worker preparing the
   backend once.

Stored in the ``drive`` collection: ``dynamics/flow``, ``dynamics/delta`` (per frame),
``motion/driver_mesh`` (M_D^t), ``motion/driver_mean``, ``motion/correspondence`` (φ) and ``mesh``
(M_P^t, NaN off B's face; written last: its provenance, set after its last shard, marks the step
complete).
"""

from __future__ import annotations

import numpy as np

from persona.plugins.base import Rejected
from persona.plugins.face.dynamics import FrameTrack, frame_mesh, smooth_tracks
from persona.plugins.face.transfer import guided_correspondence
from persona.plugins.kinds import MotionPair, Pose
from persona.stores.layout import OK, Cast, Collection, open_store
from persona.stores.provenance import cache_key

from . import stages as st
from .context import RunContext
from .graph import Target


def run_dynamics(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``dynamics``: the driver's per-frame 3D flow (Dask tasks over shards of frames); the drive's
    motion params are recorded on its group, where the tasks read them (with the transfer backend's params
    under ``transfer``, where they were before the transfer was a kind)."""
    root, cast = runner.root, target.cast
    drive, driver, puppet = (Collection(root, path) for path in (cast.drive, cast.driver, cast.puppet))
    for coll in (driver, puppet):
        problem = runner.shape_problems.get(coll.path) or (None if coll.has("shape/depth") else "not built")
        if problem:
            raise Rejected(f"{coll.path} has no 3D shape: {problem}. Without one there is no 3D puppet; "
                           "render in 2D instead with --set stages.render.backend=tps2d")
    motion = runner.motion_params()
    drive.group.attrs["motion"] = {**motion, "transfer": runner.wf.stage("transfer")[1]}
    dynamics = runner.prepare_stage(drive, st.DYNAMICS, {
        "retarget": target.made["retarget"].key, "driver_shape": driver.provenance("shape/depth").key,
        "params": cache_key(**motion["dynamics"])}, (motion["flow"]["backend"], motion["flow"]["params"]))
    runner.tasks.run_stage_tasks(drive, [("dynamics", dynamics.backend, dynamics.params)])
    target.made[stage.name] = dynamics


def run_motion(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """Steps 2-4 (see the module's docstring) for the drive ``target``: ``mesh``, B's mesh of each frame;
    then the meshes the workflow exports (``stages.motion.params.export_every``) into the drive's output."""
    _meshes(runner, stage, target)
    every = runner.motion_params()["export_every"]
    if every:
        export_meshes(runner, target.cast, target.output, every)


def _meshes(runner: RunContext, stage: st.Stage, target: Target) -> None:
    root, cast, dynamics = runner.root, target.cast, target.made["dynamics"]
    drive, driver, puppet = (Collection(root, path) for path in (cast.drive, cast.driver, cast.puppet))
    motion = runner.motion_params()
    # the workflow's denoiser when it names one, else the transfer's own default (huber_rof, off-mask excluded)
    denoise = runner.wf.stage("denoise") if "denoise" in runner.wf.stages else None
    transfer = runner.wf.stage("transfer")
    recorded, version = st.backend_key("transfer", transfer[0])
    prov = st.provenance(stage.name, backend=recorded, backend_version=version,
                         params={"transfer": transfer[1], "dynamics": motion["dynamics"], "denoise": denoise,
                                 "correspondence": motion["correspondence"]},
                         inputs={"dynamics": dynamics.key, "puppet_shape": puppet.provenance("shape/depth").key,
                                 "puppet_texture": puppet.provenance("shape/texture").key},
                         persona_version=runner.version)
    target.made[stage.name] = prov
    if st.is_done(drive, prov, *stage.done):
        return
    shape = driver.array("shape/mask").shape
    drive.create("motion/driver_mesh", (*shape, 3), np.float32, ("frame", "y", "x", "xyz"), prov)
    sums = runner.tasks.map_shards(drive, "meshes", driver_meshes, dynamics.key)
    mean = (sum(sums[start] for start in sorted(sums)) / drive.n).astype(np.float32)  # in frame order
    drive.create_single("motion/driver_mean", mean, ("y", "x", "xyz"), prov)

    puppet_mask = puppet.array("shape/mask")[...]
    corr = motion["correspondence"]
    phi = guided_correspondence(
        puppet.array("shape/texture")[...], puppet_mask, driver.array("subspace/basis")[...],
        st.default_registry().get("flow", corr["backend"])(corr["params"]),
        puppet.array("aligned/mean_fiducials")[...], driver.array("aligned/mean_fiducials")[...],
        **{k: corr[k] for k in ("landmark_guide", "guide_lambda", "pin_fiducials", "pin_lambda")})
    drive.create_single("motion/correspondence", phi.astype(np.float32), ("y", "x", "xy"), prov)
    drive.create("mesh", (*puppet_mask.shape, 3), np.float32, ("frame", "y", "x", "xyz"), prov, pending=True)
    runner.tasks.map_shards(drive, "transfer", transfer_meshes, prov.key, puppet.path, transfer, denoise)
    drive.mark_done("mesh", prov)  # after the last frame: a killed run leaves no key to trust


def driver_meshes(url: str, path: str, start: int, stop: int, key: str) -> np.ndarray:
    """One shard's task: M_D^t of frames [start, stop) into ``motion/driver_mesh``, the tracks
    smoothed over time with a halo of ``time_radius`` frames each side (frames without a track keep
    the average); returns the shard's sum of meshes, for their mean M̄_D."""
    root = open_store(url)
    drive = Collection(root, path)
    context = st.per_process(key, lambda: st.driver_model(root, path))
    model, params = context["model"], context["dynamics"]
    halo = params.time_radius
    lo, hi = max(0, start - halo), min(drive.n, stop + halo)
    ok = drive.state("dynamics")[lo:hi] == OK
    flows, deltas = drive.array("dynamics/flow")[lo:hi], drive.array("dynamics/delta")[lo:hi]
    tracks = [FrameTrack(flows[i], deltas[i], np.full(4, np.nan), np.zeros(model.shape, bool),
                         np.zeros(model.shape, bool)) if ok[i] else None for i in range(hi - lo)]
    smoothed = smooth_tracks(tracks, params)[start - lo:stop - lo]
    poses = drive.array("pose")[start:stop]
    block = np.stack([model.rest_mesh if track is None else frame_mesh(model, track, Pose.from_vector(pose))
                      for track, pose in zip(smoothed, poses)])
    drive.array("motion/driver_mesh")[start:stop] = block
    return block.sum(axis=0, dtype=np.float64)


def transfer_meshes(url: str, path: str, start: int, stop: int, key: str, puppet: str, transfer: tuple[str, dict],
                    denoise: tuple[str, dict] | None) -> None:
    """One shard's task: B's meshes M_P^t of frames [start, stop) into ``mesh`` (NaN off B's face), as the
    ``transfer`` backend (name, params) moves them; each worker prepares it once."""
    root = open_store(url)
    drive = Collection(root, path)
    mesh, mask = st.per_process(key, lambda: prepared_transfer(root, drive, Collection(root, puppet), transfer,
                                                                denoise))
    block = np.stack([mesh(t, m) for t, m in zip(range(start, stop), drive.array("motion/driver_mesh")[start:stop])])
    block[:, ~mask] = np.nan
    drive.array("mesh")[start:stop] = block.astype(np.float32)


def prepared_transfer(root, drive: Collection, puppet: Collection, transfer: tuple[str, dict],
                      denoise: tuple[str, dict] | None) -> tuple:
    """The transfer backend (name, params) prepared for this drive, with the denoiser (name, params; None: the
    backend's own): its function of a frame and A's mesh there; and B's mask."""
    depth = puppet.array("shape/depth")[...]
    ys, xs = np.mgrid[0:depth.shape[0], 0:depth.shape[1]]
    mask = puppet.array("shape/mask")[...]
    registry = st.default_registry()
    pair = MotionPair(drive.array("motion/driver_mean")[...], drive.array("motion/correspondence")[...],
                      np.stack([xs, ys, depth], axis=-1), mask, st.driver_model(root, drive.path)["model"].mask,
                      puppet.array("aligned/mean_fiducials")[...], drive.array("target")[:],
                      registry.get("denoise", denoise[0])(denoise[1]) if denoise else None)
    return registry.get("transfer", transfer[0])(transfer[1]).prepare(pair), mask


def export_meshes(runner: RunContext, cast: Cast, output: str, every: int) -> list[str]:
    """B's textured mesh of every ``every``-th frame of the drive: ``<output>/meshes/frame_<t>.ply`` and ``.obj``."""
    import open3d as o3d

    from persona.plugins.face.meshing import METRIC_UNITS, depth_to_mesh, metric_frame
    from persona.stores import storage
    from persona.stores.meshes import write_mesh

    folder = storage.join(output, "meshes")
    drive = Collection(runner.root, cast.drive)
    puppet = Collection(runner.root, cast.puppet)  # B's frame: every exported frame shares it
    origin, scale = metric_frame(puppet.array("aligned/mean_fiducials")[...], puppet.array("shape/depth")[...],
                                 puppet.array("shape/mask")[...])
    written = []
    frames = range(0, drive.n, every)
    with runner.tasks.progress_bar(f"{cast.drive:>13} export    ", len(frames)) as bar:
        for t in frames:
            mesh, texture = drive.array("mesh")[t], drive.array("texture/rgb")[t]
            face = np.isfinite(mesh).all(axis=-1)
            surface = depth_to_mesh(np.where(face, mesh[..., 2], np.nan), face, texture)
            pixels = np.round(np.asarray(surface.vertices)[:, :2]).astype(int)  # vertices are face pixels
            surface.vertices = o3d.utility.Vector3dVector(mesh[pixels[:, 1], pixels[:, 0]].astype(np.float64))
            surface.compute_vertex_normals()
            written.append(str(write_mesh(folder, f"frame_{t:05d}", surface, texture, y_up=True, origin=origin,
                                          scale=scale, units=METRIC_UNITS)["ply"]))
            bar.update()
    return written
