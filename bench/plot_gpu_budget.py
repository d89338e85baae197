"""Probe curves at the paper's resolution (the `gpu` budget's networks) beside the `cpu` budget's.

  python bench/plot_gpu_budget.py --gpu results/gpu_budget \
      --cpu results/cpu_shared_gain/shared_gain_s21_probe.jsonl results/cpu_shared_gain/shared_gain_s22_probe.jsonl \
      --cpu-oracle results/cpu_default/oracle_s21.jsonl results/cpu_default/oracle_s22.jsonl \
      --out results/gpu_budget/curves.png
GPU curves: bench/objective_sweep.py files (NAME_sSEED.jsonl); CPU curves: probe rows of the `cpu`
comparison under the default (`fit --probe` or the sweep tool). Moving-average figures where a file
has them, raw otherwise. Steps are optimiser steps: batch 1 at 256x512 on the GPU, batch 4 at 64x128
on the CPU.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

PANELS = (("normal_deg", "normals (deg)"), ("albedo_l1", "albedo L1 (0-255)"), ("reflection_l1", "reflection L1 (0-255)"))


def rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def value(r: dict, key: str) -> float:
    return r.get(f"probe_ema/{key}", r[f"probe/{key}"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gpu", type=Path, required=True, help="folder of the GPU runs' curves")
    ap.add_argument("--cpu", type=Path, nargs="*", default=[], help="the cpu budget's probe files of the default's full model")
    ap.add_argument("--cpu-oracle", type=Path, nargs="*", default=[], help="the cpu budget's oracle probe files")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 3.8))
    colours = {"full": "C0", "oracle": "C2", "shader": "C3", "default": "C4"}  # by the variant name's first word
    names = {"full": "previous defaults", "shader_nodec": "cycle-free shader (per-image gain, D_M on all maps)",
             "default": "default", "oracle": "oracle"}
    seed = lambda f: re.search(r"_s(\d+)", f.stem).group(1)  # noqa: E731
    variant = lambda f: f.stem.rsplit("_s", 1)[0]  # noqa: E731
    curves = [(f, colours.get(f.stem.split("_")[0], "C1"), "-", f"GPU 256x512 {names.get(variant(f), variant(f))}, seed {seed(f)}")
              for f in sorted(a.gpu.glob("*.jsonl"))]
    curves += [(f, "C4", ":", f"CPU 64x128 default, seed {seed(f)}") for f in a.cpu]
    curves += [(f, "C2", ":", f"CPU 64x128 oracle, seed {seed(f)}") for f in a.cpu_oracle]
    bars = None
    for f, colour, ls, label in curves:
        rs = [r for r in rows(f) if "probe/normal_deg" in r]
        for ax, (key, _) in zip(axes, PANELS):
            ax.plot([r["step"] for r in rs], [value(r, key) for r in rs], color=colour, ls=ls, lw=1.2 if ls == "-" else 0.9,
                    alpha=1.0 if ls == "-" else 0.7, label=label)
        if bars is None and ls == "-":  # the no-image bars of the GPU probe (the same for every GPU run)
            bars = rs[-1]
    for ax, (key, title) in zip(axes, PANELS):
        if bars is not None:
            ax.axhline(bars[f"probe/const_{key}"], ls="--", color="gray", lw=1, label="constant (GPU probe)")
            if f"probe/prior_{key}" in bars:
                ax.axhline(bars[f"probe/prior_{key}"], ls="-.", color="gray", lw=1, label="per-pixel prior (GPU probe)")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("optimiser step")
    fig.tight_layout()
    # the legend sits right of the panels; the tight box keeps no empty margin beside it
    fig.legend(*axes[0].get_legend_handles_labels(), loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7)
    fig.savefig(a.out, dpi=90, bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
