"""The one list of stages (persona.dag.stages.STAGES) that the plan, the progress lines, the hooks
and the per-photo tasks read."""

from persona.dag import stages as st
from persona.dag.workflow import BACKENDLESS
from persona.plugins.manager import default_registry


def test_every_stage_is_one_record_in_run_order_with_its_per_photo_work_and_its_settings():
    assert list(st.STAGES)[:6] == ["ingest", "landmarks", "pose", "frontalize", "screen", "align"]
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
