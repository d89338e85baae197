"""Second-order spherical-harmonics shading: the physical tie between normals and brightness.

A diffuse surface under any distant lighting is shaded, to within a few percent, by a quadratic
polynomial of its normal (Ramamoorthi and Hanrahan 2001): 9 coefficients per colour channel.
`fit_shading` finds, per image and in closed form, the lighting that best explains an image's
luminance from given intrinsics,

    lum(I) ~= lum(A) * sum_k c_k Y_k(N) + g * lum(F)     (on the object, linear light),

and returns the relative L1 residual. Used as a loss it says "this image's brightness follows these
normals": on R(M_s) with M_s's true maps it trains R to shade by the normals it is given; on a real
image with H's own maps it trains H's normals to explain the image's shading (as SfSNet learns
normals from unlabelled photos). Tensors are in network space (DESIGN.md): normals as they are,
colours sRGB in [-1, 1].
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .colour import srgb_decode

# Rec. 709 luminance of linear RGB
LUMA = (0.2126, 0.7152, 0.0722)
# real SH basis constants, bands 0-2
_C0, _C1, _C2, _C3, _C4 = 0.282095, 0.488603, 1.092548, 0.315392, 0.546274


def sh_basis(normals: torch.Tensor) -> torch.Tensor:
    """(n, 3, h, w) unit normals -> (n, 9, h, w) real SH basis functions Y_00 ... Y_22."""
    x, y, z = normals[:, 0:1], normals[:, 1:2], normals[:, 2:3]
    return torch.cat([torch.full_like(x, _C0), _C1 * y, _C1 * z, _C1 * x, _C2 * x * y, _C2 * y * z,
                      _C3 * (3 * z * z - 1), _C2 * x * z, _C4 * (x * x - y * y)], dim=1)


def linear(x: torch.Tensor) -> torch.Tensor:
    """Network-space sRGB ([-1, 1]) -> linear light [0, 1]."""
    return srgb_decode((x.float() + 1) * 0.5)


def luminance(lin: torch.Tensor) -> torch.Tensor:
    """(n, 3, h, w) linear RGB -> (n, 1, h, w) luminance."""
    w = torch.tensor(LUMA, device=lin.device, dtype=lin.dtype).view(1, 3, 1, 1)
    return (lin * w).sum(1, keepdim=True)


def shading_design(normals: torch.Tensor, albedo: torch.Tensor, reflection: torch.Tensor) -> torch.Tensor:
    """(n, 10, h, w) columns of the shading model: lum(A) x the 9 SH functions of N, and lum(F)."""
    n = F.normalize(normals.float(), dim=1, eps=1e-6)
    return torch.cat([luminance(linear(albedo)) * sh_basis(n), luminance(linear(reflection))], dim=1)


def _ridge_solve(x: torch.Tensor, w: torch.Tensor, y: torch.Tensor, ridge: float) -> torch.Tensor:
    """(b, k, 1) weighted least squares of y (b, 1, p) on the k columns x (b, k, p) with weights w
    (b, 1, p); `ridge`, relative to the mean diagonal of the normal equations, keeps a flat normal
    map (all columns alike) solvable. Differentiable in x, w and y."""
    xw = x * w
    gram = xw @ x.transpose(1, 2)
    scale = gram.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-6)
    eye = torch.eye(gram.shape[-1], device=gram.device, dtype=gram.dtype)
    return torch.linalg.solve(gram + ridge * scale.view(-1, 1, 1) * eye, xw @ y.transpose(1, 2))


def fit_shading(image: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor, reflection: torch.Tensor,
                mask: torch.Tensor, ridge: float = 1e-3, min_pixels: int = 16,
                gain: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image, the least-squares lighting (9 SH coefficients and a reflection gain) that explains
    lum(image) from the maps on `mask` (n, 1, h, w); returns (residual, coefficients).

    residual: (n,) mean |fit - lum(image)| over the mask divided by the mean luminance there (0 for an
    image with fewer than `min_pixels` mask pixels: nothing to fit); coefficients: (n, 10). The
    solve is differentiable, so a loss on the residual moves the maps (and the image), not only the
    lighting (`_ridge_solve`). `gain` (3,): a reflection gain fixed for every image (its luminance
    is used) instead of one fitted per image; only the 9 SH coefficients are then fitted.
    """
    w = mask.float().flatten(2)  # (n, 1, p)
    x = shading_design(normals, albedo, reflection).flatten(2)  # (n, 10, p)
    y = luminance(linear(image)).flatten(2)  # (n, 1, p)
    if gain is None:
        coeffs = _ridge_solve(x, w, y, ridge)  # (n, 10, 1)
    else:
        g = luminance(gain.float().view(1, 3, 1, 1)).view(1, 1, 1).expand(len(x), 1, 1)
        sh = _ridge_solve(x[:, :9], w, y - g * x[:, 9:], ridge)  # (n, 9, 1)
        coeffs = torch.cat([sh, g], dim=1)
    fit = coeffs.transpose(1, 2) @ x  # (n, 1, p)
    count = w.sum(dim=(1, 2))
    res = ((fit - y).abs() * w).sum(dim=(1, 2)) / (y * w).sum(dim=(1, 2)).clamp_min(1e-3)
    return torch.where(count >= min_pixels, res, torch.zeros_like(res)), coeffs[..., 0]


def shading_loss(image: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor, reflection: torch.Tensor,
                 mask: torch.Tensor, ridge: float = 1e-3, gain: torch.Tensor | None = None) -> torch.Tensor:
    """Mean relative shading residual (`fit_shading`) over the images that have an object."""
    res, _ = fit_shading(image, normals, albedo, reflection, mask, ridge, gain=gain)
    has = (mask.flatten(1).sum(1) >= 16).float()
    return (res * has).sum() / has.sum().clamp_min(1.0)


def render_sh(normals: torch.Tensor, albedo: torch.Tensor, reflection: torch.Tensor, light: torch.Tensor,
              gain: torch.Tensor) -> torch.Tensor:
    """The physically based part of a deferred shader: linear RGB = lin(A) x SH(N; light) + gain x lin(F).

    light: (3, 9) or (n, 3, 9) SH coefficients per colour channel; gain: (3,) or (n, 3). The
    background (zero normal, black albedo) takes only the reflection term, so an environment stored
    in the reflection layer shows through."""
    n = F.normalize(normals.float(), dim=1, eps=1e-6)
    basis = sh_basis(n)  # (n, 9, h, w)
    light = light.expand(len(basis), -1, -1) if light.dim() == 2 else light
    gain = gain.expand(len(basis), -1) if gain.dim() == 1 else gain
    shading = torch.einsum("bck,bkhw->bchw", light.float(), basis)
    return linear(albedo) * shading.clamp_min(0) + gain.float().view(-1, 3, 1, 1) * linear(reflection)


def fit_lighting(image: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor, reflection: torch.Tensor,
                 mask: torch.Tensor, ridge: float = 1e-3, gain: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image and colour channel, the least-squares SH lighting and reflection gain that explain
    lin(image) from the maps on `mask`: returns ((n, 3, 9) lighting, (n, 3) gains), the form
    `render_sh` takes. The same solve as `fit_shading`, one channel at a time; `gain` (3,) fixes the
    reflection gain (fitting only the lighting)."""
    n = F.normalize(normals.float(), dim=1, eps=1e-6)
    basis = sh_basis(n).flatten(2)  # (b, 9, p)
    a, f, y = linear(albedo).flatten(2), linear(reflection).flatten(2), linear(image).flatten(2)  # (b, 3, p)
    b, p = basis.shape[0], basis.shape[-1]
    w = mask.float().flatten(2).repeat_interleave(3, dim=0)  # (b * 3, 1, p)
    if gain is not None:
        g = gain.float().view(1, 3, 1)
        x = (a.unsqueeze(2) * basis.unsqueeze(1)).reshape(b * 3, 9, p)
        light = _ridge_solve(x, w, (y - g * f).reshape(b * 3, 1, p), ridge).reshape(b, 3, 9)
        return light, g.view(1, 3).expand(b, 3)
    x = torch.cat([a.unsqueeze(2) * basis.unsqueeze(1), f.unsqueeze(2)], dim=2).reshape(b * 3, 10, p)
    coeffs = _ridge_solve(x, w, y.reshape(b * 3, 1, p), ridge).reshape(b, 3, 10)
    return coeffs[..., :9], coeffs[..., 9]
