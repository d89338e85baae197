"""`iae-eval reproduce --budget sanity`: settings that separate "implementation" from "budget".

S0 (exact): M_s = half of an intrinsics set; "real" = the analytic shading (train.sanity) of the
    other half; probe = the same shading of a Table-3 set's intrinsics. A perfect renderer exists.
S1 (near): M_s = the same intrinsics; "real" = PBR renders of the training cars and skies (another
    seed) with the background masked to black; probe = the Table-3 set masked the same way.
Both use black-background intrinsics, so every real pixel is expressible as intrinsics. Each
setting trains the full model on several seeds (and the supervised oracle once, for R's input
sensitivity) with `fit --probe`; the summary reads the probe curves and says, per seed, whether
it passes: normals (of the moving-average weights, which inference uses) at least 5 degrees better
than the stronger of the two predictors that use no image (the camera-facing constant and the
per-pixel prior of the training intrinsics), and every normal component correlated at least 0.3
with the truth. Beside it: the raw weights' figure and their step-to-step swing over the last
probes, so that a difference between runs is only read where it exceeds that swing.
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import click
import numpy as np

PASS_MARGIN_DEG = 5.0
PASS_CORR = 0.3


@dataclass(frozen=True)
class SanityBudget:
    render: str
    train: tuple[int, int]
    n_intrinsics: int  # S0 splits them: first half M_s, second half shaded into "real" images
    n_real: int
    n_probe: int
    steps: int
    seeds: tuple[int, ...]
    pbr_samples: int = 4
    widths: tuple[str, ...] = ()
    note: str = ""


SANITY_BUDGETS = {
    "sanity": SanityBudget("128x64", (32, 64), 800, 240, 48, 3000, (0, 1, 2),
                           note="training at 64x32, cpu-small widths, 3 seeds per setting by default (docs/experiment_log.md: Making it learn)"),
    "sanity-smoke": SanityBudget("128x64", (32, 64), 16, 8, 4, 6, (0,), pbr_samples=1,
                                 widths=("model.r_ngf=8", "model.r_downsample=2", "model.r_blocks=1", "model.h_ngf=8",
                                         "model.h_blocks=1", "model.d_ndf=8"),
                                 note="toy size: checks that the sanity benchmark runs, its figures mean nothing"),
}


def derive(src: Path, out: Path, kind: str, indices: list[int], transform: Callable[[dict], dict],
           derivation: str) -> Path:
    """A dataset made from samples `indices` of `src` by `transform` (layers -> layers).

    Built in a temporary folder and renamed into place, so a folder that exists is whole; one
    made from another source or derivation is rebuilt."""
    from blender_gen.dataset import DatasetWriter, open_dataset

    source = open_dataset(src)
    want = {"source": str(Path(src).resolve()), "source_sha256": [source.rows[i]["sha256"] for i in indices],
            "derivation": derivation}
    if (out / "dataset.json").exists():
        info = json.loads((out / "dataset.json").read_text())
        if info.get("complete") and all(info.get(k) == v for k, v in want.items()):
            return out
        shutil.rmtree(out)
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    writer = DatasetWriter(tmp, {"kind": kind, "resolution": source.info["resolution"],
                                 "count_requested": len(indices), **want})
    for k, i in enumerate(indices):
        writer.add(k, transform(source.load(i)), car=source.rows[i].get("car"))
    writer.finish()
    tmp.rename(out)
    return out


def _shade(layers: dict) -> dict:
    """S0's image of a sample (linear light, as a PBR set stores it) beside its own intrinsics."""
    import torch

    from blender_gen.conversions import from_network, to_network
    from train.sanity import shade_network

    stack = np.concatenate([to_network(k, layers[k]) for k in ("normal", "albedo", "reflection")], axis=-1)
    img = shade_network(torch.from_numpy(stack).permute(2, 0, 1)[None])[0].permute(1, 2, 0).numpy()
    return {**layers, "rgb": from_network("rgb", img)}


def _masked(layers: dict) -> dict:
    """S1: the PBR image with its background set to black."""
    on = layers["mask"][..., :1] >= 0.5
    return {**layers, "rgb": np.where(on, layers["rgb"], 0.0).astype(np.float32)}


def _keep(layers: dict) -> dict:
    return layers


@dataclass
class SanityPlan:
    budget: SanityBudget
    name: str
    out: Path
    seed: int
    jobs: int
    threads: int
    settings: tuple[str, ...] = ("S0", "S1")
    overrides: tuple[str, ...] = ()  # --set for the full model's runs (an A/B of the defaults)
    oracle: bool = True

    def dataset_commands(self) -> list[tuple[str, list[str]]]:
        b, o, s = self.budget, self.out / "data", self.seed
        common = ["--resolution", b.render, "--workers", "auto", "--quiet"]
        return [
            ("intrinsics (training cars and skies, black background)",
             ["intrinsics", "--out", str(o / "intrinsics"), "--count", str(b.n_intrinsics), "--seed", str(s),
              "--background", "black", *common]),
            ("S1 real: PBR of the training cars and skies, another seed",
             ["pbr", "--out", str(o / "pbr_train_cars"), "--count", str(b.n_real), "--seed", str(s + 1), "--samples",
              str(b.pbr_samples), "--cars", "procedural:train", "--envmap", "procedural", *common]),
            ("probe: Table-3 set (training cars, unseen poses and paints)",
             ["pbr", "--out", str(o / "table3"), "--count", str(b.n_probe), "--seed", str(s + 2), "--cars",
              "procedural:train", "--envmap", "procedural", "--samples", str(b.pbr_samples), *common]),
        ]

    def derived_sets(self) -> dict[str, dict[str, Path]]:
        """Build S0's and S1's sets from the rendered ones; returns {setting: {role: path}}."""
        from blender_gen.dataset import open_dataset

        d = self.out / "data"
        n = len(open_dataset(d / "intrinsics"))
        half = n // 2
        n_probe = len(open_dataset(d / "table3"))
        n_real = len(open_dataset(d / "pbr_train_cars"))
        return {
            "S0": {"intrinsics": derive(d / "intrinsics", d / "s0_intrinsics", "intrinsics", list(range(half)), _keep, "first half"),
                   "real": derive(d / "intrinsics", d / "s0_real", "pbr", list(range(half, n)), _shade, "S0 shading"),
                   "probe": derive(d / "table3", d / "s0_probe", "pbr", list(range(n_probe)), _shade, "S0 shading")},
            "S1": {"intrinsics": d / "intrinsics",
                   "real": derive(d / "pbr_train_cars", d / "s1_real", "pbr", list(range(n_real)), _masked, "S1 mask"),
                   "probe": derive(d / "table3", d / "s1_probe", "pbr", list(range(n_probe)), _masked, "S1 mask")},
        }

    def runs(self) -> list[tuple[str, str, int, bool]]:
        """(setting, run name, seed, oracle): every seed of the full model, the oracle once, per setting."""
        out = []
        for setting in self.settings:
            out += [(setting, f"full_seed{s}", s, False) for s in self.budget.seeds]
            if self.oracle:
                out.append((setting, "oracle", self.budget.seeds[0], True))
        return out

    def fit_command(self, setting: str, name: str, seed: int, oracle: bool, sets: dict[str, Path]) -> list[str]:
        b = self.budget
        over = [f"data.height={b.train[0]}", f"data.width={b.train[1]}", f"optim.max_steps={b.steps}",
                f"optim.decay_start={b.steps // 2}", f"run.seed={seed}", f"run.log_every={max(1, b.steps // 100)}",
                f"run.grid_every={max(1, b.steps // 6)}", f"run.checkpoint_every={max(1, b.steps // 6)}",
                f"run.probe_every={max(1, b.steps // 24)}", *b.widths]
        if oracle:
            from train.config import h_architecture_overrides

            over += ["model.kind=oracle", *h_architecture_overrides(self.overrides)]
        else:
            over += list(self.overrides)
        cmd = [sys.executable, "-m", "train.cli", "fit", "--config", "cpu-small", "--intrinsics", str(sets["intrinsics"]),
               "--real", str(sets["real"]), "--probe", str(sets["probe"]),
               "--run-dir", str(self.out / "runs" / setting / name), "--max-steps", str(b.steps), "--quiet"]
        return cmd + [a for s in over for a in ("--set", s)]


def probe_rows(run_dir: Path) -> list[dict]:
    from train.run_folder import RunFolder

    return [r for r in RunFolder(run_dir).stats() if "probe/normal_deg" in r]


def last_probe_row(run_dir: Path) -> dict | None:
    rows = probe_rows(run_dir)
    return rows[-1] if rows else None


def judged(p: dict) -> tuple[float, str]:
    """The normal error a run is judged by and whose it is: the moving average's where logged."""
    if "probe_ema/normal_deg" in p:
        return p["probe_ema/normal_deg"], "moving average"
    return p["probe/normal_deg"], "raw"


def bar(p: dict) -> float:
    """The stronger no-image reference on normals: the constant, or the per-pixel prior where logged."""
    return min(p["probe/const_normal_deg"], p.get("probe/prior_normal_deg", float("inf")))


def swing(rows: list[dict], last: int = 4) -> float:
    """Mean absolute step-to-step change of the raw probe normals over the last `last` probes."""
    v = [r["probe/normal_deg"] for r in rows[-last - 1:]]
    return float(np.mean(np.abs(np.diff(v)))) if len(v) > 1 else float("nan")


def summarize(plan: SanityPlan) -> tuple[str, dict]:
    """A Markdown table of every run's last probe figures and, for the full model, pass or fail."""
    head = ("| setting | run | step | normal deg, moving avg. (raw; swing) | bar: constant / prior | corr x / y / z | "
            "speckle N | albedo L1 (constant) | reflection L1 (constant) | R sensitivity | pass |")
    lines = [head, "|" + "---|" * 11]
    results: dict = {"budget": plan.name, "criterion": f"normals (moving-average weights) >= {PASS_MARGIN_DEG:g} deg "
                     f"better than the stronger of the constant predictor and the per-pixel prior, and every "
                     f"component's correlation >= {PASS_CORR:g}", "runs": []}
    for setting, name, seed, oracle in plan.runs():
        rows = probe_rows(plan.out / "runs" / setting / name)
        if not rows:
            continue
        r = rows[-1]
        deg, whose = judged(r)
        prefix = "probe_ema/" if whose == "moving average" else "probe/"
        corr = [r[f"{prefix}normal_corr_{a}"] for a in "xyz"]
        ok = deg <= bar(r) - PASS_MARGIN_DEG and min(corr) >= PASS_CORR
        verdict = "-" if oracle else ("yes" if ok else "no")
        p = {k[6:]: v for k, v in r.items() if k.startswith("probe/")}
        results["runs"].append({"setting": setting, "run": name, "seed": seed, "step": r["step"], "pass": None if oracle else ok,
                                "normal_deg": deg, "weights": whose, "swing_deg": swing(rows), "probe": p,
                                "probe_ema": {k[10:]: v for k, v in r.items() if k.startswith("probe_ema/")}})
        lines.append(f"| {setting} | {name} | {r['step']} | {deg:.1f} ({p['normal_deg']:.1f}; {swing(rows):.1f}) | "
                     f"{p['const_normal_deg']:.1f} / {p.get('prior_normal_deg', float('nan')):.1f} | "
                     + " / ".join(f"{c:.2f}" for c in corr)
                     + f" | {r.get(prefix + 'normal_hf_ratio', float('nan')):.2f}"
                     f" | {r[prefix + 'albedo_l1']:.1f} ({p.get('const_albedo_l1', float('nan')):.1f}) | "
                     f"{r[prefix + 'reflection_l1']:.1f} ({p.get('const_reflection_l1', float('nan')):.1f}) | "
                     f"{r[prefix + 'r_sensitivity']:.2f} | {verdict} |")
    return "\n".join(lines), results


def curves_png(plan: SanityPlan) -> bytes | None:
    """Normal-angle probe curves of every run, one panel per setting, the constant dashed."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(plan.settings), figsize=(5.5 * len(plan.settings), 3.4), squeeze=False)
    drawn = False
    for ax, setting in zip(axes[0], plan.settings):
        last = None
        for k, (s, name, _, _) in enumerate(r for r in plan.runs() if r[0] == setting):
            rows = probe_rows(plan.out / "runs" / s / name)
            if not rows:
                continue
            drawn = True
            steps = [r["step"] for r in rows]
            ax.plot(steps, [r["probe/normal_deg"] for r in rows], color=f"C{k}", alpha=0.35, lw=0.8)
            ax.plot(steps, [judged(r)[0] for r in rows], label=f"{name} (faint: raw weights)", color=f"C{k}")
            last = rows[-1]
        if last is not None:
            ax.axhline(last["probe/const_normal_deg"], ls="--", color="gray", label="constant predictor")
            if "probe/prior_normal_deg" in last:
                ax.axhline(last["probe/prior_normal_deg"], ls="-.", color="gray", label="per-pixel prior (no image)")
            ax.axhline(bar(last) - PASS_MARGIN_DEG, ls=":", color="gray",
                       label=f"pass (stronger bar - {PASS_MARGIN_DEG:g})")
        ax.set_title(f"{setting}: H's normal error on the probe", fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel("mean angle (deg)")
        ax.legend(fontsize=6)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue() if drawn else None


def run_sanity(plan: SanityPlan) -> Path:
    from blender_gen.dataset import atomic_write_bytes, atomic_write_json

    from .reproduce import _gen, _run

    logs, t0 = plan.out / "logs", time.time()
    for k, (what, args) in enumerate(plan.dataset_commands(), 1):
        click.echo(f"[data {k}/3] {what}")
        _run(_gen(args), logs / "data.log")
    click.echo("[data] S0's shaded and S1's masked sets")
    sets = plan.derived_sets()
    runs = plan.runs()

    def train(run: tuple[str, str, int, bool]) -> str:
        setting, name, seed, oracle = run
        start = time.time()
        _run(plan.fit_command(setting, name, seed, oracle, sets[setting]), logs / f"train_{setting}_{name}.log",
             plan.threads)
        return f"{setting}/{name} ({(time.time() - start) / 60:.1f} min)"

    click.echo(f"[train] {len(runs)} runs x {plan.budget.steps} steps, {plan.jobs} at a time, "
               f"{plan.threads} thread(s) each")
    with ThreadPoolExecutor(plan.jobs) as pool:
        for k, done in enumerate(pool.map(train, runs), 1):
            click.echo(f"[train {k}/{len(runs)}] {done} done")
    table, results = summarize(plan)
    ran = (f"This run: settings {', '.join(plan.settings)}; training seeds {', '.join(map(str, plan.budget.seeds))}; "
           f"{plan.budget.steps} steps; overrides {' '.join(plan.overrides) or 'none'}; "
           f"oracle {'yes' if plan.oracle else 'no'}.")
    atomic_write_bytes(plan.out / "summary.md", (f"# Sanity benchmark ({plan.name})\n\n{plan.budget.note}\n\n{ran}\n\n"
                                                 f"Pass: {results['criterion']}.\n\n{table}\n").encode())
    atomic_write_json(plan.out / "summary.json", results)
    png = curves_png(plan)
    if png:
        atomic_write_bytes(plan.out / "curves.png", png)
    click.echo(table)
    click.echo(f"done in {(time.time() - t0) / 60:.1f} min: {plan.out / 'summary.md'}, {plan.out / 'curves.png'}")
    return plan.out
