"""How well the shading model explains images, with true maps and with H's: per image the fitted
reflection gain and the relative shading residual (train.shading.fit_shading, per-image gain).

A decomposition whose residual is *lower* than the truth's, with a larger gain, explains the image
by copying it into the reflection map rather than by its shading: the signature of S1's failure.

    python bench/shading_gains.py --probe S1=DATA/s1_probe --run S1:default=RUNS/S1/full_seed0 --out gains.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from train.probe import load_probe, object_mask
from train.shading import fit_shading


def summarise(images: torch.Tensor, maps: torch.Tensor, mask: torch.Tensor) -> dict:
    res, coeffs = fit_shading(images, maps[:, 0:3], maps[:, 3:6], maps[:, 6:9], mask)
    has = mask.flatten(1).sum(1) >= 16
    gain, res = coeffs[has, 9], res[has]
    q = torch.tensor([0.1, 0.5, 0.9])
    return {"images": int(has.sum()), "gain_p10_p50_p90": [round(float(v), 3) for v in torch.quantile(gain, q)],
            "residual_mean": round(float(res.mean()), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--probe", action="append", default=[], metavar="NAME=PBR_SET", help="a PBR set with ground truth")
    ap.add_argument("--run", action="append", default=[], metavar="PROBE:LABEL=RUN", help="H of RUN on probe PROBE")
    ap.add_argument("--size", default="64x32", help="WIDTHxHEIGHT the maps are compared at")
    ap.add_argument("--limit", type=int, default=48)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.lower().split("x"))
    probes = {k: load_probe(Path(v), h, w, limit=a.limit) for k, v in (p.split("=", 1) for p in a.probe)}
    rows = [{"what": f"{name}: true maps", **summarise(p.images, p.maps, p.masks)} for name, p in probes.items()]
    for item in a.run:
        where, run = item.split("=", 1)
        probe, label = where.split(":", 1)
        from train.inference import load_run

        cfg, model, step = load_run(Path(run))
        p = load_probe(Path(dict(x.split("=", 1) for x in a.probe)[probe]), cfg.data.height, cfg.data.width,
                       limit=a.limit)
        with torch.no_grad():
            maps = model.decompose(p.images).float()
        rows.append({"what": f"{probe}: H of {label} (step {step}, {model.weights} weights)",
                     **summarise(p.images, maps, object_mask(maps))})
    for r in rows:
        print(f"{r['what']:<60} gain p10/p50/p90 {r['gain_p10_p50_p90']}  residual {r['residual_mean']:.3f}  "
              f"({r['images']} images)")
    if a.out:
        a.out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
