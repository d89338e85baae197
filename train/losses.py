"""Loss building blocks shared by the Intrinsic Autoencoder and the baselines."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .colour import srgb_decode


def gan_loss(logits: list[torch.Tensor], real: bool, kind: str, reduce: str = "sum") -> torch.Tensor:
    """Multi-scale GAN loss, summed over scales as pix2pixHD and MUNIT do (each scale is a
    discriminator), or averaged over them (`reduce="mean"`).

    lsgan: mean (D - target)^2 (pix2pixHD/CycleGAN); bce: the paper's log-likelihood
    formula, -[t log sigmoid(D) + (1 - t) log(1 - sigmoid(D))].
    """
    total = logits[0].new_zeros(())
    for d in logits:
        target = torch.full_like(d, 1.0 if real else 0.0)
        if kind == "lsgan":
            total = total + F.mse_loss(d.float(), target.float())
        else:
            total = total + F.binary_cross_entropy_with_logits(d.float(), target.float())
    return total / len(logits) if reduce == "mean" else total


def cycle_loss(recon: torch.Tensor, target: torch.Tensor, beta: float) -> torch.Tensor:
    """Smooth-L1 (Huber) distance, the paper's cycle consistency loss."""
    return F.smooth_l1_loss(recon.float(), target.float(), beta=beta)


def object_mask(stack: torch.Tensor) -> torch.Tensor:
    """(N, 1, H, W) 1.0 where a network-space intrinsics stack has an object (its normal is set;
    the background's is zero)."""
    return (stack[:, 0:3].float().norm(dim=1, keepdim=True) > 0.5).float()


def normal_length_loss(normals: torch.Tensor, threshold: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |1 - ||n||_2| over the pixels of `mask` (N, 1, H, W) or, without one, over pixels whose
    predicted normal is longer than `threshold`.

    The synthetic maps have zero normals on the background; the threshold (or the mask of the
    known object) keeps the loss from pushing background pixels to unit length.
    """
    length = normals.float().norm(dim=1)
    weight = (length > threshold).float() if mask is None else mask[:, 0].float()
    return ((1.0 - length).abs() * weight).sum() / weight.sum().clamp_min(1.0)


def chroma_loss(image: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor, block: int = 4,
                eps: float = 0.05) -> torch.Tensor:
    """Mean L1 distance between the chromaticities (colour / sum of channels) of `image` and
    `albedo` averaged over `block` x `block` cells, on the cells `mask` (N, 1, H, W) mostly covers.

    Both in network space ([-1, 1]). Chromaticity ignores brightness, so shading may darken the
    car; cell means let reflections and highlights vary within a cell. `eps` keeps dark cells
    (near-black paint, deep shadow) from dominating.
    """
    def cells(x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x.float(), block, ceil_mode=True)

    w = cells(mask)
    on = (w > 0.5).float()
    img = cells((image.float() + 1.0) * 0.5 * mask) / w.clamp_min(1e-6)
    alb = cells((albedo.float() + 1.0) * 0.5 * mask) / w.clamp_min(1e-6)

    def chroma(x: torch.Tensor) -> torch.Tensor:
        return x / (x.sum(1, keepdim=True) + eps)

    dist = (chroma(img) - chroma(alb)).abs().sum(1, keepdim=True)
    return (dist * on).sum() / on.sum().clamp_min(1.0)


def finish_logs(total: torch.Tensor, logs: dict[str, torch.Tensor], prefix: str) -> tuple[torch.Tensor, dict[str, float]]:
    """Add `<prefix>/total` and return the loss with its logs as plain floats."""
    logs[f"{prefix}/total"] = total
    return total, {k: float(v.detach()) for k, v in logs.items()}


def discriminator_terms(disc, real: torch.Tensor, fake: torch.Tensor, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """GAN losses of a discriminator on real data (target real) and on detached fakes."""
    return gan_loss(disc(real), True, kind), gan_loss(disc(fake.detach()), False, kind)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(c,) per-channel mean of (n, c, h, w) x over the pixels of an (n, 1, h, w) mask."""
    return (x * mask).sum(dim=(0, 2, 3)) / mask.sum().clamp_min(1)


def linear_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(3,) per-channel mean in linear light over the masked pixels of (n, 3, h, w) network-space
    colour maps (an albedo or reflection level)."""
    return masked_mean(srgb_decode((x.float() + 1) * 0.5), mask)


@torch.no_grad()
def update_running(running: torch.Tensor, new: torch.Tensor, momentum: float = 0.99) -> None:
    """Fold `new` into a running-mean buffer in place; a buffer still all zero takes `new` as it is."""
    new = new.to(running.dtype)
    running.copy_(new if not bool(running.any()) else momentum * running + (1 - momentum) * new)


def level_bias_loss(level: torch.Tensor, running: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Its value: the squared log bias of a running (3,) level against the target's, summed over
    channels. Its gradient moves this batch's `level` by that bias (d/d log level = 2 x bias), so a
    population that is too bright is darkened without pulling each sample toward the mean."""
    bias = (running.clamp_min(1e-4).log() - target.clamp_min(1e-4).log()).detach()
    log_level = level.clamp_min(1e-4).log()
    return (bias ** 2).sum() + (2 * bias * (log_level - log_level.detach())).sum()
