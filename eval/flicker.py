"""Temporal flicker of a neural renderer on a camera path, relative to Cycles on the same path.

A moving camera changes every frame, so raw frame-to-frame differences mix motion with
flicker. Cycles' images of the same path (an `iae-gen turntable --pbr` set) change by the
motion alone (its seed is fixed and it is denoised), so the ratio
    mean_t |R_{t+1} - R_t|  /  mean_t |C_{t+1} - C_t|
is 1 for a renderer as steady as Cycles and grows with flicker. Both are measured in 8-bit
sRGB units over the whole frame and over car pixels (the union of both frames' masks).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from blender_gen.conversions import to_network
from train.data import IntrinsicsData, RealImages, cover_crop


def frame_differences(frames: np.ndarray, masks: np.ndarray | None = None) -> dict:
    """frames (T, H, W, 3) in [0, 255]; masks (T, H, W) bool. Mean |f_{t+1} - f_t| per pixel
    and channel, over all pixels and over pixels inside either frame's mask."""
    if len(frames) < 2:
        raise ValueError("flicker needs at least 2 frames")
    d = np.abs(np.diff(frames.astype(np.float64), axis=0))  # (T-1, H, W, 3)
    out = {"frames": int(len(frames)), "whole_frame": float(d.mean())}
    if masks is not None:
        m = masks[1:] | masks[:-1]
        out["car"] = float(d[m].mean()) if m.any() else float("nan")
    return out


def _to255(t: torch.Tensor) -> np.ndarray:
    return ((t.float().clamp(-1, 1) + 1.0) * 127.5).permute(1, 2, 0).cpu().numpy()


@torch.no_grad()
def measure_flicker(run_dir: Path, path: Path, device: str = "cpu", batch: int = 4) -> dict:
    """R's and Cycles' frame-to-frame change on a PBR turntable set, at R's training size."""
    from train.inference import load_run

    cfg, model, step = load_run(run_dir, device)
    h, w = cfg.data.height, cfg.data.width
    data = IntrinsicsData(path, h, w)
    if data.ds.kind != "pbr":
        raise ValueError(f"--path {path}: flicker needs Cycles' frames of the path (`iae-gen turntable --pbr`), "
                         f"got a dataset of kind {data.ds.kind!r}")
    cycles_set = RealImages(path, h, w)
    n = len(data)
    r_frames, c_frames, masks = [], [], []
    for start in range(0, n, batch):
        idx = list(range(start, min(n, start + batch)))
        imgs = model.render(torch.stack([data[(i, False)] for i in idx]).to(device))
        r_frames += [_to255(x) for x in imgs]
    for i in range(n):
        c_frames.append(_to255(cycles_set[(i, False)]))
        mask = to_network("mask", data.ds.load(i, ["mask"])["mask"])
        masks.append(cover_crop(torch.from_numpy(mask).permute(2, 0, 1).contiguous(), h, w)[0].numpy() > 0)
    r, c = frame_differences(np.stack(r_frames), np.stack(masks)), frame_differences(np.stack(c_frames), np.stack(masks))
    return {"run": str(run_dir), "step": step, "path": str(path), "size": [w, h], "renderer": r, "cycles": c,
            "ratio_whole_frame": r["whole_frame"] / c["whole_frame"],
            "ratio_car": r["car"] / c["car"] if c["car"] > 0 else float("nan")}
