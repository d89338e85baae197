"""The dataset format: the contract between blender_gen, train and eval (no bpy, no torch here).

```
DATASET/
  dataset.json        kind, resolution, seed, counts, software versions, recipe
  manifest.jsonl      one JSON object per finished sample, appended after its file is whole
  samples/000000.exr  one multi-layer half-float EXR per sample
  previews/           optional sRGB PNGs
```

Reading a set needs only NumPy and OpenEXR:

    from blender_gen.dataset import open_dataset
    ds = open_dataset("out/demo/pbr_eval")
    for sample in ds.samples(["rgb", "normal"]):   # checksums verified as each file is read
        sample["index"], sample["meta"]["car"]["name"], sample["rgb"].shape   # (H, W, 3) float32

Layers: `normal` (camera space, unit length, 0 off the object), `albedo`, `reflection` and `rgb`
(linear light), `mask` (coverage in [0, 1]) and `material` (integer part id) as float32 (H, W, C).
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import socket
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

FORMAT_VERSION = 1
LAYER_CHANNELS: dict[str, tuple[str, ...]] = {
    "normal": ("X", "Y", "Z"),
    "albedo": ("R", "G", "B"),
    "reflection": ("R", "G", "B"),
    "mask": ("Y",),
    "material": ("Y",),  # material id: 0 background, 1..18 part materials, 19 body paint
    "rgb": ("R", "G", "B"),
    "depth": ("Z",),  # metres along the camera's view axis; 0 on the background
    "part": ("Y",),  # part index: 0 background, k = PARTS[k - 1] (dataset.json "parts")
    "gloss": ("Y",),  # the part's glossiness (the reflection layer's weight); 0 on the background
    # PBR light transport (Cycles' passes, before denoising): on the car
    # rgb_noisy = diffuse_color x diffuse_shading + glossy + transmission + emission + environment
    "rgb_noisy": ("R", "G", "B"),
    "diffuse_color": ("R", "G", "B"),
    "diffuse_shading": ("R", "G", "B"),  # direct + indirect diffuse light
    "glossy": ("R", "G", "B"),  # glossy colour x (direct + indirect glossy light)
    "transmission": ("R", "G", "B"),  # transmission colour x (direct + indirect transmitted light)
    "emission": ("R", "G", "B"),
    "environment": ("R", "G", "B"),  # the environment seen directly (background, through glass)
}
# Layers every new intrinsics or PBR sample also holds; sets made before them have none, and
# their dataset.json lists what they hold ("layers")
EXTRA_LAYERS = ("depth", "part", "gloss")
LIGHT_LAYERS = ("rgb_noisy", "diffuse_color", "diffuse_shading", "glossy", "transmission", "emission", "environment")
KIND_EXTRA_LAYERS = {"intrinsics": EXTRA_LAYERS, "pbr": EXTRA_LAYERS + LIGHT_LAYERS}

KIND_LAYERS: dict[str, tuple[str, ...]] = {
    "intrinsics": ("normal", "albedo", "reflection", "mask", "material"),
    "pbr": ("rgb", "normal", "albedo", "reflection", "mask", "material"),
    "predictions": ("normal", "albedo", "reflection"),
}
INTRINSIC_LAYERS = ("normal", "albedo", "reflection")  # the 9-channel stack M, in this order


def recompose(layers: dict) -> np.ndarray:
    """A PBR sample's image from its light layers; equals `rgb_noisy` on the car (coverage 1)."""
    return (layers["diffuse_color"] * layers["diffuse_shading"] + layers["glossy"] + layers["transmission"]
            + layers["emission"] + layers["environment"])


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or of the wrong kind."""


class DatasetWriteError(DatasetError):
    """Writing failed (disk full, read-only folder, ...); nothing half-written was left."""


# --------------------------------------------------------------------------- files

def temp_name(path: Path) -> Path:
    """The hidden temporary a file is written under before it is renamed into place."""
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


def remove_temporaries(*folders: Path) -> None:
    """Delete the `temp_name` files of writes that never finished (a killed process leaves them).
    Call it only while holding the folders' lock: then no live writer owns one."""
    for folder in folders:
        for stale in Path(folder).glob(".*.tmp*"):
            try:
                stale.unlink(missing_ok=True)
            except OSError:  # a read-only folder: a later run removes it, and the caller's error must surface
                pass


def _write_failed(path: Path, tmp: Path, exc: BaseException) -> DatasetWriteError:
    """Remove the temporary and describe the failure in one line that names the file."""
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass
    why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).splitlines()[0] if str(exc) else repr(exc)
    return DatasetWriteError(f"cannot write {path}: {why}")


@contextmanager
def atomic_target(path: Path):
    """Yield a temporary path to write; on success it is fsynced and renamed over `path`.

    On any failure the temporary is removed and a one-line DatasetWriteError names `path`.
    """
    path = Path(path)
    tmp = temp_name(path)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except DatasetWriteError:
        tmp.unlink(missing_ok=True)
        raise
    except Exception as exc:  # OSError, or a library's own error type for a failed write
        raise _write_failed(path, tmp, exc) from exc
    except BaseException:  # Ctrl-C, SystemExit: still leave nothing behind
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a hidden temporary name in the same folder, fsync, then rename over `path`."""
    with atomic_target(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


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
    import OpenEXR  # imported where used: training on packed tensors reads no EXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_target(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def save_png(path: Path, image) -> None:
    """A PIL image or HxW(x3) uint8 array as a PNG, written atomically."""
    from PIL import Image

    img = image if isinstance(image, Image.Image) else Image.fromarray(np.asarray(image))
    with atomic_target(Path(path)) as tmp:
        img.save(tmp, format="PNG")


def read_exr_channels(path: Path) -> dict[str, np.ndarray]:
    """Every channel of every part of an EXR file, by its full name."""
    import OpenEXR

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

MAX_INDEX = 999_999  # six-digit sample file names; --count is capped at MAX_INDEX + 1 (the paper used 20,000)
_SHA256 = re.compile(r"[0-9a-f]{64}")


def sample_filename(index: int) -> str:
    return f"samples/{index:06d}.exr"


def check_row(row: object, where: str) -> dict:
    """A manifest row must name exactly its own sample file and carry its checksum.

    This is what keeps a manifest from pointing readers (or `merge`) at any other path:
    `file` is never joined to a folder unless it equals `sample_filename(index)`.
    """
    if not isinstance(row, dict):
        raise DatasetError(f"{where}: expected a JSON object, got {type(row).__name__}; the dataset is corrupt")
    index = row.get("index")
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index <= MAX_INDEX:
        raise DatasetError(f"{where}: 'index' must be an integer in [0, {MAX_INDEX}], got {index!r}; the dataset is corrupt")
    if row.get("file") != sample_filename(index):
        raise DatasetError(f"{where}: 'file' must be {sample_filename(index)!r} for sample {index}, got "
                           f"{row.get('file')!r}; the dataset is corrupt")
    sha = row.get("sha256")
    if not isinstance(sha, str) or not _SHA256.fullmatch(sha):
        raise DatasetError(f"{where}: 'sha256' must be 64 lowercase hex digits, got {sha!r}; the dataset is corrupt")
    return row


def read_manifest(path: Path) -> list[dict]:
    """Validated rows of a manifest, one per sample index (the last row of an index wins).

    A torn last line (a killed writer) is dropped; any other unreadable or invalid row
    makes the dataset corrupt (DatasetError naming the line).
    """
    path = Path(path)
    if not path.exists():
        return []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); the dataset is corrupt") from None
    by_index: dict[int, dict] = {}
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            if i == len(lines) - 1:
                break  # interrupted append: that sample is simply not finished
            raise DatasetError(f"{path}: line {i + 1} is not valid JSON ({exc})") from exc
        row = check_row(row, f"{path}: line {i + 1}")
        by_index.pop(row["index"], None)  # keep first-seen order of the survivors
        by_index[row["index"]] = row
    return list(by_index.values())


def append_manifest(path: Path, row: dict) -> None:
    """Append one row and fsync: a row exists only for a sample whose file is whole."""
    check_row(row, f"{path}: new row")
    try:
        with open(path, "a") as fh:
            fh.write(json.dumps(row, sort_keys=True) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        raise DatasetWriteError(f"cannot write {path}: {exc.strerror or exc}") from exc


def write_json_lines(path: Path, rows: list[dict]) -> None:
    """One JSON object per line, written atomically (manifests, training stats)."""
    atomic_write_bytes(Path(path), "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows).encode())


write_manifest = write_json_lines


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

    def load(self, i: int, layers: Iterable[str] | None = None, verify: bool = True) -> dict[str, np.ndarray]:
        """Sample i's layers; `verify` first checks the file against its manifest checksum (a
        valid EXR copied over another sample would otherwise be read as that sample). Hashing
        costs a few percent of decoding an EXR."""
        path = self.path(i)
        if verify and self.rows[i].get("sha256") and sha256_file(path) != self.rows[i]["sha256"]:
            raise DatasetError(f"{path}: checksum mismatch with {self.root / 'manifest.jsonl'} (sample "
                               f"{self.rows[i]['index']}): not the file the dataset recorded; `iae-gen inspect "
                               f"{self.root}` lists every bad sample, rerunning its generator redoes them")
        return read_exr(path, layers)

    def __iter__(self) -> Iterator[dict]:
        return iter(self.rows)

    @property
    def layers(self) -> tuple[str, ...]:
        """The layers every sample of this set holds (dataset.json's list; the kind's for older sets)."""
        listed = self.info.get("layers")
        return tuple(listed) if isinstance(listed, list) and listed else KIND_LAYERS[self.kind]

    def sample(self, i: int, layers: Iterable[str] | None = None, verify: bool = True) -> dict:
        """Sample i (by position) as a dict: "index" (its sample index), "meta" (its manifest row:
        car, paint, environment, camera, ...) and one float32 (H, W, C) array per layer."""
        return {"index": self.rows[i]["index"], "meta": self.rows[i], **self.load(i, layers, verify)}

    def samples(self, layers: Iterable[str] | None = None, verify: bool = True) -> Iterator[dict]:
        """Every sample in index order (`sample`), each file checked against its checksum as it is read."""
        wanted = list(layers) if layers is not None else None
        for i in range(len(self.rows)):
            yield self.sample(i, wanted, verify)

    def identity(self) -> dict:
        """What a set is, independent of where it lies: its kind, resolution, sample count and the
        digest of its manifest rows (each sample's file checksum and metadata). Two sets with equal
        identities hold the same samples; a set that grew, shrank or was regenerated differs."""
        digest = hashlib.sha256()
        for row in self.rows:
            digest.update(json.dumps(row, sort_keys=True).encode() + b"\n")
        return {"kind": self.kind, "resolution": list(self.info.get("resolution") or []), "count": len(self.rows),
                "complete": bool(self.info.get("complete")), "manifest_sha256": digest.hexdigest()}


def read_info(root: Path) -> dict:
    path = Path(root) / "dataset.json"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{root}: not a dataset (no dataset.json)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(info, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    return info


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


# --------------------------------------------------------------------------- writers

LOCK_NAME = ".lock"


def folder_is_empty(root: Path) -> bool:
    """True for a folder with nothing in it but (possibly) a writer's lock file."""
    return all(p.name == LOCK_NAME for p in Path(root).iterdir())


def lock_holder(root: Path) -> str | None:
    """Who holds the writer's lock on `root` now ("pid ... on HOST since ..."), or None: a reader's
    check that no generator is still writing the folder."""
    import fcntl

    path = Path(root) / LOCK_NAME
    if not path.exists():
        return None
    fd = os.open(path, os.O_RDONLY)
    try:
        return _try_lock(fd, fcntl.LOCK_SH)
    finally:
        os.close(fd)


def _try_lock(fd: int, mode: int) -> str | None:
    """Take `mode` on the lock file `fd` without waiting: None when taken, else who holds it (the
    holder's line in the file, or READERS when only readers hold it)."""
    import fcntl

    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
            raise
        if mode == fcntl.LOCK_EX and _try_lock(fd, fcntl.LOCK_SH) is None:
            fcntl.flock(fd, fcntl.LOCK_UN)  # only readers hold it: the line is the last writer's, long gone
            return READERS
        return os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
    return None


# What `_try_lock` reports when only readers (processes verifying the set) hold the folder.
READERS = "another process (checking its samples)"


@contextmanager
def locked_folder(root: Path, option: str = "--out", wait: Callable[[str], None] | None = None):
    """Hold an exclusive lock on a dataset folder while writing it.

    A second writer fails at once with a message naming the process that holds the lock, or,
    given `wait`, is told who holds it (`wait(holder)`) and blocks until it is free.
    The lock is an advisory `flock` on `ROOT/.lock`: the kernel releases it when the holder
    exits however it dies, so a killed run never leaves the folder locked.
    """
    import fcntl

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        holder = _try_lock(fd, fcntl.LOCK_EX)
        if holder is not None:
            if wait is not None:
                wait(holder)
                fcntl.flock(fd, fcntl.LOCK_EX)
            else:
                verb = "read" if holder == READERS else "written"
                raise DatasetError(f"{option} {root} is being {verb} by {holder}; "
                                   "wait for it to finish or choose another folder")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since "
                      f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
        yield root
    finally:
        os.close(fd)  # closing releases the lock


@contextmanager
def reading_folder(root: Path):
    """A reader's shared lock on a dataset folder: yields True while held, False (holding nothing)
    when a writer holds the folder. Readers do not exclude each other, nor `lock_holder`'s check,
    so a training can start on a set that another process is only verifying."""
    import fcntl

    path = Path(root) / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        yield _try_lock(fd, fcntl.LOCK_SH) is None
    finally:
        os.close(fd)


def verify_rows(root: Path, rows: list[dict]) -> tuple[list[dict], list[tuple[dict, str]]]:
    """Split rows into those whose file exists with the recorded sha256 and the others."""
    good, bad = [], []
    for row in rows:
        path = Path(root) / check_row(row, f"{root}: sample {row.get('index')!r}")["file"]
        if not path.exists():
            bad.append((row, "missing file"))
        elif sha256_file(path) != row["sha256"]:
            bad.append((row, "checksum mismatch"))
        else:
            good.append(row)
    return good, bad


class DatasetWriter:
    """The one writer of the format: dataset.json first (incomplete; the rows already finished
    when resuming are kept, a torn last line dropped), then per sample its EXR (atomic), its
    checksum and its manifest row, and at the end the count and `complete`.

    Used by the generator (whose worker processes write the EXRs: `append` their rows), by
    `decompose` and by the reference rows.
    """

    def __init__(self, root: Path, info: dict, rows: list[dict] | None = None):
        self.root = Path(root)
        (self.root / "samples").mkdir(parents=True, exist_ok=True)
        self.manifest = self.root / "manifest.jsonl"
        write_manifest(self.manifest, rows or [])
        self.info = {"format_version": FORMAT_VERSION, **info, "count": len(rows or []), "complete": False}
        atomic_write_json(self.root / "dataset.json", self.info)

    def add(self, index: int, layers: dict[str, np.ndarray], **row) -> dict:
        """Write a sample's EXR and append its row."""
        rel = sample_filename(index)
        write_exr(self.root / rel, layers)
        return self.append({"index": index, "file": rel, "sha256": sha256_file(self.root / rel), **row})

    def append(self, row: dict) -> dict:
        """Append the row of a sample whose file is already whole."""
        append_manifest(self.manifest, row)
        self.info["count"] += 1
        return row

    def finish(self, expected: int | None = None) -> dict:
        """Record the count (from the manifest as it is on disk) and whether all `expected` are there."""
        self.info["count"] = len(read_manifest(self.manifest))
        expected = self.info.get("count_requested", self.info["count"]) if expected is None else expected
        self.info["complete"] = self.info["count"] == expected
        atomic_write_json(self.root / "dataset.json", self.info)
        return self.info
