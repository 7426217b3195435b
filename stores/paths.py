"""What a path in the store names: the collection an array or a chunk belongs to, and what one of its
items is. The chunk checks (:mod:`.chunks`) and the layout (:mod:`.layout`) both speak of them."""

from __future__ import annotations


#: the collections whose items are a video's frames: the driver's frames and the drive (format 1),
#: every video and every drive (format 2)
FRAME_COLLECTIONS = ("driver/frames", "drive", "videos", "drives")


def item(path: str) -> str:
    """What one item of the collection at ``path`` (or of an array in it) is: a video's "frame" (the
    driver's frames, the drive) or a "photo"."""
    return "frame" if any(path == c or path.startswith(c + "/") for c in FRAME_COLLECTIONS) else "photo"


def array_of(key: str) -> tuple[str, tuple[int, ...]]:
    """The array path and chunk coordinates of a chunk's store key (``puppet/aligned/rgb/c/3/0/0/0``)."""
    path, _, coords = key.rpartition("/c/")
    if not path:  # a 0-d array's only chunk, "<path>/c"
        return key.removesuffix("/c"), ()
    return path, tuple(int(c) for c in coords.split("/"))
