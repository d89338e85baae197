"""H's figures on PBR sets no probe saw, at every checkpoint of some runs: a training curve for them.

    python bench/checkpoint_curve.py RUN [RUN ...] --sets tt/kenney_sedan_pbr [SET ...] \
        --out curve.jsonl [--plot curve.png] [--follow]
    python bench/checkpoint_curve.py --replot curve.jsonl [more.jsonl ...] --plot curve.png [--table STEP]

The training probe scores H on one set (the run's --probe) every few hundred steps; this scores it
on others afterwards or alongside, e.g. turntables of cars of another kind. For every checkpoint
(`step_*.safetensors`) of every run and every set: H's normal, albedo and reflection errors at the
run's training size with the moving-average weights (as the probe and inference use), and the two
rows that use no image, the constant predictor and the per-pixel prior of that run's own training
intrinsics (200 of them, as the training probe takes). One JSON row per (run, step, set), appended;
rows already in --out are kept and not recomputed, so a rerun resumes. `--follow` waits for new
checkpoints until every run has its last (optim.max_steps): runs keep only their newest few, so
follow a training to have them all. One thread, so it can share a machine with the trainings.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from train.checkpoint import checkpoint_files  # noqa: E402
from train.data import IntrinsicsData  # noqa: E402
from train.inference import load_run_checkpoint, load_run_options  # noqa: E402
from train.probe import evaluate_probe, load_probe, training_references  # noqa: E402
from train.run_folder import RunFolder  # noqa: E402

KEYS = ("normal_deg", "albedo_l1", "reflection_l1")


def checkpoints(run: Path) -> list[tuple[int, Path]]:
    """(step, file) of a run's checkpoints, oldest first (the step as the file name gives it)."""
    out = []
    for p in reversed(checkpoint_files(RunFolder(run).checkpoints)):
        try:
            out.append((int(p.stem.split("_")[1]), p))
        except ValueError:
            continue
    return out


def probes_for(run: Path, sets: list[Path]) -> dict[str, object]:
    """Each set at the run's training size with the run's constant and per-pixel prior."""
    opts, cfg = load_run_options(run)
    const_a, const_f, prior = training_references(IntrinsicsData(Path(opts["intrinsics"]), cfg.data.height,
                                                                   cfg.data.width))
    out = {}
    for s in sets:
        p = load_probe(s, cfg.data.height, cfg.data.width, limit=None)
        p.const_albedo, p.const_reflection, p.prior = const_a, const_f, prior
        out[str(s)] = p
    return out


def score(run: Path, step: int, path: Path, probes: dict[str, object]) -> list[dict]:
    _, model, got, _ = load_run_checkpoint(run, "cpu", path)
    rows = []
    for name, p in probes.items():
        f = evaluate_probe(model, p, prefix="")
        row = {"run": str(run), "step": got, "set": name, "weights": getattr(model, "weights", "raw")}
        for k in KEYS:
            row[k] = round(f[k], 3)
            for ref in ("const", "prior"):
                row[f"{ref}_{k}"] = round(f[f"{ref}_{k}"], 3)
        row["speckle_normal"] = round(f["normal_hf_ratio"], 3)
        rows.append(row)
    return rows


def run_label(run: str, names: dict[str, str] | None = None) -> str:
    """A run's name in the plot and the table: its --label, else the last three parts of its path."""
    return (names or {}).get(run) or "/".join(Path(run).parts[-3:])


def plot(rows: list[dict], out: Path, names: dict[str, str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = sorted({r["set"] for r in rows})
    runs = sorted({r["run"] for r in rows})
    ncol = min(4, len(sets))
    nrow = -(-len(sets) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.2 * nrow + 0.4), squeeze=False)
    for ax in axes.flat[len(sets):]:
        ax.axis("off")
    for ax, s in zip(axes.flat, sets):
        for k, run in enumerate(runs):
            rr = sorted((r for r in rows if r["set"] == s and r["run"] == run), key=lambda r: r["step"])
            if not rr:
                continue
            steps = [r["step"] for r in rr]
            label = run_label(run, names)
            ax.plot(steps, [r["normal_deg"] for r in rr], "o-", ms=3, color=f"C{k}", label=f"H, {label}")
            ax.plot(steps, [r["prior_normal_deg"] for r in rr], "x-.", ms=4, color=f"C{k}", alpha=0.6,
                    label=f"per-pixel prior, {label}")
        ax.set_xlim(0, 1.03 * max(r["step"] for r in rows))  # one step axis for every panel
        ax.set_title(Path(s).name, fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel("normal error (deg)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, (0.06 + 0.035 * ((len(labels) + 3) // 4)) / nrow, 1, 1))
    tmp = out.with_name(out.name + ".part")
    fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    tmp.replace(out)


def table(rows: list[dict], step: int, names: dict[str, str] | None = None) -> str:
    """Markdown: H's normal error at `step` per set (rows) and run (columns, in the order of the rows'
    first appearance), each with that run's per-pixel prior, and the set's constant predictor."""
    at = [r for r in rows if r["step"] == step]
    if not at:
        raise SystemExit(f"--table {step}: no rows at that step")
    runs = list(dict.fromkeys(r["run"] for r in at))
    sets = list(dict.fromkeys(r["set"] for r in at))
    lines = [f"| H's normals at step {step} (deg; the run's per-pixel prior) | "
             + " | ".join(run_label(r, names) for r in runs) + " | constant |", "|---" * (len(runs) + 2) + "|"]
    for s in sets:
        cells, const = [], ""
        for run in runs:
            r = next((r for r in at if r["set"] == s and r["run"] == run), None)
            cells.append(f"{r['normal_deg']:.1f} ({r['prior_normal_deg']:.1f})" if r else "-")
            const = f"{r['const_normal_deg']:.1f}" if r else const
        lines.append(f"| {Path(s).name} | " + " | ".join(cells) + f" | {const} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--sets", nargs="+", type=Path, help="PBR sets (images with their intrinsics)")
    ap.add_argument("--replot", nargs="+", type=Path, help="only draw --plot from these JSON-lines files")
    ap.add_argument("--label", action="append", default=[], metavar="RUN=TEXT", help="a run's name in the plot's legend")
    ap.add_argument("--out", type=Path, help="JSON-lines file, appended to")
    ap.add_argument("--plot", type=Path, help="PNG of the normal error against the step, one panel per set")
    ap.add_argument("--follow", action="store_true", help="wait for new checkpoints until each run's last")
    ap.add_argument("--poll", type=float, default=60.0, help="seconds between looks with --follow")
    ap.add_argument("--table", type=int, metavar="STEP", help="with --replot: print H's normals at STEP as Markdown")
    args = ap.parse_args()
    names = dict(item.split("=", 1) for item in args.label if "=" in item)
    if args.replot:
        if not (args.plot or args.table is not None):
            sys.exit("--replot needs --plot or --table")
        rows = [json.loads(line) for f in args.replot for line in f.read_text().splitlines() if line.strip()]
        if args.table is not None:
            print(table(rows, args.table, names))
        if args.plot:
            plot(rows, args.plot, names)
        return
    if not args.runs or not args.sets or not args.out:
        sys.exit("give run folders, --sets and --out (or --replot FILES with --plot PNG or --table STEP)")
    torch.set_num_threads(1)
    for s in args.sets:
        if not (s / "dataset.json").is_file():
            sys.exit(f"--sets {s}: not a dataset (no dataset.json)")
    for r in args.runs:
        if not (r / "training_options.json").is_file():
            sys.exit(f"{r}: not a run folder (no training_options.json)")
    rows = [json.loads(line) for line in args.out.read_text().splitlines() if line.strip()] if args.out.exists() else []
    done = {(r["run"], r["step"], r["set"]) for r in rows}
    probes: dict[Path, dict] = {}
    last = {run: load_run_options(run)[1].optim.max_steps for run in args.runs}
    while True:
        finished = True
        for run in args.runs:
            have = checkpoints(run)
            if not have or have[-1][0] < last[run]:
                finished = False
            for step, path in have:
                if all((str(run), step, str(s)) in done for s in args.sets):
                    continue
                if run not in probes:
                    probes[run] = probes_for(run, args.sets)
                try:
                    new = score(run, step, path, probes[run])
                except FileNotFoundError:  # pruned by the training between the listing and the read
                    continue
                with args.out.open("a") as f:
                    for row in new:
                        f.write(json.dumps(row) + "\n")
                rows += new
                done |= {(r["run"], r["step"], r["set"]) for r in new}
                print(f"{run} step {step}: " + ", ".join(f"{Path(r['set']).name} {r['normal_deg']:.1f} "
                                                        f"(prior {r['prior_normal_deg']:.1f})" for r in new), flush=True)
                if args.plot:
                    plot(rows, args.plot, names)
        if not args.follow or finished:
            break
        time.sleep(args.poll)
    if args.plot and rows:
        plot(rows, args.plot, names)


if __name__ == "__main__":
    main()
