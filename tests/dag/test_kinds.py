"""A user's own mouth and transfer backends, named in the workflow, are the ones the run's mouth, teeth and
motion stages call, and what they return is what the store holds."""

import contextlib
import io

import numpy as np
import pytest
import yaml

from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow
from persona.plugins import manager
from persona.plugins.base import Params
from persona.plugins.face import mouth
from persona.plugins.hookspecs import hookimpl
from persona.plugins.kinds import Mouth, MouthBackend, MouthInterior, TransferBackend
from persona.stores.layout import Collection, open_store
from pipeline import write_quick_people


class Flat(MouthBackend):
    """B's mouth one grey, its cavity black, half of B's teeth in every frame."""

    name = "flat"
    description = "a user's mouth: one grey"

    class Params(Params):
        grey: int = 70

    def interior(self, photos, *, count, min_gap, choice):
        assert choice == "driver" and len(photos) == len(photos.points) > 0
        lips = mouth.lip_curves(np.nanmean(photos.landmarks, axis=0))
        return Mouth(MouthInterior(np.full((32, 64, 3), self.params.grey, np.uint8), 6.0),
                     MouthInterior(np.zeros((32, 64, 3), np.uint8), 4.0), lips)

    def teeth(self, frames, sigma):
        return np.full(len(list(frames)), 0.5)


class Lifted(TransferBackend):
    """B's average mesh, lifted by the frame's index in depth: not the driver's motion, but plainly its own."""

    name = "lifted"
    description = "a user's transfer: B at rest, lifted by t"
    version = "3"

    def prepare(self, pair):
        assert pair.targets.shape[1:] == (49, 2) and pair.puppet.shape[-1] == 3
        return lambda t, driver_mesh: pair.puppet + np.array([0.0, 0.0, t])


@hookimpl
def persona_register_backends(register):
    register(Flat)
    register(Lifted)


@pytest.fixture(scope="module")
def users_run(tmp_path_factory):
    """A small 3D drive of synthetic faces with the two backends above named in its workflow."""
    folder = tmp_path_factory.mktemp("kinds")
    write_quick_people(folder / "data", {"puppet": (8, 0), "driver": (8, 1)}, "driver", 6)
    path = folder / "kinds.yaml"
    path.write_text(yaml.safe_dump({
        "name": "kinds", "store": "run.zarr", "output": "output", "photos_per_shard": 4,
        "puppet": {"photos": "data/puppet/*.png"},
        "driver": {"photos": "data/driver/*.png", "video": "data/driver.mp4"},
        "stages": {"pose": {"params": {"focal_factor": 2.0}}, "mouth": {"backend": "flat", "params": {"grey": 90}},
                   "transfer": {"backend": "lifted"},
                   "render": {"params": {"mouth_choice": "driver"}}},
        "evaluate": {"identity_frames": 2, "collection_sample": 4}}))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(manager, "DEFAULT_PLUGINS", (*manager.DEFAULT_PLUGINS, __name__))
        manager.default_registry.cache_clear()
        try:
            with contextlib.redirect_stderr(io.StringIO()):
                run_workflow(load_workflow(path), scheduler="sync", progress=False)
        finally:
            patch.undo()
            manager.default_registry.cache_clear()
    return open_store(str(folder / "run.zarr"), mode="r")


def test_the_users_mouth_backend_makes_the_interiors_and_the_teeth(users_run):
    puppet, drive = Collection(users_run, "puppet"), Collection(users_run, "drive")
    assert (puppet.array("texture/mouth")[...] == 90).all() and (puppet.array("texture/mouth_cavity")[...] == 0).all()
    assert puppet.array("texture/mouth_gap")[0] == 6.0 and puppet.array("texture/mouth_cavity_gap")[0] == 4.0
    lips = puppet.provenance("texture/lips")
    assert (lips.backend, lips.params["choice"]) == ("flat", "driver")
    np.testing.assert_array_equal(drive.array("mouth/teeth")[:], np.full(6, 0.5, np.float32))
    assert drive.provenance("mouth/teeth").backend == "flat"


def test_the_users_transfer_backend_moves_bs_mesh(users_run):
    drive, puppet = Collection(users_run, "drive"), Collection(users_run, "puppet")
    mask, depth = puppet.array("shape/mask")[...], puppet.array("shape/depth")[...]
    meshes = drive.array("mesh")[:]
    for t in (0, 5):
        np.testing.assert_allclose(meshes[t][mask][:, 2], (depth[mask] + t).astype(np.float32))
    assert np.isnan(meshes[:, ~mask]).all()
    made = drive.provenance("mesh")
    assert (made.backend, made.backend_version) == ("lifted", "3")
