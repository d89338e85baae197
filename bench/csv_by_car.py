"""Table-3 errors of a report's per-sample CSV split into two groups of cars.

    python bench/csv_by_car.py --cars sedan,police,ambulance,delivery,van results/kenney_cars/decomposition_mixed_s21.csv \
        results/kenney_cars/prior_mixed_s21.csv results/kenney_cars/constant_mixed_s21.csv

`iae-eval report` writes one row per image (`runs/*/decomposition.csv`, and `runs/reference/` for the
rows that use no image) with the car it shows. This prints, per file, the mean normal angle, albedo
and reflection L1 over the images of the --cars and over the others (the report's means are the
same per-image means over all of them), so a set that mixes kinds of car can be read per kind.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

COLUMNS = (("normal_mean_deg", "normal (deg)"), ("albedo_l1_srgb255", "albedo L1"),
           ("reflection_l1_srgb255", "reflection L1"))


def split(path: Path, cars: set[str]) -> dict[str, dict[str, float]]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or "car" not in rows[0]:
        raise ValueError(f"{path}: not a report's per-sample CSV (no 'car' column)")
    out = {}
    for name, keep in (("--cars", lambda r: r["car"] in cars), ("others", lambda r: r["car"] not in cars)):
        group = [r for r in rows if keep(r)]
        if group:
            out[name] = {"images": len(group), **{k: sum(float(r[k]) for r in group) / len(group) for k, _ in COLUMNS}}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csvs", nargs="+", type=Path)
    ap.add_argument("--cars", required=True, help="comma-separated car names (the CSV's 'car' column)")
    args = ap.parse_args()
    cars = {c.strip() for c in args.cars.split(",") if c.strip()}
    try:
        tables = [(p, split(p, cars)) for p in args.csvs]
    except (OSError, ValueError) as e:
        sys.exit(str(e))
    print(f"{'file':<48} {'group':<8} {'images':>6} " + " ".join(f"{t:>14}" for _, t in COLUMNS))
    for p, groups in tables:
        for name, g in groups.items():
            print(f"{str(p):<48} {name:<8} {g['images']:>6} " + " ".join(f"{g[k]:>14.2f}" for k, _ in COLUMNS))


if __name__ == "__main__":
    main()
