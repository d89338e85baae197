"""The training loop: setup, data, logging, grids, checkpoints, exact resume, multi-process.

The run folder's layout belongs to `train.run_folder.RunFolder`. Multi-GPU / multi-node: run under `torchrun`; each process takes its own slice of every
global batch and gradients are averaged with one flattened all-reduce per network group.
"""
from __future__ import annotations

import copy
import json
import math
import os
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from blender_gen.dataset import (LOCK_NAME, atomic_write_json, folder_is_empty, locked_folder, remove_temporaries,
                                 save_png, write_json_lines)
from .checkpoint import (CheckpointError, latest_checkpoint, load_ema, load_newest, load_weights, newest_state,
                         save_checkpoint)
from .config import Config, ConfigError, config_from_dict, differing_sections, unread_sections
from .data import (CachedTensors, IntrinsicsData, RealImages, StepSampler, cache_bytes, check_ready, infinite_loader,
                   set_identity, skipped_photos_note)
from .model import build_model
from .model_card import write_model_card
from .probe import EMA_PREFIX, evaluate_probe, probe_plot
from .run_folder import RunFolder


class NonFiniteLoss(RuntimeError):
    """A loss became NaN/inf; training stopped with the last good checkpoint kept."""


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    backend = "nccl" if device.startswith("cuda") else "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
    local = int(os.environ.get("LOCAL_RANK", "0"))
    return Dist(dist.get_rank(), dist.get_world_size(), local)


def all_reduce_grads(params: list[torch.nn.Parameter], world: int) -> None:
    """Average gradients over processes with one flattened all-reduce (stylegan2-ada style)."""
    if world <= 1:
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    flat = torch.cat([g.flatten() for g in grads])
    dist.all_reduce(flat)
    flat /= world
    offset = 0
    for p in params:
        n = p.numel()
        p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n


def generator_step(model, opt_g, g_params, m_s, i_r, autocast=nullcontext, world: int = 1, step: int | None = None):
    """One update of R and H (or a baseline's generators); returns the outputs and logs. `step`:
    the steps done before this one, for the loss terms that start later (loss.adv_m_from)."""
    if step is not None:
        model.step = step
    with autocast():
        out = model.forward_all(m_s, i_r)
        g_loss, g_logs = model.generator_loss(out)
    opt_g.zero_grad(set_to_none=True)
    g_loss.backward()
    all_reduce_grads(g_params, world)
    opt_g.step()
    return out, g_logs


def discriminator_step(model, opt_d, d_params, out, autocast=nullcontext, world: int = 1) -> dict:
    """One update of the discriminators on detached fakes."""
    with autocast():
        d_loss, d_logs = model.discriminator_loss(out)
    opt_d.zero_grad(set_to_none=True)  # also drops the grads G's backward left on D
    d_loss.backward()
    all_reduce_grads(d_params, world)
    opt_d.step()
    return d_logs


def lr_factor(optim) -> Callable[[int], float]:
    """The learning-rate multiplier at a step: "linear" (pix2pixHD/CycleGAN: constant, then
    linear to 0 at max_steps) or "step" (MUNIT: times step_gamma every step_size steps)."""
    if optim.lr_policy == "step":
        return lambda step: optim.step_gamma ** (step // optim.step_size)

    def linear(step: int) -> float:
        if step < optim.decay_start:
            return 1.0
        return max(0.0, 1.0 - (step - optim.decay_start) / max(1, optim.max_steps - optim.decay_start))
    return linear


def to_display(t: torch.Tensor) -> np.ndarray:
    """(3, H, W) network-space tensor -> uint8 HxWx3 (normals and sRGB both map [-1, 1] -> [0, 1])."""
    x = ((t.detach().float().clamp(-1, 1) + 1.0) * 0.5).permute(1, 2, 0).cpu().numpy()
    return (x * 255.0 + 0.5).astype(np.uint8)


GRID_COLUMNS = (("N_s", "A_s", "F_s", "R(M_s)", "H_N(R(M_s))", "H_A(R(M_s))", "H_F(R(M_s))"),
                ("I_r", "H_N(I_r)", "H_A(I_r)", "H_F(I_r)", "R(H(I_r))"))


def sample_grid(vis: dict[str, torch.Tensor]) -> np.ndarray:
    """Two rows per sample, titled: a header names each column of both kinds of row, and each row
    says which cycle it shows.

    rendering cycle:     N_s | A_s | F_s | R(M_s) | H(R(M_s)) as N, A, F
    decomposition cycle: I_r | H(I_r) as N, A, F | R(H(I_r)) | blank
    """
    from PIL import Image, ImageDraw

    rows = []
    blank = None
    for i in range(vis["M_s"].shape[0]):
        m, fm = vis["M_s"][i], vis["fake_M"][i]
        blank = np.zeros_like(to_display(m[:3]))
        rec_m = vis.get("rec_M")
        ren = [m[0:3], m[3:6], m[6:9], vis["fake_I"][i]] + ([rec_m[i][k:k + 3] for k in (0, 3, 6)] if rec_m is not None else [])
        dec = [vis["I_r"][i], fm[0:3], fm[3:6], fm[6:9]] + ([vis["rec_I"][i]] if "rec_I" in vis else [])
        r1 = [to_display(t) for t in ren]
        r2 = [to_display(t) for t in dec]
        width = max(len(r1), len(r2))
        r1 += [blank] * (width - len(r1))
        r2 += [blank] * (width - len(r2))
        rows += [np.concatenate(r1, axis=1), np.concatenate(r2, axis=1)]
    body = np.concatenate(rows, axis=0)
    th, tw = blank.shape[:2]
    margin, head = 84, 26
    sheet = Image.new("RGB", (margin + body.shape[1], head + body.shape[0]), (255, 255, 255))
    sheet.paste(Image.fromarray(body), (margin, head))
    draw = ImageDraw.Draw(sheet)
    for line, titles in enumerate(GRID_COLUMNS):  # header: rendering-row titles, then decomposition-row titles
        draw.text((2, 1 + 12 * line), ("rendering:", "decomposition:")[line], fill=(0, 0, 0))
        for c, title in enumerate(titles[:width]):
            draw.text((margin + c * tw + 2, 1 + 12 * line), title, fill=((0, 0, 160), (160, 0, 0))[line])
    for r in range(len(rows)):
        draw.text((2, head + r * th + th // 2 - 6), ("rendering", "decomposition")[r % 2],
                  fill=((0, 0, 160), (160, 0, 0))[r % 2])
    return np.asarray(sheet)


def _save_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_png(path, img)


def _resolve(flag: str, device: str) -> bool:
    return flag == "on" or (flag == "auto" and device.startswith("cuda"))


def prepare_run(run_dir: Path, cfg: Config | None, intrinsics: str | None, real: str | None,
                probe: str | None = None, accept_changed_data: bool = False,
                init_from: str | None = None) -> tuple[Config, dict]:
    """New run: check the data, then write training_options.json. Existing run: read it (the run resumes).

    Everything is validated before the folder is written, so a failed start never leaves a
    folder that refuses the corrected command. A folder whose run has no checkpoint yet holds
    nothing to resume and takes a new config.

    The run records its two sets' identities (count and content digest); a resume on a set that
    changed since is refused unless `accept_changed_data`, which records the change.

    `init_from` (a new run only): another run whose newest checkpoint's weights start this one
    (fine-tuning); its config is the default, and which checkpoint it was is recorded.
    """
    source = _init_source(init_from) if init_from else None
    if source is not None and cfg is None:
        cfg = config_from_dict(source["config"])
    run = RunFolder(run_dir)
    if run.exists():
        opts = run.options()
        saved = config_from_dict(opts["config"])
        started = latest_checkpoint(run.checkpoints) is not None
        changed = cfg is not None and cfg.to_dict() != saved.to_dict()
        if started and source is not None and source["checkpoint_sha256"] != (opts.get("init_from") or {}).get(
                "checkpoint_sha256"):
            raise ConfigError(f"--init-from {init_from}: the run in {run_dir} has started from other weights; "
                              "a resume takes no --init-from")
        if started and source is not None:
            changed = False  # the source's config, given again by --init-from, is the run's own
        moved = [k for k, given in (("intrinsics", intrinsics), ("real", real))
                 if given and str(Path(given).resolve()) != opts[k]]
        if started or not (changed or moved):
            if changed:
                diff = differing_sections(cfg, saved)
                raise ConfigError(f"--run-dir {run_dir} holds a run with another config (section(s) {diff} differ); "
                                  "resume it without --config/--set changes or choose a new --run-dir")
            if moved:
                raise ConfigError(f"--{moved[0]} {intrinsics if moved[0] == 'intrinsics' else real}: the run in "
                                  f"{run_dir} was trained on {opts[moved[0]]}")
            check_data(saved, opts["intrinsics"], opts["real"])
            now = {k: set_identity(Path(opts[k])) for k in ("intrinsics", "real")}
            was = opts.get("data_identity")
            if was is not None and was != now:
                differ = [k for k in now if was.get(k) != now[k]]
                k = differ[0]
                how = (f"{was[k].get('count')} -> {now[k].get('count')} samples" if was[k].get("count") != now[k].get("count")
                       else "same count, other content")
                if not accept_changed_data:
                    raise ConfigError(f"--{k} {opts[k]}: changed since the run in {run_dir} last trained on it ({how}); "
                                      "restore it, or resume with --accept-changed-data to train on it as it is now")
                opts.setdefault("data_changes", []).append({"step": _newest_step(run), "was": was, "now": now})
            if was != now:  # recorded at the first resume of a run from before identities were kept, or accepted
                opts["data_identity"] = now
                atomic_write_json(run.options_path, opts)
            if probe and str(Path(probe).resolve()) != opts.get("probe"):  # never used for gradients: may change
                opts["probe"] = str(Path(probe).resolve())
                atomic_write_json(run.options_path, opts)
            return saved, opts
        cfg = cfg or saved
        intrinsics, real = intrinsics or opts["intrinsics"], real or opts["real"]
        probe = probe or opts.get("probe")
    if cfg is None or not intrinsics or not real:
        missing = [name for name, v in (("--config", cfg), ("--intrinsics", intrinsics), ("--real", real)) if not v]
        raise ConfigError(f"--run-dir {run_dir}: no run there to resume; a new run needs --config, --intrinsics and "
                          f"--real ({', '.join(missing)} not given)")
    check_data(cfg, intrinsics, real)
    if probe:
        check_probe(probe)
    opts = {"config": cfg.to_dict(), "intrinsics": str(Path(intrinsics).resolve()), "real": str(Path(real).resolve()),
            "sections_not_read": unread_sections(cfg),
            "data_identity": {"intrinsics": set_identity(Path(intrinsics)), "real": set_identity(Path(real))}}
    if probe:
        opts["probe"] = str(Path(probe).resolve())
    if source is not None:
        opts["init_from"] = {k: source[k] for k in ("run", "checkpoint", "checkpoint_sha256", "step")}
    run_dir.mkdir(parents=True, exist_ok=True)
    run.stats_path.unlink(missing_ok=True)  # from a start that never reached a checkpoint
    atomic_write_json(run.options_path, opts)
    return cfg, opts


def _init_source(init_from: str) -> dict:
    """The run `init_from` names: its folder, config and newest readable checkpoint."""
    from blender_gen.dataset import sha256_file

    src = RunFolder(Path(init_from))
    opts = src.options()  # NotARunError names the folder
    newest = newest_state(src.checkpoints)
    if newest is None:
        raise ConfigError(f"--init-from {init_from}: no readable checkpoint to start from")
    path, step = newest
    return {"run": str(Path(init_from).resolve()), "config": opts["config"], "checkpoint": str(path.resolve()),
            "checkpoint_sha256": sha256_file(path), "step": step}


def load_init(model: torch.nn.Module, ema: torch.nn.Module | None, init: dict) -> None:
    """Start `model` (and its moving average) from the weights `init` names (opts["init_from"])."""
    from blender_gen.dataset import sha256_file

    path = Path(init["checkpoint"])
    if not path.is_file() or sha256_file(path) != init["checkpoint_sha256"]:
        raise ConfigError(f"--init-from: {path} is gone or changed since this run was set up; set it up again")
    try:
        load_weights(path, model)
        if ema is not None and not load_ema(path, ema):
            ema.load_state_dict(model.state_dict())
    except CheckpointError as exc:
        raise ConfigError(f"--init-from {init['run']}: its networks do not fit this run's config ({exc})") from None


def _newest_step(run: RunFolder) -> int | None:
    newest = newest_state(run.checkpoints)
    return None if newest is None else newest[1]


def check_data(cfg: Config, intrinsics: str, real: str) -> None:
    """Open both datasets (DatasetError names the one that is missing, malformed, being written
    or incomplete)."""
    check_ready(Path(intrinsics), "--intrinsics")
    check_ready(Path(real), "--real")
    IntrinsicsData(Path(intrinsics), cfg.data.height, cfg.data.width)
    reals = RealImages(Path(real), cfg.data.height, cfg.data.width)
    if cfg.model.kind == "oracle" and reals.ds is None:
        raise ConfigError(f"--real {real}: the supervised oracle needs a PBR dataset (images with their intrinsics)")


def _maybe_cached(ds, run: RunFolder, name: str, channels: int, cfg: Config, progress: bool):
    """(dataset, loader workers): the run's training-size cache when it fits in data.cache_gb, else
    the decoding dataset with data.workers loader processes."""
    if cfg.data.cache_gb <= 0 or cache_bytes(ds, channels, cfg.data.height, cfg.data.width) > cfg.data.cache_gb * 1e9:
        return ds, cfg.data.workers
    path = run.root / "cache" / f"{name}_{cfg.data.height}x{cfg.data.width}.npy"
    return CachedTensors(ds, path, stack=channels == 9, progress=progress), 0


def check_probe(probe: str) -> None:
    """A probe must be a PBR dataset (images with their intrinsics and masks)."""
    from blender_gen.dataset import open_dataset

    open_dataset(Path(probe), kinds=("pbr",))


def make_probe(opts: dict, cfg: Config, intr: IntrinsicsData, device: str):
    """The run's probe set at training size, with the constant predictor's albedo and reflection
    (the means of up to 200 training intrinsics), on `device`; None without --probe."""
    if not opts.get("probe"):
        return None
    from .probe import load_probe, training_references

    probe = load_probe(Path(opts["probe"]), cfg.data.height, cfg.data.width, limit=cfg.run.probe_samples)
    probe.const_albedo, probe.const_reflection, probe.prior = training_references(intr)
    return probe.to(device)


class StopRequest:
    """Ctrl-C or SIGTERM asks training to stop after the current step, with a checkpoint.

    A second Ctrl-C interrupts at once (KeyboardInterrupt), as usual.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        self._previous: dict = {}

    def __enter__(self) -> "StopRequest":
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        import signal

        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum

    def __exit__(self, *exc) -> None:
        import signal

        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class Interrupted(Exception):
    """Training stopped on a signal after saving a checkpoint; rerun the command to resume."""

    def __init__(self, step: int, signum: int):
        super().__init__(f"interrupted at step {step}: checkpoint saved; run the same command again to resume")
        self.step, self.signum = step, signum


def build_optimisation(cfg: Config, model) -> tuple[list, list, dict, dict]:
    """Parameters of both groups, their Adam optimisers and learning-rate schedules."""
    g_params = [p for m in model.generator_modules().values() for p in m.parameters()]
    d_params = [p for m in model.discriminator_modules().values() for p in m.parameters()]
    adam = {"lr": cfg.optim.lr, "betas": (cfg.optim.beta1, cfg.optim.beta2), "weight_decay": cfg.optim.weight_decay}
    optimizers = {"G": torch.optim.Adam(g_params, **adam)}
    if d_params:  # the supervised oracle has no discriminators
        optimizers["D"] = torch.optim.Adam(d_params, **adam)
    lam = lr_factor(cfg.optim)
    schedulers = {k: torch.optim.lr_scheduler.LambdaLR(o, lam) for k, o in optimizers.items()}
    return g_params, d_params, optimizers, schedulers


class StatsLog:
    """stats.jsonl and TensorBoard scalars of the main process; rows after `start` are dropped on resume."""

    def __init__(self, run: RunFolder, start: int, enabled: bool):
        self.path, self.writer = run.stats_path, None
        if not enabled:
            return
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(run.root), purge_step=start)
        if self.path.exists():  # torn lines and rows logged after the resumed checkpoint go
            write_json_lines(self.path, run.stats(up_to=start))

    def log(self, step: int, lr: float, logs: dict) -> None:
        if self.writer is None:
            return
        with open(self.path, "a") as fh:
            fh.write(json.dumps({"step": step, "lr": lr, **logs}) + "\n")
        for key, v in logs.items():
            self.writer.add_scalar(key, v, step)

    def image(self, tag: str, img: np.ndarray, step: int) -> None:
        """A picture (HxWx3 uint8) in TensorBoard's Images tab beside the numbers."""
        if self.writer is not None:
            self.writer.add_image(tag, img, step, dataformats="HWC")

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def fit(run_dir: Path, cfg: Config | None = None, intrinsics: str | None = None, real: str | None = None,
        max_steps: int | None = None, device: str = "cpu", progress: bool = True, probe: str | None = None,
        accept_changed_data: bool = False, init_from: str | None = None) -> dict:
    """Train (or resume) the run in `run_dir` up to `max_steps` (default: the config's).

    Ctrl-C or SIGTERM finishes the current step, saves a checkpoint and raises Interrupted.
    One writer per run folder: the main process holds `RUN/.lock` (as dataset writers do), so a
    second `fit` on the folder fails at once naming the process that trains it.
    """
    run_dir = Path(run_dir)
    if int(os.environ.get("RANK", "0")) != 0:  # torchrun's other ranks write nothing
        return _fit(run_dir, cfg, intrinsics, real, max_steps, device, progress, probe)
    created = not run_dir.exists()
    try:
        with locked_folder(run_dir, "--run-dir"):
            # a training killed mid-write leaves a temporary (a checkpoint's can be hundreds of MB)
            remove_temporaries(run_dir, run_dir / "checkpoints", run_dir / "grids")
            return _fit(run_dir, cfg, intrinsics, real, max_steps, device, progress, probe, accept_changed_data,
                        init_from)
    except BaseException:
        if created and run_dir.is_dir() and folder_is_empty(run_dir):  # a refused start leaves no folder
            (run_dir / LOCK_NAME).unlink(missing_ok=True)
            run_dir.rmdir()
        raise


def _fit(run_dir: Path, cfg: Config | None, intrinsics: str | None, real: str | None, max_steps: int | None,
         device: str, progress: bool, probe: str | None, accept_changed_data: bool = False,
         init_from: str | None = None) -> dict:
    dd = init_distributed(device)
    if device.startswith("cuda") and dd.world > 1:
        device = f"cuda:{dd.local_rank}"
        torch.cuda.set_device(dd.local_rank)
    if dd.main:
        cfg, opts = prepare_run(run_dir, cfg, intrinsics, real, probe, accept_changed_data, init_from)
    if dd.world > 1:
        dist.barrier()
        if not dd.main:
            cfg, opts = prepare_run(run_dir, None, None, None)
    end = max_steps if max_steps is not None else cfg.optim.max_steps
    torch.manual_seed(cfg.run.seed)
    np.random.seed(cfg.run.seed)

    # ---------------------------------------------------------------- model, optimisers, resume
    model = build_model(cfg).to(device)
    g_params, d_params, optimizers, schedulers = build_optimisation(cfg, model)
    opt_g, opt_d = optimizers["G"], optimizers.get("D")
    run = RunFolder(run_dir)
    ckpt_dir = run.checkpoints
    state, resumed_from, skipped = load_newest(ckpt_dir, model, optimizers, schedulers)
    for why in skipped if dd.main else []:
        tqdm.write(f"skipped an unreadable checkpoint: {why}", file=sys.stderr)
    start = int(state["step"]) if state else 0
    if dd.main:
        note_compute(run, opts, device, dd.world, fresh=state is None)
    if dd.world > 1:  # identical weights everywhere (a fresh run initialises per process)
        for p in model.state_dict().values():
            dist.broadcast(p, 0)
    channels_last = _resolve(cfg.run.channels_last, device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    ema = make_ema(model, cfg.run.ema_decay) if dd.main else None
    if ema is not None and resumed_from is not None:
        load_ema(resumed_from, ema)
    if state is None and opts.get("init_from"):  # fine-tuning: another run's weights, this run's step 0
        load_init(model, ema, opts["init_from"])
    amp = _resolve(cfg.run.amp, device)
    autocast = (lambda: torch.autocast(device_type=device.split(":")[0], dtype=torch.bfloat16)) if amp else nullcontext

    # ---------------------------------------------------------------- data
    h, w = cfg.data.height, cfg.data.width
    paired = getattr(model, "paired", False)  # the oracle: M_s are the intrinsics of the real (PBR) images
    intr = IntrinsicsData(Path(opts["real" if paired else "intrinsics"]), h, w)
    reals = RealImages(Path(opts["real"]), h, w)
    if dd.main and (note := skipped_photos_note(reals, "--real")):
        tqdm.write(note, file=sys.stderr)
    bs = cfg.data.batch_size
    s_m = StepSampler(len(intr), bs, cfg.run.seed, 1 if paired else 0, start, dd.rank, dd.world, cfg.data.hflip)
    s_i = StepSampler(len(reals), bs, cfg.run.seed, 1, start, dd.rank, dd.world, cfg.data.hflip)
    def sources():
        return (_maybe_cached(intr, run, "real_intrinsics" if paired else "intrinsics", 9, cfg, progress and dd.main),
                _maybe_cached(reals, run, "real", 3, cfg, progress and dd.main))

    if dd.main:  # the main process builds the caches; the others open them once they are whole
        (ds_m, w_m), (ds_i, w_i) = sources()
    if dd.world > 1:
        dist.barrier()
        if not dd.main:
            (ds_m, w_m), (ds_i, w_i) = sources()
    it_m = infinite_loader(ds_m, s_m, w_m)
    it_i = infinite_loader(ds_i, s_i, w_i)
    k = min(cfg.run.grid_samples, len(intr), len(reals))
    fixed_m = torch.stack([intr[(i, False)] for i in range(k)]).to(device)
    fixed_i = torch.stack([reals[(i, False)] for i in range(k)]).to(device)
    probe_set = make_probe(opts, cfg, IntrinsicsData(Path(opts["intrinsics"]), h, w), device) if dd.main else None

    # ---------------------------------------------------------------- the step loop
    stats = StatsLog(run, start, dd.main)
    bar = tqdm(total=end, initial=start, unit="it", desc=run_dir.name, disable=not (progress and dd.main),
               dynamic_ncols=True)

    def checkpoint(step: int) -> None:
        if dd.main:
            save_checkpoint(ckpt_dir, step, model, optimizers, schedulers, keep=cfg.run.keep_checkpoints, ema=ema)
            write_model_card(run, cfg, opts, model, step)
        if dd.world > 1:
            dist.barrier()

    t_start = time.perf_counter()
    step = start
    last_logs: dict = {}
    try:
        with StopRequest() as stop:
            while step < end:
                m_s = next(it_m).to(device, non_blocking=True)
                i_r = next(it_i).to(device, non_blocking=True)
                if channels_last:
                    m_s = m_s.contiguous(memory_format=torch.channels_last)
                    i_r = i_r.contiguous(memory_format=torch.channels_last)
                model.train()
                out, g_logs = generator_step(model, opt_g, g_params, m_s, i_r, autocast, dd.world, step)
                d_logs = discriminator_step(model, opt_d, d_params, out, autocast, dd.world) if opt_d else {}
                for sched in schedulers.values():
                    sched.step()
                step += 1
                if ema is not None:
                    update_ema(ema, model, cfg.run.ema_decay, step)
                logs = {**g_logs, **d_logs}
                bad = [k for k, v in logs.items() if not math.isfinite(v)]
                if bad:
                    raise NonFiniteLoss(f"step {step}: non-finite loss {bad[0]}={logs[bad[0]]}; stopped, the last "
                                        f"good checkpoint is {latest_checkpoint(ckpt_dir) or 'none (no checkpoint yet)'}")
                last_logs = logs
                bar.update()
                bar.set_postfix({k[0]: f"{logs[k]:.3f}" for k in ("G/total", "D/total") if k in logs}, refresh=False)
                probing = probe_set is not None and (step == end or (cfg.run.probe_every
                                                                      and step % cfg.run.probe_every == 0))
                if probing:
                    logs = {**logs, **evaluate_probe(model, probe_set)}
                    if ema is not None:
                        logs.update(evaluate_probe(ema, probe_set, prefix=EMA_PREFIX, references=False))
                    if progress:
                        tqdm.write(f"step {step}: probe normals {logs['probe/normal_deg']:.1f} deg (constant "
                                   f"{logs['probe/const_normal_deg']:.1f}), albedo {logs['probe/albedo_l1']:.1f}, "
                                   f"reflection {logs['probe/reflection_l1']:.1f}, R sensitivity "
                                   f"{logs['probe/r_sensitivity']:.2f}")
                if step % cfg.run.log_every == 0 or step == end or probing:
                    stats.log(step, schedulers["G"].get_last_lr()[0], logs)
                if probing:
                    write_probe_plot(run)
                if dd.main and (step % cfg.run.grid_every == 0 or step == end):
                    grid = write_grid(model, fixed_m, fixed_i, run.grid_path(step), autocast)
                    stats.image("samples", grid, step)
                stopping = _any_rank(stop.signal is not None, dd.world, device)
                if step % cfg.run.checkpoint_every == 0 or step == end or stopping:
                    checkpoint(step)
                if stopping and step < end:
                    raise Interrupted(step, stop.signal or 15)
    finally:
        bar.close()
        stats.close()
    seconds = time.perf_counter() - t_start
    return {"step": step, "steps_run": step - start, "seconds": seconds, "last": last_logs,
            "resumed_from": str(resumed_from) if resumed_from else None}


def compute_identity(device: str, world: int) -> dict:
    """What decides a run's arithmetic besides its seed and data: the order of float sums depends
    on the torch build, the device and the CPU thread count, so the same seed and data give the
    same weights byte for byte only with the same of these."""
    return {"torch": torch.__version__, "device": device.split(":")[0], "processes": world,
            "threads": torch.get_num_threads() if not device.startswith("cuda") else None}


def note_compute(run: RunFolder, opts: dict, device: str, world: int, fresh: bool) -> None:
    """Record the compute identity when a run starts; on a resume with another one, say so (the
    continuation is valid, but not the bytes one uninterrupted run would have made)."""
    now = compute_identity(device, world)
    was = opts.get("compute")
    if fresh:
        if was != now:
            opts["compute"] = now
            atomic_write_json(run.options_path, opts)
        return
    if was is None:  # a run folder from before the record: what it started with is unknown
        return
    differ = [f"{k} {was.get(k)} -> {now[k]}" for k in now if was.get(k) != now[k]]
    if differ:
        tqdm.write(f"note: {run.root} resumes with other compute than it started with ({', '.join(differ)}): "
                   "it trains on, but not to the bytes of one uninterrupted run", file=sys.stderr)


def make_ema(model, decay: float):
    """A frozen copy of the model whose generators track an exponential moving average of the
    trained ones (discriminators are copied but never used); None when `decay` is 0."""
    if not decay or not model.generator_modules():
        return None
    ema = copy.deepcopy(model).eval()
    ema.requires_grad_(False)
    return ema


@torch.no_grad()
def update_ema(ema, model, decay: float, step: int) -> None:
    """EMA of the generators' weights; the decay ramps up from 0 so early averages are not
    dominated by the random initialisation."""
    d = min(decay, (1 + step) / (10 + step))
    own = ema.generator_modules()
    for name, mod in model.generator_modules().items():
        for pe, p in zip(own[name].parameters(), mod.parameters()):
            pe.lerp_(p.detach(), 1 - d)
        for be, b in zip(own[name].buffers(), mod.buffers()):
            be.copy_(b)


def _any_rank(flag: bool, world: int, device: str) -> bool:
    """True on every process if it is true on any (a signal may reach ranks at different steps)."""
    if world <= 1:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t)
    return bool(t.item() > 0)


def write_probe_plot(run: RunFolder) -> None:
    """probe.png in the run folder: the probe curves so far (atomic, so a viewer never sees half)."""
    from blender_gen.dataset import atomic_write_bytes

    png = probe_plot(run.stats(), run.root.name)
    if png:
        atomic_write_bytes(run.root / "probe.png", png)


@torch.no_grad()
def write_grid(model, fixed_m: torch.Tensor, fixed_i: torch.Tensor, path: Path, autocast=nullcontext) -> np.ndarray:
    model.eval()
    # a private RNG: grids use the same random codes every time and never shift training's
    devices = [fixed_m.device] if fixed_m.is_cuda else []
    with torch.random.fork_rng(devices=devices), autocast():
        torch.manual_seed(0)
        out = model.forward_all(fixed_m, fixed_i, everything=True)
    grid = sample_grid({k: v.float() for k, v in model.visuals(out).items()})
    _save_png(path, grid)
    model.train()
    return grid
