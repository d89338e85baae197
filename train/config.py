"""Training configuration: plain dataclasses, TOML presets, `--set key=value` overrides.

Every value the paper leaves open is a named field here with a documented default
(pix2pixHD / CycleGAN practice). The resolved config is saved in every run folder
(`training_options.json`) and a run is resumed from that alone.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

PRESETS_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class DataConfig:
    height: int = 256  # training resolution (the paper: 256 x 512, aspect 1:2)
    width: int = 512
    batch_size: int = 1  # per process
    workers: int = 2  # DataLoader processes decoding EXRs / photos (when not cached)
    # Decode each dataset once into a training-size tensor file in the run folder when it fits in
    # this many GB (then no loader processes are needed); 0 = decode every epoch as before
    cache_gb: float = 4.0
    hflip: bool = True  # flips images and maps together; a flip negates normal X


@dataclass
class ModelConfig:
    """The Intrinsic Autoencoder's networks (model.kind = "iae"); baselines have their own sections."""

    kind: str = "iae"  # "iae" (the paper), "cyclegan", "munit", or "oracle" (R and H trained on paired PBR data)
    inputs: str = "NAF"  # which intrinsics R sees: any subset of N (normal), A (albedo), F (reflection)
    # R: pix2pixHD global generator (+ optional local enhancer)
    r_ngf: int = 64
    r_downsample: int = 4
    r_blocks: int = 9
    r_local_enhancers: int = 0  # 1 = pix2pixHD's coarse-to-fine local enhancer on top
    # H = {H_N, H_A, H_F}: ResNet generators with 5 residual blocks (the paper)
    h_ngf: int = 64
    h_downsample: int = 2
    h_blocks: int = 5
    normal_output: str = "tanh"  # "tanh" + the normal-length loss (the paper), or "normalize"
    # How H's decoders double the resolution: "transposed" (the paper's pix2pixHD/CycleGAN layers),
    # "resize" (nearest-neighbour upsampling + 3x3 convolution, free of the transposed layers'
    # checkerboard) or "subpixel" (a convolution to four phases + pixel shuffle, ICNR-initialised).
    # Measured at the cpu budget against transposed: subpixel's normals 1.0 / 1.2 / 1.5 deg better on
    # seeds 21-23 (0.6-1.4 on S0/S1, 3 seeds each), lattice peaks 1.6-2.6 against 2.1-3.5, colour maps
    # within the seed spread; resize takes the peaks to 1.0-1.4 (truth 1.0-1.1) with normals level and
    # albedo and reflection 1.2-1.9 worse (docs/normals_from_shading.md, "H's upsampling").
    h_upsample: str = "subpixel"
    # Not in the paper: "net" = R is the pix2pixHD generator alone (the paper); "shader" = R is a
    # deferred shader, lin(A) x SH(N; learned lighting) + gain x lin(F) (train.shading), plus the
    # same generator as a residual of amplitude shader_residual (network units; 0 = shader only) on
    # the background, so R's shading follows the normals from the first step and H learns to read
    # normals from shading. "shader" (the default) with loss.w_shading_ren = 3, shader_background =
    # "environment" and loss.w_dec = 0, measured against the paper's R with the previous defaults
    # (docs/normals_from_shading.md, "The cycle-free shader as the default"; EMA normals at the end of
    # each run): the 32x64 protocol (PBR images with backgrounds), 3000 steps, 3 seeds: 31.8 / 30.5 /
    # 30.6 deg against 41.4 / 40.7 / 41.7 (per-pixel prior 33.2); S0 23.3 / 23.7 / 23.4 against
    # 38.6 / 40.3 / 35.5; S1 29.4 / 29.1 / 29.2 against 36.9 / 39.8 / 38.4; the gpu budget's networks at
    # 256x512, step ~3250, 2 seeds: 35.5 / 37.5 against 47.5 / 46.3. The shader alone with the
    # decomposition cycle at 10 and the reflection gain drawing the background lost to the paper's R
    # on the protocol (48.6 / 49.3 deg at step 5000 of the cpu budget, albedo 74 / 73): the cycle
    # paid H to copy real images pixel for pixel, which the shader cannot draw. --config paper keeps "net".
    renderer: str = "shader"
    # The generator's share: 0 (measured) = R is the shader alone. A residual on the car let R and H
    # agree on a hidden code (S0 normals 27 -> 36 deg, speckle x2); one on the background only gave H a
    # cue to tell R's images from real ones (its noise against their clean background), and H then put
    # real images into its reflection map (S1 normals 37-48 deg). The shader draws the environment
    # behind the car from the reflection layer.
    shader_residual: float = 0.0
    shader_residual_on: str = "background"  # "background" (where the intrinsics have no object) or "everywhere"
    # "per_image": R(H(I_r)) is lit by the SH lighting fitted to I_r through H's maps, and R(M_s) by one
    # drawn from the last lighting_bank such fits, so H sees cars under the real images' lightings (a
    # global appearance code of 30 numbers that cannot carry the intrinsics); "global": one learned lighting
    shader_lighting: str = "per_image"
    lighting_bank: int = 256
    # The level of the bank's lightings. "fit" (the default): as fitted. "images": every lighting drawn
    # for R(M_s), and the bank's mean used by inference, scaled per colour channel so that R(M_s) is on
    # average as bright on the car as the real images are on H's car mask (running means, about 100
    # steps' memory). Measured on the protocol screen: normals level, albedo and R's input sensitivity
    # worse (0.71 / 0.68 against 0.82 / 0.82); the level was right already, the bank's split between
    # shading and reflection gain is what is off (docs/normals_from_shading.md).
    bank_level: str = "fit"
    # "shared": one learned gain per colour channel for every image, starting at shader_gain_start;
    # "per_image": each shading fit also fits a reflection gain (the default before). Fitted per image,
    # the gain let H put a real image into its reflection map, and the bank's lightings put too much
    # of each car into the gain (R's input sensitivity 0.83 / 0.79 at the cpu budget). Shared, at the
    # cpu budget (seeds 21, 22): albedo 30.7 / 26.7 against 34.5 / 33.0, KID lower, R's sensitivity
    # 1.11 / 1.14, normals level; S0 / S1 pass on three seeds, level with per_image on the two paired
    # seeds (docs/normals_from_shading.md). Its learned gain falls to 0.02 at the cpu budget: R draws
    # the car without reflections.
    shader_gain: str = "shared"
    shader_gain_start: float = 0.25
    # The shared gain's floor: the learned gain is this plus a positive part. Without one R learns to
    # draw the car without reflections at the cpu budget (gain 0.02; 0.04-0.05 on S1). At 0.1 R draws
    # them (gain 0.11-0.12) and follows its input as much as the images vary (sensitivity 0.92-0.99
    # against 1.07-1.16); at the cpu budget on four paired seeds every map is better (normals 0.6-0.8
    # deg, albedo 0.2-0.7, reflection 0.3-1.4), KID level; on S1 (three seeds) normals level, albedo
    # 0.5-2.0 worse, reflection 0.5-1.6 better; on S0, where the learned gain stays above it (0.55), level.
    # The gpu budget's unfloored gain (0.22-0.24) is above it too; no gpu run has had it yet
    # (docs/normals_from_shading.md, "The floor becomes the default").
    shader_gain_min: float = 0.1
    # Where the stack has no object (zero normal), the shader shows: "gain" = gain x lin(F), the
    # reflection gain fitted on the car scaling the environment too; "environment" = lin(F) as the
    # intrinsics store it (the scene behind the car, drawn apart from the car's shading and gain).
    # Measured on the protocol at 32x64 with w_shading_ren = 3 and the decomposition cycle at 10:
    # 55.2 / 43.6 deg against "gain"'s 52.2 / 46.1 (two seeds), no consistent effect; without that
    # cycle (loss.w_dec = 0), "environment" is part of the default measured above.
    shader_background: str = "environment"
    # D_I (3 ch) and D_M (9 ch): multi-scale PatchGAN, 2 scales (the paper)
    d_ndf: int = 64
    d_layers: int = 3
    d_scales: int = 2
    norm: str = "instance"  # "instance" or "batch"


@dataclass
class LossConfig:
    """The Intrinsic Autoencoder's objective (Eq. 7: L_cyc + L_norm + L_adv)."""

    gan: str = "bce"  # "bce" (the paper's log formula) or "lsgan" (pix2pixHD/CycleGAN practice)
    shared_discriminator: bool = True  # ablation: off = D_I sees only R(M_s), D_M only H(I_r)
    rendering_cycle: bool = True  # ablation: off = no M_s -> R -> H cycle: no synthetic intrinsics reach R or H
    decomposition_cycle: bool = True  # ablation: off = no I_r -> H -> R cycle: no real image reaches R or H
    # Eq. 7 sums the terms without weights (paper.toml keeps that). These defaults follow the
    # measurements of docs/experiment_log.md "Making it learn": cycles at 10 (CycleGAN's and pix2pixHD's lambda),
    # GAN terms averaged, D_M's terms at a tenth, L_norm on the car only.
    w_ren: float = 10.0
    # 0 with renderer = "shader" (the default): the shader cannot draw a real image pixel for pixel
    # (no shadow, sky or lamp model), so that cycle paid H to copy the image into its maps; measured
    # against 10 and 1 in docs/normals_from_shading.md (protocol at 32x64: 31.8 / 30.5 deg against 55.2 /
    # 43.6 at 10 and 32.7 / 31.5 at 1). The paper's R (renderer = "net") was measured best at 10.
    w_dec: float = 0.0
    w_norm: float = 1.0
    w_adv: float = 1.0
    smooth_l1_beta: float = 1.0 / 16  # Smooth-L1 threshold in network units ([-1, 1])
    # Not in the paper: std of Gaussian noise added to R(M_s) and H(I_r) before the second network of
    # each cycle, so neither can pass the input on as a faint hidden code (Chu et al. 2017); 0 = the paper.
    cycle_noise: float = 0.0
    # Not in the paper: each cycle loss trains only the cycle's second network (the first one's
    # output enters it detached), so neither network is rewarded for hiding its input in codes
    # the other can read (docs/experiment_log.md "It must learn first"); false = the paper's joint gradients.
    cycle_detach: bool = False
    normal_threshold: float = 0.5  # the length loss applies where |n| > this (not on background)
    # Where L_norm acts: "threshold" (wherever |n| > normal_threshold, on H(I_r) and H(R(M_s))) or
    # "car" (on H(R(M_s)) where M_s has an object: never on the background, see docs/experiment_log.md)
    normal_length_on: str = "car"
    # "sum": GAN terms summed over scales and fakes (pix2pixHD); "mean": averaged over both, so
    # each discriminator weighs as one term of Eq. 7 however many scales and fakes it judges
    gan_reduce: str = "mean"
    # D_M's generator terms weigh w_adv * w_adv_m (D_M sees no image unless adv_m_cond). 0 (H learns from R's
    # renders alone) passes S1 on three seeds (23.4-24.0 deg against 29.1-29.4) but loses 0.3 / 2.3 deg
    # on the 32x64 protocol (docs/normals_from_shading.md, "Without D_M"): 0.1 stays
    w_adv_m: float = 0.1
    # Not in the paper: D_M judges maps average-pooled by this factor (real and fakes alike), so it
    # can still judge silhouettes and broad shapes but gains nothing from pixel-level texture that
    # H cannot read from the image and would otherwise invent (speckle). 1 = the paper.
    adv_m_pool: int = 1
    # Not in the paper: where D_M judges the maps. "all" (the paper); "car": real and fake stacks
    # are zeroed outside their own object mask (normals longer than 0.5), so D_M still sees each
    # silhouette but not what the reflection map draws behind the car; "reflection": D_M sees the
    # reflection map only (normals and albedo zeroed), so H's normals and albedo learn from R's
    # renders and the shading alone, while D_M still judges the reflection map (without D_M the
    # protocol lost reflection and R's colour).
    # "reflection" (measured, docs/normals_from_shading.md "D_M on the reflection map only, on every
    # seed"): S1 23.4-24.0 deg against 29.1-29.4 and S0 22.0-22.9 against 23.3-23.7 on three seeds; the
    # 32x64 protocol level on normals over three seeds (30.8 against 31.0), better albedo, R's colour kept,
    # speckle 0.3-0.4x the truth's against 1.5x; the reflection map 1-4 worse. At the cpu budget (seeds 21 and
    # 22, the report): normals 26.3 / 26.5 against 28.9 / 27.1, 9.4 deg better than the per-pixel prior on both
    # (docs/normals_from_shading.md "The cpu budget with D_M on the reflection map")
    adv_m_on: str = "reflection"
    # Not in the paper: R1 gradient penalty on D_M (Mescheder et al. 2018), gamma / 2 x the squared
    # gradient of its logits at the real maps M_s: a D_M whose verdict cannot turn on pixel-level
    # perturbations of a real map, so it cannot ask H for texture the image does not show. 0 = the paper.
    # 0.01 passes S1 on three seeds (22.3-23.2 deg against 29.1-29.4) and S0 (21.3 on two, against 23.3-23.7),
    # but on the 32x64 protocol it is level on average over three seeds (-0.5, +2.6, -1.2 deg) and R's
    # colour correlation falls below 0.85 on two (docs/normals_from_shading.md, "D_M without the
    # reconstructions, and with a gradient penalty"); at 0.1 and 1 D_M sits at chance: 0 stays
    r1_m: float = 0.0
    # Not in the paper: what D_M judges the maps beside. "none" (the paper): the maps alone.
    # "image": each stack beside the image it goes with (M_s with R(M_s), H(I_r) with I_r, H(R(M_s))
    # with R(M_s); the images detached), and M_s beside another sample's R(M_s) as one more fake, so
    # D_M must judge whether the maps fit their image (a matching-aware discriminator, Reed et al.
    # 2016) rather than whether they look like any training map: it cannot ask H for detail its
    # image does not show. Needs the rendering cycle (the real pairs are R's renders). Measured worse
    # on S1 and the 32x64 protocol (5-6 deg at step 1250, both seeds): the image half gives the domain
    # gap away (docs/normals_from_shading.md, "D_M beside the image, and D_M from the decay's start").
    adv_m_cond: str = "none"
    # Not in the paper: the training step from which D_M's generator terms act (D_M itself learns
    # from step 0, so it judges from the first step it counts). 0 = the paper. From the decay's start
    # (1500 of 3000) S1 ends at the default's figure and the protocol 1.3-2.5 deg behind it (same section).
    adv_m_from: int = 0
    # Not in the paper: with a shared discriminator, the generator terms of the cycle
    # reconstructions (R(H(I_r)), H(R(M_s))) weigh w_adv_rec times those of the direct
    # translations (a weighted mean with gan_reduce "mean"); the discriminators still learn
    # from both. 1 = the paper; 0 (measured, docs/experiment_log.md "The cpu comparison on a GPU"): the GAN
    # gradient through the reconstructions fought the cycles and cost ~8 degrees of normals.
    w_adv_rec: float = 0.0
    # Not in the paper: R(M_s)'s chromaticity on the car follows its albedo input's, over 4x4
    # cells (train.losses.chroma_loss), the role CycleGAN's identity loss plays for colour
    # composition. The cycles alone are satisfied by any colour bijection the discriminators
    # cannot see (a hue rotation of random paints): R painted every car one colour and H's albedo
    # did not follow the paint. 10 (measured, docs/experiment_log.md "R paints cars their colour"); 1 did nothing;
    # 0 = the paper.
    w_chroma: float = 10.0
    # Not in the paper: the shading tie (train.shading). Per image, the closed-form SH lighting that
    # best explains the image's luminance from intrinsics; the weighted relative residual is the loss.
    # w_shading_ren: on R(M_s) with M_s's maps (R must shade by the normals it is given);
    # w_shading_dec: on I_r with H(I_r)'s maps on H's object mask (H's normals must explain the real
    # image's shading). 0 = the paper. w_shading_ren = 3 is the default with renderer = "shader"
    # (measured: see model.renderer); w_shading_dec = 3 beside it cost 7-9 deg on the 32x64 protocol
    # (40.7 / 40.2 against 33.9 / 32.9 at step 1500, docs/normals_from_shading.md), so it stays 0.
    w_shading_ren: float = 3.0
    w_shading_dec: float = 0.0
    # Not in the paper: the albedo-lighting scale. With D_M on the reflection map only nothing pins
    # the level of H's albedo, and the lightings fitted through it are off by the same factor (H's
    # albedo 10-30% too bright in green and blue at the cpu budget, docs/normals_from_shading.md "Why
    # R's input sensitivity reads 0.8"). > 0: the running mean (per channel, linear, on the car) of
    # H's albedo on real images is held at the training intrinsics' running mean; each batch is
    # moved by the population's bias, not toward the mean, so cars keep their own paint. 0 = the paper
    # and the default: at 3 the level was met, but H washed out the paint (protocol screen albedo
    # 57.4 / 55.9 against 43.4 / 40.3, normals level, R's sensitivity lower; same doc).
    w_albedo_level: float = 0.0


@dataclass
class CycleGANConfig:
    """The CycleGAN baseline (model.kind = "cyclegan"): the reference implementation's defaults."""

    ngf: int = 64
    n_down: int = 2
    n_blocks: int = 9  # resnet_9blocks (256 px)
    ndf: int = 64
    d_layers: int = 3  # the 70x70 PatchGAN
    norm: str = "instance"
    gan: str = "lsgan"
    w_cycle: float = 10.0  # lambda_A = lambda_B = 10
    w_adv: float = 1.0
    pool: int = 50


@dataclass
class MunitConfig:
    """The MUNIT baseline (model.kind = "munit"): the reference edges2shoes configuration."""

    dim: int = 64
    n_down: int = 2
    n_res: int = 4
    style_dim: int = 8
    mlp_dim: int = 256
    style_down: int = 4
    d_ndf: int = 64
    d_layers: int = 4
    d_scales: int = 3
    gan: str = "lsgan"
    w_adv: float = 1.0
    w_recon_x: float = 10.0
    w_recon_s: float = 1.0
    w_recon_c: float = 1.0
    w_cyc: float = 0.0


@dataclass
class OptimConfig:
    lr: float = 2e-4  # the paper
    beta1: float = 0.5  # pix2pixHD / CycleGAN
    beta2: float = 0.999
    weight_decay: float = 0.0  # MUNIT's reference uses 1e-4
    lr_policy: str = "linear"  # "linear": constant until decay_start, then linear to 0; "step": x step_gamma every step_size
    decay_start: int = 100_000
    max_steps: int = 200_000
    step_size: int = 100_000  # lr_policy = "step" (MUNIT)
    step_gamma: float = 0.5


@dataclass
class RunConfig:
    seed: int = 0
    log_every: int = 50  # steps between stats.jsonl rows
    grid_every: int = 1000  # steps between sample grids
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3
    grid_samples: int = 4  # fixed inputs shown in every grid
    probe_every: int = 250  # steps between probe evaluations (`fit --probe`); 0 = only at the end
    probe_samples: int = 64  # probe images evaluated (the first N of the --probe set)
    # Not in the paper: an exponential moving average of the generators' weights (0 = none), kept
    # beside the raw ones, probed beside them ("probe_ema/...") and used by inference and the report
    ema_decay: float = 0.999
    amp: str = "auto"  # bf16 autocast: "auto" (on CUDA), "on", "off"
    channels_last: str = "auto"  # "auto" (on CUDA), "on", "off"


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    cyclegan: CycleGANConfig = field(default_factory=CycleGANConfig)
    munit: MunitConfig = field(default_factory=MunitConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    name: str = "paper"

    def to_dict(self) -> dict:
        return asdict(self)


# The sections each model kind reads; a changed value anywhere else would be ignored, so it is refused.
KIND_SECTIONS = {"iae": ("model", "loss"), "cyclegan": ("cyclegan",), "munit": ("munit",), "oracle": ("model",)}
# Every section some kind owns, in first-owned order (model.kind itself is read by all)
MODEL_SECTIONS = tuple(dict.fromkeys(s for secs in KIND_SECTIONS.values() for s in secs))


class ConfigError(ValueError):
    """An unknown key or a bad value; the message names it and the nearest valid key."""


def _all_keys(cfg: Config) -> list[str]:
    keys = []
    for f in fields(cfg):
        sub = getattr(cfg, f.name)
        if dataclasses.is_dataclass(sub):
            keys += [f"{f.name}.{g.name}" for g in fields(sub)]
        else:
            keys.append(f.name)
    return keys


def _coerce(key: str, current: Any, value: Any) -> Any:
    if isinstance(value, str) and not isinstance(current, str):
        try:
            value = json.loads(value.lower() if value.lower() in ("true", "false") else value)
        except json.JSONDecodeError:
            raise ConfigError(f"{key}: cannot parse {value!r} as {type(current).__name__}") from None
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if isinstance(current, int) and not isinstance(current, bool):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if isinstance(current, str) and not isinstance(value, str):
        raise ConfigError(f"{key}: expected a string, got {value!r}")
    return value


def set_value(cfg: Config, key: str, value: Any) -> None:
    """Set `section.field`; unknown keys raise with the closest valid key."""
    keys = _all_keys(cfg)
    if key not in keys:
        near = difflib.get_close_matches(key, keys, n=1, cutoff=0.0)
        raise ConfigError(f"unknown config key {key!r}; did you mean {near[0]!r}?")
    if "." in key:
        section, name = key.split(".", 1)
        obj = getattr(cfg, section)
    else:
        obj, name = cfg, key
    setattr(obj, name, _coerce(key, getattr(obj, name), value))


def apply_dict(cfg: Config, data: dict, prefix: str = "", source: str = "config") -> Config:
    for key, value in data.items():
        full = f"{prefix}{key}"
        if isinstance(value, dict):
            apply_dict(cfg, value, f"{full}.", source)
        else:
            try:
                set_value(cfg, full, value)
            except ConfigError as exc:
                raise ConfigError(f"{source}: {exc}") from None
    return cfg


def _choice(key: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}: expected one of {list(allowed)}, got {value!r}")


def _at_least(cfg: Config, minimum: float, *keys: str) -> None:
    for key in keys:
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        if isinstance(value, float) and not math.isfinite(value):  # NaN fails here, not at step 1
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        if value < minimum:
            raise ConfigError(f"{key}: expected at least {minimum:g}, got {value!r}")


def _finite(cfg: Config) -> None:
    """Every number of the config finite: NaN would pass other checks and stop training at step 1 as a
    'non-finite loss', or be written to the run's options as non-standard JSON."""
    for key in _all_keys(cfg):
        if "." not in key:  # the config's name
            continue
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")


def _ignored_settings(cfg: Config) -> list[str]:
    """Keys that differ from their defaults in sections this model kind never reads."""
    defaults, used = Config(), KIND_SECTIONS[cfg.model.kind]
    out = []
    for section in MODEL_SECTIONS:
        if section in used:
            continue
        for f in fields(getattr(cfg, section)):
            if section == "model" and f.name == "kind":
                continue
            if getattr(getattr(cfg, section), f.name) != getattr(getattr(defaults, section), f.name):
                out.append(f"{section}.{f.name}")
    return out


def unread_sections(cfg: Config) -> list[str]:
    """The config sections this model kind never reads (kept at their defaults by validate), named in
    training_options.json so that a reader of a baseline's run does not take them for its settings."""
    used = KIND_SECTIONS[cfg.model.kind]
    return [("model (all but model.kind)" if s == "model" else s)
            for s in MODEL_SECTIONS if s not in used]


def validate(cfg: Config) -> Config:
    """Every value in range and every setting read by the chosen model kind; checked before any file is written."""
    m, lo, o = cfg.model, cfg.loss, cfg.optim
    _finite(cfg)
    _choice("model.kind", m.kind, tuple(KIND_SECTIONS))
    ignored = _ignored_settings(cfg)
    if ignored:
        own = ", ".join(f"[{s}]" for s in KIND_SECTIONS[m.kind])
        raise ConfigError(f"{ignored[0]} does not apply to model.kind = {m.kind!r} (its settings are in {own}); "
                          f"remove it" + (f" and {len(ignored) - 1} more" if len(ignored) > 1 else ""))
    if not m.inputs or set(m.inputs) - set("NAF") or len(set(m.inputs)) != len(m.inputs):
        raise ConfigError(f"model.inputs: expected a non-empty subset of 'NAF', got {m.inputs!r}")
    _choice("loss.gan", lo.gan, ("bce", "lsgan"))
    _choice("loss.gan_reduce", lo.gan_reduce, ("sum", "mean"))
    _choice("loss.normal_length_on", lo.normal_length_on, ("threshold", "car"))
    _choice("loss.adv_m_on", lo.adv_m_on, ("all", "car", "reflection"))
    _choice("loss.adv_m_cond", lo.adv_m_cond, ("none", "image"))
    _choice("cyclegan.gan", cfg.cyclegan.gan, ("bce", "lsgan"))
    _choice("munit.gan", cfg.munit.gan, ("bce", "lsgan"))
    _choice("model.normal_output", m.normal_output, ("tanh", "normalize"))
    _choice("model.h_upsample", m.h_upsample, ("transposed", "resize", "subpixel"))
    _choice("model.norm", m.norm, ("instance", "batch"))
    _choice("model.renderer", m.renderer, ("net", "shader"))
    _choice("model.shader_residual_on", m.shader_residual_on, ("background", "everywhere"))
    _choice("model.shader_lighting", m.shader_lighting, ("per_image", "global"))
    _choice("model.shader_gain", m.shader_gain, ("per_image", "shared"))
    _choice("model.shader_background", m.shader_background, ("gain", "environment"))
    _choice("model.bank_level", m.bank_level, ("fit", "images"))
    if not 0.001 <= m.shader_gain_start <= 10:  # NaN fails too
        raise ConfigError(f"model.shader_gain_start: expected a gain in [0.001, 10], got {m.shader_gain_start!r}")
    if not 0 <= m.shader_gain_min < m.shader_gain_start:
        raise ConfigError(f"model.shader_gain_min: expected a floor in [0, model.shader_gain_start = "
                          f"{m.shader_gain_start}), got {m.shader_gain_min!r}")
    if not 0 <= cfg.run.ema_decay < 1:
        raise ConfigError(f"run.ema_decay: expected a value in [0, 1), got {cfg.run.ema_decay!r}")
    _choice("cyclegan.norm", cfg.cyclegan.norm, ("instance", "batch"))
    _choice("optim.lr_policy", o.lr_policy, ("linear", "step"))
    for key in ("amp", "channels_last"):
        _choice(f"run.{key}", getattr(cfg.run, key), ("auto", "on", "off"))
    _at_least(cfg, 8, "data.height", "data.width")
    _at_least(cfg, 1, "data.batch_size", "model.r_ngf", "model.h_ngf", "model.d_ndf", "model.d_layers",
              "model.d_scales", "cyclegan.ngf", "cyclegan.ndf", "cyclegan.d_layers", "munit.dim", "munit.style_dim",
              "munit.mlp_dim", "munit.d_ndf", "munit.d_layers", "munit.d_scales", "optim.max_steps",
              "optim.step_size", "run.log_every", "run.grid_every", "run.checkpoint_every", "run.keep_checkpoints",
              "run.grid_samples", "run.probe_samples", "loss.adv_m_pool")
    _at_least(cfg, 0, "run.seed", "run.probe_every", "data.workers", "model.r_downsample", "model.r_blocks", "model.r_local_enhancers",
              "model.h_downsample", "model.h_blocks", "cyclegan.n_down", "cyclegan.n_blocks", "cyclegan.pool",
              "munit.n_down", "munit.n_res", "munit.style_down", "optim.decay_start", "optim.weight_decay", "data.cache_gb", "loss.adv_m_from",
              "loss.w_ren", "loss.w_dec", "loss.w_norm", "loss.w_adv", "loss.w_adv_m", "loss.w_adv_rec", "loss.w_chroma", "loss.w_shading_ren", "loss.w_shading_dec", "loss.w_albedo_level", "loss.r1_m", "model.shader_residual", "model.lighting_bank", "loss.normal_threshold", "loss.cycle_noise",
              "cyclegan.w_cycle", "cyclegan.w_adv", "munit.w_adv", "munit.w_recon_x", "munit.w_recon_s",
              "munit.w_recon_c", "munit.w_cyc")
    if not (0 < o.lr <= 1):
        raise ConfigError(f"optim.lr: expected a learning rate in (0, 1], got {o.lr!r}")
    for key in ("beta1", "beta2"):
        if not 0 <= getattr(o, key) < 1:
            raise ConfigError(f"optim.{key}: expected a value in [0, 1), got {getattr(o, key)!r}")
    if not 0 < o.step_gamma <= 1:
        raise ConfigError(f"optim.step_gamma: expected a value in (0, 1], got {o.step_gamma!r}")
    if not lo.smooth_l1_beta > 0:
        raise ConfigError(f"loss.smooth_l1_beta: expected a positive number, got {lo.smooth_l1_beta!r}")
    div = {"iae": 2 ** (m.r_downsample + m.r_local_enhancers), "oracle": 2 ** (m.r_downsample + m.r_local_enhancers),
           "cyclegan": 2 ** cfg.cyclegan.n_down,
           "munit": 2 ** cfg.munit.n_down}[m.kind]
    if cfg.data.height % div or cfg.data.width % div:
        raise ConfigError(f"data.height/width ({cfg.data.height}x{cfg.data.width}) must be multiples of {div} "
                          f"(the networks of model.kind = {m.kind!r} downsample by that much)")
    # a generator's residual blocks reflection-pad its bottleneck by 1, so it needs 2 pixels a side;
    # the shader R builds one only for its residual
    generator = m.kind in ("cyclegan", "munit") or m.renderer == "net" or m.shader_residual > 0
    if generator and min(cfg.data.height, cfg.data.width) < 2 * div:
        raise ConfigError(f"data.height/width ({cfg.data.height}x{cfg.data.width}) must be at least {2 * div} "
                          f"(the networks of model.kind = {m.kind!r} downsample by {div})")
    if not (lo.rendering_cycle or lo.decomposition_cycle):
        raise ConfigError("loss.rendering_cycle and loss.decomposition_cycle cannot both be off")
    if not lo.shared_discriminator and not (lo.rendering_cycle and lo.decomposition_cycle):
        raise ConfigError("loss.shared_discriminator = false needs both cycles: with one cycle off, one "
                          "discriminator would see no fake at all")
    if lo.adv_m_cond == "image" and not lo.rendering_cycle:
        raise ConfigError("loss.adv_m_cond = 'image' needs loss.rendering_cycle: D_M's real pairs are "
                          "the synthetic maps beside R's renders of them")
    return cfg


def load_config(name_or_file: str, overrides: list[str] | None = None) -> Config:
    """A preset name (`paper`, `cpu-small`, `cyclegan`, `munit`) or a TOML file, then overrides."""
    path = Path(name_or_file)
    if not path.suffix:
        path = PRESETS_DIR / f"{name_or_file}.toml"
        if not path.exists():
            names = sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))
            raise ConfigError(f"--config {name_or_file!r}: no such preset; choose one of {names} or a .toml file")
    elif not path.exists():
        raise ConfigError(f"--config {name_or_file}: no such file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected a TOML config") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    cfg = Config(name=path.stem)
    apply_dict(cfg, data, source=str(path))
    return apply_overrides(cfg, overrides)


def apply_overrides(cfg: Config, overrides: list[str] | None) -> Config:
    """`--set key=value` items applied to `cfg`, then the whole config validated.

    An override that changes model.kind (`--config paper --set model.kind=oracle`) drops the
    preset's values in the sections the new kind never reads (back to their defaults); only a
    setting the overrides name there is refused as not applying."""
    kind, named = cfg.model.kind, set()
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value")
        key, value = item.split("=", 1)
        set_value(cfg, key.strip(), value.strip())
        named.add(key.strip())
    if cfg.model.kind != kind and cfg.model.kind in KIND_SECTIONS:
        defaults = Config()
        for key in _ignored_settings(cfg):
            if key not in named:
                section, name = key.split(".")
                setattr(getattr(cfg, section), name, getattr(getattr(defaults, section), name))
    return validate(cfg)


def _is_objective(key: str) -> bool:
    """The training objective's settings: every loss weight and choice, and what R is (the paper's
    network or the deferred shader, and the shader's settings); not the networks' widths."""
    section, name = key.split(".")
    return section == "loss" or (section == "model" and name.startswith(("renderer", "shader_", "lighting_", "bank_")))


def objective_overrides(preset: str, objective: str) -> list[str]:
    """`--set` values that give a preset's networks, data and schedule another objective:
    "default" (the measured defaults, `Config()`) or "paper" (the `paper` preset's values, the
    paper's R and Eq. 7). Only the values that differ from the preset's are listed."""
    if objective not in ("default", "paper"):
        raise ConfigError(f"objective {objective!r}: expected 'default' or 'paper'")
    target = Config() if objective == "default" else load_config("paper")
    want = target.to_dict()
    out = []
    for key in objective_differences(load_config(preset), target):
        section, name = key.split(".")
        value = want[section][name]
        out.append(f"{key}={json.dumps(value) if not isinstance(value, str) else value}")
    return out


# H's architecture: the supervised oracle trains the same H, so its row stays the ceiling of the
# networks measured when an A/B changes them
H_ARCHITECTURE = ("model.h_ngf", "model.h_downsample", "model.h_blocks", "model.h_upsample", "model.normal_output")


def h_architecture_overrides(overrides: list[str] | tuple[str, ...]) -> list[str]:
    """The `KEY=VALUE` overrides among `overrides` that change H's architecture (H_ARCHITECTURE)."""
    return [o for o in overrides if o.split("=", 1)[0].strip() in H_ARCHITECTURE]


def objective_differences(a: Config, b: Config) -> list[str]:
    """The objective settings (`section.name`, in the config's order) in which two configs differ."""
    da, db = a.to_dict(), b.to_dict()
    out = []
    for key in _all_keys(a):
        if "." in key and _is_objective(key):
            section, name = key.split(".")
            if da[section][name] != db[section][name]:
                out.append(key)
    return out


# Settings added after runs had been trained, with the value that reproduces what such a run did
# (its training_options.json lacks the key): an older run folder resumes and loads as it trained.
LEGACY_VALUES = {"model.renderer": "net", "model.shader_residual_on": "everywhere", "model.shader_lighting": "global",
                 "model.shader_background": "gain", "loss.w_shading_ren": 0.0, "loss.w_shading_dec": 0.0,
                 "run.ema_decay": 0.0, "model.bank_level": "fit",
                 "model.shader_gain": "per_image", "model.shader_gain_min": 0.0, "model.h_upsample": "transposed"}


def differing_sections(a: Config, b: Config) -> list[str]:
    """The config sections (data, model, loss, ...) in which two configs differ."""
    da, db = a.to_dict(), b.to_dict()
    return [k for k in da if da[k] != db.get(k)]


def config_from_dict(data: dict) -> Config:
    """The config a run folder was trained with (its training_options.json "config")."""
    cfg = Config(name=data.get("name", "run"))
    for key, value in LEGACY_VALUES.items():
        section, name = key.split(".")
        if name not in data.get(section, {}):
            set_value(cfg, key, value)
    apply_dict(cfg, {k: v for k, v in data.items() if k != "name"})
    return validate(cfg)
