"""Probe curves of the `cpu` comparison run as objective sweeps (bench/variants_cpu.toml) on a GPU.

  python bench/plot_comparison.py results/cpu_gpu --out results/cpu_gpu_curves.png
  python bench/plot_comparison.py results/cpu_new/s22 [more folders] --out curves.png
Reads the sweeps' curve files (rows name their variant and seed) and `reproduce` runs' probe rows
saved as NAME_sSEED_probe.jsonl (the name says which).
Prints a Markdown table (the last probe row of every run, mean over seeds with the spread) and
draws normals, albedo and reflection (and, for the curves that have them, R's and H's colour
correlations) against the step, one colour per model, a line per seed.
"""
from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from pathlib import Path

LINE_STYLES = ("-", "--", ":")  # one per seed, in the order of the seeds drawn
METRICS = (("probe/normal_deg", "probe/const_normal_deg", "normals (deg)"),
           ("probe/albedo_l1", "probe/const_albedo_l1", "albedo L1 (0-255)"),
           ("probe/reflection_l1", "probe/const_reflection_l1", "reflection L1 (0-255)"))


def load(*folders: Path) -> dict[str, dict[int, list[dict]]]:
    runs: dict[str, dict[int, list[dict]]] = defaultdict(dict)
    for f in sorted(f for folder in folders for f in folder.glob("*.jsonl")):
        rows = [json.loads(x) for x in f.read_text().splitlines() if x.strip()]
        named = re.fullmatch(r"(.+)_s(\d+)_probe", f.stem)
        if rows and "variant" in rows[0]:
            runs[rows[0]["variant"]][int(rows[0]["seed"])] = rows
        elif rows and named:
            runs[named.group(1)][int(named.group(2))] = rows
    return runs


def table(runs: dict[str, dict[int, list[dict]]], order: list[str]) -> str:
    lines = ["| model | seeds | step | normals (deg) | corr x / y / z (mean) | albedo L1 | reflection L1 | R sensitivity "
             "| R colour corr. | H albedo colour corr. |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name in order:
        seeds = runs[name]
        last = {s: rows[-1] for s, rows in sorted(seeds.items())}
        steps = sorted({r["step"] for r in last.values()})
        col = lambda k: " / ".join(f"{r[k]:.1f}" for r in last.values())  # noqa: E731
        corr = " / ".join(f"{sum(r[f'probe/normal_corr_{a}'] for r in last.values()) / len(last):.2f}" for a in "xyz")
        sens = " / ".join(f"{r['probe/r_sensitivity']:.2f}" for r in last.values())
        colour = {k: " / ".join(f"{r[k]:.2f}" if k in r else "-" for r in last.values())  # older curves lack them
                  for k in ("probe/r_colour_corr", "probe/h_colour_corr")}
        lines.append(f"| {name} | {', '.join(map(str, last))} | {'-'.join(map(str, (steps[0], steps[-1])[:len(set(steps))]))} "
                     f"| {col(METRICS[0][0])} | {corr} | {col(METRICS[1][0])} | {col(METRICS[2][0])} | {sens} "
                     f"| {colour['probe/r_colour_corr']} | {colour['probe/h_colour_corr']} |")
    any_row = next(iter(next(iter(runs.values())).values()))[-1]
    lines.append(f"| constant predictor | | | {any_row[METRICS[0][1]]:.1f} | | {any_row[METRICS[1][1]]:.1f} | "
                 f"{any_row[METRICS[2][1]]:.1f} | | | |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", nargs="*", default=None, help="models to draw (default: all, in file order)")
    a = ap.parse_args()
    runs = load(*a.folders)
    order = a.only or list(runs)
    print(table(runs, order))
    if a.out is None:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colour = any("probe/r_colour_corr" in rows[-1] for seeds in runs.values() for rows in seeds.values())
    panels = list(METRICS) + ([("probe/r_colour_corr", None, "R colour correlation"),
                               ("probe/h_colour_corr", None, "H albedo colour correlation")] if colour else [])
    seeds = sorted({seed for name in order for seed in runs[name]})
    fig, axes = plt.subplots(1, len(panels), figsize=(5.7 * len(panels), 5.2))
    for ax, (key, const, title) in zip(axes, panels):
        for c, name in enumerate(order):
            for j, (seed, rows) in enumerate(sorted(runs[name].items())):
                rows = [r for r in rows if key in r]  # older curves lack the colour figures
                ax.plot([r["step"] for r in rows], [r[key] for r in rows], color=f"C{c % 10}",
                        ls=LINE_STYLES[seeds.index(seed) % len(LINE_STYLES)], lw=1.4,
                        label=name if j == 0 else None)
        if const:
            ax.axhline(next(iter(runs[order[0]].values()))[-1][const], color="k", ls="--", lw=1, label="constant")
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    for style, seed in zip(LINE_STYLES, seeds if len(seeds) > 1 else []):  # which line style is which seed
        axes[0].plot([], [], color="grey", ls=style, lw=1.4, label=f"seed {seed}")
    axes[0].legend(fontsize=8, ncol=2)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
