"""The procedural car catalogue: shape parameters (data) -> named part meshes (NumPy).

Car frame: +X forward, +Y left, +Z up, metres; the footprint is centred on the origin
and the tyres touch z = 0. Shapes are lofts of superellipse sections along the car's
length (lower body, greenhouse) plus rounded boxes and lathed wheels for the small parts.
Windows are the faces of the greenhouse chosen by position and facing, so the glass
follows the body's curvature exactly.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from .geometry import Mesh, lathe, loft, smooth_profile, superellipse, superellipsoid

CATALOGUE_FILE = Path(__file__).resolve().parent.parent / "data_manifests" / "cars.toml"
CATEGORIES = ("suv", "sedan", "hatchback", "station_wagon", "minivan", "van")

# Every part a procedural car has; each becomes one Blender object "<model>.<part>".
PARTS = (
    "body", "windshield", "window_side", "window_rear", "pillar_trim", "tyres", "rims",
    "brake_discs", "headlights", "indicators", "tail_lights", "grille", "bumper_front",
    "bumper_rear", "mirrors", "mirror_glass", "licence_plates", "door_handles",
    "underbody", "exhaust", "interior", "roof_rails",
)


@dataclass(frozen=True)
class CarSpec:
    """Shape parameters of one catalogue model (metres unless noted).

    Positions along the car (`*_s`) are measured from the front bumper backwards.
    """

    name: str
    category: str
    split: str  # "train" (intrinsics set) or "heldout" (PBR / evaluation set)
    length: float
    width: float
    height: float
    wheelbase: float
    front_overhang: float
    wheel_radius: float = 0.33
    tyre_width: float = 0.22
    clearance: float = 0.16
    nose_height: float = 0.72
    hood_height: float = 0.95
    belt_height: float = 1.0
    tail_height: float = 0.98
    windshield_s: float = 1.25  # windshield base
    windshield_run: float = 0.75  # horizontal length of the windshield slope
    roof_end_s: float = 3.15  # roof ends, rear window starts
    cabin_end_s: float = 3.75  # rear window meets the tail
    roundness: float = 3.2  # superellipse exponent of body sections (higher = boxier)
    tumblehome: float = 0.82  # roof width / beltline width
    doors: int = 4
    roof_rails: bool = False
    tinted_rear: bool = False

    @property
    def rear_overhang(self) -> float:
        return self.length - self.wheelbase - self.front_overhang


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
        if spec.category not in CATEGORIES:
            raise ValueError(f"{path}: car {spec.name!r}: category {spec.category!r} is not one of {CATEGORIES}")
        if spec.split not in ("train", "heldout"):
            raise ValueError(f"{path}: car {spec.name!r}: split must be 'train' or 'heldout', got {spec.split!r}")
        if spec.rear_overhang <= spec.wheel_radius:
            raise ValueError(f"{path}: car {spec.name!r}: wheelbase + front_overhang leave no room for the rear wheels")
        order = [spec.windshield_s, spec.windshield_s + spec.windshield_run, spec.roof_end_s, spec.cabin_end_s, spec.length - 0.1]
        if any(b <= a for a, b in zip(order, order[1:])):
            raise ValueError(
                f"{path}: car {spec.name!r}: expected windshield_s < windshield_s + windshield_run < roof_end_s "
                f"< cabin_end_s < length - 0.1, got {order}"
            )
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


def select_cars(catalogue: dict[str, CarSpec], selector: str) -> list[CarSpec]:
    """Resolve `procedural`, `procedural:train`, `procedural:heldout`, a category or names.

    Several selectors can be joined with commas: `sedan,van_b`.
    """
    chosen: list[CarSpec] = []
    for token in [t.strip() for t in selector.split(",") if t.strip()]:
        if token == "procedural":
            hits = list(catalogue.values())
        elif token.startswith("procedural:"):
            split = token.split(":", 1)[1]
            hits = [c for c in catalogue.values() if c.split == split]
            if split not in ("train", "heldout"):
                raise ValueError(f"--cars: unknown split {split!r}; expected procedural:train or procedural:heldout")
        elif token in CATEGORIES:
            hits = [c for c in catalogue.values() if c.category == token]
        elif token in catalogue:
            hits = [catalogue[token]]
        else:
            raise ValueError(
                f"--cars: {token!r} is neither a catalogue model, a category {CATEGORIES}, "
                "'procedural[:train|:heldout]' nor an existing model file"
            )
        chosen.extend(c for c in hits if c not in chosen)
    if not chosen:
        raise ValueError(f"--cars: {selector!r} selects no car")
    return chosen


# --------------------------------------------------------------------------- shapes

def _plan_half_width(spec: CarSpec, s: np.ndarray, p: float = 7.0) -> np.ndarray:
    """Half width seen from above: a superellipse plan with rounded corners."""
    t = np.clip(np.abs(2.0 * s / spec.length - 1.0), 0.0, 1.0)
    return 0.5 * spec.width * np.clip(1.0 - t**p, 0.0, 1.0) ** (1.0 / p)


def _x(spec: CarSpec, s):
    """Position along the car (from the front) -> X in the car frame."""
    return 0.5 * spec.length - np.asarray(s)


def _wheel_centres_s(spec: CarSpec) -> tuple[float, float]:
    return spec.front_overhang, spec.front_overhang + spec.wheelbase


def _lower_profiles(spec: CarSpec, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Top (hood, beltline, trunk) and bottom (sills, wheel arches) of the lower body."""
    L = spec.length
    top = smooth_profile(s, [
        (0.0, spec.nose_height - 0.08), (0.12, spec.nose_height),
        (spec.windshield_s, spec.hood_height), (spec.windshield_s + 0.3, spec.belt_height),
        (spec.cabin_end_s, spec.belt_height), (min(spec.cabin_end_s + 0.15, L - 0.1), spec.tail_height),
        (L - 0.1, spec.tail_height), (L, spec.tail_height - 0.12),
    ], passes=2, width=2)
    bottom = smooth_profile(s, [
        (0.0, spec.clearance + 0.22), (0.35, spec.clearance + 0.02), (L - 0.35, spec.clearance + 0.02),
        (L, spec.clearance + 0.25),
    ], passes=1, width=2)
    arch_r = spec.wheel_radius + 0.06
    for sc in _wheel_centres_s(spec):
        d = np.abs(s - sc)
        inside = d < arch_r
        arch = spec.wheel_radius + np.sqrt(np.clip(arch_r**2 - d**2, 0.0, None))
        bottom = np.where(inside, np.maximum(bottom, arch), bottom)
    return top, np.minimum(bottom, top - 0.1)


def _roof_profile(spec: CarSpec, s: np.ndarray) -> np.ndarray:
    ws_top = spec.windshield_s + spec.windshield_run
    return smooth_profile(s, [
        (spec.windshield_s, spec.belt_height - 0.04), (ws_top, spec.height),
        (spec.roof_end_s, spec.height), (spec.cabin_end_s, spec.belt_height - 0.04),
    ], passes=2, width=2)


def _orient_outward(mesh: Mesh, centre) -> Mesh:
    """Flip the winding if most faces point toward `centre` (closed, roughly convex shapes)."""
    n = mesh.face_normals()
    d = mesh.face_centroids() - np.asarray(centre)
    return mesh.flipped() if np.sum(np.einsum("ij,ij->i", n, d)) < 0 else mesh


def _lower_body(spec: CarSpec, sections: int = 90, ring: int = 36) -> Mesh:
    s = np.linspace(0.0, spec.length, sections)
    top, bottom = _lower_profiles(spec, s)
    w = _plan_half_width(spec, s)
    prof = superellipse(ring, spec.roundness)
    zc, hz = 0.5 * (top + bottom), 0.5 * (top - bottom)
    rings = np.stack([
        np.repeat(_x(spec, s)[:, None], ring, axis=1),
        w[:, None] * prof[None, :, 0],
        zc[:, None] + hz[:, None] * prof[None, :, 1],
    ], axis=2)
    return _orient_outward(loft(rings), (0.0, 0.0, float(np.mean(zc))))


def _greenhouse(spec: CarSpec, sections: int = 70, ring: int = 40) -> tuple[Mesh, np.ndarray]:
    """The cabin above the beltline, and the part name of each of its faces."""
    s = np.linspace(spec.windshield_s, spec.cabin_end_s, sections)
    roof = _roof_profile(spec, s)
    base = spec.belt_height - 0.06
    w_belt = _plan_half_width(spec, s) - 0.035
    prof = superellipse(ring, 5.0)
    v = 0.5 * (prof[:, 1] + 1.0)  # 0 at the bottom of the section, 1 at the roof
    half = w_belt[:, None] * (1.0 - (1.0 - spec.tumblehome) * v[None, :])
    rings = np.stack([
        np.repeat(_x(spec, s)[:, None], ring, axis=1),
        half * prof[None, :, 0],
        base + (roof - base)[:, None] * v[None, :],
    ], axis=2)
    mesh = _orient_outward(loft(rings), (0.0, 0.0, 0.5 * (base + spec.height)))
    return mesh, _classify_greenhouse(spec, mesh)


def _classify_greenhouse(spec: CarSpec, mesh: Mesh) -> np.ndarray:
    """Windshield, rear window, side windows, pillars and roof by position and facing."""
    n = mesh.face_normals()
    c = mesh.face_centroids()
    s = 0.5 * spec.length - c[:, 0]
    z = c[:, 2]
    names = np.full(len(c), "body", dtype=object)
    lo, hi = spec.belt_height + 0.03, spec.height - 0.05
    glass_band = (z > lo) & (z < hi)

    ws_top = spec.windshield_s + spec.windshield_run
    ws_half = 0.5 * spec.width * spec.tumblehome * 0.8
    names[glass_band & (n[:, 0] > 0.3) & (np.abs(c[:, 1]) < ws_half) & (s < ws_top + 0.05)] = "windshield"
    rear_half = 0.5 * spec.width * spec.tumblehome * 0.78
    names[glass_band & (n[:, 0] < -0.25) & (np.abs(c[:, 1]) < rear_half) & (s > spec.roof_end_s - 0.05)] = "window_rear"

    # Side glass: between the A pillar (following the windshield slope) and the C/D pillar.
    roof_s = np.linspace(spec.windshield_s, spec.cabin_end_s, 400)
    roof_z = _roof_profile(spec, roof_s)
    peak = int(np.argmax(roof_z))

    def front_edge(zq):
        return np.interp(zq, roof_z[: peak + 1], roof_s[: peak + 1])

    def rear_edge(zq):
        return np.interp(zq, roof_z[peak:][::-1], roof_s[peak:][::-1])

    side = glass_band & (np.abs(n[:, 1]) > 0.55)
    inside = side & (s > front_edge(z) + 0.12) & (s < rear_edge(z) - 0.14) & (z < hi - 0.03)
    names[inside] = "window_side"
    # Pillars between the side windows (B pillar, and C pillar on long cabins): black trim.
    cabin = spec.cabin_end_s - spec.windshield_s
    n_windows = {2: 1, 4: 2}.get(spec.doors, 3)
    if cabin > 3.2:
        n_windows += 1
    for k in range(1, n_windows):
        sb = spec.windshield_s + spec.windshield_run * 0.6 + k * (cabin - spec.windshield_run * 0.6) / n_windows
        names[inside & (np.abs(s - sb) < 0.05)] = "pillar_trim"
    return names


def _wheels(spec: CarSpec) -> dict[str, Mesh]:
    r, tw = spec.wheel_radius, spec.tyre_width
    rim_r = 0.62 * r
    tyre_profile = np.array([
        (rim_r, -0.5 * tw), (r - 0.04, -0.5 * tw), (r - 0.01, -0.45 * tw), (r, -0.3 * tw), (r, 0.3 * tw),
        (r - 0.01, 0.45 * tw), (r - 0.04, 0.5 * tw), (rim_r, 0.5 * tw),
    ])
    rim_profile = np.array([
        (1e-4, 0.42 * tw), (0.25 * rim_r, 0.44 * tw), (0.7 * rim_r, 0.40 * tw), (rim_r, 0.5 * tw),
        (rim_r, -0.3 * tw), (1e-4, -0.3 * tw),
    ])
    disc_profile = np.array([(1e-4, 0.2 * tw), (0.85 * rim_r, 0.2 * tw), (0.85 * rim_r, 0.1 * tw), (1e-4, 0.1 * tw)])
    parts = {"tyres": Mesh(), "rims": Mesh(), "brake_discs": Mesh()}
    y = 0.5 * spec.width - 0.5 * tw - 0.03
    for sc in _wheel_centres_s(spec):
        for side in (1.0, -1.0):
            centre = (float(_x(spec, sc)), side * y, r)
            # Profiles run from the inner to the outer side; +axial points outward on each side.
            parts["tyres"].extend(_orient_outward(lathe(tyre_profile, 40, centre, side), centre))
            parts["rims"].extend(lathe(rim_profile, 32, centre, side))
            parts["brake_discs"].extend(lathe(disc_profile, 24, centre, side))
    for k in ("rims", "brake_discs"):
        parts[k] = _fix_lathe_winding(parts[k], spec)
    return parts


def _fix_lathe_winding(mesh: Mesh, spec: CarSpec) -> Mesh:
    """Wheel discs are open surfaces: make their normals point away from the car's centre plane."""
    n = mesh.face_normals()
    c = mesh.face_centroids()
    return mesh.flipped(n[:, 1] * np.sign(c[:, 1]) < 0)


def _body_surface_y(spec: CarSpec, s: float, z: float) -> float:
    """|Y| of the lower body's side surface at (s, z)."""
    top, bottom = _lower_profiles(spec, np.array([s]))
    w = float(_plan_half_width(spec, np.array([s]))[0])
    zc, hz = 0.5 * (top[0] + bottom[0]), 0.5 * (top[0] - bottom[0])
    t = np.clip(abs(z - zc) / max(hz, 1e-6), 0.0, 1.0)
    return w * (1.0 - t**spec.roundness) ** (1.0 / spec.roundness)


def _body_front_s(spec: CarSpec, y: float) -> float:
    """Distance from the front bumper at which the plan reaches |Y| = y."""
    s = np.linspace(0.0, 0.5 * spec.length, 400)
    return float(np.interp(abs(y), _plan_half_width(spec, s), s))


def _small_parts(spec: CarSpec) -> dict[str, Mesh]:
    W, L = spec.width, spec.length
    parts: dict[str, Mesh] = {k: Mesh() for k in (
        "headlights", "indicators", "tail_lights", "grille", "bumper_front", "bumper_rear", "mirrors",
        "mirror_glass", "licence_plates", "door_handles", "underbody", "exhaust", "interior", "roof_rails")}
    front_x, rear_x = 0.5 * L, -0.5 * L
    for side in (1.0, -1.0):
        y = side * (0.5 * W - 0.3)
        s = _body_front_s(spec, abs(y) + 0.05)
        parts["headlights"].extend(superellipsoid(
            (front_x - s - 0.02, y, spec.nose_height - 0.1), (0.22, 0.34, 0.12), 3.0, 10))
        yi = side * (0.5 * W - 0.1)
        s = _body_front_s(spec, abs(yi) + 0.02)
        parts["indicators"].extend(superellipsoid(
            (front_x - s - 0.01, yi, spec.nose_height - 0.14), (0.12, 0.1, 0.07), 3.0, 8))
        yt = side * (0.5 * W - 0.24)
        s = _body_front_s(spec, abs(yt) + 0.05)
        parts["tail_lights"].extend(superellipsoid(
            (rear_x + s + 0.02, yt, spec.tail_height - 0.12), (0.2, 0.3, 0.14), 3.0, 10))
        # Door mirror on the door just behind the A pillar.
        sm = spec.windshield_s + 0.15
        ym = side * (float(_plan_half_width(spec, np.array([sm]))[0]) + 0.05)  # just outside the door skin
        zm = spec.belt_height + 0.03
        parts["mirrors"].extend(superellipsoid((float(_x(spec, sm)), ym, zm), (0.12, 0.2, 0.13), 3.0, 8))
        parts["mirror_glass"].extend(superellipsoid((float(_x(spec, sm)) - 0.06, ym, zm), (0.015, 0.16, 0.1), 4.0, 6))
        # Door handles, one per door on this side.
        zh = spec.belt_height - 0.12
        n_doors = 1 if spec.doors == 2 else 2
        cabin = spec.cabin_end_s - spec.windshield_s
        for k in range(n_doors):
            sh = spec.windshield_s + (0.55 + k * 0.9) * min(cabin, 2.4) / (1.6 if n_doors == 2 else 1.2)
            sh = min(sh, spec.cabin_end_s - 0.2)
            yh = side * (_body_surface_y(spec, sh, zh) + 0.005)
            parts["door_handles"].extend(superellipsoid((float(_x(spec, sh)), yh, zh), (0.15, 0.03, 0.035), 3.0, 6))
        if spec.roof_rails:
            yr = side * 0.5 * W * spec.tumblehome * 0.72
            s0, s1 = spec.windshield_s + spec.windshield_run + 0.1, spec.roof_end_s - 0.05
            parts["roof_rails"].extend(superellipsoid(
                (float(_x(spec, 0.5 * (s0 + s1))), yr, spec.height + 0.03), (s1 - s0, 0.04, 0.05), 4.0, 8))

    zb = spec.clearance + 0.2
    for name, x, sign in (("bumper_front", front_x, -1.0), ("bumper_rear", rear_x, 1.0)):
        parts[name].extend(superellipsoid((x + sign * 0.12, 0.0, zb), (0.34, 0.96 * W, 0.26), 4.0, 14))
        parts["licence_plates"].extend(superellipsoid((x - sign * 0.045, 0.0, zb + 0.02), (0.02, 0.52, 0.12), 6.0, 6))
    parts["grille"].extend(superellipsoid(
        (front_x - _body_front_s(spec, 0.5 * W - 0.55) - 0.01, 0.0, spec.nose_height - 0.18),
        (0.12, W - 1.05, 0.2), 4.0, 10))
    parts["underbody"].extend(superellipsoid(
        (0.0, 0.0, spec.clearance + 0.03), (L - 0.7, 0.88 * W, 0.05), 6.0, 10))
    parts["exhaust"].extend(superellipsoid(
        (rear_x + 0.15, -0.28 * W, spec.clearance + 0.08), (0.3, 0.08, 0.08), 2.0, 10))
    # Seats and dashboard seen through the glass: behind the windshield, below the roof line.
    s0, s1 = spec.windshield_s + 0.9 * spec.windshield_run, spec.roof_end_s
    top = spec.belt_height + 0.5 * (spec.height - spec.belt_height)
    parts["interior"].extend(superellipsoid(
        (float(_x(spec, 0.5 * (s0 + s1))), 0.0, 0.5 * (spec.belt_height - 0.1 + top)),
        (max(s1 - s0, 0.3), 0.8 * W * spec.tumblehome, top - spec.belt_height + 0.1), 3.0, 10))
    if not spec.roof_rails:
        del parts["roof_rails"]
    return parts


def build_car(spec: CarSpec) -> dict[str, Mesh]:
    """All part meshes of a catalogue model, keyed by part name (see PARTS)."""
    parts: dict[str, Mesh] = {"body": _lower_body(spec)}
    green, labels = _greenhouse(spec)
    for name in ("body", "windshield", "window_side", "window_rear", "pillar_trim"):
        ids = np.nonzero(labels == name)[0]
        if len(ids):
            piece = green.subset(ids)
            parts[name] = parts[name].extend(piece) if name in parts else piece
    parts.update(_wheels(spec))
    parts.update(_small_parts(spec))
    return {k: v for k, v in parts.items() if len(v.faces)}
