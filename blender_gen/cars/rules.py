"""Rules that map a real car model's geometry to the catalogue's parts (no bpy here).

A rules file (TOML) says how a model is oriented and sized, and which faces become which
part: by object name, by material name, or by texture-palette region (the texture colour
under a face, or the face's UV position in a palette texture). The first matching rule
wins; unmatched faces go to `default_part` and are reported.

```toml
[model]
forward = "-Y"        # axis (after import, Blender's Z-up space) that points to the car's front
up = "+Z"
length = 4.5          # metres, bumper to bumper, after normalisation
default_part = "body"
category = "sedan"

[files."van.glb"]     # per-file overrides of [model]
category = "van"
length = 5.0

[[rule]]
match = "palette"     # "object", "material" or "palette"
objects = ["body*"]   # optional: only faces of these objects (glob on names)
# files = ["police.glb"]  # optional: only in these model files (glob on file names)
# height = [0.0, 0.35]    # optional: face centre between these fractions of the model's height (0 = lowest point)
# facing = "down"         # optional: "up", "down" (normal within 45 deg of the up axis or its opposite) or "side"
uv_min = [0.0625, 0.0]  # palette: a UV box ...
uv_max = [0.125, 0.25]
# color_min = [0.8, 0.85, 0.9]  # ... and/or an sRGB colour range of the texture under the face
# color_max = [1.0, 1.0, 1.0]
part = "windows"      # a catalogue part, or "windows" / "bumpers" (split by facing / position)
```
"""
from __future__ import annotations

import fnmatch
import re
import tomllib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .spec import CATEGORIES, PARTS

MODEL_SUFFIXES = (".glb", ".gltf", ".obj", ".blend")


def is_model_file(car: str) -> bool:
    """Whether a recipe's car entry is a model file (or BODY+WHEELS files), not a catalogue selector."""
    return Path(car).suffix.lower() in MODEL_SUFFIXES


AXES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
SPLIT_PARTS = {"windows": ("windshield", "window_side", "window_rear"), "bumpers": ("bumper_front", "bumper_rear")}
_MODEL_KEYS = {"forward", "up", "length", "default_part", "category"}
_RULE_KEYS = {"match", "pattern", "objects", "files", "height", "facing", "part", "uv_min", "uv_max", "color_min", "color_max"}


class RulesError(ValueError):
    """A rules file or a model that the rules cannot handle; names the file and the rule."""


@dataclass(frozen=True)
class Rule:
    index: int
    match: str
    part: str
    pattern: str | None = None
    objects: tuple[str, ...] | None = None
    uv_min: tuple[float, float] | None = None
    uv_max: tuple[float, float] | None = None
    color_min: tuple[float, float, float] | None = None
    color_max: tuple[float, float, float] | None = None
    files: tuple[str, ...] | None = None
    height: tuple[float, float] | None = None
    facing: str | None = None


FACINGS = ("up", "down", "side")


def face_normals(tris: np.ndarray) -> np.ndarray:
    """Unit geometric normals of triangles (n, 3, 3), by their winding."""
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


FACING_COS = 0.7071  # a face looks up or down when its normal is within 45 deg of the up axis or its opposite


def facings_of(normal_up: np.ndarray) -> np.ndarray:
    """Which way faces look ("up", "down", "side"), from their unit normals' components along the
    model's up axis."""
    return np.where(normal_up > FACING_COS, "up", np.where(normal_up < -FACING_COS, "down", "side"))


@dataclass(frozen=True)
class ModelSettings:
    forward: str = "+X"
    up: str = "+Z"
    length: float = 4.5
    default_part: str = "body"
    category: str = "sedan"


@dataclass
class Rules:
    path: Path
    model: ModelSettings
    files: dict[str, ModelSettings] = field(default_factory=dict)
    rules: list[Rule] = field(default_factory=list)
    auto: bool = False  # `--car-rules auto`: parts inferred per model by `labeller.infer`

    def settings_for(self, model_path: str | Path) -> ModelSettings:
        return self.files.get(Path(model_path).name, self.model)


@dataclass(frozen=True)
class ImportedSpec:
    """A model file in a recipe's car list (the counterpart of a catalogue CarSpec)."""

    name: str
    category: str
    path: str
    tinted_rear: bool = False
    split: str = "import"


def split_car(token: str | Path) -> list[Path]:
    """A car's files: one model file, or several joined by '+' (a body and its wheels). A token that
    is itself an existing file is one file, even with '+' in its name."""
    token = str(token)
    return [Path(token)] if Path(token).is_file() else [Path(p) for p in token.split("+")]


def imported_specs(files: list[str], rules: Rules) -> list[ImportedSpec]:
    """Specs of model files ('+' joins a car's several files: a body and its wheels)."""
    first = [split_car(f)[0] for f in files]
    return [ImportedSpec(p.stem, rules.settings_for(p).category, str(f)) for p, f in zip(first, files)]


def base_name(name: str) -> str:
    """Blender's name without the '.001' suffix it adds to duplicates."""
    return re.sub(r"\.\d{3,}$", "", name)


def _globs(value, where: str) -> tuple[str, ...]:
    if isinstance(value, str):
        return (value,)
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise RulesError(f"{where}: expected a name pattern or a list of them, got {value!r}")


def _vec(value, n: int, where: str) -> tuple[float, ...]:
    if not (isinstance(value, list) and len(value) == n and all(isinstance(v, (int, float)) for v in value)):
        raise RulesError(f"{where}: expected a list of {n} numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _settings(data: dict, base: ModelSettings, where: str) -> ModelSettings:
    unknown = set(data) - _MODEL_KEYS
    if unknown:
        raise RulesError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(_MODEL_KEYS)}")
    merged = {**base.__dict__, **data}
    s = ModelSettings(**merged)
    if s.forward not in AXES or s.up not in AXES:
        raise RulesError(f"{where}: forward and up must be one of {AXES}, got {s.forward!r}, {s.up!r}")
    if s.forward[1] == s.up[1]:
        raise RulesError(f"{where}: forward ({s.forward}) and up ({s.up}) must be different axes")
    if not isinstance(s.length, (int, float)) or not 0.5 <= s.length <= 30:  # NaN and inf fail too
        raise RulesError(f"{where}: length must be a car's length in metres (0.5 to 30), got {s.length!r}")
    if s.default_part not in PARTS:
        raise RulesError(f"{where}: default_part {s.default_part!r} is not a part; parts: {list(PARTS)}")
    if s.category not in CATEGORIES:
        raise RulesError(f"{where}: category {s.category!r} is not one of {CATEGORIES}")
    return s


AUTO = "auto"


def load_rules(path: str | Path) -> Rules:
    if str(path) == AUTO:
        return Rules(Path(AUTO), ModelSettings(), auto=True)
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RulesError(f"--car-rules {path}: no such file") from None
    except UnicodeDecodeError as exc:
        raise RulesError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected a TOML rules file") from None
    except tomllib.TOMLDecodeError as exc:
        raise RulesError(f"{path}: not valid TOML ({exc})") from None
    unknown = set(data) - {"model", "files", "rule"}
    if unknown:
        raise RulesError(f"{path}: unknown section(s) {sorted(unknown)}; expected [model], [files.NAME], [[rule]]")
    model = _settings(data.get("model", {}), ModelSettings(), f"{path} [model]")
    files = {name: _settings(v, model, f"{path} [files.{name!r}]") for name, v in data.get("files", {}).items()}
    rules = []
    for i, r in enumerate(data.get("rule", []), start=1):
        where = f"{path} rule #{i}"
        extra = set(r) - _RULE_KEYS
        if extra:
            raise RulesError(f"{where}: unknown key(s) {sorted(extra)}; allowed: {sorted(_RULE_KEYS)}")
        match, part = r.get("match"), r.get("part")
        if match not in ("object", "material", "palette"):
            raise RulesError(f"{where}: match must be 'object', 'material' or 'palette', got {match!r}")
        if part not in PARTS and part not in SPLIT_PARTS:
            raise RulesError(f"{where}: part {part!r} is not a part; parts: {list(PARTS) + list(SPLIT_PARTS)}")
        if match in ("object", "material") and not isinstance(r.get("pattern"), str):
            raise RulesError(f"{where}: a '{match}' rule needs pattern = \"NAME-GLOB\"")
        rule = Rule(
            index=i, match=match, part=part, pattern=r.get("pattern"),
            objects=_globs(r["objects"], where + " objects") if "objects" in r else None,
            uv_min=_vec(r["uv_min"], 2, where + " uv_min") if "uv_min" in r else None,
            uv_max=_vec(r["uv_max"], 2, where + " uv_max") if "uv_max" in r else None,
            color_min=_vec(r["color_min"], 3, where + " color_min") if "color_min" in r else None,
            color_max=_vec(r["color_max"], 3, where + " color_max") if "color_max" in r else None,
            files=_globs(r["files"], where + " files") if "files" in r else None,
            height=_vec(r["height"], 2, where + " height") if "height" in r else None,
            facing=r.get("facing"),
        )
        if rule.facing is not None and rule.facing not in FACINGS:
            raise RulesError(f"{where}: facing must be one of {list(FACINGS)}, got {rule.facing!r}")
        if rule.height is not None and not 0 <= rule.height[0] < rule.height[1] <= 1:
            raise RulesError(f"{where}: height must be [low, high] fractions of the model's height with "
                             f"0 <= low < high <= 1, got {list(rule.height)}")
        if match == "palette":
            has_uv = rule.uv_min is not None and rule.uv_max is not None
            has_col = rule.color_min is not None and rule.color_max is not None
            if not (has_uv or has_col):
                raise RulesError(f"{where}: a palette rule needs uv_min/uv_max or color_min/color_max")
        rules.append(rule)
    if not rules:
        raise RulesError(f"{path}: no [[rule]] entries")
    return Rules(path, model, files, rules)


def face_part(rules: Rules, obj: str, material: str | None, uv, colour, model: str | None = None,
              height: float | None = None, facing: str | None = None) -> Rule | None:
    """The first rule that matches a face (object base name, material, UV centroid, texture sRGB,
    model file name, height as a fraction of the model's, "up"/"down"/"side")."""
    obj = base_name(obj)
    for rule in rules.rules:
        if rule.objects is not None and not any(fnmatch.fnmatchcase(obj, g) for g in rule.objects):
            continue
        if rule.files is not None and (model is None or not any(fnmatch.fnmatchcase(model, g) for g in rule.files)):
            continue
        if rule.height is not None and (height is None or not rule.height[0] <= height <= rule.height[1]):
            continue
        if rule.facing is not None and facing != rule.facing:
            continue
        if rule.match == "object":
            if fnmatch.fnmatchcase(obj, rule.pattern):
                return rule
        elif rule.match == "material":
            if material is not None and fnmatch.fnmatchcase(base_name(material), rule.pattern):
                return rule
        else:
            ok = True
            if rule.uv_min is not None:
                ok &= uv is not None and all(lo <= v <= hi for v, lo, hi in zip(uv, rule.uv_min, rule.uv_max))
            if rule.color_min is not None:
                ok &= colour is not None and all(lo <= c <= hi for c, lo, hi in zip(colour, rule.color_min, rule.color_max))
            if ok:
                return rule
    return None


def rule_labels(table, rules: Rules, default_part: str, model: str | Path | None = None,
                up: str = "+Z") -> tuple[np.ndarray, Counter]:
    """The part of every face by the rules' first match (default part where none matches), and
    how many faces each rule took (index 0: unmatched). `model` is the model's file (rules with
    `files`), `up` its up axis in the table's frame (rules with `height` or `facing`)."""
    labels = np.empty(len(table), dtype=object)
    hits: Counter = Counter()
    cache: dict[tuple, object] = {}
    name = Path(model).name if model is not None else None
    axis, sign = "XYZ".index(up[1]), (1.0 if up[0] == "+" else -1.0)
    heights = facings = None
    if any(r.height is not None for r in rules.rules) and len(table):
        z = table.tris[:, :, axis] * sign
        lo, hi = z.min(), z.max()
        heights = (z.mean(1) - lo) / max(hi - lo, 1e-9)
    if any(r.facing is not None for r in rules.rules) and len(table):
        facings = facings_of(face_normals(table.tris)[:, axis] * sign)
    for t in range(len(table)):
        uv = None if not np.isfinite(table.uv[t, 0]) else (float(table.uv[t, 0]), float(table.uv[t, 1]))
        colour = tuple(float(x) for x in table.colour[t]) if table.textured[t] else None
        h = None if heights is None else float(heights[t])
        f = None if facings is None else str(facings[t])
        key = (table.objects[t], table.materials[t], uv, colour, h, f)
        if key not in cache:
            cache[key] = face_part(rules, table.objects[t], table.materials[t] or None, uv, colour, name, h, f)
        rule = cache[key]
        hits[rule.index if rule else 0] += 1
        labels[t] = rule.part if rule else default_part
    return labels, hits
