"""`iae-gen cars`: every catalogue model in one fixed view, on one PNG (imports bpy)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .camera import CameraPose, look_at
from .conversions import linear_to_srgb
from .dataset import save_png
from .recipe import Recipe
from .render import SampleRenderer

LIGHT = np.array([0.35, 0.55, 0.75])  # camera space, for a simple preview shading


def shaded(layers: dict[str, np.ndarray]) -> np.ndarray:
    """A quick picture from the intrinsic layers: albedo under one light plus reflections."""
    n = layers["normal"]
    lam = np.clip(n @ (LIGHT / np.linalg.norm(LIGHT)), 0.0, 1.0)[..., None]
    rgb = layers["albedo"] * (0.25 + 0.75 * lam) + 0.35 * layers["reflection"]
    bg = np.array([0.82, 0.84, 0.86])
    a = layers["mask"]
    return ((linear_to_srgb(rgb) * a + bg * (1 - a)) * 255 + 0.5).astype(np.uint8)


def contact_sheet(out: Path, cars: tuple[str, ...] = ("procedural",), car_rules: str | None = None,
                  size: tuple[int, int] = (384, 192), columns: int = 4, paint: str = "royal_blue",
                  count: int = 24, seed: int = 0, progress: bool = True) -> Path:
    """One tile per model; a `procedural:random` selector contributes cars 0..count-1 of `seed`."""
    from tqdm import tqdm

    from .cars import RandomCars

    w, h = size
    r = SampleRenderer(Recipe(kind="intrinsics", seed=seed, width=w, height=h, cars=cars, car_rules=car_rules,
                              sky_variants=1), threads=0)
    specs = []
    for spec in r.car_specs:
        specs += [spec.car(seed, k) for k in range(count)] if isinstance(spec, RandomCars) else [spec]
    tiles = []
    try:
        for spec in tqdm(specs, desc="cars", unit="car", disable=not progress):
            car = r.car(spec)
            r.show(car)
            lo, hi = car.points.min(axis=0), car.points.max(axis=0)
            centre = 0.5 * (lo + hi)
            length = hi[0] - lo[0]
            az = math.radians(35.0)  # front three-quarter view from the car's left
            loc = centre + np.array([math.cos(az), math.sin(az), 0.0]) * 1.55 * length + np.array([0, 0, 1.2])
            pose = CameraPose(tuple(loc), tuple(map(tuple, look_at(loc, centre))), tuple(centre), 35.0, 36.0)
            r.place({"car": car, "paint": r.table.paints[paint], "rotation": 0.0, "pose": pose})
            img = Image.fromarray(shaded(r.render_current()))
            style = f", {spec.body_style}" if hasattr(spec, "body_style") else ""
            ImageDraw.Draw(img).text((6, 4), f"{spec.name} ({spec.category}{style}, {spec.split})", fill=(20, 20, 20))
            tiles.append(img)
    finally:
        r.close()
    rows = math.ceil(len(tiles) / columns)
    sheet = Image.new("RGB", (columns * w, rows * h), (255, 255, 255))
    for i, t in enumerate(tiles):
        sheet.paste(t, ((i % columns) * w, (i // columns) * h))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "contact_sheet.png"
    save_png(path, sheet)
    return path
