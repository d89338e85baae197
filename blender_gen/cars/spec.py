"""What a procedural car is: its shape parameters (`CarSpec`), body styles and part names.

Car frame: +X forward, +Y left, +Z up, metres; the footprint is centred on the origin and
the tyres touch z = 0. Positions along the car (`*_s`) are measured from the front bumper
backwards. No bpy and no geometry here: the catalogue, the random sampler and the body
builder share these definitions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

# The paper's six categories; `style` refines them (a sedan is a notchback or a fastback).
CATEGORIES = ("suv", "sedan", "hatchback", "station_wagon", "minivan", "van")
STYLES = {
    "sedan": ("notchback", "fastback"),
    "hatchback": ("hatchback",),
    "station_wagon": ("wagon",),
    "suv": ("suv", "pickup"),  # light trucks: a pickup is an SUV's cab with an open load bed
    "minivan": ("minivan",),
    "van": ("van",),
}
GRILLES = ("wide", "kidney", "trapezoid", "slot", "tall")
HEADLIGHTS = ("round", "rect", "slim", "swept")
TAIL_LIGHTS = ("vertical", "horizontal", "bar", "round")
ARCHES = ("round", "flat", "square")

# Every part a procedural car has; each becomes one Blender object "<model>.<part>".
PARTS = (
    "body", "windshield", "window_side", "window_rear", "pillar_trim", "tyres", "rims",
    "brake_discs", "headlights", "indicators", "tail_lights", "grille", "bumper_front",
    "bumper_rear", "mirrors", "mirror_glass", "licence_plates", "door_handles",
    "underbody", "exhaust", "interior", "roof_rails",
)


@dataclass(frozen=True)
class CarSpec:
    """Shape parameters of one model (metres unless noted)."""

    name: str
    category: str
    split: str  # "train" (intrinsics sets), "heldout" (PBR "real" / evaluation sets) or "random"
    length: float
    width: float
    height: float
    wheelbase: float
    front_overhang: float
    style: str = ""  # "" = the category's first style
    wheel_radius: float = 0.33
    tyre_width: float = 0.22
    clearance: float = 0.16
    nose_height: float = 0.72
    hood_height: float = 0.95
    belt_height: float = 1.0  # at the cowl; `belt_rise` lifts it toward the rear (wedge)
    belt_rise: float = 0.0
    tail_height: float = 0.98
    windshield_s: float = 1.25  # windshield base
    windshield_run: float = 0.75  # horizontal length of the windshield slope (rake)
    roof_end_s: float = 3.15  # roof ends, rear window starts
    cabin_end_s: float = 3.75  # rear window meets the tail
    roof_crown: float = 0.0  # how much the roof's middle rises above its ends
    roof_section: float = 5.0  # superellipse exponent of the greenhouse sections (higher = flatter roof)
    roundness: float = 3.2  # superellipse exponent of the lower body's sections (higher = boxier)
    plan_exponent: float = 7.0  # seen from above: higher = squarer corners
    nose_taper: float = 0.0  # fraction of the half width lost toward the nose
    tumblehome: float = 0.82  # roof width / beltline width
    arch_style: str = "round"
    arch_flare: float = 0.0  # fenders bulge out this far around the wheels
    grille: str = "wide"
    headlight: str = "rect"
    tail_light: str = "horizontal"
    doors: int = 4
    roof_rails: bool = False
    tinted_rear: bool = False

    @property
    def rear_overhang(self) -> float:
        return self.length - self.wheelbase - self.front_overhang

    @property
    def body_style(self) -> str:
        return self.style or STYLES[self.category][0]


def spec_problems(spec: CarSpec) -> list[str]:
    """Why a spec cannot be built (empty if it can); each entry names the fields involved."""
    bad: list[str] = []
    for f in ("length", "width", "height", "wheelbase", "front_overhang", "wheel_radius", "tyre_width",
              "clearance", "nose_height", "hood_height", "belt_height", "tail_height", "windshield_s",
              "windshield_run", "roof_end_s", "cabin_end_s", "roundness", "roof_section", "plan_exponent",
              "tumblehome"):
        v = getattr(spec, f)
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            bad.append(f"{f} must be a positive number, got {v!r}")
    if bad:
        return bad
    if spec.category not in CATEGORIES:
        bad.append(f"category {spec.category!r} is not one of {CATEGORIES}")
        return bad
    if spec.style and spec.style not in STYLES[spec.category]:
        bad.append(f"style {spec.style!r} is not one of {STYLES[spec.category]} for category {spec.category!r}")
    if spec.split not in ("train", "heldout", "random"):
        bad.append(f"split must be 'train' or 'heldout', got {spec.split!r}")
    for f, allowed in (("grille", GRILLES), ("headlight", HEADLIGHTS), ("tail_light", TAIL_LIGHTS),
                       ("arch_style", ARCHES)):
        if getattr(spec, f) not in allowed:
            bad.append(f"{f} {getattr(spec, f)!r} is not one of {allowed}")
    if spec.rear_overhang <= spec.wheel_radius:
        bad.append("wheelbase + front_overhang leave no room for the rear wheels")
    if spec.front_overhang <= spec.wheel_radius:
        bad.append("front_overhang must exceed wheel_radius")
    order = [spec.windshield_s, spec.windshield_s + spec.windshield_run, spec.roof_end_s, spec.cabin_end_s,
             spec.length - 0.02]
    if any(b <= a for a, b in zip(order, order[1:])):
        bad.append("expected windshield_s < windshield_s + windshield_run < roof_end_s < cabin_end_s < length - 0.02, "
                   f"got {[round(v, 3) for v in order]}")
    heights = [spec.clearance + 0.15, spec.nose_height, spec.belt_height + spec.belt_rise + 0.2, spec.height]
    if any(b <= a for a, b in zip(heights, heights[1:])):
        bad.append("expected clearance + 0.15 < nose_height < belt_height + belt_rise + 0.2 < height, "
                   f"got {[round(v, 3) for v in heights]}")
    if spec.hood_height > spec.belt_height + 0.05 or spec.hood_height < spec.nose_height - 0.05:
        bad.append(f"hood_height {spec.hood_height} must lie between nose_height - 0.05 and belt_height + 0.05")
    if not 0.5 <= spec.tumblehome <= 1.0:
        bad.append(f"tumblehome must be in [0.5, 1], got {spec.tumblehome}")
    if not 0.0 <= spec.nose_taper <= 0.2:
        bad.append(f"nose_taper must be in [0, 0.2], got {spec.nose_taper}")
    if not 0.0 <= spec.arch_flare <= 0.08 or not 0.0 <= spec.roof_crown <= 0.15 or not -0.05 <= spec.belt_rise <= 0.15:
        bad.append("expected 0 <= arch_flare <= 0.08, 0 <= roof_crown <= 0.15, -0.05 <= belt_rise <= 0.15")
    if spec.doors not in (2, 3, 4, 5):
        bad.append(f"doors must be 2, 3, 4 or 5, got {spec.doors!r}")
    return bad
