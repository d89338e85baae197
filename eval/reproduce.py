"""`iae-eval reproduce`: the paper's comparison end to end (`make reproduce BUDGET=...`).

1. generates the sets of the protocol (eval.protocol): training intrinsics, the "real"
   stand-in (held-out cars and skies, PBR), the Table-3 set (training cars in unseen poses
   and paints) and unseen intrinsics for FID;
2. trains every model of the paper's Table 1 (and w/o rendering cycle, and the supervised
   oracle) with one identical budget, several at a time on the CPU (one thread each: two
   1-thread trainings get 16% more done than one 2-thread training here, see README) or one
   after the other on all GPUs through torchrun;
3. writes the report (eval.report) with the reference rows.
Every stage resumes: datasets and runs continue where they stopped, finished ones are skipped.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import click


@dataclass(frozen=True)
class Budget:
    render: str  # WIDTHxHEIGHT the datasets are rendered at
    train: tuple[int, int]  # (height, width) the networks train at
    n_intrinsics: int
    n_real: int
    n_eval: int
    n_fid: int
    steps: int
    preset: str  # the Intrinsic Autoencoder preset; baselines and the oracle use the same widths
    widths: tuple[str, ...] = ()  # extra --set for the Intrinsic Autoencoder (and the oracle)
    cyclegan: tuple[str, ...] = ()
    munit: tuple[str, ...] = ()
    pbr_samples: int = 4
    batch: int = 4
    decay_start: int | None = None
    rate: float = 1.0  # measured it/s of one Intrinsic Autoencoder run per lane (for the time estimate)
    note: str = ""


BUDGETS = {
    # every stage at toy size: a check that the whole pipeline runs (CI), not a result
    "smoke": Budget("128x64", (32, 64), 32, 16, 6, 16, 20, "cpu-small", batch=2, pbr_samples=1, rate=4.0,
                    widths=("model.r_ngf=8", "model.r_downsample=2", "model.r_blocks=1", "model.h_ngf=8",
                            "model.h_blocks=1", "model.d_ndf=8"),
                    cyclegan=("cyclegan.ngf=8", "cyclegan.n_blocks=1", "cyclegan.ndf=8"),
                    munit=("munit.dim=8", "munit.n_res=1", "munit.mlp_dim=16", "munit.d_ndf=8", "munit.d_layers=2"),
                    note="toy size: checks the pipeline, its figures mean nothing"),
    # the largest comparison that finishes in about 2 hours on 2 CPU cores (README: measured)
    "cpu": Budget("256x128", (64, 128), 2000, 400, 48, 200, 1500, "cpu-small", decay_start=1000, rate=1.28,
                  cyclegan=("cyclegan.ngf=16", "cyclegan.n_blocks=4", "cyclegan.ndf=16"),
                  munit=("munit.dim=16", "munit.n_res=2", "munit.mlp_dim=64", "munit.d_ndf=16"),
                  note="64x128, narrow networks (cpu-small widths)"),
    # the paper's resolution and widths for one lent GPU session: a fraction of the paper's schedule
    "gpu": Budget("512x256", (256, 512), 20000, 4000, 500, 2048, 20000, "paper", batch=1, pbr_samples=8,
                  decay_start=10000, rate=8.0, note="256x512, the paper's widths, a tenth of its schedule"),
    # the paper's setting: 20,000 intrinsics, 200k steps per run (days on one GPU per run)
    "paper": Budget("512x256", (256, 512), 20000, 16000, 500, 2048, 200000, "paper", batch=1, pbr_samples=8,
                    rate=8.0, note="the paper's data sizes and a pix2pixHD-length schedule"),
}

# (name, preset or None for the budget's IAE preset, overrides): the paper's Table 1 and more
RUNS: list[tuple[str, str | None, tuple[str, ...]]] = [
    ("full", None, ()),
    ("no_shared", None, ("loss.shared_discriminator=false",)),
    ("no_dec", None, ("loss.decomposition_cycle=false",)),
    ("no_ren", None, ("loss.rendering_cycle=false",)),
    ("no_A", None, ("model.inputs=NF",)),
    ("no_N", None, ("model.inputs=AF",)),
    ("no_F", None, ("model.inputs=NA",)),
    ("cyclegan", "cyclegan", ()),
    ("munit", "munit", ()),
    ("oracle", None, ("model.kind=oracle",)),
]


@dataclass
class Plan:
    budget: Budget
    out: Path
    seed: int
    jobs: int
    threads: int
    gpus: int
    runs: list[str] = field(default_factory=list)
    run_seed: int | None = None  # the trainings' seed (default: `seed`, which also makes the data)

    def dataset_commands(self) -> list[tuple[str, list[str]]]:
        b, o, s = self.budget, self.out / "data", self.seed
        common = ["--resolution", b.render, "--workers", str(max(1, min(os.cpu_count() or 1, 8))), "--quiet"]
        return [
            ("training intrinsics (training cars, training skies)",
             ["intrinsics", "--out", str(o / "intrinsics"), "--count", str(b.n_intrinsics), "--seed", str(s), *common]),
            ("real stand-in (held-out cars, held-out skies, PBR)",
             ["pbr", "--out", str(o / "real"), "--count", str(b.n_real), "--seed", str(s + 1), "--samples",
              str(b.pbr_samples), "--cars", "procedural:heldout", "--envmap", "procedural:heldout", *common]),
            ("Table-3 set (training cars, unseen poses and paints, PBR)",
             ["pbr", "--out", str(o / "eval"), "--count", str(b.n_eval), "--seed", str(s + 2), "--cars",
              "procedural:train", "--envmap", "procedural", *common]),
            ("FID intrinsics (training cars, a seed no run sees)",
             ["intrinsics", "--out", str(o / "fid_intrinsics"), "--count", str(b.n_fid), "--seed", str(s + 3), *common]),
        ]

    def fit_command(self, name: str) -> list[str]:
        b = self.budget
        preset, extra = next((p, e) for n, p, e in RUNS if n == name)
        sets = [f"data.height={b.train[0]}", f"data.width={b.train[1]}", f"data.batch_size={b.batch}",
                f"optim.max_steps={b.steps}", f"run.seed={self.seed if self.run_seed is None else self.run_seed}",
                f"run.log_every={max(1, b.steps // 200)}", f"run.grid_every={max(1, b.steps // 6)}",
                f"run.checkpoint_every={max(1, b.steps // 10)}", f"run.probe_every={max(1, b.steps // 12)}"]
        if b.decay_start is not None:
            sets.append(f"optim.decay_start={b.decay_start}")
        if preset is None:
            preset, sets = b.preset, sets + list(b.widths)
        else:
            sets += list(b.cyclegan if preset == "cyclegan" else b.munit)
        if preset == "munit":  # MUNIT keeps its own schedule (step policy); only the length is shared
            sets = [x for x in sets if not x.startswith("optim.decay_start")]
        sets += list(extra)
        data = self.out / "data"
        cmd = ["fit", "--config", preset, "--intrinsics", str(data / "intrinsics"), "--real", str(data / "real"),
               "--run-dir", str(self.out / "runs" / name), "--max-steps", str(b.steps), "--quiet",
               "--probe", str(data / "eval")]  # the Table-3 set: curves of what the report will measure
        cmd += [a for s in sets for a in ("--set", s)]
        if self.gpus > 1:
            return ["torchrun", "--standalone", f"--nproc_per_node={self.gpus}", "-m", "train.cli", *cmd]
        return [sys.executable, "-m", "train.cli", *cmd]

    def estimate_minutes(self) -> float:
        b = self.budget
        lanes = max(1, self.jobs)
        train = len(self.runs) * b.steps / b.rate / 60 / lanes
        data = (b.n_intrinsics / 30 + b.n_real * 0.7 * b.pbr_samples / 4 + b.n_eval * 1.2 + b.n_fid / 30) / 60
        report = (len(self.runs) * (b.n_eval + 2 * b.n_fid) / 9 + b.n_real / 9) / 60
        return train + data + report + 1


def _run(cmd: list[str], log: Path, threads: int | None = None) -> None:
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
    if proc.returncode:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:]
        raise click.ClickException(f"{cmd[0] if cmd[0] != sys.executable else ' '.join(cmd[1:4])} failed "
                                   f"(exit {proc.returncode}): {tail[0] if tail else ''} (log: {log})")


def _gen(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "blender_gen.cli", *args]


def reproduce(plan: Plan, progress: bool = True) -> Path:
    out, b = plan.out, plan.budget
    logs = out / "logs"
    t0 = time.time()
    for k, (what, args) in enumerate(plan.dataset_commands(), 1):
        click.echo(f"[data {k}/4] {what}")
        _run(_gen(args), logs / "data.log")

    def train(name: str) -> str:
        start = time.time()
        _run(plan.fit_command(name), logs / f"train_{name}.log", None if plan.gpus else plan.threads)
        return f"{name} ({(time.time() - start) / 60:.1f} min)"

    click.echo(f"[train] {len(plan.runs)} runs x {b.steps} steps, {plan.jobs} at a time"
               + (f" on {plan.gpus} GPU(s)" if plan.gpus else f", {plan.threads} thread(s) each"))
    with ThreadPoolExecutor(max(1, plan.jobs)) as pool:
        for k, done in enumerate(pool.map(train, plan.runs), 1):
            click.echo(f"[train {k}/{len(plan.runs)}] {done} done")
    click.echo("[report] decomposition, FID/KID, reference rows, pictures")
    data = out / "data"
    report_dir = out / "report"
    _run([sys.executable, "-m", "eval.cli", "report", *[str(out / "runs" / r) for r in plan.runs], "--data",
          str(data / "eval"), "--real", str(data / "real"), "--intrinsics", str(data / "fid_intrinsics"),
          "--out", str(report_dir), "--quiet"], logs / "report.log")
    click.echo(f"done in {(time.time() - t0) / 60:.1f} min: {report_dir / 'report.html'}")
    return report_dir


@click.command("reproduce")
@click.option("--budget", type=click.Choice([*BUDGETS, "sanity", "sanity-smoke"]), default="smoke", show_default=True,
              help="smoke/cpu/gpu/paper: the paper's comparison; sanity: the S0/S1 settings (README: Making it learn); "
                   "sanity-smoke: the same at toy size.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: out/reproduce_BUDGET).")
@click.option("--steps", type=click.IntRange(1), default=None, help="Training steps per run (budget's by default).")
@click.option("--resolution", default=None, help="Training HEIGHTxWIDTH (the budget's by default).")
@click.option("--intrinsics", "n_intrinsics", type=click.IntRange(2), default=None, help="Training intrinsics count.")
@click.option("--real", "n_real", type=click.IntRange(2), default=None, help="Real stand-in image count.")
@click.option("--eval", "n_eval", type=click.IntRange(1), default=None, help="Table-3 set size.")
@click.option("--fid", "n_fid", type=click.IntRange(2), default=None, help="FID intrinsics count.")
@click.option("--runs", default=None, help=f"Comma-separated subset of: {', '.join(n for n, _, _ in RUNS)}.")
@click.option("--jobs", type=click.IntRange(1), default=None,
              help="Trainings at once (default: on CPU one per core, each with one thread; on GPUs 1).")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="CPU threads per training (default: cores / --jobs); set 1 when several reproduce runs share the cores.")
@click.option("--seed", type=int, default=100, show_default=True)
@click.option("--run-seed", type=int, default=None,
              help="Seed of the trainings (default: --seed): another run seed on the same data.")
@click.option("--dry-run", is_flag=True, help="Print the plan and the estimated time, then stop.")
def reproduce_cmd(budget, out, steps, resolution, n_intrinsics, n_real, n_eval, n_fid, runs, jobs, threads, seed,
                  run_seed, dry_run) -> None:
    """The paper's comparison end to end: data, every model of Table 1, the report."""
    from .cli import parse_size

    if budget.startswith("sanity"):
        return _sanity_cmd(budget, out, steps, jobs, threads, seed, dry_run)
    b = BUDGETS[budget]
    overrides = {k: v for k, v in (("steps", steps), ("n_intrinsics", n_intrinsics), ("n_real", n_real),
                                   ("n_eval", n_eval), ("n_fid", n_fid)) if v is not None}
    if resolution:
        h, w = parse_size(resolution)
        overrides.update(train=(h, w), render=f"{max(w, 128)}x{max(h, 64)}")
    if steps is not None and b.decay_start is not None:
        overrides["decay_start"] = int(steps * b.decay_start / b.steps)
    b = replace(b, **overrides)
    names = [n for n, _, _ in RUNS]
    chosen = names if runs is None else [r.strip() for r in runs.split(",") if r.strip()]
    unknown = [r for r in chosen if r not in names]
    if unknown or not chosen:
        raise click.BadParameter(f"{unknown or runs!r}: choose from {', '.join(names)}", param_hint="--runs")
    import torch

    gpus = torch.cuda.device_count()
    cores = os.cpu_count() or 1
    jobs = jobs or (1 if gpus else min(cores, len(chosen)))
    plan = Plan(b, Path(out or f"out/reproduce_{budget}"), seed, jobs, threads or max(1, cores // jobs), gpus, chosen,
                run_seed)
    click.echo(f"reproduce, budget {budget!r}: {b.note}")
    click.echo(f"  data      {b.n_intrinsics} intrinsics, {b.n_real} real stand-in, {b.n_eval} Table-3, {b.n_fid} FID "
               f"intrinsics at {b.render}")
    click.echo(f"  training  {len(chosen)} runs ({', '.join(chosen)}), {b.steps} steps each at "
               f"{b.train[0]}x{b.train[1]}, batch {b.batch}")
    click.echo(f"  hardware  {'%d GPU(s) via torchrun' % gpus if gpus else '%d CPU core(s)' % cores}, "
               f"{jobs} training(s) at a time")
    click.echo(f"  expected  about {plan.estimate_minutes():.0f} min (from rates measured on a 2-core CPU"
               f"{'; GPU rates are a guess' if gpus or budget in ('gpu', 'paper') else ''})")
    click.echo(f"  output    {plan.out}")
    if dry_run:
        return
    if shutil.which("torchrun") is None and gpus > 1:
        raise click.ClickException("torchrun not found on PATH (it comes with torch)")
    reproduce(plan)


def _sanity_cmd(budget: str, out: Path | None, steps: int | None, jobs: int | None, threads: int | None, seed: int,
                dry_run: bool) -> None:
    from .sanity import SANITY_BUDGETS, SanityPlan, run_sanity

    b = SANITY_BUDGETS[budget]
    if steps is not None:
        b = replace(b, steps=steps)
    cores = os.cpu_count() or 1
    jobs = jobs or cores
    plan = SanityPlan(b, budget, Path(out or f"out/reproduce_{budget}"), seed, jobs, threads or max(1, cores // jobs))
    n_runs = len(plan.runs())
    click.echo(f"reproduce, budget {budget!r}: {b.note}")
    click.echo(f"  data      {b.n_intrinsics} intrinsics (S0: half M_s, half shaded as real), {b.n_real} PBR of the "
               f"training cars (S1 real, masked), {b.n_probe} Table-3 probe images at {b.render}")
    click.echo(f"  training  S0 and S1: the full model on seeds {', '.join(map(str, b.seeds))} and the oracle; "
               f"{n_runs} runs x {b.steps} steps at {b.train[0]}x{b.train[1]}, {jobs} at a time")
    click.echo(f"  output    {plan.out}")
    if not dry_run:
        run_sanity(plan)
