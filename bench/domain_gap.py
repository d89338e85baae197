"""How H reads real images against R's renders, and what each loss term asks of H there.

Two measurements for trained runs of the Intrinsic Autoencoder (or any kind with `decompose` and
`render`), on a probe set with ground truth (the Table-3 set that `reproduce` passes as --probe):

  gap      Table-3 errors of H on the probe's real images, and of H on R's renders of the same
           images' true intrinsics. A large difference is the domain gap the decomposition cycle
           trains H across: it fits H to R's images, which is only worth as much as they look real.
  cosines  the mean, min and max over `iae-train diagnose --json` files of each loss term's cosine
           with the supervised direction per network (several batches and checkpoints per run).

  python bench/domain_gap.py gap --probe OUT/data/eval OUT/runs/full OUT/runs/no_dec
  python bench/domain_gap.py cosines results/cpu_new/diagnose/diag_full_*.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

NETS = ("H_N", "H_A", "H_F", "R")


def gap(probe: Path, runs: list[Path], batch: int = 16) -> None:
    import torch

    from train.inference import load_run_checkpoint
    from train.probe import decomposition_scores, load_probe

    print(f"H on the probe's images | H on R(the same images' true intrinsics); probe {probe}")
    print(f"{'run':12s} {'step':>6s}   {'normals':>8s} {'albedo':>7s} {'reflect':>7s}   "
          f"{'normals':>8s} {'albedo':>7s} {'reflect':>7s}")
    probes = {}  # decoded once per training resolution, not once per run
    for run in runs:
        cfg, model, step, _ = load_run_checkpoint(run, "cpu", None)
        size = (cfg.data.height, cfg.data.width)
        if size not in probes:
            probes[size] = load_probe(probe, *size, limit=None)
        p = probes[size]
        model.eval()
        gen = torch.Generator().manual_seed(0)  # fixed style codes where R draws them (MUNIT)
        with torch.no_grad():
            chunks = range(0, len(p.images), batch)
            real = torch.cat([model.decompose(p.images[i:i + batch]).float() for i in chunks])
            ren = torch.cat([model.render(p.maps[i:i + batch], generator=gen).float() for i in chunks])
            own = torch.cat([model.decompose(ren[i:i + batch]).float() for i in chunks])
        a, b = decomposition_scores(real, p), decomposition_scores(own, p)
        cells = [a["normal_deg"], a["albedo_l1"], a["reflection_l1"], b["normal_deg"], b["albedo_l1"], b["reflection_l1"]]
        print(f"{run.name:12s} {step:6d}   {cells[0]:8.1f} {cells[1]:7.1f} {cells[2]:7.1f}   "
              f"{cells[3]:8.1f} {cells[4]:7.1f} {cells[5]:7.1f}")


def cosines(files: list[Path]) -> None:
    runs: dict[str, list[dict]] = {}
    for f in files:
        try:
            d = json.loads(f.read_text())
            runs.setdefault(Path(d["run"]).name, []).append(d)
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise SystemExit(f"{f}: not an `iae-train diagnose --json` file ({exc})")
    for run, ds in runs.items():
        steps = sorted({d["step"] for d in ds})
        print(f"\n{run}: {len(ds)} diagnoses (steps {', '.join(map(str, steps))}); cosine with the supervised "
              "direction, mean [min, max]")
        print(f"{'term':20s} " + " ".join(f"{n:>20s}" for n in NETS))
        for term in ds[0]["terms"]:
            if all(d["terms"][term]["weight"] == 0 for d in ds):
                continue
            cells = []
            for net in NETS:
                c = [d["terms"][term][net]["cosine"] for d in ds]
                g = [d["terms"][term][net]["grad_norm"] for d in ds]
                cells.append("-" if max(g) == 0 else f"{statistics.mean(c):+.2f} [{min(c):+.2f},{max(c):+.2f}]")
            print(f"{term.removeprefix('G/'):20s} " + " ".join(f"{c:>20s}" for c in cells))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("gap")
    g.add_argument("--probe", type=Path, required=True)
    g.add_argument("runs", type=Path, nargs="+")
    c = sub.add_parser("cosines")
    c.add_argument("files", type=Path, nargs="+")
    args = ap.parse_args()
    if args.cmd == "gap":
        import torch

        torch.set_num_threads(1)  # beside running trainings
        gap(args.probe, args.runs)
    else:
        cosines(args.files)


if __name__ == "__main__":
    main()
