"""The one list of stages (persona.dag.stages.STAGES) that the plan, the progress lines, the hooks
and the per-photo tasks read."""

import numpy as np

from persona.dag import stages as st
from persona.plugins.builtin.render3d import RaycastRender
from persona.plugins.face import mouth
from persona.plugins.face.synthetic import Expression, look_at_pose, make_face
from persona.plugins.kinds import Pose
from persona.dag.workflow import BACKENDLESS
from persona.plugins.manager import default_registry


def test_every_stage_is_one_record_in_run_order_with_its_per_photo_work_and_its_settings():
    assert list(st.STAGES)[:8] == ["ingest", "landmarks", "pose", "frontalize", "screen", "mean", "subspace", "align"]
    assert st.COLLECTION_STAGES == ("ingest", "landmarks", "pose", "frontalize", "screen")
    assert [s.name for s in st.CHAIN] == ["landmarks", "pose", "frontalize"]
    assert list(st.STAGES)[-2:] == ["videos", "evaluate"]
    # every per-photo (per-frame) computation belongs to exactly one stage, and is found by its name
    photos = [p.name for s in st.STAGES.values() for p in s.photo]
    assert len(photos) == len(set(photos)) and set(photos) == set(st.PHOTO_STAGES)
    assert {"ingest", "screen", "align", "dynamics", "render", "render3d", "composite"} <= set(photos)
    kinds = set(default_registry().kinds()) | set(BACKENDLESS)  # what `stages:` of a workflow may set
    for stage in st.STAGES.values():
        assert stage.where and set(stage.where) <= {"puppet", "driver", "video", "drive"}, stage.name
        assert set(stage.settings) <= kinds, (stage.name, stage.settings)


def test_every_stage_declares_how_it_runs_what_it_reads_and_what_marks_it_done():
    order = list(st.STAGES)
    for stage in st.STAGES.values():
        assert stage.per in st.PER, stage.name
        for need in stage.needs:  # a stage of its own collection or drive before it, or one of a drive's collections
            of, _, name = need.rpartition(":")
            assert name in st.STAGES and of in ("", "puppet", "driver", "video"), (stage.name, need)
            assert of or order.index(name) < order.index(stage.name), (stage.name, need)
        assert stage.run is None or callable(stage.function()), stage.name
        assert stage.done or stage.name in ("videos", "evaluate"), stage.name  # those two: the drive's outputs key


def test_the_render_draws_the_drivers_own_mouth_interior_into_the_puppets_gap():
    """``mouth_choice: frame`` (the default): the render step samples the driver's frame between the
    driver's own inner lips and draws that into the gap of the puppet's open mouth; with ``widest`` the
    gap shows B's interior; where the driver's lips are closed, ``frame`` draws none (B's own lips close over
    the gap) and ``widest`` still draws B's."""
    face, neutral = make_face(expression=Expression(open=1.0)), make_face()
    size = (260, 240)
    rvec, tvec, camera = look_at_pose(0.0, 0.0, 0.0, face_px=170.0, image_size=size)
    frame = np.zeros((*size, 3), np.uint8)
    frame[100:140, 80:160] = (0, 200, 0)  # the driver's mouth: green between its lips
    driver = np.zeros((68, 2))
    driver[36:42], driver[42:48] = (90, 80), (150, 80)
    xs = np.linspace(90, 150, 5)
    driver[[60, 61, 62, 63, 64]] = np.c_[xs, [120, 105, 105, 105, 120]]
    driver[[60, 67, 66, 65, 64]] = np.c_[xs, [120, 135, 135, 135, 120]]
    blue = np.broadcast_to(np.float32([0, 0, 255]), (32, 64, 3)).copy()  # B's own interior
    context = {"coverage": np.ones(face.vert_mask.shape, np.float32), "fiducials": neutral.fiducials3d[:, :2],
               "lips": mouth.lip_curves(neutral.landmarks3d[:, :2]), "mouth": (blue, 10.0), "mouth_cavity": None,
               "insets": None, "jaw": None, "neutral": None}
    inputs = {"@frames/photos/size": np.array(size), "@frames/photos/rgb": frame, "@frames/landmarks/points": driver,
              "texture/rgb": (face.vert_albedo * 255).astype(np.uint8), "target": neutral.fiducials3d[:, :2],
              "pose": Pose(rvec, tvec, camera, 0.0).as_vector(), "mouth/teeth": np.float32(1),
              "mesh": np.where(face.vert_mask[..., None], face.verts, np.nan).astype(np.float32)}

    def colours(choice, points=driver):
        out = st._render(RaycastRender({"mouth_choice": choice}), {}, {**inputs, "@frames/landmarks/points": points},
                         context)
        rgb = out["render/rgb"].astype(int)
        green = (rgb[..., 1] > 150) & (rgb[..., 0] < 60) & (rgb[..., 2] < 60)
        blue = (rgb[..., 2] > 180) & (rgb[..., 0] < 60) & (rgb[..., 1] < 60)
        return np.count_nonzero(green), np.count_nonzero(blue), np.count_nonzero(out["render/own"] > 127)

    # the driver's interior, and the composite told where it is (render/own: A's own pixels, not relit)
    green, blue, own = colours("frame")
    assert green > 300 and blue == 0 and green <= own < 1.3 * green
    assert colours("widest")[0] == 0 and colours("widest")[1] > 300 and colours("widest")[2] == 0
    closed = driver.copy()
    closed[[61, 62, 63, 65, 66, 67], 1] = 120
    assert colours("frame", closed) == (0, 0, 0)
    assert colours("widest", closed)[1] > 300


def test_the_composite_and_the_light_record_the_keys_they_had_without_backends():
    """Made with the default composite and light backends, their provenance has the form it had when the two
    were backendless settings of stages.composite (backend "-" and the stage's version), so a store made
    before them resumed with nothing recomputed. Version 12: what is kept in front of B's face reaches in
    from beyond its edge, whatever B's render shows there, B's brows are not cut by A's, and skin is judged in
    the face's own light."""
    from persona.dag.workflow import parse_workflow

    wf = parse_workflow({"name": "k", "store": "s.zarr", "output": "o", "puppet": {"photos": "p"}})
    name, params = wf.stage("composite")
    light = {f"light_{k}": v for k, v in wf.stage("light")[1].items()}
    before = {"lighting": 1.0, "tone": 1.0, "tone_reach": 0.5, "hair": 1.0, "light_sigma": 3.0}
    assert {**params, **light} == before
    assert st.backend_key("composite", name) == ("-", "12") and st.backend_key("light", "steady") == ("-", "1")
    made = st.provenance("composite", backend="-", backend_version="12", params={**params, **light},
                         inputs={"render": "r", "light": "l"}, persona_version="x")
    from persona.stores.provenance import Provenance

    old = Provenance.make(stage="composite", backend="-", backend_version="12", params=before,
                          inputs={"render": "r", "light": "l"}, persona_version="x")
    assert made.key == old.key
