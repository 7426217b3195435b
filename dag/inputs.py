"""A workflow's inputs resolved before any work: every collection's photos and video frames, and the
canvas a collection's photos are decoded onto.
"""

from __future__ import annotations

from persona.stores import media, storage
from persona.stores.errors import InputError

from .workflow import VideoRange, Workflow


def resolve_inputs(wf: Workflow, *, keep_going: bool = False) -> dict[str, list[media.Source] | InputError]:
    """Every collection's photos and video frames, resolved before any work is done or any file
    created: paths that do not exist, empty folders and frame ranges, files that are not videos
    where a video is needed and videos that do not open raise an :class:`InputError` naming them
    (with ``keep_going``, the error is that collection's value instead: a batch's drives that do
    not use it still run). Takes a second or two (a video's frames are counted, not decoded). The
    buckets of a store and an output in object storage are reached first
    (:func:`persona.stores.storage.check`)."""
    storage.check(wf.store, "store")
    storage.check(wf.output, "output")
    resolved = {}
    for plan in wf.collections():
        try:
            sources = media.resolve_sources(_media_spec(plan.photos), wf.base_dir)
            if plan.video and any(s.frame is None for s in sources):
                where = "driver.video" if wf.version == 1 else "drives: video"
                raise InputError(f"{where}: {sources[0].path} is not a video; give a video file (.mp4, .mov, "
                                 "...) or a range {video: PATH, start: 0, stop: N}")
        except InputError as exc:
            if not keep_going:
                raise
            resolved[plan.path] = exc
            continue
        resolved[plan.path] = sources
    return resolved


def _media_spec(spec):
    if isinstance(spec, list):
        return [_media_spec(item) for item in spec]
    return spec.model_dump() if isinstance(spec, VideoRange) else spec


def canvas_of(sources, params) -> list[int]:
    """The smallest canvas that holds every readable photo and video frame after downscaling to max_side."""
    h = w = 1
    videos: dict[str, tuple[int, int]] = {}
    for s in sources:
        try:
            if s.frame is None:
                info = media.probe_image(s.path, max_pixels=params["max_pixels"], min_side=params["min_side"])
                height, width = info.height, info.width
            else:
                if s.path not in videos:  # a video's frame size, read once
                    with media.VideoReader(s.path) as reader:
                        videos[s.path] = reader.height, reader.width
                height, width = videos[s.path]
        except (media.PhotoRejected, InputError):
            continue
        scale = min(1.0, params["max_side"] / max(width, height))
        h, w = max(h, int(round(height * scale))), max(w, int(round(width * scale)))
    return [h, w]
