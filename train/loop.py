"""The training loop: run folders, logging, grids, checkpoints, exact resume, multi-process.

A run folder (in the manner of stylegan2-ada's) holds:
  training_options.json   the resolved config and data paths: the run is resumed from it
  stats.jsonl             every logged loss, one JSON row per logging step
  events.out.tfevents.*   the same scalars for TensorBoard
  grids/step_XXXXXXXX.png sample grids at fixed inputs
  checkpoints/            safetensors weights + JSON state, `latest.json` names the newest
Multi-GPU / multi-node: run under `torchrun`; each process takes its own slice of every
global batch and gradients are averaged with one flattened all-reduce per network group.
"""
from __future__ import annotations

import json
import math
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from PIL import Image
from tqdm import tqdm

from blender_gen.dataset import atomic_write_json
from .checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from .config import Config, ConfigError, config_from_dict
from .data import IntrinsicsData, RealImages, StepSampler, infinite_loader
from .model import build_model


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


def generator_step(model, opt_g, g_params, m_s, i_r, autocast=nullcontext, world: int = 1):
    """One update of R and H (or a baseline's generators); returns the outputs and logs."""
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


def _lr_lambda(decay_start: int, max_steps: int):
    def f(step: int) -> float:
        if step < decay_start:
            return 1.0
        return max(0.0, 1.0 - (step - decay_start) / max(1, max_steps - decay_start))
    return f


def to_display(t: torch.Tensor) -> np.ndarray:
    """(3, H, W) network-space tensor -> uint8 HxWx3 (normals and sRGB both map [-1, 1] -> [0, 1])."""
    x = ((t.detach().float().clamp(-1, 1) + 1.0) * 0.5).permute(1, 2, 0).cpu().numpy()
    return (x * 255.0 + 0.5).astype(np.uint8)


def sample_grid(vis: dict[str, torch.Tensor]) -> np.ndarray:
    """Two rows per sample.

    rendering:     N_s | A_s | F_s | R(M_s) | H(R(M_s)) as N, A, F
    decomposition: I_r | H(I_r) as N, A, F | R(H(I_r)) | blank
    """
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
    return np.concatenate(rows, axis=0)


def _save_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    Image.fromarray(img).save(tmp, format="PNG")
    tmp.replace(path)


def _resolve(flag: str, device: str) -> bool:
    return flag == "on" or (flag == "auto" and device.startswith("cuda"))


def prepare_run(run_dir: Path, cfg: Config | None, intrinsics: str | None, real: str | None) -> tuple[Config, dict]:
    """New run: write training_options.json. Existing run: read it (the run resumes)."""
    opts_path = run_dir / "training_options.json"
    if opts_path.exists():
        opts = json.loads(opts_path.read_text())
        saved = config_from_dict(opts["config"])
        if cfg is not None and cfg.to_dict() != saved.to_dict():
            diff = [k for k in cfg.to_dict() if cfg.to_dict()[k] != saved.to_dict()[k]]
            raise ConfigError(f"--run-dir {run_dir} holds a run with another config (section(s) {diff} differ); "
                              "resume it without --config/--set changes or choose a new --run-dir")
        for key, given in (("intrinsics", intrinsics), ("real", real)):
            if given and str(Path(given).resolve()) != opts[key]:
                raise ConfigError(f"--{key} {given}: the run in {run_dir} was trained on {opts[key]}")
        return saved, opts
    if cfg is None or not intrinsics or not real:
        raise ConfigError(f"--run-dir {run_dir}: no run there to resume; a new run needs --config, --intrinsics, --real")
    opts = {"config": cfg.to_dict(), "intrinsics": str(Path(intrinsics).resolve()), "real": str(Path(real).resolve())}
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(opts_path, opts)
    return cfg, opts


def fit(run_dir: Path, cfg: Config | None = None, intrinsics: str | None = None, real: str | None = None,
        max_steps: int | None = None, device: str = "cpu", progress: bool = True) -> dict:
    """Train (or resume) the run in `run_dir` up to `max_steps` (default: the config's)."""
    run_dir = Path(run_dir)
    dd = init_distributed(device)
    if device.startswith("cuda") and dd.world > 1:
        device = f"cuda:{dd.local_rank}"
        torch.cuda.set_device(dd.local_rank)
    if dd.main:
        cfg, opts = prepare_run(run_dir, cfg, intrinsics, real)
    if dd.world > 1:
        dist.barrier()
        if not dd.main:
            cfg, opts = prepare_run(run_dir, None, None, None)
    end = max_steps if max_steps is not None else cfg.optim.max_steps
    torch.manual_seed(cfg.run.seed)
    np.random.seed(cfg.run.seed)

    model = build_model(cfg).to(device)
    g_params = [p for m in model.generator_modules().values() for p in m.parameters()]
    d_params = [p for m in model.discriminator_modules().values() for p in m.parameters()]
    betas = (cfg.optim.beta1, cfg.optim.beta2)
    opt_g = torch.optim.Adam(g_params, lr=cfg.optim.lr, betas=betas)
    opt_d = torch.optim.Adam(d_params, lr=cfg.optim.lr, betas=betas)
    lam = _lr_lambda(cfg.optim.decay_start, cfg.optim.max_steps)
    sched_g = torch.optim.lr_scheduler.LambdaLR(opt_g, lam)
    sched_d = torch.optim.lr_scheduler.LambdaLR(opt_d, lam)
    optimizers, schedulers = {"G": opt_g, "D": opt_d}, {"G": sched_g, "D": sched_d}

    ckpt_dir = run_dir / "checkpoints"
    start = 0
    last = latest_checkpoint(ckpt_dir)
    if last is not None:
        start = load_checkpoint(last, model, optimizers, schedulers)["step"]
    if dd.world > 1:  # identical weights everywhere (a fresh run initialises per process)
        for p in model.state_dict().values():
            dist.broadcast(p, 0)

    channels_last = _resolve(cfg.run.channels_last, device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    amp = _resolve(cfg.run.amp, device)
    autocast = (lambda: torch.autocast(device_type=device.split(":")[0], dtype=torch.bfloat16)) if amp else nullcontext

    h, w = cfg.data.height, cfg.data.width
    intr = IntrinsicsData(Path(opts["intrinsics"]), h, w)
    reals = RealImages(Path(opts["real"]), h, w)
    bs = cfg.data.batch_size
    s_m = StepSampler(len(intr), bs, cfg.run.seed, 0, start, dd.rank, dd.world, cfg.data.hflip)
    s_i = StepSampler(len(reals), bs, cfg.run.seed, 1, start, dd.rank, dd.world, cfg.data.hflip)
    it_m = infinite_loader(intr, s_m, cfg.data.workers)
    it_i = infinite_loader(reals, s_i, cfg.data.workers)
    k = min(cfg.run.grid_samples, len(intr), len(reals))
    fixed_m = torch.stack([intr[(i, False)] for i in range(k)]).to(device)
    fixed_i = torch.stack([reals[(i, False)] for i in range(k)]).to(device)

    writer = None
    if dd.main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run_dir), purge_step=start)
    stats_path = run_dir / "stats.jsonl"
    if dd.main and stats_path.exists():  # drop rows logged after the checkpoint we resume from
        rows = [r for r in map(json.loads, stats_path.read_text().splitlines()) if r["step"] <= start]
        stats_path.write_text("".join(json.dumps(r) + "\n" for r in rows))

    bar = tqdm(total=end, initial=start, unit="it", desc=run_dir.name, disable=not (progress and dd.main),
               dynamic_ncols=True)
    t_start = time.perf_counter()
    step = start
    last_logs: dict = {}
    try:
        while step < end:
            m_s = next(it_m).to(device, non_blocking=True)
            i_r = next(it_i).to(device, non_blocking=True)
            if channels_last:
                m_s, i_r = m_s.contiguous(memory_format=torch.channels_last), i_r.contiguous(memory_format=torch.channels_last)
            model.train()
            out, g_logs = generator_step(model, opt_g, g_params, m_s, i_r, autocast, dd.world)
            d_logs = discriminator_step(model, opt_d, d_params, out, autocast, dd.world)
            sched_g.step()
            sched_d.step()
            step += 1
            logs = {**g_logs, **d_logs}
            bad = [k for k, v in logs.items() if not math.isfinite(v)]
            if bad:
                raise NonFiniteLoss(f"step {step}: non-finite loss {bad[0]}={logs[bad[0]]}; stopped, the last good "
                                    f"checkpoint is {latest_checkpoint(ckpt_dir) or 'none (no checkpoint yet)'}")
            last_logs = logs
            bar.update()
            bar.set_postfix({"G": f"{logs['G/total']:.3f}", "D": f"{logs['D/total']:.3f}"}, refresh=False)
            if dd.main and (step % cfg.run.log_every == 0 or step == end):
                row = {"step": step, "lr": sched_g.get_last_lr()[0], **logs}
                with open(stats_path, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
                for key, v in logs.items():
                    writer.add_scalar(key, v, step)
            if dd.main and (step % cfg.run.grid_every == 0 or step == end):
                write_grid(model, fixed_m, fixed_i, run_dir / "grids" / f"step_{step:08d}.png", autocast)
            if step % cfg.run.checkpoint_every == 0 or step == end:
                if dd.main:
                    save_checkpoint(ckpt_dir, step, model, optimizers, schedulers, keep=cfg.run.keep_checkpoints)
                if dd.world > 1:
                    dist.barrier()
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    seconds = time.perf_counter() - t_start
    return {"step": step, "steps_run": step - start, "seconds": seconds, "last": last_logs}


@torch.no_grad()
def write_grid(model, fixed_m: torch.Tensor, fixed_i: torch.Tensor, path: Path, autocast=nullcontext) -> None:
    model.eval()
    # a private RNG: grids use the same random codes every time and never shift training's
    devices = [fixed_m.device] if fixed_m.is_cuda else []
    with torch.random.fork_rng(devices=devices), autocast():
        torch.manual_seed(0)
        out = model.forward_all(fixed_m, fixed_i)
    _save_png(path, sample_grid({k: v.float() for k, v in model.visuals(out).items()}))
    model.train()
