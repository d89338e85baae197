"""What a dataset is made from: the recipe (plain data) and per-sample random draws.

Sample i depends only on (seed, i): any worker, shard or resumed run renders the same
sample from it. The recipe's identity (everything but count, workers and shard) is stored
in dataset.json and compared on every re-run so a folder never mixes two recipes.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .camera import CameraRanges, Orbit
from .dataset import KIND_EXTRA_LAYERS, KIND_LAYERS
from .envmap import DEFAULT_SKY_VARIANTS, HELDOUT_SKY_VARIANTS, PROCEDURAL_PREFIX, PROCEDURAL_SETS

KINDS = ("intrinsics", "pbr")


@dataclass(frozen=True)
class Recipe:
    kind: str
    seed: int
    width: int
    height: int
    cars: tuple[str, ...] = ("procedural:train",)
    car_rules: str | None = None
    envmaps: tuple[str, ...] = ("procedural",)
    samples: int = 1
    camera: CameraRanges = field(default_factory=CameraRanges)
    sky_variants: int = DEFAULT_SKY_VARIANTS
    # Consecutive samples [k*v, (k+1)*v) share a car model (drawn at random per block):
    # swapping the model in Cycles costs about as much as rendering a view.
    views_per_car: int = 4
    # A camera path around one car instead of random views (`iae-gen turntable`); None = random.
    orbit: Orbit | None = None
    # Intrinsics only. "black": the background of every layer is 0 (DESIGN.md). "environment":
    # the reflection layer's background is the environment seen directly behind the car, so the
    # sky and ground of a real image are expressible as intrinsics (docs/experiment_log.md: Making it learn).
    background: str = "black"
    # How the environment background is made: "lookup" = the environment map sampled along each
    # pixel's view ray in NumPy (no world to render: as fast as "black"); "cycles" = Cycles'
    # Environment pass behind the car as a holdout (sets made before "lookup" existed).
    environment_pass: str = "lookup"
    # Layers beyond the kind's first ones (depth, part, gloss; PBR: the light passes too); None = all
    # of the kind's, () = a set made before them.
    extra_layers: tuple[str, ...] | None = None
    # PBR only: Cycles' adaptive-sampling threshold. A pixel stops once the *image* is that clean,
    # so its light layers (diffuse shading under a glossy roof) can stay noisy; 0 = every pixel
    # takes all `samples` (converged light layers for a shading benchmark, slower).
    noise_threshold: float = 0.03

    def extras(self) -> tuple[str, ...]:
        return KIND_EXTRA_LAYERS[self.kind] if self.extra_layers is None else tuple(self.extra_layers)

    def layers(self) -> tuple[str, ...]:
        """The layers each sample of this recipe holds, in the order dataset.json lists them."""
        return KIND_LAYERS[self.kind] + self.extras()

    def identity(self) -> dict:
        """The fields that define the samples; files are named by content, not by path."""
        d = asdict(self)
        d["envmaps"] = [_file_identity(e) if e not in PROCEDURAL_SETS else e for e in self.envmaps]
        from .cars.rules import split_car

        d["cars"] = [[_file_identity(str(f)) for f in split_car(c)] if len(split_car(c)) > 1 else _file_identity(c)
                     if Path(c).suffix else c for c in self.cars]
        if self.car_rules == "auto":  # inferred parts: the labeller's version is the rules' identity
            from .cars.labeller import LABELLER_VERSION

            d["car_rules"] = {"auto": LABELLER_VERSION}
        else:
            d["car_rules"] = _file_identity(self.car_rules) if self.car_rules else None
        if any(not Path(c).suffix for c in self.cars):  # procedural cars: which catalogue and sampler
            from .cars import catalogue_digest

            d["catalogue"] = catalogue_digest()
        if self.background == "black":  # sets made before the option existed keep their identity
            del d["background"]
        if self.background == "black" or self.environment_pass == "cycles":
            del d["environment_pass"]  # likewise sets made before the lookup existed
        if self.extras():
            d["extra_layers"] = list(self.extras())
        else:
            del d["extra_layers"]  # and sets made before the extra layers
        if self.camera.max_coverage == CameraRanges.max_coverage:
            del d["camera"]["max_coverage"]  # no maximum: sets made before the option keep their identity
        if self.kind != "pbr" or self.noise_threshold == Recipe.noise_threshold:
            del d["noise_threshold"]  # the default: sets made before the option keep their identity
        if self.orbit is None:  # per-sample Cycles noise by frame number (render.py); older sets
            d["noise"] = "frame"  # used the first-rendered sample's seed and cannot be resumed
        return d

    def envmap_names(self) -> list[str]:
        """The environment choices a sample draws from, in a fixed order."""
        names: list[str] = []
        for e in self.envmaps:
            if e in ("procedural", "procedural:train"):
                names += [f"{PROCEDURAL_PREFIX}sky_{k:02d}" for k in range(self.sky_variants)]
            elif e == "procedural:heldout":
                first = DEFAULT_SKY_VARIANTS  # fixed, whatever sky_variants a recipe uses
                names += [f"{PROCEDURAL_PREFIX}sky_{k:02d}" for k in range(first, first + HELDOUT_SKY_VARIANTS)]
            else:
                names.append(e)
        return names


def _file_identity(path: str) -> dict:
    """A file by content; a model file also by every file its import reads (an OBJ's .mtl and
    textures, a glTF's external buffers and images), so editing one of them makes another recipe."""
    p = Path(path)
    d = {"name": p.name, "sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
    reads = companion_files(p)
    if reads:  # absent for a self-contained file: recipes made before this keep their identity
        d["reads"] = [_read_identity(p, rel) for rel in reads]
    return d


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tga", ".bmp", ".tif", ".tiff")


def _read_identity(model: Path, rel: str) -> dict:
    """A file an import reads: by content where it is, else the texture found by name in its place
    (what the renderer reads: cars/faces.py), else missing."""
    target = model.parent / rel
    if target.is_file():
        return {"name": rel, "sha256": hashlib.sha256(target.read_bytes()).hexdigest()}
    found = texture_by_name(Path(rel).name, model) if Path(rel).suffix.lower() in IMAGE_SUFFIXES else None
    if found is None:
        return {"name": rel, "missing": True}
    return {"name": rel, "found": found.relative_to(model.parent.parent).as_posix(),
            "sha256": hashlib.sha256(found.read_bytes()).hexdigest()}


# How far the search for a texture by name looks: Gazebo's materials/textures/ is two folders below
# the folder above meshes/. The bounds keep a model saved in a large folder (a home folder's
# Downloads) from walking the whole disk.
TEXTURE_SEARCH_DEPTH = 3
TEXTURE_SEARCH_ENTRIES = 50_000


def texture_by_name(name: str, model: Path) -> Path | None:
    """A texture the importer could not open where the model names it (a bare name of a file kept
    elsewhere, a Gazebo model:// URI): the first file of that name (in path order) at most
    TEXTURE_SEARCH_DEPTH folders below the model's folder, else below the folder above it (model
    libraries keep textures beside the meshes folder: Gazebo's materials/textures/). The second
    walk skips the model's folder, which the first searched deeper than the second would."""
    for folder, skip in ((model.parent, None), (model.parent.parent, model.parent)):
        hits = sorted(_files_named(folder, name, skip))
        if hits:
            return hits[0]
    return None


def _files_named(top: Path, name: str, skip: Path | None = None) -> list[Path]:
    """Files called exactly `name` (no pattern: names may hold '[' or '*') in `top` and up to
    TEXTURE_SEARCH_DEPTH folders below it, except under `skip`, looking at TEXTURE_SEARCH_ENTRIES
    entries at most."""
    hits: list[Path] = []
    level, seen = [top], 0
    for _ in range(TEXTURE_SEARCH_DEPTH + 1):
        below = []
        for folder in level:
            try:
                with os.scandir(folder) as it:
                    entries = sorted(it, key=lambda e: e.name)  # the same walk on every file system
            except OSError:  # unreadable folder: nothing found there
                continue
            for e in entries:
                seen += 1
                if e.name == name and e.is_file():
                    hits.append(Path(e.path))
                elif e.is_dir(follow_symlinks=False) and (skip is None or Path(e.path) != skip):
                    below.append(e.path)
            if seen > TEXTURE_SEARCH_ENTRIES:
                return hits
        level = below
    return hits


_MTL_MAPS = ("map_", "bump", "disp", "decal", "refl", "norm")


def _named_file(folder: Path, rest: str) -> str | None:
    """The file a directive names: the whole rest of the line if it exists, else its last token
    (texture options such as `-bm 0.5` come first)."""
    rest = rest.strip()
    if not rest:
        return None
    return rest if (folder / rest).is_file() else rest.split()[-1]


# A Gazebo model package keeps meshes/ and materials/textures/ side by side under the folder that
# holds model.sdf or model.config, and its .mtl files name textures as ../materials/textures/X.png.
PACKAGE_MARKERS = ("model.sdf", "model.config")


def model_root(path: Path) -> Path:
    """The folder whose files importing `path` may read: the model file's own folder, or the
    model package above it (a Gazebo package: its model.sdf or model.config one level up)."""
    folder = Path(path).resolve().parent
    if any((folder.parent / m).is_file() for m in PACKAGE_MARKERS):
        return folder.parent
    return folder


def companion_files(path: Path) -> list[str]:
    """Files (relative to the model file's folder, sorted) that importing `path` also reads. One
    outside `model_root` (`../` past it, an absolute path elsewhere) is refused before anything
    reads it."""
    found = _companions(Path(path))
    folder, root = Path(path).resolve().parent, model_root(path)
    for rel in found:
        target = (folder / rel).resolve()
        if root not in target.parents:
            where = "its model package" if root != folder else "the model's folder"
            raise ValueError(f"--cars {path}: refers to {rel!r}, outside {where}; a model may only read files "
                             "beside or below it (or in its Gazebo model package, marked by model.sdf or model.config)")
    return found


def _companions(path: Path) -> list[str]:
    folder, suffix = path.parent, path.suffix.lower()
    found: set[str] = set()
    if suffix == ".obj":
        libs = []
        with open(path, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.startswith("mtllib"):
                    rest = line[len("mtllib"):].strip()
                    libs += [rest] if (folder / rest).is_file() else rest.split()
        for lib in libs:
            found.add(lib)
            if not (folder / lib).is_file():
                continue
            for line in (folder / lib).read_text(encoding="utf-8", errors="replace").splitlines():
                key, _, rest = line.strip().partition(" ")
                if key.lower().startswith(_MTL_MAPS):
                    name = _named_file((folder / lib).parent, rest)
                    if name:
                        found.add(str(Path(lib).parent / name) if Path(lib).parent != Path(".") else name)
    elif suffix == ".gltf":
        import json

        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError):
            return []  # the importer reports a broken file; its identity is its bytes
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and uri and not uri.startswith("data:"):
                from urllib.parse import unquote

                found.add(unquote(uri))
    return sorted(found)


def recipe_from_identity(info: dict) -> dict:
    return info.get("recipe", {})


def sample_seed(seed: int, index: int) -> int:
    """A 31-bit seed for sample `index` (Cycles takes a signed int)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0] & 0x7FFFFFFF)


def block_seed(seed: int, index: int, views_per_car: int) -> int:
    """Seed of the random car choice shared by a block of `views_per_car` samples."""
    return int(np.random.SeedSequence([seed, index // views_per_car, 1]).generate_state(1)[0])


def _as_recorded(new, old):
    """`new` with each texture found by name written as `old` recorded it where `old` called it
    missing: sets made before such textures were hashed keep their identity (they never tracked them)."""
    if isinstance(new, dict) and isinstance(old, dict):
        if old.get("missing") and "found" in new and new.get("name") == old.get("name"):
            return old
        return {k: _as_recorded(v, old.get(k)) for k, v in new.items()}
    if isinstance(new, list) and isinstance(old, list) and len(new) == len(old):
        return [_as_recorded(n, o) for n, o in zip(new, old)]
    return new


def identity_diff(old: dict, new: dict) -> str | None:
    """The first field where two recipe identities differ, as text; None if equal."""
    new, old = _as_recorded(new, old), _as_recorded(old, new)  # either may be the older (merged shards)
    for key in sorted(set(old) | set(new)):
        if key == "noise" and key not in old and old:
            return ("it was made by an older iae-gen whose samples depended on the order they were rendered "
                    "in, so it cannot be extended or resumed byte-identically")
        if old.get(key) != new.get(key):
            return f"{key!r} is {old.get(key)!r} there and {new.get(key)!r} here"
    return None
