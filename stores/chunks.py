"""Chunks that say when they are damaged.

Every array Persona writes carries a CRC32C checksum after its compressor (:data:`COMPRESSORS`;
in sharded arrays on every inner chunk, and zarr checksums the shard index already), and
writes every chunk even when it holds only the fill value, so a chunk file that is not there
was lost, never just empty. Importing this module sets both for the process (workers too:
they import it with the store layer).

A chunk that cannot be decoded (checksum mismatch, a broken compressed stream) raises
:class:`ChunkError` naming the array, the chunk file and the photos it holds, wherever it is
read: the codec pipeline every zarr read goes through is :class:`NamedChunkErrors`.
Arrays written before checksums keep opening and reading as they are.
"""

from __future__ import annotations

import zarr
from zarr.codecs import Crc32cCodec, ShardingCodec, ZstdCodec
from zarr.core.codec_pipeline import BatchedCodecPipeline
from zarr.registry import register_pipeline

from .errors import PersonaError
from .paths import array_of, item

#: bytes-to-bytes codecs of every array Persona creates: Zstandard at level 1, then a checksum. At zarr's
#: default level (3) a drive's or a person's arrays were 9-10 % smaller and took 1.7-1.8 times as long to
#: compress, 3-4 % of a drive's time on two cores (docs/CHANGELOG.md). Arrays keep the codecs they were
#: written with, so older stores read as they are.
COMPRESSORS = (ZstdCodec(level=1, checksum=False), Crc32cCodec())


def has_checksums(array: zarr.Array) -> bool:
    """Whether an array's chunks carry a CRC32C (arrays made before checksums do not, and may also
    omit chunks that held only the fill value)."""
    codecs = list(array.metadata.codecs)
    for codec in array.metadata.codecs:
        if isinstance(codec, ShardingCodec):
            codecs += codec.codecs
    return any(isinstance(codec, Crc32cCodec) for codec in codecs)


class ChunkError(PersonaError, ValueError):
    """A chunk of an array cannot be decoded: the store is damaged there."""

    def __init__(self, key: str, rows: tuple[int, int] | None, reason: str):
        super().__init__(key, rows, reason)  # the arguments, so that it pickles (from Dask workers)

    @property
    def key(self) -> str:
        return self.args[0]

    @property
    def reason(self) -> str:
        return self.args[2]

    @property
    def array(self) -> str:
        return array_of(self.key)[0]

    def __str__(self) -> str:
        key, rows, reason = self.args
        coords = array_of(key)[1]
        held = f" ({item(self.array)}s {rows[0]}–{rows[1] - 1})" if rows is not None else ""
        return (f"{self.array}: shard {coords[0] if coords else 0}{held} cannot be read, the chunk file {key} "
                f"is damaged ({reason}). Run the workflow again: a run recomputes what it finds damaged. "
                "`persona inspect --verify STORE` lists every damaged chunk; deleting the file and running "
                "again recomputes it and everything made from it")


class NamedChunkErrors(BatchedCodecPipeline):
    """zarr's codec pipeline, but a chunk that fails to decode raises a :class:`ChunkError` naming it."""

    async def read(self, batch_info, out, drop_axes=()):
        batch_info = list(batch_info)
        try:
            await super().read(batch_info, out, drop_axes)
        except ChunkError:
            raise
        except Exception:
            named = [info for info in batch_info if hasattr(info[0], "path")]
            if not named:  # the chunks inside a shard: the shard's own read names the file
                raise
            for info in named:  # which chunk of the batch: each again, alone
                try:
                    await super().read([info], out, drop_axes)
                except Exception as alone:
                    byte_getter, spec = info[0], info[1]
                    coords = array_of(byte_getter.path)[1]
                    rows = (coords[0] * spec.shape[0], (coords[0] + 1) * spec.shape[0]) if coords else None
                    raise ChunkError(byte_getter.path, rows, f"{type(alone).__name__}: {alone}") from alone
            raise


register_pipeline(NamedChunkErrors)
zarr.config.set({"codec_pipeline.path": f"{NamedChunkErrors.__module__}.{NamedChunkErrors.__qualname__}",
                 "array.write_empty_chunks": True})
