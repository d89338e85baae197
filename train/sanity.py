"""The sanity settings that separate "implementation" from "budget" (docs/experiment_log.md "Making it learn").

S0, exact: the "real" images are a fixed analytic shading of held-out intrinsics,
    sRGB(A (0.3 + 0.7 max(0, n.l)) + 0.5 F), l = (0.3, 0.6, 0.7) normalised, camera space,
so a perfect renderer exists exactly and the two domains differ only in the pairing.
S1, near: the "real" images are PBR renders of the training cars and skies (another seed) with
the background masked to black, so every real pixel is expressible as intrinsics.

Tensors here are in network space (DESIGN.md): normals as they are, colours sRGB in [-1, 1].
"""
from __future__ import annotations

from pathlib import Path

import torch

from .colour import srgb_decode, srgb_encode  # noqa: F401  (the sanity shader's colour transfer)

LIGHT = torch.tensor([0.3, 0.6, 0.7]) / torch.tensor([0.3, 0.6, 0.7]).norm()


def shade_network(maps: torch.Tensor) -> torch.Tensor:
    """S0's analytic renderer: (n, 9, h, w) network-space intrinsics -> (n, 3, h, w) network-space image.

    The background (zero normal, black albedo and reflection) shades to black."""
    n = maps[:, 0:3]
    albedo = srgb_decode((maps[:, 3:6] + 1) * 0.5)
    refl = srgb_decode((maps[:, 6:9] + 1) * 0.5)
    ndl = (n * LIGHT.to(maps).view(1, 3, 1, 1)).sum(1, keepdim=True).clamp_min(0)
    return srgb_encode(albedo * (0.3 + 0.7 * ndl) + 0.5 * refl) * 2 - 1


def load_stacks(root: Path, height: int, width: int, limit: int | None = None) -> torch.Tensor:
    """(n, 9, h, w) network-space intrinsics of a dataset at training size."""
    from .data import IntrinsicsData

    data = IntrinsicsData(Path(root), height, width)
    n = len(data) if limit is None else min(limit, len(data))
    return torch.stack([data[(i, False)] for i in range(n)])


def load_pbr(root: Path, height: int, width: int, limit: int | None = None) -> tuple[torch.Tensor, ...]:
    """(images, intrinsics, masks) of a PBR dataset at training size, network space (masks in [0, 1])."""
    from .probe import load_probe

    p = load_probe(Path(root), height, width, limit=limit)
    return p.images, p.maps, p.masks


def masked_black(images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """S1's "real" images: the background set to black (network -1)."""
    return torch.where(masks >= 0.5, images, torch.full_like(images, -1.0))
