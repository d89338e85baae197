"""A trained run as a Python object that takes and returns NumPy images.

    import train
    run = train.load_run("runs/paper")
    maps = run.decompose(photo)          # HxWx3 uint8 / float / PIL image -> dict of HxWx3 float32 maps
    image = run.render(maps)             # the maps (a dict or an HxWx9 array) -> HxWx3 sRGB in [0, 1]

The maps are in the datasets' units (docs/dataset_format.md), so a sample read with
`blender_gen.dataset` renders as it is and a decomposition can be saved beside one. The networks
see each picture as `iae-train decompose` shows them photos: whole, aspect ratio kept, resized to
about the pixel count they trained at (train/photos.py); what they return is resized back.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from blender_gen.conversions import from_network, to_network
from blender_gen.dataset import INTRINSIC_LAYERS

from .config import Config
from .data import photo_to_srgb01, resize
from .inference import load_run_checkpoint
from .photos import at_network_size

__all__ = ["IntrinsicRun", "load_run"]


def load_run(run_dir: str | Path, device: str = "cpu", checkpoint: str | Path | None = None) -> IntrinsicRun:
    """A run folder's networks, ready to decompose and render (the newest checkpoint unless one is
    named; the moving-average weights where the checkpoint has them). Loading runs no pickled code."""
    cfg, model, step, path = load_run_checkpoint(Path(run_dir), device, Path(checkpoint) if checkpoint else None)
    return IntrinsicRun(Path(run_dir), cfg, model, step, path, device)


@dataclass
class IntrinsicRun:
    """H (decompose) and R (render) of one checkpoint; `load_run` makes one."""

    run_dir: Path
    config: Config = field(repr=False)
    model: torch.nn.Module = field(repr=False)
    step: int
    checkpoint: Path
    device: str = "cpu"

    @property
    def weights(self) -> str:
        """'moving average' or 'raw': which of the checkpoint's weights are loaded."""
        return getattr(self.model, "weights", "raw")

    @torch.no_grad()
    def decompose(self, image: Any, size: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
        """H's maps of one picture: `normal` (camera space, unit length where H sees the car),
        `albedo` and `reflection` (linear colour), each (H, W, 3) float32 at the picture's size, or
        at `size` = (width, height).

        `image`: an (H, W, 3) array, sRGB as photos are: uint8 (0-255), uint16 (0-65535) or float
        (0-1); (H, W) grey and (H, W, 4) with alpha are accepted too; or a PIL image."""
        photo, img = self._input(image)
        maps = self.model.decompose(img)[0].float().cpu()
        arr = resize(maps, *_out_size(photo.shape[-2:], size)).permute(1, 2, 0).numpy()
        return {k: from_network(k, arr[..., 3 * j:3 * j + 3]) for j, k in enumerate(INTRINSIC_LAYERS)}

    @torch.no_grad()
    def render(self, intrinsics: Mapping[str, np.ndarray] | np.ndarray, size: tuple[int, int] | None = None,
               seed: int = 0) -> np.ndarray:
        """R's image of intrinsic maps: (H, W, 3) float32 sRGB in [0, 1], at their size or `size`.

        `intrinsics`: a dict with `normal`, `albedo` and `reflection` (H, W, 3) arrays in the datasets'
        units (what `decompose` returns, or a dataset sample), or one (H, W, 9) array of the three in
        that order. `seed` draws the style code of a model that has one (MUNIT)."""
        stack = _intrinsics_stack(intrinsics)
        m = torch.from_numpy(stack).permute(2, 0, 1).float()
        small = at_network_size(m, self.config.data.height, self.config.data.width).to(self.device)
        img = self.model.render(small, generator=torch.Generator().manual_seed(seed))[0].float().cpu()
        return _srgb01(resize(img, *_out_size(m.shape[-2:], size)))

    @torch.no_grad()
    def reconstruct(self, image: Any, size: tuple[int, int] | None = None) -> np.ndarray:
        """R(H(image)) as the decomposition cycle makes it (lit as the image is, where R fits a
        lighting per image): (H, W, 3) float32 sRGB in [0, 1]; `image` as for `decompose`."""
        photo, img = self._input(image)
        maps = self.model.decompose(img).float()
        again = self.model.reconstruct(img, maps) if hasattr(self.model, "reconstruct") else self.model.render(maps)
        return _srgb01(resize(again[0].float().cpu(), *_out_size(photo.shape[-2:], size)))

    def _input(self, image: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """(the picture as (3, H, W) network space, the same at about H's training pixel count on the device)."""
        photo = torch.from_numpy(as_srgb01(image)).permute(2, 0, 1) * 2.0 - 1.0
        return photo, at_network_size(photo, self.config.data.height, self.config.data.width).to(self.device)


def as_srgb01(image: Any) -> np.ndarray:
    """A picture as (H, W, 3) float32 sRGB in [0, 1], or a ValueError that says what was expected."""
    from PIL import Image

    if isinstance(image, Image.Image):
        return photo_to_srgb01(image)
    if isinstance(image, torch.Tensor):
        raise ValueError("image: expected a NumPy array (H, W, 3) or a PIL image, got a torch tensor "
                         "(use tensor.permute(1, 2, 0).numpy() for a (3, H, W) one)")
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[-1] not in (1, 3, 4) or min(arr.shape[:2]) < 1:
        raise ValueError(f"image: expected an (H, W, 3) array (or (H, W), (H, W, 4)), got shape {tuple(np.shape(image))}")
    if arr.dtype == np.uint8:
        out = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        out = arr.astype(np.float32) / 65535.0
    elif np.issubdtype(arr.dtype, np.floating):
        out = arr.astype(np.float32)
        if not np.isfinite(out).all():
            raise ValueError("image: holds NaN or infinite values")
        if out.min() < -1e-3 or out.max() > 1.0 + 1e-3:
            raise ValueError(f"image: float values must be sRGB in [0, 1], got {out.min():.3g} to {out.max():.3g} "
                             "(divide 8-bit values by 255)")
        out = np.clip(out, 0.0, 1.0)
    else:
        raise ValueError(f"image: expected uint8, uint16 or float values, got {arr.dtype}")
    if out.shape[-1] == 1:
        out = np.repeat(out, 3, axis=-1)
    return np.ascontiguousarray(out[..., :3])


def _intrinsics_stack(intrinsics: Mapping[str, np.ndarray] | np.ndarray) -> np.ndarray:
    """(H, W, 9) network-space stack of normal, albedo, reflection given in the datasets' units."""
    if isinstance(intrinsics, Mapping):
        missing = [k for k in INTRINSIC_LAYERS if k not in intrinsics]
        if missing:
            raise ValueError(f"intrinsics: missing {', '.join(missing)} (expected normal, albedo, reflection)")
        layers = [np.asarray(intrinsics[k], dtype=np.float32) for k in INTRINSIC_LAYERS]
    else:
        arr = np.asarray(intrinsics, dtype=np.float32)
        if arr.ndim != 3 or arr.shape[-1] != 9:
            raise ValueError(f"intrinsics: expected an (H, W, 9) array or a dict of maps, got shape {arr.shape}")
        layers = [arr[..., 3 * j:3 * j + 3] for j in range(3)]
    shapes = {a.shape for a in layers}
    if len(shapes) != 1 or next(iter(shapes))[-1:] != (3,) or len(next(iter(shapes))) != 3:
        raise ValueError(f"intrinsics: expected three (H, W, 3) maps of one size, got "
                         + ", ".join(f"{k} {a.shape}" for k, a in zip(INTRINSIC_LAYERS, layers)))
    if not all(np.isfinite(a).all() for a in layers):
        raise ValueError("intrinsics: hold NaN or infinite values")
    return np.concatenate([to_network(k, a) for k, a in zip(INTRINSIC_LAYERS, layers)], axis=-1)


def _out_size(hw: torch.Size | tuple[int, int], size: tuple[int, int] | None) -> tuple[int, int]:
    """(height, width) of an output: the input's, or `size` given as (width, height)."""
    if size is None:
        return int(hw[0]), int(hw[1])
    if len(size) != 2 or min(size) < 1:
        raise ValueError(f"size: expected (width, height) of at least 1 pixel, got {size}")
    return int(size[1]), int(size[0])


def _srgb01(img: torch.Tensor) -> np.ndarray:
    """(3, H, W) network-space image -> (H, W, 3) float32 sRGB in [0, 1]."""
    return np.clip((img.permute(1, 2, 0).numpy() + 1.0) * 0.5, 0.0, 1.0).astype(np.float32)
