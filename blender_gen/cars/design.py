"""How the named catalogue was chosen: the most distinct cars of many seeded draws.

`python -m blender_gen.cars.design --out data_manifests/cars.toml` draws `--candidates` cars
per category from the sampler, keeps per category the `counts` cars whose silhouettes differ
most (greedy farthest-point selection on mean silhouette IoU over all categories' models
chosen so far), marks one per category held out, and writes every parameter of every model,
so the catalogue is plain data that does not change when the sampler does.
"""
from __future__ import annotations

import argparse
import tomllib
from pathlib import Path

import numpy as np

from .body import build_car
from .catalogue import CATALOGUE_FILE
from .sampler import draw_spec
from .silhouette import pair_iou, silhouettes
from .spec import CATEGORIES, CarSpec

COUNTS = {"sedan": 5, "hatchback": 5, "station_wagon": 4, "suv": 5, "minivan": 4, "van": 5}
PREFIX = {"sedan": "sedan", "hatchback": "hatch", "station_wagon": "wagon", "suv": "suv", "minivan": "minivan",
          "van": "van"}


def design(seed: int = 2026, candidates: int = 80, counts: dict[str, int] = COUNTS,
           passes: int = 3) -> list[CarSpec]:
    """Per category, the `counts` most mutually distinct of `candidates` draws, each still more
    like its own category's models (mean silhouette IoU) than like any other category's."""
    rng = np.random.default_rng(seed)
    pools: dict[str, list[tuple[CarSpec, dict]]] = {}
    for cat in CATEGORIES:
        pool = []
        while len(pool) < candidates:
            spec = draw_spec(rng, cat, "candidate")
            if spec is not None:
                pool.append((spec, silhouettes(build_car(spec), pixel=0.04)))
        pools[cat] = pool
    # Start from the most typical candidate of each category (highest mean IoU with its pool).
    picked: dict[str, list[int]] = {}
    for cat, pool in pools.items():
        ious = np.array([[pair_iou(a[1], b[1]) for b in pool] for a in pool])
        picked[cat] = [int(np.argmax(ious.mean(axis=1)))]

    def mean_iou(c, members) -> float:
        return float(np.mean([pair_iou(c[1], m[1]) for m in members])) if members else 0.0

    def score(cat: str, i: int, slot: int) -> tuple[float, bool]:
        c = pools[cat][i]
        own = mean_iou(c, [pools[cat][j] for k, j in enumerate(picked[cat]) if k != slot])
        foreign = max(mean_iou(c, [pools[o][j] for j in picked[o]]) for o in CATEGORIES if o != cat)
        return own, foreign < own

    # Fill the slots greedily, then revisit every slot (`passes` times) with all categories chosen:
    # the least like its own category's other models, among the candidates that stay separable.
    for p in range(passes):
        for cat in CATEGORIES:
            slots = range(1, counts[cat]) if p else range(len(picked[cat]), counts[cat])
            for slot in slots:
                if p == 0:
                    picked[cat].append(-1)
                free = [i for i in range(len(pools[cat])) if i not in picked[cat] or picked[cat][slot] == i]
                scored = [(*score(cat, i, slot), i) for i in free]
                ok = [t for t in scored if t[1]] or scored
                picked[cat][slot] = min(ok)[2]
    out = []
    for cat in CATEGORIES:
        for k, i in enumerate(picked[cat]):
            spec = pools[cat][i][0]
            split = "heldout" if k == 1 else "train"  # one per category, not the most typical one
            out.append(CarSpec(**{**spec.__dict__, "name": f"{PREFIX[cat]}_{'abcdefgh'[k]}", "split": split}))
    return out


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


def write_catalogue(specs: list[CarSpec], out: Path, header_from: Path = CATALOGUE_FILE) -> None:
    """Keep the header and [part_materials] of the current file; replace every model."""
    text = Path(header_from).read_text()
    data = tomllib.loads(text)
    lines = ["# The procedural car catalogue: 28 named models of the paper's six categories.",
             "#",
             "# Chosen by `python -m blender_gen.cars.design` (blender_gen/cars/design.py): the most",
             "# distinct of many seeded draws of the sampler's design space (blender_gen/cars/sampler.py,",
             "# proportions within data_manifests/car_ranges.toml), every parameter written out.",
             "# Fields: blender_gen/cars/spec.py (CarSpec). Lengths in metres; positions `*_s` are",
             "# measured from the front bumper backwards.",
             "# split = \"train\": used for the synthetic intrinsics set; \"heldout\": kept out of it",
             "# for the PBR \"real\" images and the decomposition evaluation (unseen cars).",
             ""]
    table = dict(data["part_materials"])
    # (Top level, before any table: inside [part_materials] it was read as a part's row.)
    tinted = data.get("tinted_side_material", table.pop("tinted_side_material", "tinted_glass"))
    lines += ["# Cars with tinted_rear = true use this material for their side windows.",
              f"tinted_side_material = {_toml_value(tinted)}", "",
              "# Which of the 18 part materials each part uses (\"paint\" = the per-sample body paint).",
              "[part_materials]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    lines.append("")
    for s in specs:
        lines.append("[[car]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in s.__dict__.items()]
        lines.append("")
    tmp = Path(out).with_suffix(".tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=CATALOGUE_FILE)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--candidates", type=int, default=80)
    args = ap.parse_args()
    specs = design(args.seed, args.candidates)
    write_catalogue(specs, args.out)
    print(f"{args.out}: {len(specs)} models")


if __name__ == "__main__":
    main()
