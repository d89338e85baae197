"""The sRGB transfer function on tensors (IEC 61966-2-1), shared by the shader, the probe and the
sanity benchmark's analytic renderer."""
from __future__ import annotations

import torch


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded [0, 1] -> linear (IEC 61966-2-1)."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """Linear -> sRGB-encoded, clipped to [0, 1]."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
