"""Probe curves of objective sweeps (bench/objective_sweep.py output) as one figure and a table.

  python bench/plot_sweeps.py results/sweeps --out results/making_it_learn.png
Each sub-folder is a setting (s0, s1, protocol, protocol_env); each NAME_sSEED.jsonl a run.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TITLES = {"s0_first": "S0, first sweep (8.3 min, 18 runs at once)", "s0": "S0: analytic shading (exact)", "s1": "S1: PBR, black background",
          "protocol": "protocol: PBR with background", "protocol_env": "protocol, environment in M_s's reflection"}
ORDER = ["paper", "w10", "w10_mean", "w10_mean_car", "w10_mean_car_noise", "w10_mean_car_detach",
         "w10_mean_car_lsgan", "w10_mean_car_dm01", "oracle"]


COLOURS = {"paper": "C0", "w10": "C1", "w10_mean": "C4", "w10_mean_car": "C3", "w10_mean_car_noise": "C5",
           "w10_mean_car_detach": "C6", "w10_mean_car_lsgan": "C8", "w10_mean_car_dm01": "C2", "oracle": "goldenrod"}


def load(folder: Path) -> dict[str, dict[int, list[dict]]]:
    """{variant: {seed: probe rows}} of a folder of bench/objective_sweep.py curves."""
    runs: dict[str, dict[int, list[dict]]] = defaultdict(dict)
    for f in sorted(folder.glob("*.jsonl")):
        rows = [json.loads(x) for x in f.read_text().splitlines() if x.strip()]
        if rows:
            runs[rows[0]["variant"]][int(rows[0]["seed"])] = rows
    return runs


def table(root: Path) -> str:
    lines = ["| setting | variant | seed | step | normal deg | const | corr x / y / z | albedo | const | reflection | "
             "const | R sens. |", "|" + "---|" * 12]
    for setting in TITLES:
        if not (root / setting).is_dir():
            continue
        runs = load(root / setting)
        for v in sorted(runs, key=lambda k: ORDER.index(k) if k in ORDER else 99):
            for seed, rows in sorted(runs[v].items()):
                r = rows[-1]
                p = lambda k: r[f"probe/{k}"]  # noqa: E731
                lines.append(f"| {setting} | {v} | {seed} | {r['step']} | {p('normal_deg'):.1f} | {p('const_normal_deg'):.1f} | "
                             f"{p('normal_corr_x'):.2f} / {p('normal_corr_y'):.2f} / {p('normal_corr_z'):.2f} | "
                             f"{p('albedo_l1'):.1f} | {p('const_albedo_l1'):.1f} | {p('reflection_l1'):.1f} | "
                             f"{p('const_reflection_l1'):.1f} | {p('r_sensitivity'):.2f} |")
    return "\n".join(lines)


def figure(root: Path, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = [s for s in TITLES if (root / s).is_dir() and s != "s0_first"]
    fig, axes = plt.subplots(1, len(settings), figsize=(4.2 * len(settings), 3.6), sharey=True)
    for ax, setting in zip(axes, settings):
        runs = load(root / setting)
        const = None
        for v in sorted(runs, key=lambda k: ORDER.index(k) if k in ORDER else 99):
            colour = COLOURS.get(v, "C9")
            for k, (seed, rows) in enumerate(sorted(runs[v].items())):
                ax.plot([r["step"] for r in rows], [r["probe/normal_deg"] for r in rows], color=colour, lw=1,
                        alpha=0.8, label=v if k == 0 else None)
                const = rows[-1]["probe/const_normal_deg"]
        if const is not None:
            ax.axhline(const, ls="--", color="gray", lw=1, label="constant predictor")
            ax.axhline(const - 5, ls=":", color="gray", lw=1, label="constant - 5 deg")
        ax.set_title(TITLES[setting], fontsize=9)
        ax.set_xlabel("step (batch 4, 32x64)")
        ax.set_ylim(10, 80)
        ax.legend(fontsize=6)
    axes[0].set_ylabel("H normals on the probe: mean angle (deg)")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def runs_figure(runs: list[Path], out: Path) -> None:
    """Probe curves (normals, albedo, reflection beside the constant predictor's) of run folders."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from train.run_folder import RunFolder

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for k, run in enumerate(runs):
        rows = [r for r in RunFolder(run).stats() if "probe/normal_deg" in r]
        seed = RunFolder(run).config().run.seed
        steps = [r["step"] for r in rows]
        for ax, key in zip(axes, ("normal_deg", "albedo_l1", "reflection_l1")):
            ax.plot(steps, [r[f"probe/{key}"] for r in rows], color=f"C{k}", label=f"full model, seed {seed}")
            if k == 0:
                ax.plot(steps, [r[f"probe/const_{key}"] for r in rows], "--", color="gray", label="constant predictor")
    for ax, title in zip(axes, ("normals: mean angle (deg)", "albedo L1 (0-255)", "reflection L1 (0-255)")):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("step (batch 4, 64x128)")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, nargs="?", default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--runs", type=Path, nargs="+", default=None, help="run folders: their probe curves instead")
    a = ap.parse_args()
    if a.runs:
        runs_figure(a.runs, a.out)
        print(f"wrote {a.out}")
        return
    print(table(a.root))
    if a.out:
        figure(a.root, a.out)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
