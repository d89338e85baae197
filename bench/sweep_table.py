"""Table and curves of objective sweeps (bench/objective_sweep.py output), moving-average figures first.

  python bench/sweep_table.py results/shading_ren --out results/shading_ren/curves.png [--plot-only V ...]
Each sub-folder of ROOT is a setting (s0, s1, protocol, ...), or ROOT itself holds the curves;
each NAME_sSEED.jsonl a run.
Per run, the last probe row: normals of the moving-average weights (probe_ema/, what inference
uses) and of the raw weights, the step-to-step swing of the raw normals over the last three
probes (a difference between runs is read only where it exceeds it), the pass line of the sanity
benchmark (the stronger no-image bar less 5 deg), speckle (H's normals' high-frequency energy
over the truth's), albedo, reflection and R's input sensitivity and colour correlation. Writes
ROOT/table.md and ROOT/table.json; --out draws the moving-average normal curves per setting.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.plot_sweeps import load  # noqa: E402
from eval.sanity import PASS_MARGIN_DEG  # noqa: E402  (the sanity benchmark's pass line)


def settings(root: Path) -> list[str]:
    """The sub-folders of ROOT, or ROOT itself when its curves lie in it."""
    if any(root.glob("*.jsonl")):
        return [root.name]
    return sorted(p.name for p in root.iterdir() if p.is_dir())


def folder(root: Path, setting: str) -> Path:
    return root if setting == root.name and any(root.glob("*.jsonl")) else root / setting


def summary(rows: list[dict]) -> dict:
    r = rows[-1]
    ema = "probe_ema/" if "probe_ema/normal_deg" in r else "probe/"
    tail = [x["probe/normal_deg"] for x in rows[-3:]]
    bar = min(r["probe/const_normal_deg"], r.get("probe/prior_normal_deg", r["probe/const_normal_deg"]))
    return {"step": r["step"], "normal_deg": r[f"{ema}normal_deg"], "normal_deg_raw": r["probe/normal_deg"],
            "swing_deg": max(abs(a - b) for a, b in zip(tail, tail[1:])) if len(tail) > 1 else 0.0,
            "pass_line_deg": bar - PASS_MARGIN_DEG, "passes": r[f"{ema}normal_deg"] <= bar - PASS_MARGIN_DEG,
            "speckle": r.get(f"{ema}normal_hf_ratio"), "albedo_l1": r[f"{ema}albedo_l1"],
            "reflection_l1": r[f"{ema}reflection_l1"], "r_sensitivity": r["probe/r_sensitivity"],
            "r_colour_corr": r.get("probe/r_colour_corr"), "const_normal_deg": r["probe/const_normal_deg"],
            "prior_normal_deg": r.get("probe/prior_normal_deg"), "const_albedo_l1": r.get("probe/const_albedo_l1"),
            "prior_albedo_l1": r.get("probe/prior_albedo_l1"), "prior_reflection_l1": r.get("probe/prior_reflection_l1"),
            "seconds": r.get("t")}


def _f(x, fmt: str = ".1f") -> str:
    return "-" if x is None else format(x, fmt)


def tables(root: Path, order: list[str] | None) -> tuple[str, dict]:
    lines = ["| setting | variant | seed | step | normals, EMA (deg) | raw | swing | pass line | speckle | albedo L1 "
             "| reflection L1 | R sens. | R colour corr. |", "|" + "---|" * 13]
    data: dict = {}
    bars = []
    for setting in settings(root):
        runs = load(folder(root, setting))
        names = [v for v in (order or []) if v in runs] + sorted(v for v in runs if v not in (order or []))
        for v in names:
            for seed, rows in sorted(runs[v].items()):
                s = summary(rows)
                data.setdefault(setting, {}).setdefault(v, {})[seed] = s
                lines.append(f"| {setting} | {v} | {seed} | {s['step']} | **{s['normal_deg']:.1f}** | "
                             f"{s['normal_deg_raw']:.1f} | {s['swing_deg']:.1f} | {s['pass_line_deg']:.1f} | "
                             f"{_f(s['speckle'], '.2f')} | {s['albedo_l1']:.1f} | {s['reflection_l1']:.1f} | "
                             f"{s['r_sensitivity']:.2f} | {_f(s['r_colour_corr'], '.2f')} |")
        if names:
            s = summary(next(iter(runs[names[0]].values())))
            bars.append(f"| {setting} | {s['const_normal_deg']:.1f} | {_f(s['prior_normal_deg'])} | "
                        f"{_f(s['const_albedo_l1'])} | {_f(s['prior_albedo_l1'])} | {_f(s['prior_reflection_l1'])} |")
    lines += ["", "No-image bars on the same probe pixels:", "",
              "| setting | constant normals | per-pixel prior normals | constant albedo | prior albedo | prior reflection |",
              "|---|---|---|---|---|---|", *bars]
    return "\n".join(lines) + "\n", data


def figure(root: Path, data: dict, out: Path, order: list[str] | None, only: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [st for st in data if only is None or any(v in only for v in data[st])]  # no empty panels
    fig, axes = plt.subplots(1, len(shown), figsize=(4.4 * len(shown), 3.8), sharey=True, squeeze=False)
    for ax, setting in zip(axes[0], shown):
        runs = load(folder(root, setting))
        names = [v for v in (order or []) if v in runs] + sorted(v for v in runs if v not in (order or []))
        names = [v for v in names if only is None or v in only]
        every = list(dict.fromkeys([*(order or []), *sorted(v for d in data.values() for v in d)]))
        for v in names:
            k = every.index(v)  # one colour per variant in every panel
            for j, (seed, rows) in enumerate(sorted(runs[v].items())):
                key = "probe_ema/normal_deg" if "probe_ema/normal_deg" in rows[-1] else "probe/normal_deg"
                ax.plot([r["step"] for r in rows], [r[key] for r in rows], color=f"C{k}", lw=1,
                        ls=("-", "--", ":")[j % 3], label=v if j == 0 else None)
        s = next(iter(next(iter(data[setting].values())).values()))
        ax.axhline(s["const_normal_deg"], ls="--", color="gray", lw=1, label="constant predictor")
        if s["prior_normal_deg"] is not None:
            ax.axhline(s["prior_normal_deg"], ls="-.", color="gray", lw=1, label="per-pixel prior")
        ax.axhline(s["pass_line_deg"], ls=":", color="black", lw=1, label="pass line (bar - 5)")
        ax.set_title(setting, fontsize=9)
        ax.set_xlabel("step")
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("H normals on the probe, EMA weights (deg)")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="a PNG of the curves")
    ap.add_argument("--order", nargs="*", default=None, help="variants in this order first")
    ap.add_argument("--plot-only", nargs="*", default=None, metavar="VARIANT",
                    help="draw only these variants' curves (the tables keep every variant)")
    a = ap.parse_args()
    md, data = tables(a.root, a.order)
    unknown = sorted(set(a.plot_only or []) - {v for d in data.values() for v in d})
    if unknown:
        ap.error(f"--plot-only: no runs of {', '.join(unknown)} under {a.root}")
    (a.root / "table.md").write_text(md)
    (a.root / "table.json").write_text(json.dumps(data, indent=1) + "\n")
    print(md)
    if a.out:
        figure(a.root, data, a.out, a.order, a.plot_only)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
