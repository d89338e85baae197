"""Unlimited seeded cars: `random_spec(seed, k)` draws car k of a body style's design space.

Proportions come from real-world ranges per category (`data_manifests/car_ranges.toml`,
with the reference models they span); the shape (hood length and slope, windshield and
rear-window rake, greenhouse height, roof crown, tumblehome, beltline wedge, section and
plan roundness, wheel arches, front and rear designs) from per-style ranges below. A draw
that cannot be built, or whose silhouettes resemble a held-out catalogue model (mean IoU
above `HELDOUT_IOU`), is redrawn from the same random stream, so car k stays a pure
function of (seed, k, categories) and never reproduces a model kept for evaluation.
"""
from __future__ import annotations

import tomllib
from functools import lru_cache
from pathlib import Path

import numpy as np

from .spec import CATEGORIES, STYLES, CarSpec, spec_problems

RANGES_FILE = Path(__file__).resolve().parents[2] / "data_manifests" / "car_ranges.toml"
# Bump when the same (seed, k) would draw another car (part of recipe identities).
SAMPLER_VERSION = 2  # 2: SUVs include pickups
HELDOUT_IOU = 0.92  # a random car this close to a held-out model (mean silhouette IoU) is redrawn
STYLE_RANGES = ("pickup",)  # body styles with ranges of their own (a pickup is longer than an SUV)
DIMENSIONS = ("length", "width", "height", "wheelbase", "front_overhang", "wheel_diameter", "clearance")

# Per style: (low, high) ranges in metres (or unitless), and the discrete choices.
# hood = windshield base from the front bumper; tail = cabin end to the rear bumper;
# rear_run = rear-window length along the car; glass = height above the beltline at the cowl.
_STYLE = {
    "notchback": dict(hood=(1.15, 1.7), ws_run=(0.65, 1.05), tail=(0.7, 1.15), rear_run=(0.45, 0.75),
                      glass=(0.40, 0.50), nose_drop=(0.22, 0.34), hood_drop=(0.03, 0.1), tail_delta=(-0.05, 0.03),
                      roundness=(2.5, 4.2), plan=(4.0, 11.0), arches=("round", "flat"), flare=(0.0, 0.03),
                      grilles=("wide", "kidney", "trapezoid", "slot"), tails=("horizontal", "bar", "vertical", "round"),
                      doors=(2, 4), rails=0.0, tinted=0.1),
    "fastback": dict(hood=(1.3, 1.75), ws_run=(0.8, 1.1), tail=(0.2, 0.45), rear_run=(1.0, 1.5),
                     glass=(0.36, 0.46), nose_drop=(0.22, 0.34), hood_drop=(0.03, 0.1), tail_delta=(-0.04, 0.02),
                     roundness=(2.5, 4.0), plan=(4.0, 10.0), arches=("round", "flat"), flare=(0.0, 0.04),
                     grilles=("wide", "kidney", "trapezoid", "slot"), tails=("horizontal", "bar"),
                     doors=(2, 4), rails=0.0, tinted=0.2),
    "hatchback": dict(hood=(0.9, 1.4), ws_run=(0.6, 1.0), tail=(0.12, 0.3), rear_run=(0.2, 0.8),
                      glass=(0.4, 0.55), nose_drop=(0.2, 0.3), hood_drop=(0.03, 0.08), tail_delta=(-0.02, 0.03),
                      roundness=(2.5, 4.2), plan=(4.0, 10.0), arches=("round", "flat"), flare=(0.0, 0.03),
                      grilles=("wide", "trapezoid", "slot"), tails=("vertical", "horizontal", "bar"),
                      doors=(2, 4), rails=0.1, tinted=0.2),
    "wagon": dict(hood=(1.1, 1.65), ws_run=(0.65, 1.05), tail=(0.1, 0.25), rear_run=(0.12, 0.6),
                  glass=(0.38, 0.52), nose_drop=(0.22, 0.32), hood_drop=(0.03, 0.09), tail_delta=(-0.02, 0.03),
                  roundness=(2.5, 4.2), plan=(4.0, 11.0), arches=("round", "flat"), flare=(0.0, 0.03),
                  grilles=("wide", "kidney", "trapezoid", "slot"), tails=("vertical", "horizontal", "bar"),
                  doors=(4,), rails=0.5, tinted=0.3),
    "suv": dict(hood=(1.05, 1.6), ws_run=(0.5, 0.95), tail=(0.08, 0.22), rear_run=(0.1, 0.8),
                glass=(0.42, 0.58), nose_drop=(0.2, 0.32), hood_drop=(0.03, 0.1), tail_delta=(-0.02, 0.03),
                roundness=(3.0, 5.5), plan=(6.0, 12.0), arches=("round", "flat", "square"), flare=(0.0, 0.05),
                grilles=("tall", "trapezoid", "wide", "kidney"), tails=("vertical", "horizontal", "bar"),
                doors=(4, 5), rails=0.6, tinted=0.7),
    # tail = the load bed behind the cab; rear_run = the cab's near-upright back window
    "pickup": dict(hood=(1.35, 1.8), ws_run=(0.55, 0.85), tail=(1.5, 2.05), rear_run=(0.08, 0.18),
                   glass=(0.42, 0.54), nose_drop=(0.12, 0.26), hood_drop=(0.02, 0.08), tail_delta=(-0.04, 0.02),
                   roundness=(3.5, 6.0), plan=(7.0, 12.0), arches=("square", "flat", "round"), flare=(0.0, 0.05),
                   grilles=("tall", "wide", "trapezoid"), tails=("vertical",), doors=(2, 4), rails=0.0, tinted=0.3),
    "minivan": dict(hood=(0.7, 1.25), ws_run=(0.8, 1.45), tail=(0.06, 0.18), rear_run=(0.12, 0.35),
                    glass=(0.48, 0.65), nose_drop=(0.25, 0.38), hood_drop=(0.08, 0.18), tail_delta=(-0.02, 0.03),
                    roundness=(3.0, 5.0), plan=(6.0, 11.0), arches=("round", "flat"), flare=(0.0, 0.02),
                    grilles=("wide", "trapezoid", "slot"), tails=("vertical", "horizontal"),
                    doors=(5,), rails=0.3, tinted=0.6),
    "van": dict(hood=(0.4, 1.0), ws_run=(0.25, 0.8), tail=(0.03, 0.08), rear_run=(0.03, 0.1),
                glass=(0.55, 0.9), nose_drop=(0.2, 0.35), hood_drop=(0.05, 0.15), tail_delta=(-0.02, 0.02),
                roundness=(3.5, 7.0), plan=(8.0, 14.0), arches=("square", "flat", "round"), flare=(0.0, 0.03),
                grilles=("tall", "wide", "trapezoid"), tails=("vertical",),
                doors=(3, 4), rails=0.0, tinted=0.5),
}
_CROWN = {"van": (0.0, 0.04)}
_TUMBLEHOME = {"van": (0.88, 0.97), "minivan": (0.84, 0.92), "suv": (0.8, 0.9)}
_HEADLIGHTS = ("round", "rect", "slim", "swept")


@lru_cache(maxsize=1)
def load_ranges(path: Path = RANGES_FILE) -> dict[str, dict]:
    """Category (and the styles of STYLE_RANGES) -> {dimension: (low, high), "references": [...]};
    errors name the file."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the car ranges: {exc}") from exc
    out = {}
    for cat in CATEGORIES + STYLE_RANGES:
        row = data.get(cat)
        if not isinstance(row, dict):
            raise ValueError(f"{path}: no [{cat}] table")
        out[cat] = {"references": list(row.get("references", []))}
        for d in DIMENSIONS:
            v = row.get(d)
            if not (isinstance(v, list) and len(v) == 2 and 0 < v[0] <= v[1]):
                raise ValueError(f"{path}: [{cat}] {d} must be [low, high] in metres, got {v!r}")
            out[cat][d] = (float(v[0]), float(v[1]))
    return out


def ranges_for(category: str, style: str) -> dict:
    """The real-world ranges a car of this category and body style is drawn from."""
    ranges = load_ranges()
    return ranges[style] if style in STYLE_RANGES else ranges[category]


def draw_spec(rng: np.random.Generator, category: str, name: str, split: str = "random") -> CarSpec | None:
    """One draw of the design space of `category` (None if the draw cannot be built)."""
    style = STYLES[category][int(rng.integers(len(STYLES[category])))]
    r = ranges_for(category, style)
    p = _STYLE[style]

    def u(lo_hi) -> float:
        return float(rng.uniform(*lo_hi))

    # Bumpers and plates reach 5 cm beyond the body's ends: the drawn length is bumper to bumper.
    length, width, height = u(r["length"]) - 0.05, u(r["width"]), u(r["height"])
    wheelbase, front_overhang = u(r["wheelbase"]), u(r["front_overhang"])
    diameter, clearance = u(r["wheel_diameter"]), u(r["clearance"])
    glass, belt_rise = u(p["glass"]), u((0.0, 0.07 if style not in ("van", "minivan") else 0.03))
    belt = height - glass
    hood_s = min(u(p["hood"]), front_overhang + 0.75 * wheelbase)
    cabin_end = length - u(p["tail"])
    roof_end = cabin_end - u(p["rear_run"])
    spec = CarSpec(
        name=name, category=category, split=split, style=style,
        length=round(length, 3), width=round(width, 3), height=round(height, 3),
        wheelbase=round(wheelbase, 3), front_overhang=round(front_overhang, 3),
        wheel_radius=round(0.5 * diameter, 3), tyre_width=round(0.19 + 0.4 * (diameter - 0.58), 3),
        clearance=round(clearance, 3),
        nose_height=round(max(belt - u(p["nose_drop"]), clearance + 0.4), 3),
        hood_height=round(belt - u(p["hood_drop"]), 3),
        belt_height=round(belt, 3), belt_rise=round(belt_rise, 3),
        tail_height=round(belt + belt_rise + u(p["tail_delta"]), 3),
        windshield_s=round(hood_s, 3), windshield_run=round(u(p["ws_run"]), 3),
        roof_end_s=round(roof_end, 3), cabin_end_s=round(cabin_end, 3),
        roof_crown=round(u(_CROWN.get(style, (0.0, 0.06))), 3), roof_section=round(u((2.5, 9.0)), 2),
        roundness=round(u(p["roundness"]), 2), plan_exponent=round(u(p["plan"]), 2),
        nose_taper=round(u((0.0, 0.12)), 3), tumblehome=round(u(_TUMBLEHOME.get(style, (0.66, 0.88))), 3),
        arch_style=p["arches"][int(rng.integers(len(p["arches"])))], arch_flare=round(u(p["flare"]), 3),
        grille=p["grilles"][int(rng.integers(len(p["grilles"])))],
        headlight=_HEADLIGHTS[int(rng.integers(len(_HEADLIGHTS)))],
        tail_light=p["tails"][int(rng.integers(len(p["tails"])))],
        doors=int(p["doors"][int(rng.integers(len(p["doors"])))]),
        roof_rails=bool(rng.random() < p["rails"]), tinted_rear=bool(rng.random() < p["tinted"]),
    )
    return None if spec_problems(spec) else spec


@lru_cache(maxsize=1)
def _heldout_silhouettes() -> tuple:
    from .body import build_car
    from .catalogue import load_catalogue
    from .silhouette import silhouettes

    return tuple((s.name, silhouettes(build_car(s), pixel=0.04)) for s in load_catalogue().values()
                 if s.split == "heldout")


def resembles_heldout(spec: CarSpec) -> tuple[str, float] | None:
    """The held-out model a spec's silhouettes resemble (mean IoU > HELDOUT_IOU), if any."""
    from .body import build_car
    from .silhouette import pair_iou, silhouettes

    mine = silhouettes(build_car(spec), pixel=0.04)
    best = max(((name, pair_iou(mine, sil)) for name, sil in _heldout_silhouettes()), key=lambda t: t[1])
    return best if best[1] > HELDOUT_IOU else None


@lru_cache(maxsize=64)
def random_spec(seed: int, k: int, categories: tuple[str, ...] = CATEGORIES) -> CarSpec:
    """Car k of the random cars of `seed` (categories drawn uniformly from `categories`)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(k), 0x0CA7]))
    category = categories[int(rng.integers(len(categories)))]
    tag = "" if tuple(categories) == CATEGORIES else "_" + "_".join(categories)
    name = f"random{tag}_s{seed}_{k:06d}"
    for _ in range(200):
        spec = draw_spec(rng, category, name)
        if spec is not None and resembles_heldout(spec) is None:
            return spec
    raise RuntimeError(f"no buildable {category} car in 200 draws for seed {seed}, car {k}: check {RANGES_FILE}")
