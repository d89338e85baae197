"""Temporal flicker of a neural renderer on a camera path, relative to Cycles on the same path.

A moving camera changes every frame, so raw frame-to-frame differences mix motion with
flicker. Cycles' images of the same path (an `iae-gen turntable --pbr` set) change by the
motion alone (its seed is fixed and it is denoised), so the ratio
    mean_t |R_{t+1} - R_t|  /  mean_t |C_{t+1} - C_t|
is 1 for a renderer as steady as Cycles and grows with flicker. Both are measured in 8-bit
sRGB units over the whole frame and over car pixels (the union of both frames' masks).
A blurry renderer changes less than a sharp one, so the ratio rewards blur; the temporal
error mean_t |(R_{t+1} - R_t) - (C_{t+1} - C_t)| (TecoGAN's idea of comparing temporal
differences with the reference's) is 0 only for a renderer that changes exactly as Cycles does.
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
    return {"frames": int(len(frames)), **_means(np.abs(np.diff(frames.astype(np.float64), axis=0)), masks)}


def temporal_error(frames: np.ndarray, reference: np.ndarray, masks: np.ndarray | None = None) -> dict:
    """Mean |(f_{t+1} - f_t) - (g_{t+1} - g_t)| of two frame sequences (T, H, W, 3), whole frame
    and (given masks) over pixels inside either frame's mask."""
    return _means(np.abs(np.diff(frames.astype(np.float64), axis=0) - np.diff(reference.astype(np.float64), axis=0)),
                  masks)


def _means(d: np.ndarray, masks: np.ndarray | None) -> dict:
    """Mean of per-step differences d (T-1, H, W, 3): whole frame and, given masks (T, H, W),
    over pixels inside either frame's mask."""
    out = {"whole_frame": float(d.mean())}
    if masks is not None:
        m = masks[1:] | masks[:-1]
        out["car"] = float(d[m].mean()) if m.any() else float("nan")
    return out


def _to255(t: torch.Tensor) -> np.ndarray:
    return ((t.float().clamp(-1, 1) + 1.0) * 127.5).permute(1, 2, 0).cpu().numpy()


# Recipe fields that place the camera and the car: an --intrinsics path must agree on all of them.
_SAME_PATH = ("orbit", "cars", "seed", "width", "height", "envmaps", "camera")


def _trained_background(run_dir: Path) -> str | None:
    """The reflection background of the intrinsics a run was trained on (None if they are gone)."""
    from blender_gen.dataset import read_info
    from train.inference import load_run_options

    opts, _ = load_run_options(run_dir)
    try:
        return (read_info(Path(opts["intrinsics"])).get("recipe") or {}).get("background", "black")
    except (OSError, ValueError, KeyError):
        return None


def _check_consecutive(ds, option: str, root: Path) -> None:
    """Neighbours must be consecutive frames of the orbit: frames 0..n-1 of its frame count, none missing."""
    indices = [r["index"] for r in ds.rows]
    wanted = int(ds.info.get("count_requested", len(indices)))
    missing = sorted(set(range(wanted)) - set(indices))
    if missing or indices != list(range(len(indices))):
        shown = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
        raise ValueError(f"{option} {root}: frames {shown or 'beyond the orbit'} missing or out of order "
                         f"({len(indices)} of {wanted}); rerun its `iae-gen turntable` to finish the path")


@torch.no_grad()
def measure_flicker(run_dir: Path, path: Path, intrinsics: Path | None = None, device: str = "cpu") -> dict:
    """R's and Cycles' frame-to-frame change on a PBR turntable set, at R's training size.

    R renders the PBR set's own intrinsic layers, or those of `intrinsics`: an intrinsics
    turntable of the same orbit, e.g. with `--background environment` for a run trained so
    (the PBR set's reflection layer is black off the car)."""
    from train.inference import load_run

    cfg, model, step = load_run(run_dir, device)
    h, w = cfg.data.height, cfg.data.width
    cycles_set = RealImages(path, h, w)
    path_recipe = cycles_set.ds.info.get("recipe") or {}
    if cycles_set.ds.kind != "pbr":
        raise ValueError(f"--path {path}: flicker needs Cycles' frames of the path (`iae-gen turntable --pbr`), "
                         f"got a dataset of kind {cycles_set.ds.kind!r}")
    if not path_recipe.get("orbit"):  # random views: their ratios would mean nothing
        raise ValueError(f"--path {path}: not a camera path (made by `iae-gen pbr`, not `iae-gen turntable --pbr`); "
                         "flicker compares consecutive frames of one orbit")
    _check_consecutive(cycles_set.ds, "--path", path)
    data = IntrinsicsData(intrinsics or path, h, w)
    theirs = data.ds.info.get("recipe") or {}
    background = theirs.get("background", "black")
    if intrinsics:
        differ = [k for k in _SAME_PATH if theirs.get(k) != path_recipe.get(k)]
        if differ or len(data) != len(cycles_set):
            what = ", ".join(differ) if differ else f"{len(data)} frames against {len(cycles_set)}"
            raise ValueError(f"--intrinsics {intrinsics}: not the camera path of --path {path} ({what} differ); "
                             "make it with the same `iae-gen turntable` options")
        _check_consecutive(data.ds, "--intrinsics", intrinsics)
    trained = _trained_background(run_dir)
    if trained is not None and trained != background:
        raise ValueError(f"--run {run_dir} was trained on intrinsics with the {trained!r} background, but R would "
                         f"render the {background!r} background of {intrinsics or path}; pass --intrinsics with an "
                         f"`iae-gen turntable ... --background {trained}` set of the same path")
    n = len(data)
    r_frames, c_frames, masks = [], [], []
    for i in range(n):
        # one style code for every frame (MUNIT): only the camera changes
        img = model.render(data[(i, False)][None].to(device), generator=torch.Generator().manual_seed(0))
        r_frames.append(_to255(img[0]))
        c_frames.append(_to255(cycles_set[(i, False)]))
        mask = to_network("mask", data.ds.load(i, ["mask"])["mask"])
        masks.append(cover_crop(torch.from_numpy(mask).permute(2, 0, 1).contiguous(), h, w)[0].numpy() > 0)
    rf, cf, mf = np.stack(r_frames), np.stack(c_frames), np.stack(masks)
    r, c = frame_differences(rf, mf), frame_differences(cf, mf)
    if c["whole_frame"] == 0:
        raise ValueError(f"--path {path}: Cycles' frames do not change along the path (a still camera?): there is "
                         "no motion to compare R's change with")
    return {"run": str(run_dir), "step": step, "path": str(path), "intrinsics": str(intrinsics or path),
            "size": [w, h], "renderer": r, "cycles": c,
            "temporal_error": temporal_error(rf, cf, mf),
            "ratio_whole_frame": r["whole_frame"] / c["whole_frame"],
            "ratio_car": r["car"] / c["car"] if c["car"] > 0 else float("nan")}
