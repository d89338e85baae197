"""Shape diversity of the procedural cars, measured: pairwise IoU of metric silhouettes.

Every car is seen by one orthographic camera per view (the limit of a distant long-lens camera;
pixels are metres, 2 cm): side (the two sides mirror each other), end (front and rear alike)
and top; a pair's IoU is the mean over the three views. Printed for the first catalogue
(`data_manifests/cars_v1.toml`, built by today's body code), the named catalogue, and
random cars of `procedural:random`: median IoU within and across categories, the closest
pair, pairs above 0.93, and whether categories are separable by silhouettes (leave-one-out
category of the nearest model, and of the highest mean IoU with a category's members).
Then the dimension table: every named model's measured size against the real-world ranges
of `data_manifests/car_ranges.toml`.
Usage: python bench/bench_car_diversity.py [--random 48] [--seed 0] [--json out.json] [--sheet sil.png]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from blender_gen.cars import CATEGORIES, build_car, load_catalogue
from blender_gen.cars.sampler import load_ranges, random_spec
from blender_gen.cars.silhouette import diversity, iou_matrix, silhouettes

ROOT = Path(__file__).resolve().parent.parent


def measure(specs: list) -> tuple[dict, list]:
    sils = [silhouettes(build_car(s)) for s in specs]
    m = iou_matrix(sils)
    return diversity([s.name for s in specs], [s.category for s in specs], m), sils


def dimensions(spec) -> dict:
    parts = build_car(spec)
    body = np.concatenate([parts[k].verts for k in ("body", "windshield") if k in parts])
    pts = np.concatenate([m.verts for k, m in parts.items() if k != "roof_rails"])
    return {"length": float(np.ptp(pts[:, 0])), "width": float(np.ptp(body[:, 1])), "height": float(pts[:, 2].max()),
            "wheelbase": spec.wheelbase, "front_overhang": spec.front_overhang,
            "wheel_diameter": 2 * spec.wheel_radius, "clearance": spec.clearance}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--random", type=int, default=48, help="random cars to measure")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random cars")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sheet", type=Path, default=None, help="PNG of every named model's side silhouette")
    args = ap.parse_args()

    sets = {
        "before (cars_v1.toml)": list(load_catalogue(ROOT / "data_manifests" / "cars_v1.toml").values()),
        "named catalogue (cars.toml)": list(load_catalogue().values()),
        f"random, seed {args.seed}": [random_spec(args.seed, k) for k in range(args.random)],
    }
    results = {}
    print(f"{'set':30s} {'models':>6s} {'within':>7s} {'across':>7s} {'>0.93':>6s} {'NN cat':>7s} {'mean cat':>8s}  closest pair")
    for label, specs in sets.items():
        d, sils = measure(specs)
        results[label] = d
        a, b, v = d["closest_pair"]
        print(f"{label:30s} {d['models']:6d} {d['within_median']:7.3f} {d['across_median']:7.3f} {d['pairs_above_0.93']:6d} "
              f"{d['nn_category_accuracy']:7.2f} {d['mean_category_accuracy']:8.2f}  {a} / {b} {v:.3f}", flush=True)
        if label.startswith("named") and args.sheet:
            tiles = [s["side"][60:] for s in sils]
            rows = [np.concatenate(tiles[i:i + 4] + [np.zeros_like(tiles[0])] * (4 - len(tiles[i:i + 4])), axis=1)
                    for i in range(0, len(tiles), 4)]
            from PIL import Image
            Image.fromarray((~np.concatenate(rows, axis=0)).astype(np.uint8) * 255).save(args.sheet)
    print("\nthe same, from the two sides and the two ends only (no top view):")
    for label in list(sets)[:2]:
        sils = [silhouettes(build_car(s)) for s in sets[label]]
        d = diversity([s.name for s in sets[label]], [s.category for s in sets[label]],
                      iou_matrix(sils, ("side", "end")))
        a, b, v = d["closest_pair"]
        print(f"{label:30s} within {d['within_median']:.3f}  across {d['across_median']:.3f}  "
              f"pairs > 0.93: {d['pairs_above_0.93']}  closest {a} / {b} {v:.3f}")
    print("\nper category, median IoU within (before -> named -> random):")
    for c in CATEGORIES:
        vals = [results[k]["per_category"].get(c, {}).get("median_iou") for k in results]
        print(f"  {c:14s} " + " -> ".join("-" if v is None else f"{v:.3f}" for v in vals))

    ranges = load_ranges()
    print("\nnamed models against the real-world ranges (data_manifests/car_ranges.toml); * = outside")
    keys = ("length", "width", "height", "wheelbase", "front_overhang", "wheel_diameter", "clearance")
    print(f"  {'model':12s} {'style':10s} " + " ".join(f"{k[:10]:>10s}" for k in keys))
    outside = 0
    table = {}
    for spec in sets["named catalogue (cars.toml)"]:
        dims = dimensions(spec)
        table[spec.name] = dims
        cells = []
        for k in keys:
            lo, hi = ranges[spec.category][k]
            bad = not (lo - 0.03 <= dims[k] <= hi + 0.03)  # measured meshes: 3 cm for bumpers and rounding
            outside += bad
            cells.append(f"{dims[k]:9.2f}{'*' if bad else ' '}")
        print(f"  {spec.name:12s} {spec.body_style:10s} " + " ".join(cells))
    print(f"  {outside} value(s) outside their category's range")
    if args.json:
        args.json.write_text(json.dumps({"diversity": results, "dimensions": table, "outside": outside}, indent=2))


if __name__ == "__main__":
    main()
