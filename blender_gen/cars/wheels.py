"""Put wheel files that are authored at the origin into the body's wheel arches (no bpy).

Some models ship a body and separate wheel files modelled around the origin, which the
simulator they come from places and mirrors from its own vehicle config (MetaDrive's Beetle:
`vehicle.gltf` + `right_tire_front.gltf` + `right_tire_back.gltf`). Joined with '+', such a car
would have its wheels inside the cabin. Here the arches are found in the body itself: seen from
the side, the lowest body face along the car rises to a peak over each axle. A wheel file goes
to the arch its name says (front / back or rear; neither: both), to the side its name says
(right / left; neither: the side its hub protrudes to) and is mirrored to the other side unless
a file names that side itself. Its outer face sits just inside the body's side at the arch and
all wheels share one axle height, so the car stands level. Files that are already placed
(not centred on the origin) are left alone.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from .labeller import FaceTable, _frame
from .rules import RulesError

ARCH_GAP = 0.1  # clearance between tyre and arch top, in tyre radii
FRONT, BACK = ("front",), ("back", "rear")  # words in a wheel file's name that pick its axle
SIDE_BANDS = (0.6, 0.7, 0.8, 0.9)  # faces this far out (share of the half width) form a side profile
SIDE_INSET = 0.02  # the tyre's outer face sits this share of the body width inside the body's side


def take(table: FaceTable, idx: np.ndarray) -> FaceTable:
    return FaceTable(**{f.name: getattr(table, f.name)[idx] for f in fields(FaceTable)})


def concat(tables: list[FaceTable]) -> FaceTable:
    return FaceTable(**{f.name: np.concatenate([getattr(t, f.name) for t in tables]) for f in fields(FaceTable)})


def at_origin(tris: np.ndarray, body_tris: np.ndarray) -> bool:
    """A part modelled around the origin: its box is centred there and small against the body's."""
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    size = float((hi - lo).max())
    body = np.ptp(body_tris.reshape(-1, 3), axis=0).max()
    return bool(np.abs((lo + hi) / 2).max() < 0.25 * size and size < 0.5 * body)


@dataclass(frozen=True)
class Arch:
    x: float  # along the car (forward +)
    top: float  # lowest body point above the wheel
    outer: float  # the body's half width at the arch


def _arch_in(x, z, mask, edges, window, radius) -> Arch | None:
    """The arch in one half of the car: the peak of the side profile (lowest face per bin along
    the car) within `window`, its run of bins above half its rise; None if it is no arch."""
    mids = (edges[:-1] + edges[1:]) / 2
    which = np.clip(np.searchsorted(edges, x[mask], side="right") - 1, 0, len(mids) - 1)
    floor = np.full(len(mids), np.nan)
    for k in np.unique(which):
        floor[k] = z[mask][which == k].min()
    ok = window & np.isfinite(floor)
    if not ok.any():
        return None
    peak = int(np.argmax(np.where(ok, floor, -np.inf)))
    base = np.nanmin(floor[ok])
    rise = floor[peak] - base
    above = ok & (floor > base + 0.5 * rise)
    a = b = peak
    while a > 0 and above[a - 1]:
        a -= 1
    while b < len(mids) - 1 and above[b + 1]:
        b += 1
    chord = edges[b + 1] - edges[a]
    if rise < 0.5 * radius or not 0.6 * radius <= chord <= 4 * radius:
        return None
    return Arch(x=float((edges[a] + edges[b + 1]) / 2), top=float(floor[peak]), outer=0.0)


def find_arches(body: np.ndarray, radius: float) -> tuple[Arch, Arch]:
    """The front and back arches of a body given as face centres (n, 3) in the car frame
    (x forward, y left, z up). Raises RulesError where the side profile shows no arches.

    Seen from the side, the lowest body face along the car peaks over each wheel. Which faces
    form the side profile depends on the body (fenders, running boards, wheel-well liners), so
    several lateral bands are tried; a liner or axle seen inside the arch only lowers its peak,
    so the band whose arches are highest, at equal height front and back, wins. Axles lie in
    the outer parts of the car (wheelbase 50-85% of the length)."""
    x, y, z = body[:, 0], body[:, 1], body[:, 2]
    lo, hi = x.min(), x.max()
    edges = np.linspace(lo, hi, max(8, int((hi - lo) / (0.25 * radius))) + 1)
    u = ((edges[:-1] + edges[1:]) / 2 - (lo + hi) / 2) / ((hi - lo) / 2)  # -1 back end .. +1 front end
    best: tuple[Arch, Arch] | None = None
    for band in SIDE_BANDS:
        side = np.abs(y) > band * np.abs(y).max()
        front = _arch_in(x, z, side, edges, (u > 0.35) & (u < 0.95), radius)
        back = _arch_in(x, z, side, edges, (u < -0.35) & (u > -0.95), radius)
        if front is None or back is None or abs(front.top - back.top) > 0.3 * radius:
            continue
        if best is None or min(front.top, back.top) > min(best[0].top, best[1].top) + 1e-6:
            best = (front, back)
    if best is None:
        raise RulesError("the body's side profile shows no front and back wheel arch for wheel files "
                         "modelled at the origin; place the wheels in the model files")

    def outer(arch: Arch) -> Arch:  # the body's half width beside the wheel, below the arch top
        near = (np.abs(x - arch.x) < radius) & (z < arch.top)
        return Arch(x=arch.x, top=arch.top, outer=float(np.abs(y[near]).max() if near.any() else np.abs(y).max()))

    return outer(best[0]), outer(best[1])


def _mirror(tris: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflect across the car's y = 0 plane (car frame), keeping faces wound outwards."""
    t, n = tris.copy(), normals.copy()
    t[..., 1] *= -1
    n[..., 1] *= -1
    return t[:, [0, 2, 1]], n[:, [0, 2, 1]]


def place_wheel_files(table: FaceTable, file_index: np.ndarray, names: list[str],
                      forward: str, up: str) -> tuple[FaceTable, list[str]]:
    """Table with every wheel file that sits at the origin moved into the arches (and mirrored);
    the other files unchanged. Returns the table and one line per placed copy."""
    body = file_index == 0
    loose = [k for k in range(1, len(names)) if (file_index == k).any()
             and at_origin(table.tris[file_index == k], table.tris[body])]
    if not loose:
        return table, []
    rot = _frame(table.tris, forward, up)  # rows: car x, y, z in model coordinates
    body_c = table.tris[body].mean(1) @ rot.T
    wheels = {k: take(table, np.nonzero(file_index == k)[0]) for k in loose}
    framed = {k: (w.tris @ rot.T, w.normals @ rot.T) for k, w in wheels.items()}
    radius = max(np.ptp(t.reshape(-1, 3)[:, [0, 2]], axis=0).max() / 2 for t, _ in framed.values())
    for k, (t, _) in framed.items():
        ext = np.ptp(t.reshape(-1, 3), axis=0)
        if int(np.argmin(ext)) != 1:
            raise RulesError(f"{names[k]}: a wheel modelled at the origin should be thinnest across the car "
                             f"(its extents along the car, across, up: {np.round(ext, 3).tolist()})")
    front, back = find_arches(body_c, radius)
    axle = min(front.top, back.top) - (1 + ARCH_GAP) * radius
    width = 2 * np.abs(body_c[:, 1]).max()

    def named(k: int, words: tuple[str, ...]) -> bool:
        return any(w in names[k].lower() for w in words)

    sides = {}
    for k, (t, _) in framed.items():
        pts = t.reshape(-1, 3)
        if named(k, ("right",)):
            sides[k] = -1.0
        elif named(k, ("left",)):
            sides[k] = 1.0
        else:  # the hub protrudes outwards
            c = (pts[:, 1].min() + pts[:, 1].max()) / 2
            sides[k] = -1.0 if c - pts[:, 1].min() > pts[:, 1].max() - c else 1.0
    out = [take(table, np.nonzero(~np.isin(file_index, loose))[0])]
    report = []
    for k in loose:
        t, n = framed[k]
        centre = (t.reshape(-1, 3).min(0) + t.reshape(-1, 3).max(0)) / 2
        t = t - centre
        both = [(front, FRONT), (back, BACK)]
        axles = [(a, words) for a, words in both if named(k, words)] or both
        for arch, words in axles:
            axle_name = "front" if arch is front else "back"
            others = [j for j in loose if j != k and (named(j, words) or not named(j, FRONT + BACK))]
            mirror_ok = not any(sides[j] == -sides[k] for j in others)
            for side in (sides[k], -sides[k]) if mirror_ok else (sides[k],):
                tt, nn = (t, n) if side == sides[k] else _mirror(t, n)
                pts = tt.reshape(-1, 3)
                outer_face = pts[:, 1].max() if side > 0 else -pts[:, 1].min()
                y = side * (arch.outer - SIDE_INSET * width - outer_face)
                moved = tt + np.array([arch.x, y, axle])  # back to model coordinates: rot is orthonormal
                out.append(replace(wheels[k], tris=moved @ rot, normals=nn @ rot))
                report.append(f"{names[k]}: {axle_name} {'left' if side > 0 else 'right'} wheel at "
                              f"({arch.x:.2f}, {y:.2f}, {axle:.2f}) along, across, up (model units)"
                              f"{'' if side == sides[k] else ' (mirrored)'}")
    return concat(out), report
