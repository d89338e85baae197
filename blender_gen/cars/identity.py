"""What procedural cars are made from, as one digest (above `catalogue`, `sampler` and `body`, which
it reads; none of them imports it)."""
from __future__ import annotations

import hashlib
from pathlib import Path

from .body import GEOMETRY_VERSION
from .catalogue import CATALOGUE_FILE
from .sampler import RANGES_FILE, SAMPLER_VERSION


def catalogue_digest(path: Path = CATALOGUE_FILE) -> str:
    """Content hash of what procedural cars are made from (the catalogue, the sampler's ranges,
    the geometry and sampler versions), for recipe identities: a set never mixes two versions."""
    h = hashlib.sha256(Path(path).read_bytes())
    h.update(Path(RANGES_FILE).read_bytes())
    h.update(f"geometry:{GEOMETRY_VERSION} sampler:{SAMPLER_VERSION}".encode())
    return h.hexdigest()[:16]
