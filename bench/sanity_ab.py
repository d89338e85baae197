"""Side by side: the probe figures of several sanity-setting runs (an A/B of objectives).

    python bench/sanity_ab.py --out results/shading LABEL=RUN_DIR [LABEL=RUN_DIR ...] [LABEL=ROWS.jsonl ...]

Each run folder comes from `iae-eval reproduce --budget sanity [--set ...]` (OUT/runs/S0/full_seedN) or
`iae-train fit --probe`. A committed probe-rows file (`LABEL_probe.jsonl` written here, or a
`bench/objective_sweep.py` curve) joins the table and the curves as a reference; its seed comes
from the `LABEL_training_options.json` beside it (else its rows' `seed` field), and nothing of it
is copied, so a table can be redrawn from its committed files. Writes, into --out: `table.md`
(the last probe row of every run: moving-average and raw normals, the raw curve's step-to-step
swing over its last 4 probes, the two no-image bars, albedo, reflection, speckle, R's input
sensitivity and colour correlation), `curves.png` (moving average solid, raw faint, the bars
dashed) and per run its probe rows (`LABEL_probe.jsonl`) and `LABEL_training_options.json`, so
that every figure quoted from the table can be traced and redrawn. A run folder's seed is read
from its training options. `--until STEP` reads every run up to that step
only: a run stopped early (to be resumed) beside complete ones, compared at the same step.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eval.sanity import bar, judged, probe_rows, swing  # noqa: E402


def row_figures(rows: list[dict]) -> dict:
    r = rows[-1]
    deg, whose = judged(r)
    pre = "probe_ema/" if whose == "moving average" else "probe/"
    return {"step": r["step"], "normal_deg": deg, "weights": whose, "raw_normal_deg": r["probe/normal_deg"],
            "swing_deg": swing(rows), "const_normal_deg": r["probe/const_normal_deg"],
            "prior_normal_deg": r.get("probe/prior_normal_deg"), "bar_deg": bar(r),
            "albedo_l1": r[pre + "albedo_l1"], "reflection_l1": r[pre + "reflection_l1"],
            "normal_hf_ratio": r.get(pre + "normal_hf_ratio"), "albedo_hf_ratio": r.get(pre + "albedo_hf_ratio"),
            "corr": [r[f"{pre}normal_corr_{a}"] for a in "xyz"], "r_sensitivity": r[pre + "r_sensitivity"],
            "r_colour_corr": r[pre + "r_colour_corr"]}


def _line(label: str, f: dict) -> str:
    nan = float("nan")
    return (f"| {label} | {f['seed']} | {f['step']} | {f['normal_deg']:.1f} ({f['raw_normal_deg']:.1f}; "
            f"{f['swing_deg']:.1f}) | {f['const_normal_deg']:.1f} / {f['prior_normal_deg'] or nan:.1f} | "
            f"{f['albedo_l1']:.1f} | {f['reflection_l1']:.1f} | {f['normal_hf_ratio'] or nan:.2f} / "
            f"{f['albedo_hf_ratio'] or nan:.2f} | " + " / ".join(f"{c:.2f}" for c in f["corr"])
            + f" | {f['r_sensitivity']:.2f} / {f['r_colour_corr']:.2f} |")


def legend_label(label: str, degrees: list[float], ylim: tuple[float, float] | None) -> str:
    """A curve that leaves the plotted range is named with its end, so that it is not lost: an
    untrained ablation (80-140 deg) would otherwise squeeze the curves that learn into a band."""
    if ylim is None or all(ylim[0] <= d <= ylim[1] for d in degrees):
        return label
    return f"{label} (off the scale: ends at {degrees[-1]:.0f}°)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR or LABEL=ROWS.jsonl")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--title", default="probe normals")
    ap.add_argument("--relative-to", type=Path, default=None,
                    help="write paths under this folder (the reproduce --out) as OUT/... in the copied options")
    ap.add_argument("--until", type=int, default=None, metavar="STEP",
                    help="use the probe rows up to this step only (compare runs at one step)")
    ap.add_argument("--ylim", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="the curves' vertical range in degrees; a run outside it is named in the legend with its end")
    args = ap.parse_args()
    runs = []
    for item in args.runs:
        label, _, path = item.partition("=")
        if path.endswith(".jsonl") and Path(path).is_file():
            rows = [r for r in map(json.loads, filter(str.strip, Path(path).read_text().splitlines())) if "probe/normal_deg" in r]
        elif not path or not (Path(path) / "stats.jsonl").exists():
            sys.exit(f"{item}: expected LABEL=RUN_DIR with a stats.jsonl, or LABEL=ROWS.jsonl")
        else:
            rows = probe_rows(Path(path))
        if args.until is not None:
            rows = [r for r in rows if r["step"] <= args.until]
        if not rows:
            sys.exit(f"{path}: no probe rows" + (f" up to step {args.until}" if args.until is not None
                                                  else " (train with --probe)"))
        runs.append((label, Path(path), rows))
    args.out.mkdir(parents=True, exist_ok=True)
    lines = ["| run | seed | step | normals, moving avg. (raw; swing) | constant / prior | albedo L1 | reflection L1 | "
             "speckle N / A | corr x / y / z | R sensitivity / colour |", "|" + "---|" * 10]
    summary = {}
    for label, path, rows in runs:
        f = row_figures(rows)
        reference = path.is_file()  # a committed curve: nothing of it is copied
        # a committed LABEL_probe.jsonl written here has its LABEL_training_options.json beside it
        options = (path.with_name(path.name.removesuffix("_probe.jsonl") + "_training_options.json")
                   if reference else path / "training_options.json")
        f["seed"] = (json.loads(options.read_text())["config"]["run"]["seed"] if options.is_file()
                     else rows[-1].get("seed", "-"))
        summary[label] = f
        lines.append(_line(label, f))
        if reference:
            continue
        with open(args.out / f"{label}_probe.jsonl", "w") as fh:
            for r in rows:
                fh.write(json.dumps({k: v for k, v in r.items() if k == "step" or k.startswith("probe")}) + "\n")
        text = (path / "training_options.json").read_text()
        if args.relative_to is not None:
            text = text.replace(str(args.relative_to.resolve()).rstrip("/") + "/", "OUT/")
        (args.out / f"{label}_training_options.json").write_text(text)
    (args.out / "table.md").write_text("\n".join(lines) + "\n")
    (args.out / "table.json").write_text(json.dumps(summary, indent=1) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for k, (label, _, rows) in enumerate(runs):
        steps = [r["step"] for r in rows]
        color, style = f"C{k % 10}", ("-", "--", ":")[k // 10 % 3]  # more than ten runs: a line style apart
        ax.plot(steps, [r["probe/normal_deg"] for r in rows], color=color, alpha=0.3, lw=0.8)
        judged_deg = [judged(r)[0] for r in rows]
        ax.plot(steps, judged_deg, color=color, ls=style, label=legend_label(label, judged_deg, args.ylim))
    last = runs[0][2][-1]
    ax.axhline(last["probe/const_normal_deg"], ls="--", color="gray", label="constant predictor")
    if "probe/prior_normal_deg" in last:
        ax.axhline(last["probe/prior_normal_deg"], ls="-.", color="gray", label="per-pixel prior (no image)")
    if args.ylim is not None:
        ax.set_ylim(*args.ylim)
    ax.set_xlabel("step")
    ax.set_ylabel("H's mean normal error (deg)")
    ax.set_title(f"{args.title} (solid: moving-average weights; faint: raw)", fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(args.out / "curves.png", dpi=100)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
