"""Rows that tell a reader what the numbers mean, measured on the same sets as the runs.

Table 3: the constant predictor (every normal toward the camera, the training intrinsics'
mean albedo and reflection), and the per-pixel prior (at each pixel the training intrinsics' mean
normal direction, albedo and reflection, after the same crop and resize): neither looks at the
image, so a decomposition must beat the stronger of the two to have read anything from it. The
prior knows where in the frame a car tends to be and which way its surfaces face there.
Table 1: the renderer that only copies albedo (the intrinsics' own albedo as the image).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from blender_gen.conversions import preview_srgb8
from blender_gen.dataset import DatasetWriter, open_dataset, save_png


def training_means(intrinsics: Path, limit: int = 500) -> dict[str, np.ndarray]:
    """Mean linear albedo and reflection over the object pixels of (up to `limit`) training samples."""
    ds = open_dataset(intrinsics, kinds=("intrinsics", "pbr"))
    picks = np.linspace(0, len(ds) - 1, min(limit, len(ds))).round().astype(int)
    sums = {"albedo": np.zeros(3), "reflection": np.zeros(3)}
    n = 0
    for i in picks:
        layers = ds.load(int(i), ["albedo", "reflection", "mask"])
        on = layers["mask"][..., 0] >= 0.5
        for k in sums:
            sums[k] += layers[k][on].sum(axis=0, dtype=np.float64)
        n += int(on.sum())
    return {k: (v / max(n, 1)).astype(np.float32) for k, v in sums.items()}


def constant_predictions(intrinsics: Path, data: Path, out: Path, progress: bool = True) -> Path:
    """A predictions dataset for `data` holding the constant predictor's maps."""
    means = training_means(intrinsics)
    gt = open_dataset(data, kinds=("pbr",))
    w, h = gt.resolution
    writer = DatasetWriter(out, {"kind": "predictions", "resolution": [w, h], "count_requested": len(gt),
                                 "source": str(Path(data).resolve()), "source_recipe": gt.info.get("recipe"),
                                 "model": "constant", "training_means": {k: v.tolist() for k, v in means.items()}})
    layers = {"normal": np.broadcast_to(np.array([0, 0, 1], np.float32), (h, w, 3)),
              "albedo": np.broadcast_to(means["albedo"], (h, w, 3)),
              "reflection": np.broadcast_to(means["reflection"], (h, w, 3))}
    for row in tqdm(gt.rows, desc="constant predictor", unit="sample", disable=not progress):
        writer.add(row["index"], layers, source=row["file"], source_sha256=row["sha256"])
    writer.finish()
    return Path(out)


def pixel_prior(intrinsics: Path, size: tuple[int, int], limit: int = 500) -> dict[str, np.ndarray]:
    """Per-pixel mean normal direction (unit) and linear albedo and reflection over the object
    pixels of up to `limit` training samples, each cover-cropped and resized to `size` (w, h) as
    training and the report resize; the camera-facing normal and the global means where no sample
    has an object."""
    import torch

    from train.data import cover_crop

    ds = open_dataset(intrinsics, kinds=("intrinsics", "pbr"))
    w, h = size
    picks = np.linspace(0, len(ds) - 1, min(limit, len(ds))).round().astype(int)
    sums = {k: np.zeros((h, w, 3)) for k in ("normal", "albedo", "reflection")}
    count = np.zeros((h, w, 1))
    for i in picks:
        layers = ds.load(int(i), ["normal", "albedo", "reflection", "mask"])
        t = {k: cover_crop(torch.from_numpy(np.ascontiguousarray(v[..., :3] if k != "mask" else v[..., :1]))
                           .permute(2, 0, 1).float(), h, w).permute(1, 2, 0).numpy() for k, v in layers.items()}
        on = (t["mask"] >= 0.5).astype(np.float64)
        for k in sums:
            sums[k] += t[k] * on
        count += on
    means = training_means(intrinsics, limit)
    normal = sums["normal"] / np.maximum(np.linalg.norm(sums["normal"], axis=-1, keepdims=True), 1e-8)
    out = {"normal": np.where(count > 0, normal, np.array([0, 0, 1.0]))}
    for k in ("albedo", "reflection"):
        out[k] = np.where(count > 0, sums[k] / np.maximum(count, 1), means[k])
    return {k: v.astype(np.float32) for k, v in out.items()}


def prior_predictions(intrinsics: Path, data: Path, out: Path, progress: bool = True) -> Path:
    """A predictions dataset for `data` holding the per-pixel prior's maps (`pixel_prior`)."""
    gt = open_dataset(data, kinds=("pbr",))
    w, h = gt.resolution
    layers = pixel_prior(intrinsics, (w, h))
    writer = DatasetWriter(out, {"kind": "predictions", "resolution": [w, h], "count_requested": len(gt),
                                 "source": str(Path(data).resolve()), "source_recipe": gt.info.get("recipe"),
                                 "model": "per-pixel prior"})
    for row in tqdm(gt.rows, desc="per-pixel prior", unit="sample", disable=not progress):
        writer.add(row["index"], layers, source=row["file"], source_sha256=row["sha256"])
    writer.finish()
    return Path(out)


def albedo_images(intrinsics: Path, out: Path, limit: int | None = None, progress: bool = True) -> Path:
    """The intrinsics' albedo as sRGB PNGs: what a renderer that only copies albedo would show."""
    ds = open_dataset(intrinsics, kinds=("intrinsics", "pbr"))
    n = len(ds) if limit is None else min(limit, len(ds))
    Path(out).mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(n), desc="albedo copies", unit="image", disable=not progress):
        save_png(Path(out) / f"{ds.rows[i]['index']:06d}.png", preview_srgb8("albedo", ds.load(i, ["albedo"])["albedo"]))
    return Path(out)
