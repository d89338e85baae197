"""Image sets for FID/KID and the report: photo folders, PBR datasets, rendered PNG folders.

Every set passes through the trainer's own preprocessing (`train.data.RealImages`: scale to
cover the size, centre crop), so real and generated images reach Inception the same way.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from train.data import RealImages, read_photo


def image_size(root: Path) -> tuple[int, int]:
    """(height, width) of the first image of a set, e.g. generated images at the run's size."""
    t = RealImages(Path(root), 8, 8)  # any size: only to find the first image
    if t.ds is not None:
        w, h = t.ds.resolution
        return h, w
    return read_photo(t.files[0]).shape[:2]  # upright, as training reads it (EXIF orientation)


def image_source(root: Path, size: tuple[int, int], limit: int | None = None) -> tuple[int, Iterator[np.ndarray]]:
    """(count, iterator of HxWx3 uint8 sRGB images at `size` = (height, width)).

    Uses every image unless `limit` caps it; callers print the count beside every figure.
    """
    data = RealImages(Path(root), *size)
    n = len(data) if limit is None else min(limit, len(data))

    def gen() -> Iterator[np.ndarray]:
        for i in range(n):
            t = data[(i, False)]
            yield ((t.clamp(-1, 1) + 1.0) * 127.5 + 0.5).to(torch.uint8).permute(1, 2, 0).numpy()

    return n, gen()
