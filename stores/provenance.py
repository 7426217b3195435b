"""Provenance: what made an array, recorded on the array itself.

Every array a stage writes carries ``attrs["provenance"]``, validated by
:class:`Provenance`. Its ``key`` hashes everything that determines the content
(stage, backend, backend version, params, the keys of the inputs), so a re-run
whose key matches can skip the work (snakemake's rerun triggers, in one hash).
"""

from __future__ import annotations

import hashlib
import json
from datetime import datetime, timezone
from typing import Any

from pydantic import BaseModel, ConfigDict, Field


def cache_key(**parts: Any) -> str:
    """A stable hash of JSON-serialisable parts."""
    text = json.dumps(parts, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


class Provenance(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    stage: str = Field(description="the stage that wrote the array")
    backend: str = Field(description="backend name, or '-' for a stage without a backend")
    backend_version: str
    params: dict[str, Any]
    inputs: dict[str, str] = Field(description="input name -> its cache key or content token")
    key: str = Field(description="cache key of this output: equal keys mean equal content")
    created: str = Field(description="UTC time the array was created (ISO 8601)")
    persona_version: str

    @classmethod
    def make(cls, *, stage: str, backend: str, backend_version: str, params: dict,
             inputs: dict[str, str], persona_version: str) -> "Provenance":
        key = cache_key(stage=stage, backend=backend, backend_version=backend_version,
                        params=params, inputs=inputs)
        return cls(stage=stage, backend=backend, backend_version=backend_version, params=params,
                   inputs=inputs, key=key, created=datetime.now(timezone.utc).isoformat(),
                   persona_version=persona_version)
