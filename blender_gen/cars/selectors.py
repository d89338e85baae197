"""`--cars` selectors: catalogue names, categories, splits and `procedural:random` pools (above
`catalogue`, which loads the named models, and `sampler`, which draws the random ones)."""
from __future__ import annotations

from dataclasses import dataclass

from .catalogue import RANDOM_PREFIX
from .sampler import random_spec
from .spec import CATEGORIES, CarSpec


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
