"""Runs trained on the same photos with differently framed intrinsics, scored on one PBR set.

    python bench/framing_ab.py --data CLOSE_PBR_SET --out results/framing/ab \
        LABEL=RUN_DIR [LABEL=RUN_DIR ...]

Every kept checkpoint of every run (the last three, by default 100 steps apart) decomposes --data
(H at its training size, as `iae-eval decomposition` does) and is scored against its ground
truth; each run's training intrinsics also give the two no-image rows (the constant predictor and
the per-pixel prior). Writes `table.md` and `results.json`; the spread of a run's last checkpoints
is its step-to-step swing.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eval.decomposition import score_predictions  # noqa: E402
from eval.reference_rows import constant_predictions, prior_predictions  # noqa: E402
from train.inference import decompose_images, load_run_options  # noqa: E402

KEYS = ("normal_mean_deg", "albedo_l1_srgb255", "reflection_l1_srgb255", "normal_hf_ratio")


def _summary(data: Path, predictions: Path) -> dict:
    _, s = score_predictions(data, predictions, progress=False)
    return {k: round(float(s[k]), 3) for k in KEYS if k in s}


def intrinsics_of(run: Path) -> Path:
    return Path(load_run_options(run)[0]["intrinsics"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--data", type=Path, required=True, help="a PBR set with ground truth")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {"data": args.data.name, "runs": {}, "references": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.runs:
            label, run = spec.split("=", 1)
            run = Path(run)
            ckpts = sorted((run / "checkpoints").glob("step_*.safetensors"))
            rows = {}
            for ckpt in ckpts:
                step = int(ckpt.stem.split("_")[1])
                pred = decompose_images(run, args.data, Path(tmp) / f"{label}_{step}", checkpoint=ckpt, progress=False)
                rows[step] = _summary(args.data, pred)
                print(label, step, rows[step], flush=True)
            results["runs"][label] = rows
            intr = intrinsics_of(run)
            if str(intr) not in results["references"]:
                refs = {}
                for name, make in (("constant", constant_predictions), ("per-pixel prior", prior_predictions)):
                    refs[name] = _summary(args.data, make(intr, args.data, Path(tmp) / f"{name}_{label}", progress=False))
                results["references"][str(intr)] = {"first_run": label, **refs}
    (args.out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    lines = [f"Scored on `{args.data.name}` (H at its training size, resized back); steps are each run's kept "
             "checkpoints; the swing is the largest minus the smallest normal error over them.", "",
             "| run | steps | normals (deg), last | swing | albedo L1 | reflection L1 | speckle N |",
             "|---|---|---|---|---|---|---|"]
    for label, rows in results["runs"].items():
        steps = sorted(rows)
        last = rows[steps[-1]]
        normals = [rows[s]["normal_mean_deg"] for s in steps]
        lines.append(f"| {label} | {', '.join(map(str, steps))} | {last['normal_mean_deg']:.1f} | "
                     f"{np.ptp(normals):.1f} | {last['albedo_l1_srgb255']:.1f} | {last['reflection_l1_srgb255']:.1f} | "
                     f"{last.get('normal_hf_ratio', float('nan')):.2f} |")
    for intr, refs in results["references"].items():
        for name in ("constant", "per-pixel prior"):
            r = refs[name]
            lines.append(f"| {name} (intrinsics of {refs['first_run']}) | | {r['normal_mean_deg']:.1f} | | "
                         f"{r['albedo_l1_srgb255']:.1f} | {r['reflection_l1_srgb255']:.1f} | |")
    (args.out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
