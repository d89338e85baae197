"""The named catalogue (`data_manifests/cars.toml`) and the `--cars` selectors.

Selectors: `procedural` (every named model), `procedural:train`, `procedural:heldout`, a
category, model names, and `procedural:random[:CATEGORY][@SEED]`: a new seeded car for
every block of views (see `RandomCars`). Several join with commas: `sedan,van_b`.
"""
from __future__ import annotations

import tomllib
from dataclasses import fields
from pathlib import Path

from .spec import PARTS, CarSpec, spec_problems

CATALOGUE_FILE = Path(__file__).resolve().parents[2] / "data_manifests" / "cars.toml"
RANDOM_PREFIX = "procedural:random"


def load_catalogue(path: Path = CATALOGUE_FILE) -> dict[str, CarSpec]:
    """Read `cars.toml`; errors name the file, the model and the field."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the car catalogue: {exc}") from exc
    defaults = data.get("defaults", {})
    known = {f.name for f in fields(CarSpec)}
    out: dict[str, CarSpec] = {}
    for i, row in enumerate(data.get("car", [])):
        row = {**defaults.get(row.get("category", ""), {}), **row}
        unknown = set(row) - known
        if unknown:
            raise ValueError(f"{path}: car #{i} ({row.get('name', '?')}): unknown field(s) {sorted(unknown)}")
        try:
            spec = CarSpec(**row)
        except TypeError as exc:
            raise ValueError(f"{path}: car #{i} ({row.get('name', '?')}): {exc}") from exc
        problems = spec_problems(spec)
        if spec.split == "random":
            problems.append("split 'random' is reserved for generated cars")
        if problems:
            raise ValueError(f"{path}: car {spec.name!r}: {'; '.join(problems)}")
        if spec.name in out:
            raise ValueError(f"{path}: car {spec.name!r} is defined twice")
        out[spec.name] = spec
    if not out:
        raise ValueError(f"{path}: no [[car]] entries")
    return out


def load_part_materials(path: Path = CATALOGUE_FILE) -> tuple[dict[str, str], str]:
    """Part -> material name ("paint" for the body paint), and the tinted side-glass material."""
    data = tomllib.loads(Path(path).read_text())
    table = data.get("part_materials")
    if not isinstance(table, dict):
        raise ValueError(f"{path}: missing [part_materials] table")
    missing = [p for p in PARTS if p not in table]
    if missing:
        raise ValueError(f"{path}: [part_materials] has no entry for part(s) {missing}")
    return dict(table), str(data.get("tinted_side_material", table["window_side"]))
