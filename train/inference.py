"""Inference with a trained run: R as a renderer, H as a decomposer writing datasets."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm import tqdm

from blender_gen.conversions import from_network, preview_srgb8
from blender_gen.dataset import (INTRINSIC_LAYERS, append_manifest, atomic_write_json, sample_filename,
                                 sha256_file, write_exr)
from .checkpoint import CheckpointError, latest_checkpoint, load_weights
from .config import Config, config_from_dict
from .data import IntrinsicsData, RealImages
from .loop import _save_png, to_display
from .model import build_model


def load_run(run_dir: Path, device: str = "cpu", checkpoint: Path | None = None) -> tuple[Config, torch.nn.Module, int]:
    """Config and weights of a run folder (the newest checkpoint unless one is named)."""
    run_dir = Path(run_dir)
    opts_path = run_dir / "training_options.json"
    if not opts_path.exists():
        raise CheckpointError(f"--run {run_dir}: not a run folder (no training_options.json)")
    cfg = config_from_dict(json.loads(opts_path.read_text())["config"])
    path = Path(checkpoint) if checkpoint else latest_checkpoint(run_dir / "checkpoints")
    if path is None or not path.exists():
        raise CheckpointError(f"--run {run_dir}: no checkpoint yet (train it with `iae-train fit` first)")
    model = build_model(cfg)
    load_weights(path, model)
    step = json.loads(path.with_suffix(".json").read_text())["step"]
    return cfg, model.to(device).eval(), step


def _srgb_png(path: Path, t: torch.Tensor) -> None:
    """R's output is sRGB-encoded network space: write it as it is."""
    _save_png(path, to_display(t))


@torch.no_grad()
def render_dataset(run_dir: Path, intrinsics: Path, out: Path, device: str = "cpu", batch: int = 4,
                   style_seed: int = 0, limit: int | None = None, progress: bool = True) -> list[Path]:
    """R applied to every sample of an intrinsics dataset: one sRGB PNG per sample."""
    cfg, model, _ = load_run(run_dir, device)
    data = IntrinsicsData(intrinsics, cfg.data.height, cfg.data.width)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = len(data) if limit is None else min(limit, len(data))
    gen = torch.Generator().manual_seed(style_seed)
    written = []
    for start in tqdm(range(0, n, batch), desc="render", unit="batch", disable=not progress):
        idx = list(range(start, min(n, start + batch)))
        m = torch.stack([data[(i, False)] for i in idx]).to(device)
        imgs = model.render(m, generator=gen)
        for i, img in zip(idx, imgs):
            path = out / f"{data.ds.rows[i]['index']:06d}.png"
            _srgb_png(path, img)
            written.append(path)
    return written


@torch.no_grad()
def decompose_images(run_dir: Path, images: Path, out: Path, device: str = "cpu", batch: int = 4,
                     limit: int | None = None, progress: bool = True) -> Path:
    """H applied to photos or a PBR dataset, written as a `predictions` dataset (EXR + PNG previews).

    Predictions of a PBR dataset are resized back to its resolution and keep its sample
    indices, so `iae-eval decomposition --predictions` compares them pixel by pixel.
    """
    cfg, model, step = load_run(run_dir, device)
    reals = RealImages(images, cfg.data.height, cfg.data.width)
    out = Path(out)
    if (out / "manifest.jsonl").exists():
        raise FileExistsError(f"--out {out}: already holds predictions; choose another folder")
    (out / "samples").mkdir(parents=True, exist_ok=True)
    (out / "previews").mkdir(exist_ok=True)
    if reals.ds is not None:
        src_w, src_h = reals.ds.resolution
    else:
        src_w, src_h = cfg.data.width, cfg.data.height
    n = len(reals) if limit is None else min(limit, len(reals))
    info = {"kind": "predictions", "resolution": [src_w, src_h], "count": 0, "complete": False,
            "source": str(Path(images).resolve()), "run": str(Path(run_dir).resolve()), "step": step,
            "model": cfg.model.kind, "config_name": cfg.name, "layers": list(INTRINSIC_LAYERS)}
    atomic_write_json(out / "dataset.json", info)
    for start in tqdm(range(0, n, batch), desc="decompose", unit="batch", disable=not progress):
        idx = list(range(start, min(n, start + batch)))
        img = torch.stack([reals[(i, False)] for i in idx]).to(device)
        pred = model.decompose(img).float()
        if pred.shape[-2:] != (src_h, src_w):
            pred = F.interpolate(pred, size=(src_h, src_w), mode="bilinear", align_corners=False)
        for i, p in zip(idx, pred):
            arr = p.permute(1, 2, 0).cpu().numpy()
            layers = {k: from_network(k, arr[..., 3 * j:3 * j + 3]) for j, k in enumerate(INTRINSIC_LAYERS)}
            index = reals.ds.rows[i]["index"] if reals.ds is not None else i
            rel = sample_filename(index)
            write_exr(out / rel, layers)
            preview = np.concatenate([preview_srgb8(k, layers[k]) for k in INTRINSIC_LAYERS], axis=1)
            Image.fromarray(preview).save(out / "previews" / f"{index:06d}.png")
            append_manifest(out / "manifest.jsonl", {"index": index, "file": rel, "sha256": sha256_file(out / rel),
                                                     "source": reals.source_name(i)})
    info["count"], info["complete"] = n, True
    atomic_write_json(out / "dataset.json", info)
    return out
