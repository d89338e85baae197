"""Image sets for FID/KID and the report: photo folders, PBR datasets, rendered PNG folders."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image

from blender_gen.conversions import linear_to_srgb
from blender_gen.dataset import DatasetError, open_dataset

SUFFIXES = (".png", ".jpg", ".jpeg")


def image_source(root: Path, limit: int | None = None) -> tuple[int, Iterator[np.ndarray]]:
    """(count, iterator of HxWx3 uint8 sRGB images) for a photo folder or a PBR dataset."""
    root = Path(root)
    if (root / "dataset.json").exists():
        ds = open_dataset(root, kinds=("pbr",))
        n = len(ds) if limit is None else min(limit, len(ds))

        def gen_ds():
            for i in range(n):
                yield (linear_to_srgb(ds.load(i, ["rgb"])["rgb"]) * 255.0 + 0.5).astype(np.uint8)

        return n, gen_ds()
    if not root.is_dir():
        raise DatasetError(f"{root}: no such image folder or PBR dataset")
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in SUFFIXES)
    if limit is not None:
        files = files[:limit]
    if not files:
        raise DatasetError(f"{root}: no .png/.jpg images found")

    def gen_files():
        for p in files:
            try:
                yield np.asarray(Image.open(p).convert("RGB"))
            except OSError as exc:
                raise DatasetError(f"{p}: cannot read image ({exc})") from exc

    return len(files), gen_files()
