"""Training data: intrinsics stacks M_s and real images I_r, in network space.

EXR decoding and photo resizing run in DataLoader worker processes. Which sample (and
whether it is flipped) a step sees is a pure function of (seed, stream, step, rank), so a
resumed run reads exactly the batches an uninterrupted one would.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch.utils.data import DataLoader, Dataset, Sampler

from blender_gen.conversions import to_network
from blender_gen.dataset import INTRINSIC_LAYERS, DatasetError, open_dataset

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff")
PHOTO_KINDS = ".jpg/.png/.webp/.bmp/.tif"  # IMAGE_SUFFIXES as messages name them
# photo formats Pillow does not read here (a phone's HEIC, cameras' raw files, AVIF, JPEG XL): a
# folder of them is named with what to do instead of seeming empty or smaller than it is
UNREAD_PHOTO_SUFFIXES = (".heic", ".heif", ".avif", ".jxl", ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf",
                         ".orf", ".rw2")


def set_identity(root: Path) -> dict:
    """What a training set is now: a dataset's Dataset.identity(), or for a photo folder the
    count and a digest of its file names and sizes. A run records it and compares on resume."""
    import hashlib

    root = Path(root)
    if (root / "dataset.json").exists():
        return open_dataset(root).identity()
    files = image_files(root)
    digest = hashlib.sha256()
    for f in files:  # names and sizes: hashing every photo's bytes would cost more than a resume
        digest.update(f"{f.relative_to(root)}\0{f.stat().st_size}\n".encode())
    return {"kind": "images", "count": len(files), "manifest_sha256": digest.hexdigest()}


def check_ready(root: Path, option: str) -> None:
    """Refuse a dataset that a generator is still writing or that stopped short of its count:
    training would see only the samples that happened to be there."""
    from blender_gen.dataset import lock_holder, read_info, read_manifest

    root = Path(root)
    if not (root / "dataset.json").exists():
        return
    holder = lock_holder(root)
    if holder is not None:
        raise DatasetError(f"{option} {root} is being written by {holder}; train once it has finished")
    info = read_info(root)
    n = len(read_manifest(root / "manifest.jsonl"))
    wanted = info.get("count_requested", n)
    # a shard's count_requested is the whole set's; its own `complete` says whether its part is done
    if info.get("complete") is False or (info.get("complete") is None and n < wanted):
        raise DatasetError(f"{option} {root}: incomplete ({n} of {wanted} samples); rerun its generator to finish "
                           "it (it resumes), then train")


def image_files(root: Path) -> list[Path]:
    """The photos (JPG, PNG, WebP, BMP, TIFF) under a folder (recursively), in a fixed order."""
    return sorted(p for p in Path(root).rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)


def unread_photos(root: Path) -> list[Path]:
    """The photos under a folder in formats that are not read here (HEIC, raw, ...), sorted."""
    root = Path(root)
    if not root.is_dir() or (root / "dataset.json").exists():
        return []
    return sorted(p for p in root.rglob("*") if p.suffix.lower() in UNREAD_PHOTO_SUFFIXES)


def unread_photos_summary(root: Path) -> str | None:
    """'N photo(s) in formats not read here (.heic; first NAME)' for a folder's unread photos, or None."""
    unread = unread_photos(root)
    if not unread:
        return None
    kinds = ", ".join(sorted({p.suffix.lower() for p in unread}))
    return f"{len(unread)} photo(s) in formats not read here ({kinds}; first {unread[0].name})"


def unread_photos_hint(root: Path) -> str:
    """What a 'no photos' error adds about a folder's unread photos: '; N photo(s) ...: convert them', or ''."""
    summary = unread_photos_summary(root)
    return f"; {summary}: convert them to JPG or PNG" if summary else ""


def unread_photos_note(root: Path, option: str) -> str | None:
    """One line naming the photos under `root` that are left out for their format, or None."""
    summary = unread_photos_summary(root)
    return f"note: {option} {root}: {summary} are left out; convert them to JPG or PNG to use them" if summary else None


def resize(t: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(C, H, W) -> (C, h, w); area averaging when shrinking, bilinear when growing."""
    if t.shape[1:] == (h, w):
        return t
    mode = "area" if t.shape[1] >= h and t.shape[2] >= w else "bilinear"
    kw = {} if mode == "area" else {"align_corners": False}
    return F.interpolate(t[None], size=(h, w), mode=mode, **kw)[0]


def cover_crop(t: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Scale (C, H, W) to cover h x w, keeping its aspect ratio, then cut out the centre.

    The one way an image becomes training size: photos, PBR renders and (for FID) generated
    images all pass through it, so an aspect ratio never changes a comparison by itself.
    """
    H, W = t.shape[1:]
    if (H, W) == (h, w):
        return t
    scale = max(h / H, w / W)
    t = resize(t, max(h, round(H * scale)), max(w, round(W * scale)))
    top, left = (t.shape[1] - h) // 2, (t.shape[2] - w) // 2
    return t[:, top:top + h, left:left + w].contiguous()


def flip_stack(m: torch.Tensor) -> torch.Tensor:
    """Mirror a 9-channel stack left-right; the normal's X component changes sign."""
    m = torch.flip(m, dims=[-1])
    m[..., 0, :, :] = -m[..., 0, :, :]
    return m


class LayerDataset(Dataset):
    """Any dataset of this project as a torch Dataset for one's own training code: item i is a dict
    with "index" and one (C, H, W) float32 tensor per layer, in the dataset's units (linear colour,
    unit normals) or, with `network=True`, in this trainer's network space ([-1, 1], sRGB colour).

        loader = DataLoader(LayerDataset("out/demo/pbr_eval", ["rgb", "normal"]), batch_size=8)
    """

    def __init__(self, root: Path, layers: list[str] | tuple[str, ...] | None = None, network: bool = False):
        self.ds = open_dataset(root)
        self.layers = tuple(layers) if layers is not None else self.ds.layers
        unknown = [k for k in self.layers if k not in self.ds.layers]
        if unknown:
            raise DatasetError(f"{root}: a {self.ds.kind} set has no layer(s) {unknown}; it has {list(self.ds.layers)}")
        self.network = network

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> dict:
        arrays = self.ds.load(i, self.layers)
        out: dict = {"index": self.ds.rows[i]["index"]}
        for k, a in arrays.items():
            a = to_network(k, a) if self.network and k != "material" else a
            out[k] = torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1).contiguous()
        return out


class IntrinsicsData(Dataset):
    """M_s = (normal, albedo, reflection) -> (9, H, W) in network space."""

    def __init__(self, root: Path, height: int, width: int):
        self.ds = open_dataset(root, kinds=("intrinsics", "pbr"))
        if len(self.ds) == 0:
            raise DatasetError(f"{root}: the intrinsics dataset has no finished samples")
        self.h, self.w = height, width

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, item: tuple[int, bool]) -> torch.Tensor:
        index, flip = item
        layers = self.ds.load(index, INTRINSIC_LAYERS)
        for k in INTRINSIC_LAYERS:  # NaN/inf would stop training as "non-finite loss" naming no file
            if not np.isfinite(layers[k]).all():
                raise DatasetError(f"{self.ds.path(index)}: layer {k!r} holds NaN or infinite values")
        stack = np.concatenate([to_network(k, layers[k]) for k in INTRINSIC_LAYERS], axis=-1)
        m = cover_crop(torch.from_numpy(stack).permute(2, 0, 1).contiguous(), self.h, self.w)
        return flip_stack(m) if flip else m


def photo_to_srgb01(img: Image.Image) -> np.ndarray:
    """Any image mode Pillow reads -> HxWx3 float32 sRGB values in [0, 1].

    `convert("RGB")` would clip 16-bit and 32-bit grey modes (a 16-bit grey PNG opens as I;16 or
    I with values up to 65535) to nearly all white; those are scaled by their own range instead.
    Alpha is dropped; palette, CMYK, YCbCr and 1-bit images convert as Pillow defines."""
    if img.mode.startswith("I;16") or img.mode == "I":
        grey = np.asarray(img, dtype=np.float64) / 65535.0
    elif img.mode == "F":
        grey = np.asarray(img, dtype=np.float64)
    else:
        return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
    return np.repeat(np.clip(grey, 0.0, 1.0)[..., None], 3, axis=-1).astype(np.float32)


def readable_photos(files: list[Path]) -> tuple[list[Path], list[tuple[Path, str]]]:
    """(photos whose header Pillow reads, [(photo, why) for the others]): a fast check (no decoding)
    that catches files that are not images, of an unknown format or decompression bombs."""
    good, bad = [], []
    for path in files:
        try:
            with Image.open(path):
                good.append(path)
        except (OSError, Image.DecompressionBombError, ValueError) as exc:
            bad.append((path, f"{path}: cannot read image ({exc})"))
    return good, bad


def skipped_photos_note(reals: "RealImages", option: str) -> str | None:
    """One line naming the photos a folder's reader left out, or None."""
    bad = reals.unreadable
    if not bad:
        return None
    more = ", ".join(p.name for p, _ in bad[1:4]) + (" ..." if len(bad) > 4 else "")
    return (f"{option}: skipped {len(bad)} photo(s) that could not be read ({bad[0][1]}"
            + (f"; also {more}" if more else "") + f"); using the other {len(reals)}")


def read_photo(path: Path) -> np.ndarray:
    """A photo as HxWx3 sRGB in [0, 1], upright as its EXIF orientation says (a phone stores a
    portrait shot as landscape pixels plus that tag); a one-line DatasetError names an unreadable
    or oversized file."""
    from PIL import ImageOps

    try:
        with Image.open(path) as img:
            return photo_to_srgb01(ImageOps.exif_transpose(img))
    except (OSError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot read image ({exc})") from None


class RealImages(Dataset):
    """I_r from a PBR dataset (its `rgb` layer) or a folder of photos (`image_files`) -> (3, H, W).

    Both are scaled to cover the training size and centre-cropped (`cover_crop`).
    """

    def __init__(self, root: Path, height: int, width: int):
        root = Path(root)
        self.h, self.w = height, width
        self.ds = None
        self.unreadable: list[tuple[Path, str]] = []
        if (root / "dataset.json").exists():
            self.ds = open_dataset(root, kinds=("pbr",))
            self.files: list[Path] = []
            n = len(self.ds)
        elif root.is_dir():
            # a photo whose header cannot be read is left out here, named in `unreadable`, so one
            # corrupt file neither stops a training nor shifts which photo an index means mid-run
            self.files, self.unreadable = readable_photos(image_files(root))
            n = len(self.files)
            if n == 0 and self.unreadable:
                path, why = self.unreadable[0]
                raise DatasetError(f"{root}: none of its {len(self.unreadable)} photo(s) could be read ({why})")
        else:
            raise DatasetError(f"{root}: no such folder of images or PBR dataset")
        if n == 0:
            raise DatasetError(f"{root}: no images found (expected a PBR dataset or {PHOTO_KINDS} photos)"
                               + unread_photos_hint(root))
        self._failed: set[int] = set()

    def __len__(self) -> int:
        return len(self.ds) if self.ds is not None else len(self.files)

    def source_name(self, index: int) -> str:
        return self.ds.rows[index]["file"] if self.ds is not None else str(self.files[index])

    def load_photo(self, path: Path) -> np.ndarray:
        return read_photo(path) * 2.0 - 1.0  # photos are already sRGB-encoded

    def _load_readable(self, index: int) -> np.ndarray:
        """Photo `index`, or where it fails to decode (a truncated file whose header reads), the next
        one that does: the same substitute every time, named once on stderr."""
        for k in range(len(self.files)):
            i = (index + k) % len(self.files)
            if i in self._failed:
                continue
            try:
                return self.load_photo(self.files[i])
            except DatasetError as exc:
                self._failed.add(i)
                print(f"skipped: {exc}; another photo takes its place", file=sys.stderr)
        raise DatasetError(f"{self.files[index].parent}: none of its photos could be decoded")

    def __getitem__(self, item: tuple[int, bool]) -> torch.Tensor:
        index, flip = item
        if self.ds is not None:
            rgb = self.ds.load(index, ["rgb"])["rgb"]
            if not np.isfinite(rgb).all():
                raise DatasetError(f"{self.ds.path(index)}: layer 'rgb' holds NaN or infinite values")
            arr = to_network("rgb", rgb)
        else:
            arr = self._load_readable(index)
        t = cover_crop(torch.from_numpy(arr).permute(2, 0, 1).contiguous(), self.h, self.w)
        return torch.flip(t, dims=[-1]) if flip else t


class StepSampler(Sampler):
    """Infinite batches of (index, flip); batch `s` depends only on (seed, stream, s, rank).

    Epochs are seeded permutations of the dataset; the global batch (all ranks) takes
    consecutive positions, each rank its own slice.
    """

    def __init__(self, n: int, batch: int, seed: int, stream: int, start_step: int = 0,
                 rank: int = 0, world: int = 1, hflip: bool = True):
        self.n, self.batch, self.seed, self.stream = n, batch, seed, stream
        self.start, self.rank, self.world, self.hflip = start_step, rank, world, hflip
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _epoch(self, e: int) -> tuple[np.ndarray, np.ndarray]:
        if e not in self._cache:
            rng = np.random.default_rng([self.seed, self.stream, e])
            self._cache = {e: (rng.permutation(self.n), rng.random(self.n) < 0.5)}
        return self._cache[e]

    def batch_at(self, step: int) -> list[tuple[int, bool]]:
        out = []
        for j in range(self.batch):
            pos = (step * self.world + self.rank) * self.batch + j
            perm, flips = self._epoch(pos // self.n)
            k = pos % self.n
            out.append((int(perm[k]), bool(flips[k]) and self.hflip))
        return out

    def __iter__(self) -> Iterator[list[tuple[int, bool]]]:
        step = self.start
        while True:
            yield self.batch_at(step)
            step += 1


def infinite_loader(ds: Dataset, sampler: StepSampler, workers: int) -> Iterator[torch.Tensor]:
    # A private generator: creating the iterator draws a base seed, which must not shift the
    # global RNG that training (style codes, image pool) uses and checkpoints restore.
    gen = torch.Generator().manual_seed(sampler.seed * 1000 + sampler.stream)
    loader = DataLoader(ds, batch_sampler=sampler, num_workers=workers, persistent_workers=workers > 0,
                        prefetch_factor=4 if workers > 0 else None, generator=gen)
    return iter(loader)


# --------------------------------------------------------------------------- training-size cache

def content_key(ds: Dataset) -> str:
    """What a dataset's training-size tensors depend on: its samples' checksums (EXR sets) or its
    photos' paths, sizes, inodes and modification and change times (a photo replaced by another of
    the same size and modification time has a new change time, which no tool can set back)."""
    import hashlib

    h = hashlib.sha256()
    inner = getattr(ds, "ds", None)
    if inner is not None:
        for row in inner.rows:
            h.update(f"{row['index']}:{row['sha256']};".encode())
    else:
        for p in ds.files:
            st = p.stat()
            h.update(f"{p.resolve()}:{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}:{st.st_ino};".encode())
    return h.hexdigest()


class CachedTensors(Dataset):
    """A dataset's unflipped training-size tensors decoded once into a memory-mapped .npy file
    (float32, so batches are bit-identical to decoding on the fly); flips are applied on read.

    The file is keyed by the content and the resolution (a .json beside it, written last), so a
    changed dataset or size rebuilds it, and a half-built file is never used. The cache is derived
    data: a damaged key or a truncated array costs a rebuild, not the run, and the temporary of a
    build that was killed is removed by the next (the run folder's lock makes it the only writer)."""

    def __init__(self, ds: Dataset, path: Path, stack: bool, progress: bool = False):
        from blender_gen.dataset import atomic_write_json, temp_name
        from tqdm import tqdm

        self.stack = stack
        path, meta = Path(path), Path(path).with_suffix(".json")
        sample = ds[(0, False)]
        key = {"content": content_key(ds), "shape": [len(ds), *sample.shape], "dtype": "float32"}
        for stale in path.parent.glob(f".{path.name}.tmp*"):  # a build killed before its rename
            stale.unlink(missing_ok=True)
        self.data = self._open(path, meta, key)
        if self.data is None:
            meta.unlink(missing_ok=True)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = temp_name(path)
            arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=tuple(key["shape"]))
            for i in tqdm(range(len(ds)), desc=f"cache {path.name}", unit="sample", disable=not progress):
                arr[i] = ds[(i, False)].numpy()
            arr.flush()
            del arr
            os.replace(tmp, path)
            atomic_write_json(meta, key)
            self.data = np.load(path, mmap_mode="r")

    @staticmethod
    def _open(path: Path, meta: Path, key: dict) -> np.ndarray | None:
        """The cached array if its key matches and it reads whole, else None (to be rebuilt)."""
        import json

        try:
            if json.loads(meta.read_text()) != key:
                return None
            data = np.load(path, mmap_mode="r")
        except (OSError, ValueError):  # missing, damaged key, truncated or corrupt array
            return None
        return data if list(data.shape) == key["shape"] and data.dtype == np.float32 else None

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, item: tuple[int, bool]) -> torch.Tensor:
        index, flip = item
        t = torch.from_numpy(np.array(self.data[index]))
        if not flip:
            return t
        return flip_stack(t) if self.stack else torch.flip(t, dims=[-1])


def cache_bytes(ds: Dataset, channels: int, height: int, width: int) -> int:
    return len(ds) * channels * height * width * 4
