"""Propose the parts of a car model that has no rules file (no bpy here: works on a FaceTable).

Evidence, strongest first, each face keeping the first that decides it:
- names: object and material names (wheel/tyre/rim, glass/window, light/lamp, plate, mirror,
  bumper, grille, interior);
- material: transmission or alpha below 1 -> glass; emission -> a light (front or rear by position);
- geometry: wheels are the parts of the model in the four lower corners (connected pieces low
  beside the axles), tyres their dark or outer faces, rims the rest; faces looking at the ground
  from the lower third of the car are the underbody;
- colour: faces are grouped by their texture/base colour; a group other than the paint that lies
  in the greenhouse band and faces sideways, forwards or backwards is glass (a dark one face by
  face: one black often paints the windows, the trim and the floor); bright white/yellow
  groups at the front end are headlights, red ones at the rear tail lights, amber ones indicators;
  very dark groups low on the body are bumpers/underbody, grey ones bumpers unless they are a
  white or silver paint's baked shading.
Everything else is the painted body. A textured model's faces arrive cut along their texture's
edges (`texsplit.py`, done by the reader), so colour decides pieces, not whole large triangles.
Orientation (up, forward) is inferred when not given: up is the axis that most area faces along
(roof, hood), forward the end without the red lamps (or, failing those, the end whose top is
lower: the hood).
"""
from __future__ import annotations

import fnmatch
from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np

from .rules import AXES, FACING_COS, RulesError, face_normals

LABELLER_VERSION = 4  # 4: category from the roof's length and the proportions; the length guessed
FLOOR_HEIGHT = (0.0, 0.35)  # the band (fractions of the model's height) whose ground-facing faces are floor
DARK_GLASS_V = 0.36  # clusters darker than this are glass face by face in the greenhouse band


@dataclass
class FaceTable:
    tris: np.ndarray  # (n, 3, 3) corners
    normals: np.ndarray  # (n, 3, 3) corner normals
    objects: np.ndarray  # (n,) object base names
    materials: np.ndarray  # (n,) material base names ("" when none)
    uv: np.ndarray  # (n, 2) UV centroid, NaN without UVs
    colour: np.ndarray  # (n, 3) sRGB of the texture under the UV centroid, else the base colour; NaN if neither
    textured: np.ndarray  # (n,) bool: colour comes from a texture
    alpha: np.ndarray  # (n,) material alpha (1 = opaque)
    transmission: np.ndarray  # (n,) material transmission weight
    emission: np.ndarray  # (n,) emission strength x luminance of its colour

    def __len__(self) -> int:
        return len(self.tris)

    def areas(self) -> np.ndarray:
        t = self.tris
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

NAME_HINTS: list[tuple[tuple[str, ...], str]] = [  # (globs on lower-case object/material names, part)
    (("*tyre*", "*tire*", "*rubber*"), "tyres"),
    (("*rim*", "*wheel*", "*hubcap*", "*alloy*"), "wheel"),  # tyre or rim: decided by colour/radius
    (("*windshield*", "*windscreen*"), "windshield"),
    (("*glass*", "*window*", "*glas*"), "windows"),
    (("*headl*", "*head_l*", "*head-l*", "*front*light*", "*front*lamp*"), "headlights"),
    (("*tail*", "*brake*light*", "*rear*light*", "*rear*lamp*", "*back*light*"), "tail_lights"),
    (("*indicator*", "*blinker*", "*turn*signal*", "*siren*", "*beacon*"), "indicators"),
    (("*plate*", "*licen*"), "licence_plates"),
    (("*mirror*",), "mirrors"),
    (("*bumper*",), "bumpers"),
    (("*grill*",), "grille"),
    (("*interior*", "*seat*", "*steering*", "*dashboard*"), "interior"),
    (("*exhaust*",), "exhaust"),
    (("*light*", "*lamp*"), "lights"),  # front or rear by position
]


def named_part(obj: str, material: str) -> bool:
    """Whether an object or material name alone decides a part (NAME_HINTS)."""
    name = f"{obj} {material}".lower()
    return any(fnmatch.fnmatchcase(name, g) for globs, _ in NAME_HINTS for g in globs)


@dataclass
class Labelling:
    labels: np.ndarray  # (n,) part per face ("windows" and "bumpers" are split later by the importer)
    evidence: np.ndarray  # (n,) what decided it: name, material, wheel, colour, geometry (floor), default
    forward: str
    up: str
    category: str
    warnings: list[str] = field(default_factory=list)
    length: float = 4.5  # metres: the model's own length where plausible for its category, else the category's typical

    def summary(self, areas: np.ndarray) -> list[tuple[str, int, float, dict[str, int]]]:
        """(part, faces, area share, {evidence: faces}) per part, largest area first."""
        total = float(areas.sum()) or 1.0
        out = []
        for part in sorted(set(self.labels), key=lambda p: -areas[self.labels == p].sum()):
            sel = self.labels == part
            out.append((part, int(sel.sum()), float(areas[sel].sum()) / total, dict(Counter(self.evidence[sel]))))
        return out


def _axis_vec(axis: str) -> np.ndarray:
    v = np.zeros(3)
    v["XYZ".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
    return v


def infer_up(tris: np.ndarray, areas: np.ndarray) -> str:
    """Up is the short axis along which the car narrows: the roof is narrower than the wheels and
    sills (tumblehome), while the two sides of a car are mirror images. Bottoms are no guide:
    some models close them with a flat plate larger than the roof."""
    pts = tris.reshape(-1, 3)
    ext = np.ptp(pts, axis=0)
    short = [k for k in np.argsort(ext)[:2]]
    best, score = "+Z", -np.inf
    for a in short:
        b = next(k for k in short if k != a)
        x = pts[:, a]
        lo, hi = x.min(), x.max()
        span = max(hi - lo, 1e-9)
        top = pts[x > hi - 0.15 * span, b]
        bot = pts[x < lo + 0.15 * span, b]
        w_top, w_bot = np.ptp(top) if len(top) else 0.0, np.ptp(bot) if len(bot) else 0.0
        if abs(w_top - w_bot) > score:
            score = abs(w_top - w_bot)
            best = f"{'+' if w_top < w_bot else '-'}{'XYZ'[a]}"
    return best


def _away_from(tris: np.ndarray, low: np.ndarray) -> str:
    """The signed short axis pointing from the faces `low` (the wheels) to the rest of the car."""
    pts = tris.mean(1)
    ext = np.ptp(pts, axis=0)
    d = pts[~low].mean(0) - pts[low].mean(0)
    d[np.argmax(ext)] = 0.0  # not the length axis
    k = int(np.argmax(np.abs(d)))
    return f"{'+' if d[k] > 0 else '-'}{'XYZ'[k]}"


def _frame(tris: np.ndarray, forward: str, up: str) -> np.ndarray:
    f, u = _axis_vec(forward), _axis_vec(up)
    return np.stack([f, np.cross(u, f), u])  # rows: car x (forward), y (left), z (up)


def _hsv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb = np.nan_to_num(rgb, nan=0.5)
    mx, mn = rgb.max(1), rgb.min(1)
    v, c = mx, mx - mn
    s = np.where(mx > 1e-6, c / np.maximum(mx, 1e-6), 0.0)
    r, g, b = rgb.T
    m = c > 1e-6
    hr = ((g - b) / np.where(m, c, 1)) % 6
    hg = (b - r) / np.where(m, c, 1) + 2
    hb = (r - g) / np.where(m, c, 1) + 4
    h = np.where(mx == r, hr, np.where(mx == g, hg, hb)) * 60.0
    return np.where(m, h, 0.0), s, v


def _is_red(h, s, v):
    return ((h < 18) | (h > 335)) & (s > 0.45) & (v > 0.3)


def _is_amber(h, s, v):
    return (h >= 18) & (h < 40) & (s > 0.5) & (v > 0.5)


def _is_lamp_white(h, s, v):
    return (v > 0.8) & ((s < 0.25) | ((h >= 40) & (h < 70) & (s > 0.35)))  # white or yellow


def _colour_groups(colour: np.ndarray, uv: np.ndarray | None = None, bins: int = 12, uv_cells: int = 16) -> np.ndarray:
    """Faces grouped by colour bin and, where there are UVs, by texture cell: a palette's swatches
    are UV regions, and a red car's red tail lights live in another swatch than its paint."""
    q = np.clip((np.nan_to_num(colour, nan=-1.0) * bins).astype(int), -1, bins)
    if uv is not None:
        cell = np.where(np.isfinite(uv), np.floor(np.nan_to_num(uv) % 1.0 * uv_cells), -1).astype(int)
        q = np.concatenate([q, cell], axis=1)
    _, inv = np.unique(q, axis=0, return_inverse=True)
    return inv.ravel()


def infer_forward(pts: np.ndarray, areas: np.ndarray, colour: np.ndarray, groups: np.ndarray, length_axis: int) -> float:
    """+1 if the car faces +length_axis, -1 if the other way, 0 if its lamps do not tell: small
    red face groups gather at the rear (tail lights), small white or yellow ones at the front."""
    x = pts[:, length_axis]
    lo, hi = x.min(), x.max()
    span = max(hi - lo, 1e-9)
    total = areas.sum()
    toward_hi = toward_lo = 0.0  # evidence that the front is at the high / low end
    for g in np.unique(groups):
        sel = groups == g
        a = areas[sel]
        if a.sum() <= 0 or a.sum() > 0.03 * total or not np.isfinite(colour[sel, 0]).all():
            continue
        gh, gs, gv = (float(t[0]) for t in _hsv(np.average(colour[sel], axis=0, weights=a)[None]))
        at_hi = a[x[sel] > hi - 0.15 * span].sum() / a.sum() > 0.7
        at_lo = a[x[sel] < lo + 0.15 * span].sum() / a.sum() > 0.7
        if _is_red(gh, gs, gv):
            toward_lo += a.sum() * at_hi
            toward_hi += a.sum() * at_lo
        elif _is_lamp_white(gh, gs, gv) and gs > 0.35:  # yellow: white is too common to tell
            toward_hi += a.sum() * at_hi
            toward_lo += a.sum() * at_lo
    if max(toward_hi, toward_lo) > 2 * min(toward_hi, toward_lo):
        return 1.0 if toward_hi > toward_lo else -1.0
    return 0.0


MIN_FACES = 12  # fewer cannot form a body with wheels


def infer(table, forward: str | None = None, up: str | None = None) -> Labelling:
    """Parts for every face of a FaceTable (see the module docstring)."""
    tris, areas = table.tris, table.areas()
    n = len(tris)
    ext = np.ptp(tris.reshape(-1, 3), axis=0) if n else np.zeros(3)
    if n < MIN_FACES or np.sort(ext)[1] <= 1e-6 or not np.isfinite(areas).all() or areas.sum() <= 0:
        raise RulesError(f"{n} faces spanning {' x '.join(f'{e:.3g}' for e in ext)} (total area {areas.sum():.3g}): "
                         f"too few or degenerate to be a car (at least {MIN_FACES} faces with a 3-D extent)")
    warnings: list[str] = []
    groups = _colour_groups(table.colour, table.uv)  # used by the lamps (forward) and the colour stage
    if up is None:  # the wheels are at the bottom; failing named wheels, the car narrows upwards
        wheels = np.array([any(fnmatch.fnmatchcase(f"{o} {m}".lower(), g) for g in ("*wheel*", "*tyre*", "*tire*"))
                           for o, m in zip(table.objects, table.materials)], bool)
        up = infer_up(tris, areas) if not wheels.any() or wheels.all() else _away_from(tris, wheels)
    if forward is None:
        u = _axis_vec(up)
        candidates = [a for a in AXES if abs(_axis_vec(a) @ u) < 0.5]
        extents = {a: np.ptp(tris.reshape(-1, 3) @ _axis_vec(a)) for a in candidates}
        length_axis = max(extents, key=extents.get)
        k = "XYZ".index(length_axis[1])
        centres = tris.mean(1)
        sign = infer_forward(centres, areas, table.colour, groups, k)
        if sign == 0.0:  # no lamps to go by: the hood is lower than the roof's rear end
            x, z = centres[:, k], centres @ u
            lo, hi = x.min(), x.max()
            top_hi = np.percentile(z[x > hi - 0.2 * (hi - lo)], 95)
            top_lo = np.percentile(z[x < lo + 0.2 * (hi - lo)], 95)
            sign = 1.0 if top_hi < top_lo else -1.0
            warnings.append("forward axis guessed from the body's height profile (no tail or yellow head lights found)")
        forward = f"{'+' if sign > 0 else '-'}{length_axis[1]}"
    rot = _frame(tris, forward, up)
    pts = tris.reshape(-1, 3) @ rot.T
    lo, hi = pts.min(0), pts.max(0)
    size = np.maximum(hi - lo, 1e-9)
    # car frame normalised: x in [-1, 1] back to front, y in [-1, 1] right to left, z in [0, 1] up
    c = ((pts.reshape(-1, 3, 3).mean(1) - (lo + hi) / 2) / (size / 2))
    c[:, 2] = (pts.reshape(-1, 3, 3).mean(1)[:, 2] - lo[2]) / size[2]
    fn = face_normals(tris) @ rot.T
    labels = np.full(n, "", dtype=object)
    evidence = np.full(n, "", dtype=object)

    def decide(mask: np.ndarray, part: str | np.ndarray, why: str) -> None:
        m = mask & (labels == "")
        labels[m] = part[m] if isinstance(part, np.ndarray) else part
        evidence[m] = why

    # 1. names
    names = np.array([f"{o} {m}".lower() for o, m in zip(table.objects, table.materials)], dtype=object)
    for globs, part in NAME_HINTS:
        hit = np.array([any(fnmatch.fnmatchcase(nm, g) for g in globs) for nm in names], bool)
        if part == "lights":
            decide(hit, np.where(c[:, 0] >= 0, "headlights", "tail_lights").astype(object), "name")
        elif part == "wheel":
            decide(hit, "wheel", "name")
        else:
            decide(hit, part, "name")
    # 2. material properties
    # transparent materials, unless one covers much of the car: OBJ importers turn the MTL's
    # default transmission filter (Tf 1 1 1) of an opaque body into full transmission
    see_through = (table.transmission > 0.5) | (table.alpha < 0.9)
    for m in np.unique(table.materials[see_through]):
        sel = see_through & (table.materials == m)
        if areas[table.materials == m].sum() < 0.3 * areas.sum():
            decide(sel, "windows", "material")
    decide(table.emission > 0.05, np.where(c[:, 0] >= 0, "headlights", "tail_lights").astype(object), "material")
    # 3. wheels: whole objects that sit in a lower corner, when names did not find them
    if not (labels == "wheel").any() and not (labels == "tyres").any():
        for obj in np.unique(table.objects):
            sel = table.objects == obj
            cs = c[sel]
            if (cs[:, 2].max() < 0.55 and np.abs(cs[:, 0]).min() > 0.2 and np.abs(cs[:, 1]).min() > 0.2
                    and areas[sel].sum() < 0.15 * areas.sum()):
                decide(sel, "wheel", "wheel")
    wheel = labels == "wheel"
    h, s, v = _hsv(table.colour)
    if wheel.any():
        # tyre: dark faces of a wheel and its outer ring (a textured wheel's fan triangles see tyre
        # and rim at once), rims the rest. One object may hold all four wheels: each corner's
        # faces are one wheel
        dark = (v < 0.3) & np.isfinite(table.colour[:, 0])
        outer = np.zeros(n, bool)
        corner = np.sign(c[:, 0]) * 2 + np.sign(c[:, 1])
        for obj in np.unique(table.objects[wheel]):
            for k in np.unique(corner[wheel & (table.objects == obj)]):
                sel = wheel & (table.objects == obj) & (corner == k)
                p = pts.reshape(-1, 3, 3)[sel].mean(1)
                centre = (p.min(0) + p.max(0)) / 2
                r = np.hypot(p[:, 0] - centre[0], p[:, 2] - centre[2])
                outer[np.nonzero(sel)[0]] = r > 0.75 * r.max()
        tyre = (dark | outer) if dark[wheel].any() else outer
        labels[wheel & tyre] = "tyres"
        labels[wheel & ~tyre] = "rims"
    # 4. colour on what is left. Fine groups (colour bin x texture cell) are chained into colour
    # clusters (a palette's gradient swatch, a texture's shading); the largest cluster is the
    # paint. Lamps are small groups at an end; the other clusters are told by colour and place.
    rest = labels == ""
    if rest.any() and np.isfinite(table.colour[rest, 0]).any():
        ids = [g for g in np.unique(groups[rest]) if np.isfinite(table.colour[rest & (groups == g), 0]).all()]
        gsel = {g: rest & (groups == g) for g in ids}
        garea = {g: float(areas[gsel[g]].sum()) for g in ids}
        ids = [g for g in ids if garea[g] > 0]
        gmean = {g: np.average(table.colour[gsel[g]], axis=0, weights=areas[gsel[g]]) for g in ids}
        gcell = {g: np.nanmedian(np.floor(np.nan_to_num(table.uv[gsel[g]], nan=-1) % 1.0 * 16), axis=0) for g in ids}
        cluster = _chain(ids, gmean, gcell, 0.1)
        carea, ctop = defaultdict(float), defaultdict(float)
        # roof, hood, boot lid and the doors' belt: painted on nearly every car
        top = ((fn[:, 2] > 0.85) & (c[:, 2] > 0.5)) | ((np.abs(fn[:, 1]) > 0.8) & (c[:, 2] > 0.35) & (c[:, 2] < 0.55))
        for g in ids:
            carea[cluster[g]] += garea[g]
            ctop[cluster[g]] += float(areas[gsel[g] & top].sum())
        paint = max(carea, key=lambda k: (ctop[k], carea[k]))

        def members(k) -> np.ndarray:  # the faces of colour cluster k
            sel = np.zeros(n, bool)
            for g in ids:
                if cluster[g] == k:
                    sel |= gsel[g]
            return sel

        psel = members(paint)
        _, ps, pv = (float(x[0]) for x in _hsv(np.average(table.colour[psel], axis=0, weights=areas[psel])[None]))
        # a neutral, light paint (white, silver) shades to mid greys where a texture bakes its lighting
        shaded_paint = ps < 0.1 and pv > 0.7
        rest_area = max(areas[rest].sum(), 1e-12)

        def stats(sel):
            w = areas[sel]
            hsv = tuple(float(x[0]) for x in _hsv(np.average(table.colour[sel], axis=0, weights=w)[None]))
            return (w.sum() / rest_area, hsv, np.average(c[sel, 2], weights=w), np.average(fn[sel, 2] > 0.85, weights=w),
                    np.average(fn[sel, 2] < -0.5, weights=w), np.average(c[sel, 0] > 0.7, weights=w),
                    np.average(c[sel, 0] < -0.7, weights=w))

        for g in ids:  # lamps
            share, (gh, gs, gv), _, up_facing, _, front_end, rear_end = stats(gsel[g])
            # lamps are small in any colour cluster (a red car's paint cut into pieces is no tail
            # light) and look forwards, backwards or sideways (nor is a pale hood a headlight)
            if share > 0.03 or carea[cluster[g]] / rest_area > 0.03 or up_facing > 0.5:
                continue
            if _is_red(gh, gs, gv) and rear_end > 0.6:
                decide(gsel[g], "tail_lights", "colour")
            elif cluster[g] != paint and _is_lamp_white(gh, gs, gv) and front_end > 0.6:
                decide(gsel[g], "headlights", "colour")
            elif cluster[g] != paint and _is_amber(gh, gs, gv) and (front_end > 0.6 or rear_end > 0.6):
                decide(gsel[g], "indicators", "colour")
        for k in carea:
            if k == paint:
                continue
            sel = members(k) & (labels == "")
            if not sel.any() or areas[sel].sum() <= 0:
                continue
            share, (gh, gs, gv), zc, up_facing, down_facing, front_end, rear_end = stats(sel)
            r, _, b = np.average(table.colour[sel], axis=0, weights=areas[sel])
            glassy = gs < 0.3 and (gv < 0.45 or b - r > 0.05)  # dark, or pale and bluish
            if gs < 0.3 and gv < DARK_GLASS_V:
                # dark: glass where it lies in the greenhouse band and does not face up, face by face,
                # as one texture's black is often windows up there and trim, tyres and floor below
                pane = sel & (c[:, 2] > 0.5) & (fn[:, 2] < 0.6)
                if pane.any() and areas[pane].sum() / rest_area < 0.35:
                    decide(pane, "windows", "colour")
                    sel = sel & ~pane & (c[:, 2] < 0.5)  # the rest: trim and floor below, paint (a black roof) above
                    if not sel.any():
                        continue
                    share, (gh, gs, gv), zc, up_facing, down_facing, front_end, rear_end = stats(sel)
            if zc > 0.5 and up_facing < 0.6 and share < 0.35 and glassy and gv > 0.1:
                decide(sel, "windows", "colour")  # dark or pale blue panes in the greenhouse band
            elif gs < 0.3 and gv < 0.35 and (down_facing > 0.5 or zc < 0.15):
                decide(sel, "underbody", "colour")
            elif shaded_paint and gs < 0.1 and gv >= 0.4 and zc < 0.5:
                pass  # a white or silver paint's baked shading on the lower doors: paint
            elif gs < 0.3 and gv < 0.65 and zc < 0.5:
                decide(sel, "bumpers", "colour")  # grey plastic on the lower half: bumpers and sills
    # 5. the floor: faces that look at the ground from the lower third of the car are its underside
    # whatever their colour (a floor pan often shares the paint's or the bumpers' texture swatch);
    # decided after the colour clusters, which it would otherwise skew toward the car's top
    floor = np.isin(labels, ["", "bumpers"]) & (fn[:, 2] < -FACING_COS) & (c[:, 2] < FLOOR_HEIGHT[1])
    labels[floor], evidence[floor] = "underbody", "geometry"
    decide(labels == "", "body", "default")
    for part in ("windows", "tyres", "headlights", "tail_lights"):
        if not np.isin(labels, [part, "windshield"] if part == "windows" else [part]).any():
            warnings.append(f"no {part.replace('_', ' ')} found: their faces are painted body")
    category = guess_category(c, size)
    return Labelling(labels, evidence, forward, up, category, warnings, guess_length(category, float(size[0])))


def guess_category(c: np.ndarray, size: np.ndarray) -> str:
    """A category from two shape cues that survive a stylised model's proportions: how much of the
    length the roof covers (faces in the top 15% of the height; a sedan's cabin is short, a van's
    roof runs nearly its whole length) and height over length; where the model's units look like
    metres, a length above the hatchbacks' (4.45 m) makes a hatchback-shaped model an SUV.
    Thresholds from the 28 named models (24 right: every sedan, wagon and van, 4 of 5 hatchbacks
    and minivans, 3 of 5 SUVs) and the 7 Kenney models (7 of 7 against their hand-written rules)."""
    top = c[:, 2] > 0.85
    cover = float(np.ptp(c[top, 0])) / 2 if top.sum() > 1 else 0.0  # c[:, 0] spans [-1, 1] along the length
    hl = float(size[2] / size[0])
    if cover >= 0.71 or (cover >= 0.58 and hl >= 0.40):
        return "van"
    if cover >= 0.58:
        return "minivan"
    if cover < 0.38:
        return "sedan"
    if hl >= 0.40:
        return "suv"
    if hl <= 0.35:
        return "station_wagon"
    if cover >= 0.50:
        return "suv"
    return "suv" if 4.45 < size[0] <= 8.0 else "hatchback"


def guess_length(category: str, model_length: float) -> float:
    """The model's own length when its units look like metres for its category (0.75-1.6 times the
    category's typical length, data_manifests/car_ranges.toml), else that typical length."""
    from .sampler import load_ranges

    lo, hi = load_ranges()[category]["length"]
    typical = round((lo + hi) / 2, 2)
    return round(model_length, 2) if 0.75 * typical <= model_length <= 1.6 * typical else typical


def _chain(ids: list, mean: dict, cell: dict, tol: float, spread: float = 0.35) -> dict:
    """Single-linkage clusters of face groups that are neighbours in the texture (UV cells at most
    one apart) and close in colour (RGB distance < tol): a palette's gradient swatch, a painted
    panel's shading; distinct swatches side by side differ in colour and stay apart. A cluster's
    colours stay within `spread` per channel, so a chain of in-between shades cannot link white
    paint to black glass."""
    parent = {g: g for g in ids}

    def root(g):
        while parent[g] != g:
            parent[g] = parent[parent[g]]
            g = parent[g]
        return g

    cols = np.array([mean[g] for g in ids])
    cells = np.array([cell[g] for g in ids], dtype=float)
    lo = {g: mean[g].copy() for g in ids}  # colour box per cluster root
    hi = {g: mean[g].copy() for g in ids}
    for i in range(len(ids)):
        d = np.linalg.norm(cols[i + 1:] - cols[i], axis=1)
        near = np.abs(cells[i + 1:] - cells[i]).max(axis=1) <= 1
        for j in np.nonzero((d < tol) & near)[0]:
            a, b = root(ids[i]), root(ids[i + 1 + j])
            if a == b:
                continue
            # no chains across a texture's edges: small in-between groups (where a split face
            # straddles white paint and a black window) would link the two otherwise
            box_lo, box_hi = np.minimum(lo[a], lo[b]), np.maximum(hi[a], hi[b])
            if (box_hi - box_lo).max() > spread:
                continue
            parent[b] = a
            lo[a], hi[a] = box_lo, box_hi
    return {g: root(g) for g in ids}


def agreement(a: np.ndarray, b: np.ndarray, areas: np.ndarray) -> float:
    """Area-weighted share of faces with the same part."""
    return float(areas[a == b].sum() / max(areas.sum(), 1e-12))


def rules_reproduce(table, lab: Labelling, rules_path, model_file) -> float:
    """Share of the area to which the rules file at rules_path gives the part `lab` inferred.

    Applied as the importer applies them (the model's first file names it; its up axis decides
    heights and facing), so a proposal is checked the way it will be used. Raises RulesError
    when the file does not load.
    """
    from .rules import load_rules, rule_labels

    again, _ = rule_labels(table, load_rules(rules_path), "body", model_file, lab.up)
    return agreement(again, lab.labels, table.areas())


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.4f}" for x in v) + "]"


def propose_rules(table, lab: Labelling, model_name: str, length: float | None = None, min_share: float = 0.0005) -> str:
    """A rules file (TOML text) that reproduces a labelling: an object rule where an object is one
    part, material rules where materials separate its parts, else palette rules (a UV box and a
    colour range per colour group of a part). Groups under `min_share` of the area are left to
    the object's main part; `rule_labels` on the result measures what that costs."""
    areas = table.areas()
    total = float(areas.sum()) or 1.0
    length = lab.length if length is None else length
    lines = [f"# Proposed by `iae-gen label-parts` (labeller v{LABELLER_VERSION}) for {model_name}: check the",
             "# part-colour preview, edit what is wrong, then use it with --car-rules.", "",
             "[model]", f"forward = {_toml_str(lab.forward)}", f"up = {_toml_str(lab.up)}", f"length = {length}",
             'default_part = "body"', f"category = {_toml_str(lab.category)}", ""]
    by_name, floor_rule, by_colour, whole = [], [], [], []
    floor = lab.evidence == "geometry"
    if floor.any():  # the floor by the labeller's own geometric test: after the rules of parts found by
        # name, material or wheel shape (a tyre's bottom keeps its part), before the colour rules
        # (the floor shares a swatch with paint or bumpers)
        floor_rule.append({"match": "object", "pattern": "*", "objects": sorted(set(table.objects[floor])),
                           "height": FLOOR_HEIGHT, "facing": "down", "part": "underbody"})
    groups = _colour_groups(table.colour, table.uv, bins=32)
    z = table.tris @ _axis_vec(lab.up)  # heights as the rules measure them (fractions of the model's)
    height = (z.mean(1) - z.min()) / max(float(np.ptp(z)), 1e-9)
    for obj in sorted(set(table.objects)):
        in_obj = (table.objects == obj) & ~floor
        if not in_obj.any():
            continue
        parts = Counter()
        for p, a in zip(lab.labels[in_obj], areas[in_obj]):
            parts[p] += a
        main = max(parts, key=parts.get)
        for part in sorted(parts, key=lambda p: -parts[p]):
            if part == main:
                continue
            sel = in_obj & (lab.labels == part)
            mats = set(table.materials[sel])
            if all(m for m in mats) and not (in_obj & ~sel & np.isin(table.materials, list(mats))).any():
                for m in sorted(mats):
                    by_name.append({"match": "material", "pattern": m, "objects": [obj], "part": part})
                continue
            for g in np.unique(groups[sel]):
                gs = sel & (groups == g)
                if areas[gs].sum() / total < min_share or not np.isfinite(table.uv[gs, 0]).all():
                    continue
                uv, col = table.uv[gs], table.colour[gs]
                rule = {"match": "palette", "objects": [obj], "part": part,
                        "uv_min": uv.min(0) - 1e-4, "uv_max": uv.max(0) + 1e-4}
                if (lab.evidence[gs] == "colour").any():  # colour decisions depend on height (glass above the
                    # belt, trim below in one black): the group's band keeps the rule to its faces
                    lo_h, hi_h = float(height[gs].min()), float(height[gs].max())
                    rule["height"] = (max(0.0, lo_h - 1e-3), min(1.0, hi_h + 1e-3))
                if table.textured[gs].all():
                    rule["color_min"], rule["color_max"] = col.min(0) - 1e-3, col.max(0) + 1e-3
                strong = np.isin(lab.evidence[gs], ["name", "material", "wheel"]).mean() > 0.5
                (by_name if strong else by_colour).append(rule)
        if main != "body":
            whole.append({"match": "object", "pattern": obj, "part": main})
    specific = by_name + floor_rule + by_colour
    for r in specific + whole:
        lines.append("[[rule]]")
        lines.append(f"match = {_toml_str(r['match'])}")
        if "pattern" in r:
            lines.append(f"pattern = {_toml_str(r['pattern'])}")
        if "objects" in r:
            lines.append("objects = [" + ", ".join(_toml_str(o) for o in r["objects"]) + "]")
        if "height" in r:
            lines.append(f"height = {_fmt(r['height'])}")
        if "facing" in r:
            lines.append(f"facing = {_toml_str(r['facing'])}")
        for k in ("uv_min", "uv_max", "color_min", "color_max"):
            if k in r:
                lines.append(f"{k} = {_fmt(r[k])}")
        lines.append(f"part = {_toml_str(r['part'])}")
        lines.append("")
    if not specific and not whole:  # a rules file needs one rule; this one keeps everything paint
        lines += ["[[rule]]", 'match = "object"', 'pattern = "*"', 'part = "body"', ""]
    return "\n".join(lines)


PART_COLOURS = {
    "body": "#b0b0b0", "windows": "#3d8bfd", "windshield": "#1f5fbf", "window_side": "#3d8bfd",
    "window_rear": "#7fb2ff", "tyres": "#202020", "rims": "#e0c040", "headlights": "#fff27a",
    "tail_lights": "#e02020", "indicators": "#ff9900", "bumpers": "#6a3d9a", "bumper_front": "#6a3d9a",
    "bumper_rear": "#9b6ad0", "grille": "#33a02c", "mirrors": "#00c0c0", "licence_plates": "#ffffff",
    "underbody": "#5a4030", "interior": "#a05030", "exhaust": "#808000", "wheel": "#e0c040",
}


def preview(table, labels: np.ndarray, forward: str, up: str, out, title: str = "") -> None:
    """Part colours in side, front, top and bottom views (matplotlib, painter's order): a PNG to check
    a labelling at a glance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Patch

    rot = _frame(table.tris, forward, up)
    pts = table.tris @ rot.T  # car frame: x forward, y left, z up
    views = (("left side", 0, 2, 1, 1), ("front", 1, 2, 0, 1), ("top", 0, 1, 2, 1), ("bottom", 0, 1, 2, -1))
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.2), gridspec_kw={"width_ratios": [2.2, 1, 2.2, 2.2]})
    for ax, (name, a, b, depth, sign) in zip(axes, views):
        order = np.argsort(sign * pts[:, :, depth].mean(1))  # far faces first
        polys = pts[order][:, :, [a, b]]
        if name == "front":
            polys = polys * np.array([-1, 1])  # seen from the front, the car's left is on the right
        elif name == "bottom":
            polys = polys * np.array([1, -1])  # seen from below, the car's left is at the bottom
        cols = [PART_COLOURS.get(p, "#ff00ff") for p in labels[order]]
        ax.add_collection(PolyCollection(polys, facecolors=cols, edgecolors="none"))
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.axis("off")
    present = [p for p in PART_COLOURS if p in set(labels)]
    fig.legend(handles=[Patch(color=PART_COLOURS[p], label=p) for p in present], loc="lower center",
               ncol=min(8, len(present)), fontsize=8, frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(out, dpi=80, format="png")
    plt.close(fig)
