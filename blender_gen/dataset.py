"""The dataset format: the contract between blender_gen, train and eval (no bpy here).

```
DATASET/
  dataset.json        kind, resolution, seed, counts, software versions, recipe
  manifest.jsonl      one JSON object per finished sample, appended after its file is whole
  samples/000000.exr  one multi-layer half-float EXR per sample
  previews/           optional sRGB PNGs
```
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import OpenEXR

FORMAT_VERSION = 1
LAYER_CHANNELS: dict[str, tuple[str, ...]] = {
    "normal": ("X", "Y", "Z"),
    "albedo": ("R", "G", "B"),
    "reflection": ("R", "G", "B"),
    "mask": ("Y",),
    "material": ("Y",),  # material id: 0 background, 1..18 part materials, 19 body paint
    "rgb": ("R", "G", "B"),
}
KIND_LAYERS: dict[str, tuple[str, ...]] = {
    "intrinsics": ("normal", "albedo", "reflection", "mask", "material"),
    "pbr": ("rgb", "normal", "albedo", "reflection", "mask", "material"),
    "predictions": ("normal", "albedo", "reflection"),
}
INTRINSIC_LAYERS = ("normal", "albedo", "reflection")  # the 9-channel stack M, in this order


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or of the wrong kind."""


# --------------------------------------------------------------------------- files

def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a hidden temporary name in the same folder, fsync, then rename over `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def atomic_write_json(path: Path, obj: object) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_exr(path: Path, layers: dict[str, np.ndarray], half: bool = True) -> None:
    """One multi-layer EXR (`layer.channel` names), written atomically.

    Half float by default, ZIP-compressed scanlines: readable by every EXR tool.
    """
    path = Path(path)
    channels: dict[str, np.ndarray] = {}
    dtype = np.float16 if half else np.float32
    for name, arr in layers.items():
        names = LAYER_CHANNELS[name]
        arr = np.asarray(arr)
        if arr.ndim == 2:
            arr = arr[..., None]
        if arr.shape[-1] != len(names):
            raise ValueError(f"layer {name!r}: expected {len(names)} channels, got shape {arr.shape}")
        for i, ch in enumerate(names):
            channels[f"{name}.{ch}"] = np.ascontiguousarray(arr[..., i].astype(dtype))
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with OpenEXR.File(header, channels) as f:
        f.write(str(tmp))
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def read_exr_channels(path: Path) -> dict[str, np.ndarray]:
    """Every channel of every part of an EXR file, by its full name."""
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
    except Exception as exc:  # OpenEXR raises bare exceptions for unreadable files
        raise DatasetError(f"{path}: not a readable EXR file ({exc})") from exc
    out: dict[str, np.ndarray] = {}
    with f:
        for part in f.parts:
            for name, ch in part.channels.items():
                out[name] = ch.pixels
    return out


def read_exr(path: Path, layers: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Layers of a sample as float32 (H, W, C) arrays."""
    chans = read_exr_channels(path)
    present = sorted({k.split(".")[0] for k in chans if "." in k})
    wanted = list(layers) if layers is not None else [n for n in LAYER_CHANNELS if n in present]
    out = {}
    for name in wanted:
        names = [f"{name}.{c}" for c in LAYER_CHANNELS[name]]
        missing = [n for n in names if n not in chans]
        if missing:
            raise DatasetError(f"{path}: missing channel(s) {missing} (layers present: {present})")
        out[name] = np.stack([chans[n].astype(np.float32) for n in names], axis=-1)
    return out


# --------------------------------------------------------------------------- manifest

def sample_filename(index: int) -> str:
    return f"samples/{index:06d}.exr"


def read_manifest(path: Path) -> list[dict]:
    """Rows of a manifest; a torn last line (a killed writer) is dropped, others are errors."""
    path = Path(path)
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    rows = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as exc:
            if i == len(lines) - 1:
                break  # interrupted append: that sample is simply not finished
            raise DatasetError(f"{path}: line {i + 1} is not valid JSON ({exc})") from exc
    return rows


def append_manifest(path: Path, row: dict) -> None:
    """Append one row and fsync: a row exists only for a sample whose file is whole."""
    with open(path, "a") as fh:
        fh.write(json.dumps(row, sort_keys=True) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def write_manifest(path: Path, rows: list[dict]) -> None:
    atomic_write_bytes(Path(path), "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows).encode())


# --------------------------------------------------------------------------- datasets

@dataclass
class Dataset:
    """A dataset directory opened for reading; rows sorted by sample index."""

    root: Path
    info: dict
    rows: list[dict]

    @property
    def kind(self) -> str:
        return self.info["kind"]

    @property
    def resolution(self) -> tuple[int, int]:
        w, h = self.info["resolution"]
        return int(w), int(h)

    def __len__(self) -> int:
        return len(self.rows)

    def path(self, i: int) -> Path:
        return self.root / self.rows[i]["file"]

    def load(self, i: int, layers: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        return read_exr(self.path(i), layers)

    def __iter__(self) -> Iterator[dict]:
        return iter(self.rows)


def read_info(root: Path) -> dict:
    path = Path(root) / "dataset.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{root}: not a dataset (no dataset.json)") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc


def open_dataset(root: Path, kinds: Iterable[str] | None = None) -> Dataset:
    """Open a dataset; `kinds` restricts which kinds are acceptable (clear error otherwise)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: no such dataset directory")
    info = read_info(root)
    kind = info.get("kind")
    if kind not in KIND_LAYERS:
        raise DatasetError(f"{root}/dataset.json: unknown kind {kind!r}; expected one of {sorted(KIND_LAYERS)}")
    if kinds is not None and kind not in set(kinds):
        raise DatasetError(f"{root}: dataset of kind {kind!r}, expected {' or '.join(sorted(kinds))}")
    rows = sorted(read_manifest(root / "manifest.jsonl"), key=lambda r: r["index"])
    return Dataset(root, info, rows)


def verify_rows(root: Path, rows: list[dict]) -> tuple[list[dict], list[tuple[dict, str]]]:
    """Split rows into those whose file exists with the recorded sha256 and the others."""
    good, bad = [], []
    for row in rows:
        path = Path(root) / row["file"]
        if not path.exists():
            bad.append((row, "missing file"))
        elif sha256_file(path) != row["sha256"]:
            bad.append((row, "checksum mismatch"))
        else:
            good.append(row)
    return good, bad
