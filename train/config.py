"""Training configuration: plain dataclasses, TOML presets, `--set key=value` overrides.

Every value the paper leaves open is a named field here with a documented default
(pix2pixHD / CycleGAN practice). The resolved config is saved in every run folder
(`training_options.json`) and a run is resumed from that alone.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
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
    workers: int = 2  # DataLoader processes decoding EXRs / photos
    hflip: bool = True  # flips images and maps together; a flip negates normal X


@dataclass
class ModelConfig:
    kind: str = "iae"  # "iae" (the paper), "cyclegan", "munit"
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
    # D_I (3 ch) and D_M (9 ch): multi-scale PatchGAN, 2 scales (the paper)
    d_ndf: int = 64
    d_layers: int = 3
    d_scales: int = 2
    norm: str = "instance"  # "instance" or "batch"
    # MUNIT baseline
    munit_style_dim: int = 8
    munit_mlp_dim: int = 256


@dataclass
class LossConfig:
    gan: str = "lsgan"  # "lsgan" (pix2pixHD/CycleGAN default) or "bce" (the paper's log formula)
    shared_discriminator: bool = True  # ablation: off = D_I sees only R(M_s), D_M only H(I_r)
    rendering_cycle: bool = True  # ablation: off = no H(R(M_s)) and no L_ren
    decomposition_cycle: bool = True  # ablation: off = no R(H(I_r)) and no L_dec
    w_ren: float = 10.0  # cycle weights: CycleGAN's lambda = 10
    w_dec: float = 10.0
    w_norm: float = 1.0
    w_adv: float = 1.0
    smooth_l1_beta: float = 1.0 / 16  # Smooth-L1 threshold in network units ([-1, 1])
    normal_threshold: float = 0.5  # the length loss applies where |n| > this (not on background)
    # baselines
    cyclegan_pool: int = 50
    munit_w_recon_x: float = 10.0
    munit_w_recon_s: float = 1.0
    munit_w_recon_c: float = 1.0
    munit_w_cyc: float = 0.0


@dataclass
class OptimConfig:
    lr: float = 2e-4  # the paper
    beta1: float = 0.5  # pix2pixHD / CycleGAN
    beta2: float = 0.999
    decay_start: int = 100_000  # constant lr until this step, then linear decay to 0 at max_steps
    max_steps: int = 200_000


@dataclass
class RunConfig:
    seed: int = 0
    log_every: int = 50  # steps between stats.jsonl rows
    grid_every: int = 1000  # steps between sample grids
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3
    grid_samples: int = 4  # fixed inputs shown in every grid
    amp: str = "auto"  # bf16 autocast: "auto" (on CUDA), "on", "off"
    channels_last: str = "auto"  # "auto" (on CUDA), "on", "off"


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    name: str = "paper"

    def to_dict(self) -> dict:
        return asdict(self)


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


def validate(cfg: Config) -> Config:
    m, lo = cfg.model, cfg.loss
    if m.kind not in ("iae", "cyclegan", "munit"):
        raise ConfigError(f"model.kind: expected 'iae', 'cyclegan' or 'munit', got {m.kind!r}")
    if not m.inputs or set(m.inputs) - set("NAF") or len(set(m.inputs)) != len(m.inputs):
        raise ConfigError(f"model.inputs: expected a non-empty subset of 'NAF', got {m.inputs!r}")
    if lo.gan not in ("lsgan", "bce"):
        raise ConfigError(f"loss.gan: expected 'lsgan' or 'bce', got {lo.gan!r}")
    if m.normal_output not in ("tanh", "normalize"):
        raise ConfigError(f"model.normal_output: expected 'tanh' or 'normalize', got {m.normal_output!r}")
    if m.norm not in ("instance", "batch"):
        raise ConfigError(f"model.norm: expected 'instance' or 'batch', got {m.norm!r}")
    div = 2 ** (m.r_downsample + m.r_local_enhancers)
    if cfg.data.height % div or cfg.data.width % div:
        raise ConfigError(f"data.height/width ({cfg.data.height}x{cfg.data.width}) must be multiples of {div} "
                          "(2^(r_downsample + r_local_enhancers))")
    if not (lo.rendering_cycle or lo.decomposition_cycle):
        raise ConfigError("loss.rendering_cycle and loss.decomposition_cycle cannot both be off")
    for key in ("amp", "channels_last"):
        if getattr(cfg.run, key) not in ("auto", "on", "off"):
            raise ConfigError(f"run.{key}: expected 'auto', 'on' or 'off'")
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
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    cfg = Config(name=path.stem)
    apply_dict(cfg, data, source=str(path))
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value")
        key, value = item.split("=", 1)
        set_value(cfg, key.strip(), value.strip())
    return validate(cfg)


def config_from_dict(data: dict) -> Config:
    cfg = Config(name=data.get("name", "run"))
    apply_dict(cfg, {k: v for k, v in data.items() if k != "name"})
    return validate(cfg)
