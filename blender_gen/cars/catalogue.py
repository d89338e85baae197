"""The named catalogue (`data_manifests/cars.toml`) and the `--cars` selectors.

Selectors: `procedural` (every named model), `procedural:train`, `procedural:heldout`, a
category, model names, and `procedural:random[:CATEGORY][@SEED]`: a new seeded car for
every block of views (see `RandomCars`). Several join with commas: `sedan,van_b`.
"""
from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

from .spec import CATEGORIES, PARTS, CarSpec, spec_problems

CATALOGUE_FILE = Path(__file__).resolve().parents[2] / "data_manifests" / "cars.toml"
RANDOM_PREFIX = "procedural:random"


def catalogue_digest(path: Path = CATALOGUE_FILE) -> str:
    """Content hash of what procedural cars are made from (the catalogue, the sampler's ranges,
    the geometry and sampler versions), for recipe identities: a set never mixes two versions."""
    from .body import GEOMETRY_VERSION
    from .sampler import RANGES_FILE, SAMPLER_VERSION

    h = hashlib.sha256(Path(path).read_bytes())
    h.update(Path(RANGES_FILE).read_bytes())
    h.update(f"geometry:{GEOMETRY_VERSION} sampler:{SAMPLER_VERSION}".encode())
    return h.hexdigest()[:16]


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


@dataclass(frozen=True)
class RandomCars:
    """`procedural:random[:CATEGORY][@SEED]`: car k is `random_spec(seed, k)`, a pure function of
    the seed and k, redrawn while it resembles a held-out model (see `sampler`).

    A dataset draws car k = its block index, so every block of `views_per_car` views shows a
    new car. The seed is the recipe's unless `@SEED` fixes it: two sets with one car seed and
    different recipe seeds show the same cars in other poses (the Table-3 rule).
    """

    categories: tuple[str, ...] = CATEGORIES
    seed: int | None = None
    name: str = RANDOM_PREFIX
    category: str = "random"
    split: str = "random"
    tinted_rear: bool = False

    def car(self, recipe_seed: int, k: int) -> CarSpec:
        from .sampler import random_spec

        return random_spec(recipe_seed if self.seed is None else self.seed, k, self.categories)


def _random_selector(token: str) -> RandomCars:
    body, _, seed = token.partition("@")
    cat = body[len(RANDOM_PREFIX) + 1:]
    if cat and cat not in CATEGORIES:
        raise ValueError(f"--cars: {token!r}: unknown category {cat!r}; expected one of {CATEGORIES}")
    if seed and not seed.lstrip("-").isdigit():
        raise ValueError(f"--cars: {token!r}: the car seed after '@' must be an integer, got {seed!r}")
    return RandomCars((cat,) if cat else CATEGORIES, int(seed) if seed else None, name=token)


def select_cars(catalogue: dict[str, CarSpec], selector: str) -> list:
    """Resolve selectors to catalogue models (and `RandomCars` pools), in order, no repeats."""
    chosen: list = []
    for token in [t.strip() for t in selector.split(",") if t.strip()]:
        if token.split("@")[0] == RANDOM_PREFIX or token.startswith(RANDOM_PREFIX + ":"):
            hits = [_random_selector(token)]
        elif token == "procedural":
            hits = list(catalogue.values())
        elif token.startswith("procedural:"):
            split = token.split(":", 1)[1]
            if split not in ("train", "heldout"):
                raise ValueError(f"--cars: unknown selector {token!r}; expected procedural, procedural:train, "
                                 "procedural:heldout or procedural:random[:CATEGORY]")
            hits = [c for c in catalogue.values() if c.split == split]
        elif token in CATEGORIES:
            hits = [c for c in catalogue.values() if c.category == token]
        elif token in catalogue:
            hits = [catalogue[token]]
        else:
            raise ValueError(
                f"--cars: {token!r} is neither a catalogue model, a category {CATEGORIES}, "
                "'procedural[:train|:heldout]', 'procedural:random[:CATEGORY][@SEED]' nor an existing model file"
            )
        chosen.extend(c for c in hits if c not in chosen)
    if not chosen:
        raise ValueError(f"--cars: {selector!r} selects no car")
    return chosen
