"""The experiment's datasets and the rules that keep them apart (the paper's protocol).

Four sets take part in a comparison:
  training intrinsics M_s   training cars, training environments            (the run's --intrinsics)
  real images I_r           held-out cars under held-out environments       (the run's --real)
  evaluation PBR set        training cars in unseen poses and paints        (Table 3, --data)
  FID intrinsics            training cars, a seed the run never saw         (Table 1, --intrinsics)
Two generated sets with the same sample recipe (seed, cars, environments, camera ranges)
show the same cars in the same poses whatever their kind or resolution, so a shared recipe
is an overlap: it is refused. Shared car models or environments are allowed but reported.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from blender_gen.dataset import DatasetError, open_dataset
from train.data import set_identity

# Recipe fields that do not change which car, paint, environment and camera a sample shows.
_NOT_SAMPLE_FIELDS = {"kind", "samples", "width", "height", "background"}


class ProtocolError(ValueError):
    """Two sets of a comparison overlap where the protocol needs them apart."""


@dataclass
class SetInfo:
    role: str
    path: Path
    kind: str
    count: int
    seed: int | None = None
    cars: Counter = field(default_factory=Counter)
    envmaps: Counter = field(default_factory=Counter)
    sample_key: str | None = None  # None for photo folders
    identity: dict = field(default_factory=dict)  # resolution and content digest (Dataset.identity)
    framing: str = "-"  # how much of the frame the car covers (generated sets; `framing_of`)

    def summary(self) -> dict:
        return {"role": self.role, "path": str(self.path), "kind": self.kind, "count": self.count, "seed": self.seed,
                "cars": dict(sorted(self.cars.items())), "envmaps": dict(sorted(self.envmaps.items())),
                "resolution": self.identity.get("resolution"), "content_sha256": self.identity.get("manifest_sha256"),
                "framing": self.framing}


def framing_of(recipe: dict) -> str:
    """A generated set's framing from its recipe: a coverage range (photo-like), the paper's rule,
    or a turntable's camera path."""
    if recipe.get("orbit"):
        return "turntable orbit"
    camera = recipe.get("camera") or {}
    if "max_coverage" in camera:
        return f"{camera.get('min_coverage', 0):.2f}-{camera['max_coverage']:.2f}"
    return f"paper's rule (>= {camera.get('min_coverage', 0.08):.2f})" if camera else "-"


def describe(role: str, root: Path) -> SetInfo:
    """What a dataset (or a folder of photos) holds: its cars, environments and seed."""
    root = Path(root).resolve()
    if not (root / "dataset.json").exists():
        if not root.is_dir():
            raise DatasetError(f"{role} {root}: no such dataset or image folder")
        identity = set_identity(root)  # names and sizes, as a run records its photo folder
        return SetInfo(role, root, "images", identity["count"], identity=identity)
    ds = open_dataset(root)
    recipe = ds.info.get("recipe") or {}
    key = {k: v for k, v in recipe.items() if k not in _NOT_SAMPLE_FIELDS}
    return SetInfo(role, root, ds.kind, len(ds), ds.info.get("seed"),
                   Counter(r.get("car", {}).get("name", "?") for r in ds.rows),
                   Counter(r.get("envmap", {}).get("name", "?") for r in ds.rows),
                   repr(sorted(key.items())) if key else None, ds.identity(), framing_of(recipe))


def _same_samples(a: SetInfo, b: SetInfo) -> bool:
    return a.path == b.path or (a.sample_key is not None and a.sample_key == b.sample_key)


def check_sets(train: SetInfo | None, real: SetInfo | None, evaluation: SetInfo | None,
               fid: SetInfo | None) -> list[str]:
    """Refuse overlapping sets (ProtocolError); return warnings for what is shared but allowed."""
    pairs = [
        (evaluation, real, "the evaluation set repeats the samples of the real training images"),
        (evaluation, train, "the evaluation set shows the poses of the training intrinsics"),
        (fid, train, "the FID intrinsics are the run's training intrinsics: fakes must come from intrinsics the run "
                     "never saw (same cars, a new --seed)"),
    ]
    for a, b, why in pairs:
        if a is not None and b is not None and _same_samples(a, b):
            raise ProtocolError(f"{a.path} and {b.path} share a sample recipe: {why}")
    warnings = []
    if evaluation and real and real.kind != "images":
        shared = sorted(set(evaluation.cars) & set(real.cars))
        if shared:
            warnings.append(f"the evaluation set shares {len(shared)} car model(s) with the real training images "
                            f"({', '.join(shared[:4])}): Table 3 would partly score cars H was trained on as 'real'")
        envs = sorted(set(evaluation.envmaps) & set(real.envmaps))
        if envs:
            warnings.append(f"the evaluation set shares {len(envs)} environment(s) with the real training images")
    if evaluation and train:
        unseen = sorted(set(evaluation.cars) - set(train.cars))
        if unseen:
            warnings.append(f"the evaluation set shows {len(unseen)} car model(s) absent from the training "
                            f"intrinsics ({', '.join(unseen[:4])}); the paper evaluates on training cars")
    return warnings
