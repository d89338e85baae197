"""A procedural car's geometry: `CarSpec` (data) -> named part meshes (NumPy, no bpy).

Shapes are lofts of superellipse sections along the car's length (lower body, greenhouse)
plus rounded boxes and lathed wheels for the small parts. The side profile comes from key
heights (nose, hood, cowl, a rising beltline, a crowned roof, the tail) smoothed so panels
curve without creases; the plan view from a superellipse with a tapered nose and flared
fenders. Windows are the faces of the greenhouse chosen by position and facing, so the glass
follows the body's curvature exactly. Front and rear designs (grille, headlight and
tail-light shapes) are small parts placed on the body's surface.
"""
from __future__ import annotations

import numpy as np

from ..geometry import Mesh, lathe, loft, smooth_profile, superellipse, superellipsoid
from .spec import CarSpec

# Bump when the same spec would give other meshes: recipe identities of named-model sets
# include it (catalogue_digest), so a dataset never mixes two geometries.
GEOMETRY_VERSION = 2


def _x(spec: CarSpec, s):
    """Position along the car (from the front) -> X in the car frame."""
    return 0.5 * spec.length - np.asarray(s)


def _wheel_centres_s(spec: CarSpec) -> tuple[float, float]:
    return spec.front_overhang, spec.front_overhang + spec.wheelbase


def _plan_half_width(spec: CarSpec, s: np.ndarray, flare: bool = False) -> np.ndarray:
    """Half width seen from above: a superellipse plan with rounded corners, narrower toward
    the nose by `nose_taper`, and (lower body) bulging by `arch_flare` around the wheels."""
    s = np.asarray(s, dtype=np.float64)
    p = spec.plan_exponent
    t = np.clip(np.abs(2.0 * s / spec.length - 1.0), 0.0, 1.0)
    half = 0.5 * spec.width - spec.arch_flare
    w = half * np.clip(1.0 - t**p, 0.0, 1.0) ** (1.0 / p)
    if spec.nose_taper:
        w = w * (1.0 - spec.nose_taper * np.clip(1.0 - s / (0.5 * spec.length), 0.0, 1.0) ** 2)
    if flare and spec.arch_flare:
        for sc in _wheel_centres_s(spec):
            w = w + spec.arch_flare * np.exp(-(((s - sc) / (1.15 * spec.wheel_radius + 0.1)) ** 4))
    return w


def belt_line(spec: CarSpec, s) -> np.ndarray:
    """Beltline height along the car: `belt_height` at the cowl rising by `belt_rise` to the rear."""
    u = np.clip((np.asarray(s, dtype=np.float64) - spec.windshield_s) / (spec.cabin_end_s - spec.windshield_s), 0, 1)
    return spec.belt_height + spec.belt_rise * u


def _lower_profiles(spec: CarSpec, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Top (hood, beltline, deck) and bottom (sills, wheel arches) of the lower body."""
    L = spec.length
    belt_end = float(belt_line(spec, spec.cabin_end_s))
    blunt = spec.body_style in ("van", "minivan")
    tail_start = min(spec.cabin_end_s + 0.15, L - 0.1)
    top = smooth_profile(s, [
        (0.0, spec.nose_height - (0.05 if blunt else 0.1)), (0.1 if blunt else 0.18, spec.nose_height),
        (spec.windshield_s, spec.hood_height), (spec.windshield_s + 0.3, float(belt_line(spec, spec.windshield_s + 0.3))),
        (spec.cabin_end_s, belt_end), (tail_start, spec.tail_height),
        (L - 0.1, spec.tail_height), (L, spec.tail_height - (0.06 if blunt else 0.12)),
    ], passes=2, width=2)
    bottom = smooth_profile(s, [
        (0.0, spec.clearance + 0.22), (0.35, spec.clearance + 0.02), (L - 0.35, spec.clearance + 0.02),
        (L, spec.clearance + 0.25),
    ], passes=1, width=2)
    r = spec.wheel_radius
    for sc in _wheel_centres_s(spec):
        d = np.abs(s - sc)
        if spec.arch_style == "round":
            R = r + 0.06
            arch = r + np.sqrt(np.clip(R**2 - d**2, 0.0, None))
        elif spec.arch_style == "flat":  # a wide arc with its crown cut flat
            R = r + 0.16
            arch = np.minimum(r * 0.6 + np.sqrt(np.clip(R**2 - d**2, 0.0, None)), 2 * r + 0.07)
        else:  # "square": near-vertical sides and a flat top (off-road and utility bodies)
            R = r + 0.1
            arch = r * 0.9 + (r * 0.1 + R) * np.clip(1.0 - (d / R) ** 4, 0.0, 1.0) ** 0.25
        inside = d < R
        bottom = np.where(inside, np.maximum(bottom, arch), bottom)
    return top, np.minimum(bottom, top - 0.1)


def roof_line(spec: CarSpec, s: np.ndarray) -> np.ndarray:
    """Greenhouse top along the car: windshield, a roof crowned by `roof_crown`, rear glass."""
    ws_top = spec.windshield_s + spec.windshield_run
    u = np.linspace(0.0, 1.0, 9)
    roof_pts = [(ws_top + (spec.roof_end_s - ws_top) * v, spec.height - spec.roof_crown * (2 * v - 1) ** 2) for v in u]
    return smooth_profile(s, [
        (spec.windshield_s, float(belt_line(spec, spec.windshield_s)) - 0.04), *roof_pts,
        (spec.cabin_end_s, float(belt_line(spec, spec.cabin_end_s)) - 0.04),
    ], passes=2, width=2)


def _orient_outward(mesh: Mesh, centre) -> Mesh:
    """Flip the winding if most faces point toward `centre` (closed, roughly convex shapes)."""
    n = mesh.face_normals()
    d = mesh.face_centroids() - np.asarray(centre)
    return mesh.flipped() if np.sum(np.einsum("ij,ij->i", n, d)) < 0 else mesh


def _lower_body(spec: CarSpec, sections: int = 90, ring: int = 36) -> Mesh:
    s = np.linspace(0.0, spec.length, sections)
    top, bottom = _lower_profiles(spec, s)
    w = _plan_half_width(spec, s, flare=True)
    prof = superellipse(ring, spec.roundness)
    zc, hz = 0.5 * (top + bottom), 0.5 * (top - bottom)
    rings = np.stack([
        np.repeat(_x(spec, s)[:, None], ring, axis=1),
        w[:, None] * prof[None, :, 0],
        zc[:, None] + hz[:, None] * prof[None, :, 1],
    ], axis=2)
    body = _orient_outward(loft(rings), (0.0, 0.0, float(np.mean(zc))))
    return _open_bed(spec, body, rings, s, prof) if spec.body_style == "pickup" else body


BED_WALL = 0.1  # cab back wall and tailgate thickness (m)
BED_DEPTH = 0.5  # rail to floor, where the wheel arches leave room (m)


def _open_bed(spec: CarSpec, body: Mesh, rings: np.ndarray, s: np.ndarray, prof: np.ndarray) -> Mesh:
    """A pickup's load bed: the lower body's top quads behind the cab are removed (the loft's quad
    (i, j) joins rings i, i+1 at ring points j, j+1) and a tub put in the hole: walls dropped
    from the hole's edge to a floor above the wheel arches, the floor a quad grid under the hole."""
    n_sec, k = rings.shape[:2]
    inside_s = np.nonzero((s >= spec.cabin_end_s + BED_WALL) & (s <= spec.length - BED_WALL))[0]
    top_pts = np.nonzero((prof[:, 1] > 0.3) & (np.abs(prof[:, 0]) < 0.86))[0]  # contiguous about the top
    i0, i1, j0, j1 = int(inside_s.min()), int(inside_s.max()), int(top_pts.min()), int(top_pts.max())
    hole = np.zeros((n_sec - 1, k), bool)
    hole[i0:i1, j0:j1] = True
    keep = body.subset(np.nonzero(~hole.ravel())[0])
    rail = float(rings[i0:i1 + 1, j0:j1 + 1, 2].min())
    floor_z = max(rail - BED_DEPTH, 2.0 * spec.wheel_radius + 0.12)
    grid = rings[i0:i1 + 1, j0:j1 + 1].copy()  # the hole's edge and inside, (i, j)
    floor = grid.copy()
    floor[..., 2] = floor_z
    ni, nj = grid.shape[:2]
    a = (np.arange(ni - 1)[:, None] * nj + np.arange(nj - 1)[None, :]).ravel()
    floor_mesh = Mesh(floor.reshape(-1, 3), np.stack([a, a + 1, a + nj + 1, a + nj], axis=1))
    floor_mesh = floor_mesh.flipped(floor_mesh.face_normals()[:, 2] < 0)
    edge = np.concatenate([grid[0, :], grid[1:, -1], grid[-1, -2::-1], grid[-2:0:-1, 0]])  # closed loop
    low = edge.copy()
    low[:, 2] = floor_z
    m = len(edge)
    idx = np.arange(m)
    walls = Mesh(np.concatenate([edge, low]), np.stack([idx, (idx + 1) % m, (idx + 1) % m + m, idx + m], axis=1))
    centre = np.array([floor[..., 0].mean(), 0.0, floor_z])
    d = centre - walls.face_centroids()
    walls = walls.flipped(np.einsum("ij,ij->i", walls.face_normals(), d) < 0)  # the walls face the bed
    return keep.extend(walls).extend(floor_mesh)


def _greenhouse(spec: CarSpec, sections: int = 70, ring: int = 40) -> tuple[Mesh, np.ndarray]:
    """The cabin above the beltline, and the part name of each of its faces."""
    s = np.linspace(spec.windshield_s, spec.cabin_end_s, sections)
    roof = roof_line(spec, s)
    base = belt_line(spec, s) - 0.06
    w_belt = _plan_half_width(spec, s) - 0.035
    prof = superellipse(ring, spec.roof_section)
    v = 0.5 * (prof[:, 1] + 1.0)  # 0 at the bottom of the section, 1 at the roof
    half = w_belt[:, None] * (1.0 - (1.0 - spec.tumblehome) * v[None, :])
    rings = np.stack([
        np.repeat(_x(spec, s)[:, None], ring, axis=1),
        half * prof[None, :, 0],
        base[:, None] + (roof - base)[:, None] * v[None, :],
    ], axis=2)
    mesh = _orient_outward(loft(rings), (0.0, 0.0, 0.5 * (float(np.mean(base)) + spec.height)))
    return mesh, _classify_greenhouse(spec, mesh)


def _classify_greenhouse(spec: CarSpec, mesh: Mesh) -> np.ndarray:
    """Windshield, rear window, side windows, pillars and roof by position and facing."""
    n = mesh.face_normals()
    c = mesh.face_centroids()
    s = 0.5 * spec.length - c[:, 0]
    z = c[:, 2]
    names = np.full(len(c), "body", dtype=object)
    roof_s = np.linspace(spec.windshield_s, spec.cabin_end_s, 400)
    roof_z = roof_line(spec, roof_s)
    lo = belt_line(spec, s) + 0.03
    # Windshield and rear glass: up to just below the roof; side glass: below the roof line at the
    # face's own position (a crowned roof is lower at its ends).
    glass_band = (z > lo) & (z < spec.height - 0.05)
    hi = np.interp(s, roof_s, roof_z) - 0.05

    ws_top = spec.windshield_s + spec.windshield_run
    ws_half = 0.5 * spec.width * spec.tumblehome * 0.8
    names[glass_band & (n[:, 0] > 0.3) & (np.abs(c[:, 1]) < ws_half) & (s < ws_top + 0.05)] = "windshield"
    rear_half = 0.5 * spec.width * spec.tumblehome * 0.78
    names[glass_band & (n[:, 0] < -0.25) & (np.abs(c[:, 1]) < rear_half) & (s > spec.roof_end_s - 0.05)] = "window_rear"

    # Side glass: between the A pillar (following the windshield slope) and the C/D pillar.
    peak = int(np.argmax(roof_z))

    def front_edge(zq):
        return np.interp(zq, roof_z[: peak + 1], roof_s[: peak + 1])

    def rear_edge(zq):
        return np.interp(zq, roof_z[peak:][::-1], roof_s[peak:][::-1])

    side = glass_band & (z < hi) & (np.abs(n[:, 1]) > 0.55)
    inside = side & (s > front_edge(z) + 0.12) & (s < rear_edge(z) - 0.14) & (z < hi - 0.03)
    names[inside] = "window_side"
    # Pillars between the side windows (B pillar, and C pillar on long cabins): black trim.
    cabin = spec.cabin_end_s - spec.windshield_s
    n_windows = {2: 1, 3: 2, 4: 2}.get(spec.doors, 3)
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
        parts[k] = _fix_lathe_winding(parts[k])
    return parts


def _fix_lathe_winding(mesh: Mesh) -> Mesh:
    """Wheel discs are open surfaces: make their normals point away from the car's centre plane."""
    n = mesh.face_normals()
    c = mesh.face_centroids()
    return mesh.flipped(n[:, 1] * np.sign(c[:, 1]) < 0)


def _body_surface_y(spec: CarSpec, s: float, z: float) -> float:
    """|Y| of the lower body's side surface at (s, z)."""
    top, bottom = _lower_profiles(spec, np.array([s]))
    w = float(_plan_half_width(spec, np.array([s]), flare=True)[0])
    zc, hz = 0.5 * (top[0] + bottom[0]), 0.5 * (top[0] - bottom[0])
    t = np.clip(abs(z - zc) / max(hz, 1e-6), 0.0, 1.0)
    return w * (1.0 - t**spec.roundness) ** (1.0 / spec.roundness)


def _surface_s(spec: CarSpec, y: float, z: float, rear: bool = False) -> float:
    """Distance from the front (or rear) bumper at which the lower body's surface first covers
    the point (|Y| = y, Z = z) seen along the car: where a lamp or grille centred there sits."""
    s = np.linspace(0.0, 0.5 * spec.length, 300)
    sq = spec.length - s if rear else s
    top, bottom = _lower_profiles(spec, sq)
    w = _plan_half_width(spec, sq, flare=True)
    zc, hz = 0.5 * (top + bottom), 0.5 * (top - bottom)
    t = np.clip(np.abs(z - zc) / np.maximum(hz, 1e-6), 0.0, 1.0)
    covered = w * (1.0 - t**spec.roundness) ** (1.0 / spec.roundness) >= abs(y)
    return float(s[int(np.argmax(covered))]) if covered.any() else 0.0


def _inset(spec: CarSpec, y: float, z: float, half: float, rear: bool = False) -> float:
    """`y` moved inward so a lamp of half width `half` at height `z` stays inside the body's side
    (sections narrow toward the top of the lower body, where lamps sit)."""
    s = spec.length - 0.25 if rear else 0.25
    limit = max(_body_surface_y(spec, s, z) - half - 0.02, 0.0)
    return float(np.sign(y) * min(abs(y), limit))


def _front_design(spec: CarSpec, parts: dict[str, Mesh]) -> None:
    """Headlights, indicators and grille of the spec's front design."""
    W, front_x, zn = spec.width, 0.5 * spec.length, spec.nose_height

    def on_nose(y: float, depth: float, z: float) -> float:  # the lamp's front 4 cm proud of the surface
        return front_x - _surface_s(spec, abs(y), z) - 0.5 * depth + 0.04

    for side in (1.0, -1.0):
        if spec.headlight == "round":
            for k, dy in enumerate((0.3, 0.5) if W > 1.85 else (0.32,)):
                y = _inset(spec, side * (0.5 * W - dy), zn - 0.1, 0.1)
                parts["headlights"].extend(superellipsoid((on_nose(y, 0.16, zn - 0.1), y, zn - 0.1), (0.16, 0.2, 0.2), 2.0, 10))
        elif spec.headlight == "rect":
            y = _inset(spec, side * (0.5 * W - 0.3), zn - 0.1, 0.17)
            parts["headlights"].extend(superellipsoid((on_nose(y, 0.22, zn - 0.1), y, zn - 0.1), (0.22, 0.34, 0.13), 3.0, 10))
        elif spec.headlight == "slim":
            y = _inset(spec, side * (0.5 * W - 0.3), zn - 0.03, 0.22)
            parts["headlights"].extend(superellipsoid((on_nose(y, 0.2, zn - 0.03), y, zn - 0.03), (0.2, 0.44, 0.07), 3.0, 10))
        else:  # "swept": long lamps that wrap around the corner toward the fender
            y = _inset(spec, side * (0.5 * W - 0.2), zn - 0.05, 0.15)
            parts["headlights"].extend(superellipsoid((on_nose(y, 0.4, zn - 0.05) - 0.05, y, zn - 0.05), (0.42, 0.3, 0.1), 2.5, 10))
        yi = _inset(spec, side * (0.5 * W - 0.1), zn - 0.18, 0.05)
        parts["indicators"].extend(superellipsoid((on_nose(yi, 0.12, zn - 0.18) - 0.02, yi, zn - 0.18), (0.12, 0.1, 0.07), 3.0, 8))

    if spec.grille == "kidney":
        for side in (1.0, -1.0):
            y = side * 0.15
            parts["grille"].extend(superellipsoid((on_nose(y, 0.12, zn - 0.14), y, zn - 0.14), (0.12, 0.2, 0.26), 3.0, 10))
    elif spec.grille == "trapezoid":
        half = 0.5 * W - 0.45
        parts["grille"].extend(superellipsoid((on_nose(0.6 * half, 0.12, zn - 0.24), 0.0, zn - 0.24), (0.12, 2 * half, 0.32), 2.6, 12))
    elif spec.grille == "slot":
        half = 0.5 * W - 0.5
        parts["grille"].extend(superellipsoid((on_nose(0.6 * half, 0.08, zn - 0.05), 0.0, zn - 0.05), (0.08, 2 * half, 0.06), 4.0, 10))
    elif spec.grille == "tall":
        half = 0.5 * W - 0.52
        parts["grille"].extend(superellipsoid((on_nose(0.6 * half, 0.12, zn - 0.17), 0.0, zn - 0.17), (0.12, 2 * half, 0.36), 5.0, 12))
    else:  # "wide"
        half = 0.5 * W - 0.55
        parts["grille"].extend(superellipsoid((on_nose(0.6 * half, 0.12, zn - 0.18), 0.0, zn - 0.18), (0.12, 2 * half, 0.2), 4.0, 10))


def _rear_design(spec: CarSpec, parts: dict[str, Mesh]) -> None:
    W, rear_x, zt = spec.width, -0.5 * spec.length, spec.tail_height
    if spec.body_style == "pickup":  # lamps below the bed rail, beside the tailgate
        zt -= 0.2

    def on_tail(y: float, depth: float, z: float) -> float:
        return rear_x + _surface_s(spec, abs(y), z, rear=True) + 0.5 * depth - 0.04

    for side in (1.0, -1.0):
        if spec.tail_light == "vertical":
            y = _inset(spec, side * (0.5 * W - 0.12), zt - 0.05, 0.08, rear=True)
            parts["tail_lights"].extend(superellipsoid((on_tail(y, 0.16, zt - 0.05), y, zt - 0.05), (0.16, 0.16, 0.4), 3.0, 10))
        elif spec.tail_light == "bar":
            y = _inset(spec, side * (0.5 * W - 0.22), zt - 0.1, 0.15, rear=True)
            parts["tail_lights"].extend(superellipsoid((on_tail(y, 0.18, zt - 0.1), y, zt - 0.1), (0.18, 0.3, 0.08), 3.0, 10))
        elif spec.tail_light == "round":
            for dy in (0.2, 0.4):
                y = _inset(spec, side * (0.5 * W - dy), zt - 0.12, 0.08, rear=True)
                parts["tail_lights"].extend(superellipsoid((on_tail(y, 0.1, zt - 0.12), y, zt - 0.12), (0.1, 0.15, 0.15), 2.0, 8))
        else:  # "horizontal"
            y = _inset(spec, side * (0.5 * W - 0.24), zt - 0.12, 0.15, rear=True)
            parts["tail_lights"].extend(superellipsoid((on_tail(y, 0.2, zt - 0.12), y, zt - 0.12), (0.2, 0.3, 0.14), 3.0, 10))
    if spec.tail_light == "bar":  # the strip joining the two lamps
        half = 0.5 * W - 0.4
        parts["tail_lights"].extend(superellipsoid((on_tail(0.6 * half, 0.1, zt - 0.1), 0.0, zt - 0.1), (0.1, 2 * half, 0.05), 4.0, 10))


def _small_parts(spec: CarSpec) -> dict[str, Mesh]:
    W, L = spec.width, spec.length
    parts: dict[str, Mesh] = {k: Mesh() for k in (
        "headlights", "indicators", "tail_lights", "grille", "bumper_front", "bumper_rear", "mirrors",
        "mirror_glass", "licence_plates", "door_handles", "underbody", "exhaust", "interior", "roof_rails")}
    front_x, rear_x = 0.5 * L, -0.5 * L
    _front_design(spec, parts)
    _rear_design(spec, parts)
    cabin = spec.cabin_end_s - spec.windshield_s
    for side in (1.0, -1.0):
        # Door mirror on the door just behind the A pillar.
        sm = spec.windshield_s + 0.15
        ym = side * (float(_plan_half_width(spec, np.array([sm]))[0]) + 0.05)  # just outside the door skin
        zm = float(belt_line(spec, sm)) + 0.03
        parts["mirrors"].extend(superellipsoid((float(_x(spec, sm)), ym, zm), (0.12, 0.2, 0.13), 3.0, 8))
        parts["mirror_glass"].extend(superellipsoid((float(_x(spec, sm)) - 0.06, ym, zm), (0.015, 0.16, 0.1), 4.0, 6))
        # Door handles, one per side door.
        n_doors = 1 if spec.doors in (2, 3) else 2
        for k in range(n_doors):
            sh = spec.windshield_s + (0.55 + k * 0.9) * min(cabin, 2.4) / (1.6 if n_doors == 2 else 1.2)
            sh = min(sh, spec.cabin_end_s - 0.2)
            zh = float(belt_line(spec, sh)) - 0.12
            yh = side * (_body_surface_y(spec, sh, zh) + 0.005)
            parts["door_handles"].extend(superellipsoid((float(_x(spec, sh)), yh, zh), (0.15, 0.03, 0.035), 3.0, 6))
        if spec.roof_rails:
            yr = side * 0.5 * W * spec.tumblehome * 0.72
            s0, s1 = spec.windshield_s + spec.windshield_run + 0.1, spec.roof_end_s - 0.05
            parts["roof_rails"].extend(superellipsoid(
                (float(_x(spec, 0.5 * (s0 + s1))), yr, spec.height + 0.03), (s1 - s0, 0.04, 0.05), 4.0, 8))

    zb = spec.clearance + 0.2
    for name, x, sign in (("bumper_front", front_x, -1.0), ("bumper_rear", rear_x, 1.0)):
        # Bumper face 1 cm, plate 2 cm beyond the body's end: `length` is the car's length.
        parts[name].extend(superellipsoid((x + sign * 0.16, 0.0, zb), (0.34, 0.96 * W, 0.26), 4.0, 14))
        parts["licence_plates"].extend(superellipsoid((x - sign * 0.01, 0.0, zb + 0.02), (0.02, 0.52, 0.12), 6.0, 6))
    parts["underbody"].extend(superellipsoid(
        (0.0, 0.0, spec.clearance + 0.03), (L - 0.7, 0.88 * W, 0.05), 6.0, 10))
    parts["exhaust"].extend(superellipsoid(
        (rear_x + 0.15, -0.28 * W, spec.clearance + 0.08), (0.3, 0.08, 0.08), 2.0, 10))
    # Seats and dashboard seen through the glass: behind the windshield, below the roof line.
    s0, s1 = spec.windshield_s + 0.9 * spec.windshield_run, spec.roof_end_s
    belt = float(belt_line(spec, 0.5 * (s0 + s1)))
    top = belt + 0.5 * (spec.height - belt)
    parts["interior"].extend(superellipsoid(
        (float(_x(spec, 0.5 * (s0 + s1))), 0.0, 0.5 * (belt - 0.1 + top)),
        (max(s1 - s0, 0.3), 0.8 * W * spec.tumblehome, top - belt + 0.1), 3.0, 10))
    if not spec.roof_rails:
        del parts["roof_rails"]
    return parts


def build_car(spec: CarSpec) -> dict[str, Mesh]:
    """All part meshes of a model, keyed by part name (see `PARTS`)."""
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
