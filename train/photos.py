"""Decompositions of a user's photos as people look at them: the whole photo (no crop), each map at
the photo's own size and named after it, and one labelled panel per photo with the input beside
H's maps and R's re-render of them.

H is fully convolutional, so it runs on the whole photo resized to about the pixel count it was
trained at, aspect ratio kept (sides rounded to a multiple of SIDE_MULTIPLE, which every
downsampling depth of the presets divides); its maps are then resized to the photo's size.
"""
from __future__ import annotations

import html
import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw

from blender_gen.conversions import from_network
from blender_gen.dataset import INTRINSIC_LAYERS as MAP_KEYS
from blender_gen.dataset import save_png, write_exr

from .data import resize
from .loop import to_display

SIDE_MULTIPLE = 16
MAX_SIDE = 2048  # outputs larger than this are scaled down (a 24-megapixel photo's maps are not needed)
PANEL_HEIGHT = 256
PANEL_LABELS = ("photo", "normal (H)", "albedo (H)", "reflection (H)", "R(H(photo))")


def network_size(h: int, w: int, train_h: int, train_w: int) -> tuple[int, int]:
    """(height, width) with about train_h * train_w pixels and the aspect ratio of h x w."""
    scale = (train_h * train_w / (h * w)) ** 0.5
    return (max(SIDE_MULTIPLE, round(h * scale / SIDE_MULTIPLE) * SIDE_MULTIPLE),
            max(SIDE_MULTIPLE, round(w * scale / SIDE_MULTIPLE) * SIDE_MULTIPLE))


def at_network_size(t: torch.Tensor, train_h: int, train_w: int) -> torch.Tensor:
    """(C, H, W) -> (1, C, h, w) at `network_size`: how H and R see a photo or a map of any size."""
    return resize(t, *network_size(*t.shape[-2:], train_h, train_w))[None]


def output_size(h: int, w: int, size: int | tuple[int, int] | None = None) -> tuple[int, int]:
    """(height, width) of a photo's maps: its own size (at most MAX_SIDE a side) by default; `size`
    an int: that longer side, aspect kept; a (width, height) pair: exactly that."""
    if isinstance(size, tuple):
        return size[1], size[0]
    scale = min(1.0, MAX_SIDE / max(h, w)) if size is None else size / max(h, w)
    return max(1, round(h * scale)), max(1, round(w * scale))


def parse_size(text: str | None) -> int | tuple[int, int] | None:
    """`--size`: None or 'photo' (each photo's own size), 'N' (longer side N) or 'WIDTHxHEIGHT'."""
    if text is None or text.strip().lower() == "photo":
        return None
    parts = text.lower().split("x")
    try:
        values = [int(v) for v in parts]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or min(values) < 1 or max(values) > 4 * MAX_SIDE:
        raise ValueError(f"--size {text!r}: expected photo, a longer side such as 1024, or WIDTHxHEIGHT such as "
                         f"640x480 (1 to {4 * MAX_SIDE} pixels a side)")
    return values[0] if len(values) == 1 else (values[0], values[1])


def photo_name(path: Path, root: Path) -> str:
    """A file-name-safe name for a photo, unique within its folder tree (sub/car.jpg -> sub__car)."""
    rel = Path(path).relative_to(root) if Path(root).is_dir() else Path(Path(path).name)
    return re.sub(r"[^A-Za-z0-9._-]+", "_", "__".join(rel.with_suffix("").parts))


OUTPUT_KEYS = ("normal", "albedo", "reflection", "render")


def photo_names(paths: list[Path], root: Path) -> list[str]:
    """`photo_name` of each photo, made unique across the list, so that no photo's files overwrite
    another's: car.jpg beside car.png, or a photo named like another's output (car_normal.jpg beside
    car.jpg), keep their suffix (car_jpg, car_png); a name still taken gets the photo's position."""
    from collections import Counter

    base = [photo_name(p, root) for p in paths]
    count = Counter(base)
    outputs = {f"{b}_{k}" for b in base for k in OUTPUT_KEYS}
    names = [f"{b}_{Path(p).suffix.lstrip('.').lower()}" if count[b] > 1 or b in outputs else b
             for b, p in zip(base, paths)]
    outputs = {f"{n}_{k}" for n in names for k in OUTPUT_KEYS}
    taken: set[str] = set()
    for i, n in enumerate(names):
        if n in taken or n in outputs:  # car.JPG beside car.jpg
            names[i] = n = f"{n}_{i}"
        taken.add(n)
    return names


def write_photo_outputs(folder: Path, name: str, photo: torch.Tensor, full: torch.Tensor,
                        rerender: torch.Tensor) -> Path:
    """NAME_normal/_albedo/_reflection/_render.png, the maps as NAME.exr and the labelled panel NAME.png. `photo` (3, H, W),
    `full`: H's maps (9, h, w) already at `output_size` of the photo, `rerender` (3, h', w'), network space."""
    h, w = full.shape[-2:]
    # interpolated normals are shorter than unit length: the picture shows them normalised
    tiles = {"normal": F.normalize(full[0:3].float(), dim=0), "albedo": full[3:6].float(),
             "reflection": full[6:9].float(), "render": resize(rerender.float(), h, w)}
    for key, t in tiles.items():  # OUTPUT_KEYS
        save_png(folder / f"{name}_{key}.png", to_display(t))
    # the maps in full precision and the datasets' units (linear colour; normals as H gives them)
    arr = full.float().permute(1, 2, 0).cpu().numpy()
    write_exr(folder / f"{name}.exr", {k: from_network(k, arr[..., 3 * j:3 * j + 3]) for j, k in enumerate(MAP_KEYS)})
    ph = PANEL_HEIGHT
    pw = max(1, round(w * ph / h))
    pictures = [resize(photo.float(), ph, pw)] + [resize(t, ph, pw) for t in tiles.values()]
    sheet = Image.new("RGB", (pw * len(pictures), 18 + ph), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c, (label, t) in enumerate(zip(PANEL_LABELS, pictures)):
        draw.text((c * pw + 4, 3), label, fill=(0, 0, 0))
        sheet.paste(Image.fromarray(to_display(t)), (c * pw, 18))
    panel = folder / f"{name}.png"
    save_png(panel, np.asarray(sheet))
    return panel


def write_gallery(folder: Path, entries: list[tuple[str, str]], title: str) -> Path:
    """index.html: every photo's panel with its source file name (entries: (name, source))."""
    rows = "\n".join(f'<figure><img src="{html.escape(n)}.png" alt="{html.escape(s)}"><figcaption>'
                     f'{html.escape(s)}</figcaption></figure>' for n, s in entries)
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>"
            "body{font-family:sans-serif;margin:16px} img{max-width:100%} figure{margin:0 0 18px}"
            f"</style></head><body><h1>{html.escape(title)}</h1>\n{rows}\n</body></html>\n")
    path = folder / "index.html"
    path.write_text(page, encoding="utf-8")
    return path
