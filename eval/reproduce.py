"""`iae-eval reproduce`: the paper's comparison end to end (`make reproduce BUDGET=...`).

1. generates the sets of the protocol (eval.protocol): training intrinsics, the "real"
   stand-in (held-out cars and skies, PBR), the Table-3 set (training cars in unseen poses
   and paints) and unseen intrinsics for FID;
2. trains every model of the paper's Table 1 (and w/o rendering cycle, and the supervised
   oracle) with one identical budget, several at a time on the CPU (one thread each: two
   1-thread trainings get 16% more done than one 2-thread training here, see docs/experiment_log.md) or one
   after the other on all GPUs through torchrun;
3. writes the report (eval.report) with the reference rows.
Every stage resumes: datasets and runs continue where they stopped, finished ones are skipped.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
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
    # 64x128 and narrow networks; 5000 steps because the probe curves (docs/experiment_log.md "The cpu comparison
    # on a GPU") still fall at 3000: about 5.7 h for the ten runs on 2 CPU cores
    # (bench/objective_sweep.py ran them all at once on one H100 in 11 min)
    "cpu": Budget("256x128", (64, 128), 2000, 400, 48, 200, 5000, "cpu-small", decay_start=3333, rate=1.28,
                  cyclegan=("cyclegan.ngf=16", "cyclegan.n_blocks=4", "cyclegan.ndf=16"),
                  munit=("munit.dim=16", "munit.n_res=2", "munit.mlp_dim=64", "munit.d_ndf=16"),
                  note="training at 128x64 (width x height), narrow networks (cpu-small widths)"),
    # the paper's resolution and widths for one lent GPU session: a fraction of the paper's schedule
    "gpu": Budget("512x256", (256, 512), 20000, 4000, 500, 2048, 20000, "paper", batch=1, pbr_samples=8,
                  decay_start=10000, rate=8.0, note="training at 512x256, the paper's widths, a tenth of its schedule"),
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
    data: Path | None = None  # the datasets' folder (default: OUT/data); parts of one seed may share it
    # a user's own data: car tokens for every generated set (iae-gen --cars), their rules, and a folder
    # of photos as the real images (a few held out for the report's gallery) instead of the stand-in
    cars: tuple[str, ...] = ()
    car_rules: str | None = None
    photos: Path | None = None
    gallery: int = 8
    overrides: tuple[str, ...] = ()  # --set for the Intrinsic Autoencoder's runs (the oracle: H's architecture only)
    objective: str = "default"  # the Intrinsic Autoencoder's objective: the measured defaults or the paper's
    # the fraction of the frame the car covers in every generated set (iae-gen --min/--max-coverage),
    # matched to the photos' framing (eval/framing.py); None = the paper's camera rule
    coverage: tuple[float, float] | None = None

    def objective_sets(self) -> list[str]:
        """--set values that put the chosen objective on the budget's preset (widths and sizes stay)."""
        from train.config import objective_overrides

        return objective_overrides(self.budget.preset, self.objective)

    @property
    def data_dir(self) -> Path:
        return Path(self.data) if self.data is not None else self.out / "data"

    @property
    def real_dir(self) -> Path:
        """The real images the runs train on: the stand-in PBR set, or the user's photos less the gallery."""
        return self.data_dir / ("photos_train" if self.photos is not None else "real")

    def photo_split(self) -> tuple[list[Path], set[int]]:
        """The user's photos (sorted by path) and the indices held out for the gallery: every k-th."""
        from train.data import PHOTO_KINDS, image_files, unread_photos_hint

        files = image_files(self.photos)
        if len(files) < 4:
            raise ValueError(f"--real {self.photos}: {len(files)} photo(s); at least 4 are needed ({PHOTO_KINDS})"
                             + unread_photos_hint(self.photos))
        k = min(self.gallery, len(files) // 4)
        held = {round(j * (len(files) - 1) / max(1, k - 1)) for j in range(k)} if k > 1 else {len(files) // 2}
        return files, held

    def split_photos(self) -> tuple[int, int]:
        """Links to the user's photos in DATA/photos_train and DATA/photos_gallery: every k-th photo
        (sorted by path) is held out for the gallery, the rest train. Deterministic, so parts of one
        seed agree; (training, gallery) counts."""
        files, held = self.photo_split()
        for name, keep in (("photos_train", lambda j: j not in held), ("photos_gallery", lambda j: j in held)):
            folder = self.data_dir / name
            want = {"__".join(f.relative_to(self.photos).parts): f.resolve() for j, f in enumerate(files) if keep(j)}
            have = {p.name: p for p in folder.iterdir()} if folder.is_dir() else {}
            if {n: p.resolve() for n, p in have.items()} != want:
                for p in have.values():
                    p.unlink()
                folder.mkdir(parents=True, exist_ok=True)
                for n, target in want.items():
                    (folder / n).symlink_to(target)
        return len(files) - len(held), len(held)

    def dataset_commands(self) -> list[tuple[str, list[str]]]:
        b, o, s = self.budget, self.data_dir, self.seed
        common = ["--resolution", b.render, "--workers", "auto", "--quiet"]
        if self.coverage is not None:  # every set framed like the photos (the stand-in and Table-3 sets too)
            common += ["--min-coverage", f"{self.coverage[0]:.2f}", "--max-coverage", f"{self.coverage[1]:.2f}"]
        # iae-gen's --cars is repeated per token (a file name may hold a comma)
        mine = ([a for c in self.cars for a in ("--cars", c)]
                + (["--car-rules", self.car_rules] if self.car_rules else [])) if self.cars else []
        train_cars = mine or ["--cars", "procedural:train"]
        which = "your cars" if self.cars else "training cars"
        commands = [
            (f"training intrinsics ({which}, training skies)",
             ["intrinsics", "--out", str(o / "intrinsics"), "--count", str(b.n_intrinsics), "--seed", str(s), *mine,
              *common]),
            ("real stand-in (held-out cars, held-out skies, PBR)",
             ["pbr", "--out", str(o / "real"), "--count", str(b.n_real), "--seed", str(s + 1), "--samples",
              str(b.pbr_samples), "--cars", "procedural:heldout", "--envmap", "procedural:heldout", *common]),
            (f"Table-3 set ({which}, unseen poses and paints, PBR)",
             ["pbr", "--out", str(o / "eval"), "--count", str(b.n_eval), "--seed", str(s + 2), *train_cars,
              "--envmap", "procedural", *common]),
            (f"FID intrinsics ({which}, a seed no run sees)",
             ["intrinsics", "--out", str(o / "fid_intrinsics"), "--count", str(b.n_fid), "--seed", str(s + 3), *mine,
              *common]),
        ]
        return [c for c in commands if not (self.photos is not None and "real stand-in" in c[0])]

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
        if preset == b.preset and name != "oracle":
            sets += [*self.objective_sets(), *self.overrides]
        elif name == "oracle":
            from train.config import h_architecture_overrides

            sets += h_architecture_overrides(self.overrides)
        data = self.data_dir
        cmd = ["fit", "--config", preset, "--intrinsics", str(data / "intrinsics"), "--real", str(self.real_dir),
               "--run-dir", str(self.out / "runs" / name), "--max-steps", str(b.steps), "--quiet",
               "--probe", str(data / "eval")]  # the Table-3 set: curves of what the report will measure
        cmd += [a for s in sets for a in ("--set", s)]
        if self.gpus > 1:
            return ["torchrun", "--standalone", f"--nproc_per_node={self.gpus}", "-m", "train.cli", *cmd]
        return [sys.executable, "-m", "train.cli", *cmd]

    def check_shared_data(self) -> None:
        """Refuse a --data folder whose sets were made for other counts: the generators would extend
        (or stop short of) sets that other parts of the seed already trained on."""
        import json

        for _, args in self.dataset_commands():
            folder, count = Path(args[args.index("--out") + 1]), int(args[args.index("--count") + 1])
            info_path = folder / "dataset.json"
            if not info_path.exists():
                continue
            had = json.loads(info_path.read_text()).get("count_requested")
            if had is not None and int(had) != count:
                raise ValueError(f"--data {self.data_dir}: {folder.name} was made with {had} samples and this plan asks "
                                 f"for {count}; runs on it trained on {had}: use another --data, or the same counts")

    def check_configs(self) -> None:
        """Resolve every run's config now (ConfigError names the setting), so a size the networks
        cannot take fails before any data is generated; and refuse now, before the plan measures
        or promises anything, a started run folder that holds another config (its training would
        refuse to resume)."""
        from train.checkpoint import newest_state
        from train.config import ConfigError, config_from_dict, differing_sections, load_config
        from train.run_folder import RunFolder

        for name in self.runs:
            cfg = load_config(*self._config_args(name))
            run = RunFolder(self.out / "runs" / name)
            if not run.exists() or newest_state(run.checkpoints) is None:
                continue
            diff = differing_sections(cfg, config_from_dict(run.options()["config"]))
            if diff:
                raise ConfigError(f"{run.root}: run {name!r} was trained with another config (section(s) {diff} "
                                  "differ); rerun with the --objective and --set options it started with, or choose "
                                  "another --out")

    def lanes(self) -> int:
        # Trainings beyond the runs, or beyond the cores on a CPU, cannot run side by side.
        cap = 1 if self.gpus else (os.cpu_count() or 1)  # on GPUs one torchrun after another
        return max(1, min(self.jobs, len(self.runs), cap))

    def _config_args(self, name: str) -> tuple[str, list[str]]:
        cmd = self.fit_command(name)
        return cmd[cmd.index("--config") + 1], [cmd[k + 1] for k in range(len(cmd)) if cmd[k] == "--set"]

    def steps_done(self, name: str) -> int:
        """The step of run `name`'s newest readable checkpoint in this plan's output (0: none):
        a rerun resumes there, so only the steps after it take time."""
        from train.checkpoint import newest_state

        newest = newest_state(self.out / "runs" / name / "checkpoints")  # as the trainer falls back
        return 0 if newest is None else newest[1]

    def steps_left(self, name: str) -> int:
        return max(0, self.budget.steps - self.steps_done(name))

    def _data_left(self, folder: str) -> float:
        """The fraction of dataset `folder` still to generate (generation resumes a partial one)."""
        try:
            info = json.loads((self.data_dir / folder / "dataset.json").read_text())
            return 0.0 if info.get("complete") else 1 - info["count"] / max(1, info["count_requested"])
        except (OSError, ValueError, KeyError, TypeError):
            return 1.0

    def measure_rates(self, steps: int = 2) -> dict[str, float]:
        """Steps per second of every run with steps left, measured `lanes()` at a time with the
        plan's threads each (eval.step_rate), as the trainings will run."""
        todo = [n for n in self.runs if self.steps_left(n)]
        lanes = max(1, min(self.lanes(), len(todo)))
        groups = [todo[k::lanes] for k in range(lanes)]
        env = dict(os.environ, OMP_NUM_THREADS=str(self.threads), MKL_NUM_THREADS=str(self.threads))
        procs = [subprocess.Popen([sys.executable, "-m", "eval.step_rate",
                                   json.dumps([[n, *self._config_args(n)] for n in group]), str(steps)],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                  cwd=Path(__file__).resolve().parents[1])
                 for group in groups if group]
        rates: dict[str, float] = {}
        for proc in procs:
            out, err = proc.communicate()
            if proc.returncode:
                raise click.ClickException(f"measuring the training speed failed: {err.strip()[-300:]}")
            rates.update(json.loads(out.strip().splitlines()[-1]))
        return rates

    def estimate_minutes(self, rates: dict[str, float] | None = None) -> float:
        """Data, training and report time still to spend: training from `rates` (measured steps/s
        per run) when given, else from the budget's fixed rate, for the steps after each run's
        newest checkpoint; lanes take the next run as they free up. Data counts what is missing."""
        b = self.budget
        lanes = self.lanes()
        left = {n: self.steps_left(n) for n in self.runs}
        if rates:
            busy = [0.0] * lanes
            for name in self.runs:
                if left[name]:
                    k = busy.index(min(busy))
                    busy[k] += left[name] / rates[name]
            train = max(busy) / 60
        else:
            train = sum(left.values()) / b.rate / 60 / lanes
        data = (b.n_intrinsics / 30 * self._data_left("intrinsics")
                + (0 if self.photos is not None else b.n_real * 0.7 * b.pbr_samples / 4 * self._data_left("real"))
                + b.n_eval * 1.2 * self._data_left("eval") + b.n_fid / 30 * self._data_left("fid_intrinsics")) / 60
        report = (len(self.runs) * (b.n_eval + 2 * b.n_fid) / 9 + b.n_real / 9) / 60
        return train + data + report + 1


def cars_summary(cars: tuple[str, ...]) -> str:
    """--cars as the plan shows it: the catalogue selectors, then the model files counted once each,
    with the shares of the draw where a file is given several times (each entry is one share)."""
    from blender_gen.cars.rules import is_model_file

    files = [c for c in cars if is_model_file(c)]  # the renderer's rule: these are drawn as files
    parts = list(dict.fromkeys(c for c in cars if c not in files))
    if files:
        n = len(set(files))
        parts.append(f"{n} model file{'s' if n > 1 else ''}"
                     + (f" ({len(files)} shares of the draw)" if len(files) > n else ""))
    return " + ".join(parts)


def _term_with_parent() -> None:
    """In the child before exec: ask Linux for SIGTERM when the parent dies (PR_SET_PDEATHSIG)."""
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: the run folder's lock still refuses a second writer
        pass


def _run(cmd: list[str], log: Path, threads: int | None = None) -> None:
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        # The child gets SIGTERM when this process dies, even by SIGKILL: a training saves a
        # checkpoint and stops instead of living on as a second writer of a rerun's folder.
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, preexec_fn=_term_with_parent)
    if proc.returncode:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:]
        raise click.ClickException(f"{cmd[0] if cmd[0] != sys.executable else ' '.join(cmd[1:4])} failed "
                                   f"(exit {proc.returncode}): {tail[0] if tail else ''} (log: {log})")


def _gen(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "blender_gen.cli", *args]


def reproduce(plan: Plan, progress: bool = True) -> Path:
    from blender_gen.dataset import locked_folder

    out, b = plan.out, plan.budget
    logs = out / "logs"
    t0 = time.time()
    # parts of one seed sharing --data take turns generating and checking it; the sets' own writer
    # locks would make the second fail
    with locked_folder(plan.data_dir, "--data",
                       wait=lambda holder: click.echo(f"[data] waiting: {holder} is generating or checking "
                                                      f"{plan.data_dir}")):
        plan.check_shared_data()
        commands = plan.dataset_commands()
        if plan.photos is not None:
            n_train, n_gallery = plan.split_photos()
            click.echo(f"[data] your photos: {n_train} to train on, {n_gallery} held out for the gallery")
        for k, (what, args) in enumerate(commands, 1):
            click.echo(f"[data {k}/{len(commands)}] {what}")
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
    data = plan.data_dir
    report_dir = out / "report"
    gallery = ["--gallery", str(data / "photos_gallery")] if plan.photos is not None else []
    _run([sys.executable, "-m", "eval.cli", "report", *[str(out / "runs" / r) for r in plan.runs], "--data",
          str(data / "eval"), "--real", str(plan.real_dir), "--intrinsics", str(data / "fid_intrinsics"),
          "--out", str(report_dir), "--quiet", *gallery], logs / "report.log")
    click.echo(f"done in {(time.time() - t0) / 60:.1f} min: {report_dir / 'report.html'}")
    return report_dir
