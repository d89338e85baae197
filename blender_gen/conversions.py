"""Colour and network-space conversions: the one place that defines them.

Network space (DESIGN.md): normals as they are in [-1, 1]; albedo, reflection and rgb
sRGB-encoded with the standard transfer function, clipped to [0, 1], mapped to [-1, 1].
"""
from __future__ import annotations

import numpy as np

# The IEC 61966-2-1 sRGB transfer functions exactly as colour-science computes them
# (`colour.models.eotf_sRGB` / `eotf_inverse_sRGB`, tests/test_pure.py checks bit-equality).
# Written out because `import colour` loads its plotting stack (matplotlib, SciPy's interpolation):
# seconds of start-up in every process that converts one image.
_L_KNEE = 0.0031308
_V_KNEE = _L_KNEE * 12.92  # colour-science's eotf_inverse_sRGB(0.0031308): the inverse's knee, linear side


def _spow(a: np.ndarray, p: float) -> np.ndarray:
    """sign(a) |a|^p (colour-science's `spow`): defined for negative inputs."""
    return np.sign(a) * np.abs(a) ** p


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear."""
    v = np.asarray(x, dtype=np.float64)
    return np.where(v <= _V_KNEE, v / 12.92, _spow((v + 0.055) / 1.055, 2.4))


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear -> sRGB-encoded, clipped to [0, 1] (HDR values saturate)."""
    lin = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(lin <= _L_KNEE, lin * 12.92, 1.055 * _spow(lin, 1 / 2.4) - 0.055)


COLOUR_LAYERS = ("albedo", "reflection", "rgb")


def to_network(layer: str, x: np.ndarray) -> np.ndarray:
    """A dataset layer (H, W, C) in its stored units -> network space [-1, 1], float32."""
    if layer == "normal":
        return np.clip(np.asarray(x, dtype=np.float32), -1.0, 1.0)
    if layer in COLOUR_LAYERS:
        return (linear_to_srgb(x) * 2.0 - 1.0).astype(np.float32)
    if layer == "mask":
        return (np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0) * 2.0 - 1.0)
    raise ValueError(f"no network-space conversion for layer {layer!r}")


def from_network(layer: str, x: np.ndarray) -> np.ndarray:
    """Network space [-1, 1] -> the dataset's stored units (linear colour, raw normals)."""
    x = np.asarray(x, dtype=np.float64)
    if layer == "normal":
        return np.clip(x, -1.0, 1.0).astype(np.float32)
    if layer in COLOUR_LAYERS:
        return srgb_to_linear(np.clip((x + 1.0) * 0.5, 0.0, 1.0)).astype(np.float32)
    if layer == "mask":
        return np.clip((x + 1.0) * 0.5, 0.0, 1.0).astype(np.float32)
    raise ValueError(f"no network-space conversion for layer {layer!r}")


def preview_srgb8(layer: str, x: np.ndarray) -> np.ndarray:
    """A layer as an 8-bit sRGB picture for people: normals as (n + 1) / 2."""
    if layer == "normal":
        img = (np.clip(np.asarray(x, dtype=np.float64), -1, 1) + 1.0) * 0.5
    elif layer == "depth":  # near bright, far dark, over this picture's range; background black
        d = np.asarray(x, dtype=np.float64)[..., 0]
        on = d > 0
        lo, hi = (d[on].min(), d[on].max()) if on.any() else (0.0, 1.0)
        img = np.repeat(np.where(on, 1.0 - 0.8 * (d - lo) / max(hi - lo, 1e-6), 0.0)[..., None], 3, axis=-1)
    elif layer == "part":  # a fixed colour per part index (golden-ratio hues), background black
        k = np.round(np.asarray(x)[..., 0]).astype(np.int64)
        hue = (k * 0.618034) % 1.0
        rgb = np.stack([np.abs(hue * 6 - 3) - 1, 2 - np.abs(hue * 6 - 2), 2 - np.abs(hue * 6 - 4)], axis=-1)
        img = np.where((k > 0)[..., None], 0.25 + 0.75 * np.clip(rgb, 0, 1), 0.0)
    elif layer in ("mask", "material", "gloss"):
        img = np.repeat(np.clip(np.asarray(x, dtype=np.float64), 0, 1), 3, axis=-1) if x.shape[-1] == 1 else x
    else:
        img = linear_to_srgb(x)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
