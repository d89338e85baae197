"""The material table of the paper: 18 part materials and 15 body paints (data in TOML)."""
from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .conversions import srgb_to_linear

MATERIALS_FILE = Path(__file__).resolve().parent.parent / "data_manifests" / "materials.toml"
N_PART_MATERIALS = 18
N_PAINTS = 15
BODY_MATERIAL_ID = N_PART_MATERIALS + 1  # id of the body paint in the `material` layer
_HEX = re.compile(r"^#[0-9a-fA-F]{6}$")


@dataclass(frozen=True)
class Material:
    """One row of the table. `albedo` is linear RGB; the rest feeds the Cycles PBR set."""

    id: int
    name: str
    albedo: tuple[float, float, float]
    gloss: float
    metallic: float = 0.0
    roughness: float = 0.5
    transmission: float = 0.0
    ior: float = 1.45
    emission: float = 0.0
    emission_color: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class MaterialTable:
    parts: dict[str, Material]
    paints: dict[str, Material]


def _colour(path: Path, where: str, value: object) -> tuple[float, float, float]:
    if not isinstance(value, str) or not _HEX.match(value):
        raise ValueError(f"{path}: {where}: expected an sRGB colour like '#a1b2c3', got {value!r}")
    rgb = np.array([int(value[i:i + 2], 16) for i in (1, 3, 5)], dtype=np.float64) / 255.0
    return tuple(float(v) for v in srgb_to_linear(rgb))


def _row(path: Path, kind: str, index: int, row: dict, mat_id: int) -> Material:
    where = f"[[{kind}]] #{index} ({row.get('name', '?')})"
    allowed = {"name", "color", "gloss", "metallic", "roughness", "transmission", "ior", "emission", "emission_color"}
    unknown = set(row) - allowed
    if unknown:
        raise ValueError(f"{path}: {where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    for key in ("name", "color", "gloss"):
        if key not in row:
            raise ValueError(f"{path}: {where}: missing field {key!r}")
    for key in ("gloss", "metallic", "roughness", "transmission"):
        if key in row and not 0.0 <= float(row[key]) <= 1.0:
            raise ValueError(f"{path}: {where}: {key} must be in [0, 1], got {row[key]!r}")
    return Material(
        id=mat_id, name=str(row["name"]), albedo=_colour(path, where + ".color", row["color"]),
        gloss=float(row["gloss"]), metallic=float(row.get("metallic", 0.0)),
        roughness=float(row.get("roughness", 0.5)), transmission=float(row.get("transmission", 0.0)),
        ior=float(row.get("ior", 1.45)), emission=float(row.get("emission", 0.0)),
        emission_color=_colour(path, where + ".emission_color", row.get("emission_color", "#ffffff")),
    )


@lru_cache(maxsize=4)
def load_materials(path: Path = MATERIALS_FILE) -> MaterialTable:
    """Read and validate the table: exactly 18 part materials and 15 paints, unique names."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the material table: {exc}") from exc
    parts = [_row(path, "part", i, r, i + 1) for i, r in enumerate(data.get("part", []))]
    paints = [_row(path, "paint", i, r, BODY_MATERIAL_ID) for i, r in enumerate(data.get("paint", []))]
    if len(parts) != N_PART_MATERIALS or len(paints) != N_PAINTS:
        raise ValueError(f"{path}: expected {N_PART_MATERIALS} [[part]] and {N_PAINTS} [[paint]] rows, "
                         f"got {len(parts)} and {len(paints)}")
    names = [m.name for m in parts + paints]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes or "paint" in names:
        raise ValueError(f"{path}: material names must be unique and not 'paint': {dupes or ['paint']}")
    return MaterialTable({m.name: m for m in parts}, {m.name: m for m in paints})
