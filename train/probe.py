"""Validation while training: H's decomposition errors and R's input sensitivity on a probe set.

A probe is a set of images with their true intrinsics and object masks (a PBR dataset), held
at training size in memory and never used for gradients. Its figures are the Table-3 errors
of `eval.decomposition` computed on network-space tensors (|difference| x 127.5 in network
space is the 8-bit sRGB L1 the report prints), so a curve in `stats.jsonl` and the final
table agree up to resizing.

R's *input sensitivity*: how much R's output changes between different intrinsics, relative
to how much the true images of those intrinsics differ (car pixels, pairs of probe samples).
A renderer that draws one picture for every input scores 0, a perfect one 1.

R's *colour correlation*: whether R paints a car the colour it is. Per probe sample, the mean
colour of R's object pixels and of the true image's, each less its own grey level (so brightness
and exposure do not count) and less that channel's mean over the probe; the correlation of the
two over samples and channels. A renderer that draws every car in one colour of its own scores
about 0 however sharp its shapes are.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .losses import linear_mean, object_mask
from .colour import srgb_decode, srgb_encode

PROBE_PREFIX = "probe/"
EMA_PREFIX = "probe_ema/"  # the same figures of the moving-average weights


@dataclass
class ProbeSet:
    """(n, 3, h, w) images, (n, 9, h, w) true intrinsics, (n, 1, h, w) masks, network space; masks in [0, 1]."""

    images: torch.Tensor
    maps: torch.Tensor
    masks: torch.Tensor
    # constant predictor's albedo and reflection (network space, 3 values each): the training means
    const_albedo: torch.Tensor | None = None
    const_reflection: torch.Tensor | None = None
    # the per-pixel prior (9, h, w): the training intrinsics' mean at each pixel, which knows where
    # in the frame a car tends to be and which way its surfaces face there, and uses no image
    prior: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = len(self.images)
        if n < 2 or len(self.maps) != n or len(self.masks) != n:
            raise ValueError(f"a probe needs at least 2 samples with images, maps and masks alike (got {n})")

    def to(self, device: str | torch.device) -> "ProbeSet":
        mv = {k: (getattr(self, k).to(device) if getattr(self, k) is not None else None)
              for k in ("images", "maps", "masks", "const_albedo", "const_reflection", "prior")}
        return ProbeSet(**mv)


def load_probe(root: Path, height: int, width: int, limit: int | None = 64) -> ProbeSet:
    """The first `limit` samples of a PBR dataset at training size (cover-crop as in training)."""
    from blender_gen.conversions import to_network
    from blender_gen.dataset import DatasetError, INTRINSIC_LAYERS, open_dataset

    from .data import cover_crop

    ds = open_dataset(Path(root), kinds=("pbr",))
    n = len(ds) if limit is None else min(limit, len(ds))
    if n < 2:
        raise DatasetError(f"--probe {root}: needs at least 2 finished PBR samples (has {len(ds)})")
    imgs, maps, masks = [], [], []
    for i in range(n):
        layers = ds.load(i, ["rgb", *INTRINSIC_LAYERS, "mask"])
        for k, arr in layers.items():  # NaN would give plausible wrong figures (zero correlations), not an error
            if not np.isfinite(arr).all():
                raise DatasetError(f"--probe {ds.path(i)}: layer '{k}' holds NaN or infinite values (sample "
                                   f"{ds.rows[i]['index']}); regenerate it or choose another probe set")
        stack = np.concatenate([to_network(k, layers[k]) for k in INTRINSIC_LAYERS], axis=-1)
        for dst, arr in ((imgs, to_network("rgb", layers["rgb"])), (maps, stack),
                         (masks, np.clip(layers["mask"][..., :1].astype(np.float32), 0, 1))):
            dst.append(cover_crop(torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1).contiguous(), height, width))
    return ProbeSet(torch.stack(imgs), torch.stack(maps), torch.stack(masks))


def training_means(maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean albedo and reflection over object pixels (|normal| > 0.5) of network-space stacks,
    averaged in linear light and returned in network space: the constant predictor's values."""
    on = object_mask(maps)
    albedo, reflection = (srgb_encode(linear_mean(maps[:, sl], on)) * 2 - 1 for sl in (slice(3, 6), slice(6, 9)))
    return albedo, reflection


def pixel_prior(maps: torch.Tensor) -> torch.Tensor:
    """(9, h, w) per-pixel prior of (n, 9, h, w) network-space training stacks: at each pixel the mean
    normal direction and the mean linear albedo and reflection (network space), over the samples
    with an object there; the camera-facing normal and the global means where none has one."""
    on = object_mask(maps)  # (n, 1, h, w)
    count = on.sum(0)  # (1, h, w)
    normal = F.normalize((maps[:, 0:3] * on).sum(0), dim=0, eps=1e-6)
    normal = torch.where(count > 0, normal, torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).to(maps))
    out = [normal]
    for sl, glob in zip((slice(3, 6), slice(6, 9)), training_means(maps)):
        lin = (srgb_decode((maps[:, sl] + 1) * 0.5) * on).sum(0) / count.clamp_min(1)
        out.append(torch.where(count > 0, srgb_encode(lin) * 2 - 1, glob.view(3, 1, 1)))
    return torch.cat(out)


def training_references(intr, n: int = 200) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The no-image rows' values from up to `n` training intrinsics spread evenly over `intr` (an
    IntrinsicsData): the constant predictor's albedo and reflection, and the per-pixel prior."""
    picks = np.linspace(0, len(intr) - 1, min(n, len(intr))).round().astype(int)
    stacks = torch.stack([intr[(int(i), False)] for i in picks])
    albedo, reflection = training_means(stacks)
    return albedo, reflection, pixel_prior(stacks)


LAPLACE = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])


def high_frequency(x: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
    """(n,) mean |Laplacian| of (n, c, h, w) maps over the interior of the mask `on` (n, h, w)
    (pixels whose 4 neighbours are also on, so the silhouette's edge does not count), averaged over
    channels: the speckle figure. Piecewise-smooth maps score low, per-pixel noise high."""
    c = x.shape[1]
    k = LAPLACE.to(x).view(1, 1, 3, 3).repeat(c, 1, 1, 1)
    lap = F.conv2d(F.pad(x.float(), (1, 1, 1, 1), mode="replicate"), k, groups=c).abs().mean(1)
    m = F.pad(on.bool(), (1, 1, 1, 1))
    inner = on.bool() & m[:, :-2, 1:-1] & m[:, 2:, 1:-1] & m[:, 1:-1, :-2] & m[:, 1:-1, 2:]
    return (lap * inner).sum(dim=(1, 2)) / inner.sum(dim=(1, 2)).clamp_min(1)


def speckle_scores(pred: torch.Tensor, probe: "ProbeSet") -> dict[str, float]:
    """High-frequency energy of predicted normals (unit length) and albedo on the car, over the
    ground truth's: 1 = as smooth as the truth; a hidden code shows as several times more."""
    on = probe.masks[:, 0] >= 0.5
    out = {}
    for name, sl in (("normal", slice(0, 3)), ("albedo", slice(3, 6))):
        p, g = pred[:, sl], probe.maps[:, sl]
        if name == "normal":
            p, g = F.normalize(p, dim=1, eps=1e-6), F.normalize(g, dim=1, eps=1e-6)
        hp, hg = float(high_frequency(p, on).mean()), float(high_frequency(g, on).mean())
        out[f"{name}_hf"] = hp
        out[f"{name}_hf_ratio"] = hp / hg if hg > 0 else float("nan")
    return out


def _angles(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    cos = (F.normalize(pred, dim=1, eps=1e-8) * F.normalize(gt, dim=1, eps=1e-8)).sum(1)
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1)))


def _corr(u: torch.Tensor, v: torch.Tensor) -> float:
    u, v = u - u.mean(), v - v.mean()
    d = (u.norm() * v.norm()).item()
    return float((u * v).sum().item() / d) if d > 0 else 0.0


def _per_sample_mean(x: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
    """(n, h, w) values, (n, h, w) bool mask -> mean over masked pixels per sample."""
    return (x * on).sum(dim=(1, 2)) / on.sum(dim=(1, 2)).clamp_min(1)


@torch.no_grad()
def decomposition_scores(pred: torch.Tensor, probe: ProbeSet, prefix: str = "") -> dict[str, float]:
    """Table-3 errors of (n, 9, h, w) network-space predictions on the probe's object pixels."""
    gt, on = probe.maps, probe.masks[:, 0] >= 0.5
    keep = on.flatten(1).any(1)
    pred, gt, on = pred[keep], gt[keep], on[keep]
    ang = _angles(pred[:, 0:3], gt[:, 0:3])
    out = {f"{prefix}normal_deg": float(_per_sample_mean(ang, on).mean())}
    for name, sl in (("albedo_l1", slice(3, 6)), ("reflection_l1", slice(6, 9))):
        err = (pred[:, sl] - gt[:, sl]).abs().mean(1) * 127.5  # = 8-bit sRGB L1
        out[f"{prefix}{name}"] = float(_per_sample_mean(err, on).mean())
    return out


@torch.no_grad()
def evaluate_probe(model, probe: ProbeSet, batch: int = 16, prefix: str = PROBE_PREFIX,
                   references: bool = True) -> dict[str, float]:
    """`probe/...` figures of a model of any kind: H on the probe images, R on their intrinsics;
    `references` adds the constant predictor's and the per-pixel prior's figures."""
    was_training = model.training
    model.eval()
    try:
        preds, renders = [], []
        # fixed style codes (MUNIT draws them on the CPU and moves them: a CUDA generator fails there)
        gen = torch.Generator(device="cpu").manual_seed(0)
        for i in range(0, len(probe.images), batch):
            preds.append(model.decompose(probe.images[i:i + batch]).float())
            renders.append(model.render(probe.maps[i:i + batch], generator=gen).float())
    finally:
        model.train(was_training)
    pred, ren = torch.cat(preds), torch.cat(renders)
    on = probe.masks[:, 0] >= 0.5
    out = {f"{prefix}{k}": v for k, v in decomposition_scores(pred, probe).items()}
    for c, axis in enumerate("xyz"):
        out[f"{prefix}normal_corr_{axis}"] = _corr(pred[:, c][on], probe.maps[:, c][on])
    out.update({f"{prefix}{k}": v for k, v in speckle_scores(pred, probe).items()})
    if references:
        out.update(reference_scores(probe, prefix))
    # R: error against the true images on object pixels, and input sensitivity
    err = (ren - probe.images).abs().mean(1) * 127.5
    out[f"{prefix}render_l1"] = float(_per_sample_mean(err, on).mean())
    out[f"{prefix}r_sensitivity"] = input_sensitivity(ren, probe.images, on)
    out[f"{prefix}r_colour_corr"] = colour_correlation(ren, probe.images, on)
    gain = model.shared_gain() if hasattr(model, "shared_gain") else None  # the baselines have none
    if gain is not None:
        out[f"{prefix}r_gain"] = float(gain.mean())
    # H: does its albedo follow each car's paint (1), or give every car one colour (0)?
    out[f"{prefix}h_colour_corr"] = colour_correlation(pred[:, 3:6], probe.maps[:, 3:6], on)
    return out


@torch.no_grad()
def reference_scores(probe: ProbeSet, prefix: str = PROBE_PREFIX) -> dict[str, float]:
    """The rows that use no image, on the probe's pixels: the constant predictor ("const_") and,
    when the probe has one, the per-pixel prior of the training intrinsics ("prior_")."""
    out: dict[str, float] = {}
    # the constant predictor on the same pixels, for reference in every curve
    const = torch.zeros_like(probe.maps)
    const[:, 2] = 1.0
    if probe.const_albedo is not None:
        const[:, 3:6] = probe.const_albedo.view(1, 3, 1, 1)
        const[:, 6:9] = probe.const_reflection.view(1, 3, 1, 1)
    for k, v in decomposition_scores(const, probe).items():
        if k == "normal_deg" or probe.const_albedo is not None:
            out[f"{prefix}const_{k}"] = v
    if probe.prior is not None:
        prior = probe.prior.unsqueeze(0).expand(len(probe.maps), -1, -1, -1)
        out.update({f"{prefix}prior_{k}": v for k, v in decomposition_scores(prior, probe).items()})
    return out


def colour_correlation(renders: torch.Tensor, images: torch.Tensor, on: torch.Tensor) -> float:
    """Correlation over samples and channels of the object's mean chroma (mean colour less its
    grey level) in R's renders and in the true images. 1: R's car colours vary as the images'."""
    keep = on.flatten(1).any(1)
    if keep.sum() < 2:
        return 0.0
    w = on[keep].unsqueeze(1).float()

    def chroma(x: torch.Tensor) -> torch.Tensor:  # less each channel's mean over samples: only variation counts
        mean = (x[keep] * w).sum(dim=(2, 3)) / w.sum(dim=(2, 3)).clamp_min(1)  # (n, 3)
        c = mean - mean.mean(1, keepdim=True)
        return c - c.mean(0, keepdim=True)

    return _corr(chroma(renders).flatten(), chroma(images).flatten())


def input_sensitivity(renders: torch.Tensor, images: torch.Tensor, on: torch.Tensor) -> float:
    """Mean |R(M_i) - R(M_j)| over |I_i - I_j| for consecutive pairs (i, i+1), on pixels that are
    object in both. 0: R ignores its input; 1: R's outputs differ as much as the true images."""
    both = (on[:-1] & on[1:]).unsqueeze(1).float()
    d_r = ((renders[:-1] - renders[1:]).abs() * both).sum()
    d_i = ((images[:-1] - images[1:]).abs() * both).sum()
    return float(d_r / d_i) if d_i > 0 else 0.0


def probe_plot(rows: list[dict], title: str = "") -> bytes | None:
    """PNG of the probe curves in `stats.jsonl` rows (None when no row has them): see probe_figure."""
    fig = probe_figure(rows, title)
    if fig is None:
        return None
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def probe_figure(rows: list[dict], title: str = ""):
    """The probe curves of `stats.jsonl` rows as a matplotlib figure (None when no row has them).

    H's errors with the moving-average weights (solid; what inference uses) and the raw weights
    (faint), beside the two bars that use no image: the constant predictor (dashed) and the
    per-pixel prior (dash-dot), the stronger of which a decomposition has to beat; H's speckle
    (high-frequency energy over the truth's); normal correlations, R's input sensitivity and
    colour correlation, and the shader R's shared reflection gain."""
    rows = [r for r in rows if f"{PROBE_PREFIX}normal_deg" in r]
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["step"] for r in rows]
    has_ema = any(f"{EMA_PREFIX}normal_deg" in r for r in rows)

    def series(key: str, prefix: str = PROBE_PREFIX) -> list[float]:
        return [r.get(prefix + key, np.nan) for r in rows]

    def h_curve(ax, key: str, label: str, color: str) -> None:
        if has_ema:
            ax.plot(steps, series(key, EMA_PREFIX), label=f"{label} (moving avg.)", color=color)
            ax.plot(steps, series(key), label=f"{label} (raw)", color=color, alpha=0.3, lw=0.8)
        else:
            ax.plot(steps, series(key), label=label, color=color)

    def bars(ax, key: str, label: str, color: str) -> None:
        ax.plot(steps, series(f"const_{key}"), "--", color=color, alpha=0.6, label=f"{label}, constant")
        if any(np.isfinite(series(f"prior_{key}"))):
            ax.plot(steps, series(f"prior_{key}"), "-.", color=color, alpha=0.6, label=f"{label}, per-pixel prior")

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4))
    h_curve(axes[0], "normal_deg", "H normals", "C0")
    bars(axes[0], "normal_deg", "no image", "0.4")
    axes[0].set_ylabel("mean angle (deg)")
    for k, (key, name) in enumerate((("albedo_l1", "albedo"), ("reflection_l1", "reflection"))):
        h_curve(axes[1], key, name, f"C{k + 1}")
        bars(axes[1], key, name, f"C{k + 1}")
    axes[1].plot(steps, series("render_l1"), label="R image", color="C3")
    axes[1].set_ylabel("L1 (0-255 sRGB, object pixels)")
    pre = EMA_PREFIX if has_ema else PROBE_PREFIX
    axes[2].plot(steps, series("normal_hf_ratio", pre), label="normals", color="C0")
    axes[2].plot(steps, series("albedo_hf_ratio", pre), label="albedo", color="C1")
    axes[2].axhline(1.0, color="0.4", ls="--", lw=0.8, label="the truth's")
    axes[2].set_ylabel("high-frequency energy / truth's")
    for k, axis in enumerate("xyz"):
        axes[3].plot(steps, series(f"normal_corr_{axis}"), label=f"normal corr {axis}", color=f"C{k + 4}")
    axes[3].plot(steps, series("r_sensitivity"), label="R input sensitivity", color="k")
    axes[3].plot(steps, series("r_colour_corr"), ":", label="R colour corr.", color="k")
    axes[3].plot(steps, series("h_colour_corr"), ":", label="H albedo colour corr.", color="C3")
    if any(np.isfinite(series("r_gain"))):
        axes[3].plot(steps, series("r_gain"), "--", label="R reflection gain", color="k", alpha=0.6)
    top = np.nanmax([1.2, *series("r_sensitivity")])  # a renderer above 1 stays in view
    axes[3].set_ylim(-0.2, top + 0.1)
    for ln in (ln for ax in axes for ln in ax.get_lines() if len(ln.get_xdata()) == 1):
        ln.set_marker("o")  # a line through one probe draws nothing (before the legends, which copy it)
        ln.set_markersize(4)
    whats = ("H: normals (lower is better)", "H: albedo, reflection; R", "H: speckle", "agreement")
    for ax, what in zip(axes, whats):
        ax.set_xlabel("step")
        ax.set_title(f"{title}: {what}" if title else what, fontsize=9)
        ax.legend(fontsize=6)
    fig.tight_layout()
    return fig
