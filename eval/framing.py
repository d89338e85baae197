"""How much of the frame the car fills in a set of photos: the framing the synthetic cameras match.

Photos frame a car far tighter than the paper's camera rule does (cameras 3.5-8 m away, the car
covering as little as 8% of the frame). H trained on such photos with loosely framed intrinsics
learns to draw a small car in the middle of every photo, so the own-data command estimates the
photos' framing first and draws the synthetic cameras to match (`iae-gen --min-coverage
--max-coverage`).

The estimate: each photo is brought to the training frame exactly as the trainer does it (scaled
to cover, centre-cropped; `train.data.cover_crop`) at 128x64, OpenCV's GrabCut separates the car
from a rectangle 3% inside the border, and the largest foreground component's bounding box over
the frame is the photo's coverage. No learned weights, deterministic (OpenCV's RNG is seeded).
On a PBR set, whose material layer gives the true coverage, `iae-eval framing` prints the estimate's error
beside it (docs/evaluation.md, "Framing").
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator

import numpy as np

if TYPE_CHECKING:
    from PIL import Image

# the frame the estimate works in: the training aspect ratio, small enough for about 0.1 s a photo
ESTIMATE_SIZE = (64, 128)  # height, width
MARGIN = 0.03  # GrabCut's rectangle: this fraction of each side is background
LIMIT = 200  # photos read at most, spread evenly over the sorted names
PERCENTILES = (10, 90)  # the coverage range the synthetic cameras draw from


@dataclass(frozen=True)
class Framing:
    """Coverage of the car's bounding box per photo, and the range the synthetic cameras use."""

    coverages: tuple[float, ...]
    skipped: tuple[str, ...]  # unreadable photos, named
    low: float
    high: float

    def describe(self) -> str:
        c = np.asarray(self.coverages)
        return (f"the car fills {100 * np.median(c):.0f}% of the frame in the median photo, "
                f"{100 * self.low:.0f}-{100 * self.high:.0f}% from the {PERCENTILES[0]}th to the "
                f"{PERCENTILES[1]}th percentile ({len(c)} photos, GrabCut at {ESTIMATE_SIZE[1]}x{ESTIMATE_SIZE[0]}"
                + (f"; {len(self.skipped)} unreadable skipped" if self.skipped else "") + ")")

    def gen_options(self) -> list[str]:
        """The `iae-gen` options that draw cameras with this framing."""
        return ["--min-coverage", f"{self.low:.2f}", "--max-coverage", f"{self.high:.2f}"]


def to_frame(rgb01: np.ndarray, size: tuple[int, int] = ESTIMATE_SIZE) -> np.ndarray:
    """HxWx3 sRGB in [0, 1] -> the training frame at `size` as uint8, cropped as the trainer crops."""
    import torch

    from train.data import cover_crop

    t = cover_crop(torch.from_numpy(np.ascontiguousarray(rgb01, dtype=np.float32)).permute(2, 0, 1), *size)
    return (t.permute(1, 2, 0).numpy().clip(0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (inclusive pixels)


def mask_box(mask: np.ndarray) -> Box | None:
    """The bounding box of a boolean mask's True pixels (None when there are none)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())


def box_coverage(box: Box | None, shape: tuple[int, ...]) -> float:
    """The fraction of an HxW frame a box covers."""
    if box is None:
        return 0.0
    return (box[2] - box[0] + 1) * (box[3] - box[1] + 1) / (shape[0] * shape[1])


def car_box(frame: np.ndarray) -> Box | None:
    """The estimated box of the car in one HxWx3 uint8 frame (None when GrabCut finds nothing)."""
    import cv2

    h, w = frame.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    mx, my = max(1, round(MARGIN * w)), max(1, round(MARGIN * h))
    background, foreground = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut's colour models start from a k-means with random centres
    try:
        cv2.grabCut(frame, mask, (mx, my, w - 2 * mx, h - 2 * my), background, foreground, 5,
                    cv2.GC_INIT_WITH_RECT)
    except cv2.error:  # a frame of one flat colour: nothing to separate
        return None
    car = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(car, connectivity=8)
    if n <= 1:
        return None
    return mask_box(labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])))


def photo_coverage(frame: np.ndarray) -> float:
    """The estimated coverage of the car in one HxWx3 uint8 frame (0 when GrabCut finds nothing)."""
    return box_coverage(car_box(frame), frame.shape)


def coverage_range(coverages: list[float] | np.ndarray) -> tuple[float, float]:
    """The synthetic cameras' range from the photos' coverages: the 10th to 90th percentile, kept
    within 0.05-0.9 (the car whole in the frame) and at least 0.1 wide."""
    lo, hi = (float(v) for v in np.percentile(np.asarray(coverages, dtype=np.float64), PERCENTILES))
    lo, hi = max(0.05, lo), min(0.9, hi)
    if hi - lo < 0.1:
        mid = min(max(0.5 * (lo + hi), 0.1), 0.85)
        lo, hi = mid - 0.05, mid + 0.05
    return round(lo, 2), round(hi, 2)


def spread(items: list, limit: int = LIMIT) -> list:
    """At most `limit` items spread evenly over the list (all of them when there are fewer)."""
    if len(items) <= limit:
        return list(items)
    return [items[round(k * (len(items) - 1) / (limit - 1))] for k in range(limit)]


def photo_frames(photos: list[Path], limit: int, progress: bool) -> Iterator[tuple[str, np.ndarray | None]]:
    """(name, frame or None when unreadable) for up to `limit` photos spread over the sorted list."""
    from tqdm import tqdm

    from blender_gen.dataset import DatasetError
    from train.data import read_photo

    for path in tqdm(spread(sorted(photos), limit), desc="framing", unit="photo", disable=not progress):
        try:
            yield str(path), to_frame(read_photo(path))
        except DatasetError:
            yield str(path), None


Boxed = tuple[str, np.ndarray, Box | None, Box | None]  # name, frame, estimated box, true box (None: unknown)


def measure(frames: Iterable[tuple[str, np.ndarray | None, Box | None]], total: int) -> tuple[Framing, list[Boxed]]:
    """The framing of (name, frame or None when unreadable, true box or None) items, and each
    readable frame with its estimated and true boxes; unreadable ones are skipped and named. A
    one-line ValueError when none of the `total` images can be read."""
    boxed, skipped = [], []
    for name, frame, truth in frames:
        if frame is None:
            skipped.append(name)
        else:
            boxed.append((name, frame, car_box(frame), truth))
    if not boxed:
        shown = ", ".join(skipped[:3]) + (f" and {len(skipped) - 3} more" if len(skipped) > 3 else "")
        raise ValueError(f"no readable photo among {total} to estimate the framing from (unreadable: {shown})")
    coverages = [box_coverage(box, frame.shape) for _, frame, box, _ in boxed]
    return Framing(tuple(coverages), tuple(skipped), *coverage_range(coverages)), boxed


def estimate_framing(photos: list[Path], limit: int = LIMIT, progress: bool = True) -> Framing:
    """The framing of a list of photo files (`measure`)."""
    return measure(((name, frame, None) for name, frame in photo_frames(photos, limit, progress)), len(photos))[0]


def pbr_frames(root: Path, limit: int = LIMIT, progress: bool = True) -> Iterator[tuple[str, np.ndarray, Box | None]]:
    """(name, frame, true box) of a PBR set's images: the estimator checked where the answer is known."""
    from tqdm import tqdm

    from blender_gen.conversions import linear_to_srgb
    from blender_gen.dataset import open_dataset

    ds = open_dataset(Path(root), kinds=("pbr",))
    for i in tqdm(spread(list(range(len(ds))), limit), desc="framing", unit="image", disable=not progress):
        s = ds.load(i, ["rgb", "material"])
        # the car is every pixel with a part material: the mask layer leaves out glass (it shows
        # what is behind), while the cameras and a person count windows and glass roofs as the car
        car = (s["material"][..., 0] > 0).astype(np.float32)
        car = np.repeat(car[..., None], 3, axis=-1)
        yield ds.rows[i]["file"], to_frame(linear_to_srgb(s["rgb"][..., :3])), mask_box(to_frame(car)[..., 0] >= 128)


def contact_sheet(items: list[Boxed], columns: int = 4,
                  scale: int = 2) -> Image.Image:
    """Frames with the estimated box (red) and, where known, the true one (green), labelled with
    their coverages: what the estimate saw, for a person to check."""
    from PIL import Image, ImageDraw

    h, w = items[0][1].shape[:2]
    cw, ch = w * scale, h * scale + 14
    rows = -(-len(items) // columns)
    sheet = Image.new("RGB", (columns * cw, rows * ch), "white")
    draw = ImageDraw.Draw(sheet)
    for k, (name, frame, est, truth) in enumerate(items):
        x, y = (k % columns) * cw, (k // columns) * ch
        sheet.paste(Image.fromarray(frame).resize((w * scale, h * scale), Image.NEAREST), (x, y))
        label = f"est {box_coverage(est, frame.shape):.2f}"
        for box, colour in ((truth, (0, 200, 0)), (est, (230, 0, 0))):
            if box is not None:
                draw.rectangle([x + box[0] * scale, y + box[1] * scale, x + (box[2] + 1) * scale - 1,
                                y + (box[3] + 1) * scale - 1], outline=colour, width=2)
        if truth is not None:
            label += f"  true {box_coverage(truth, frame.shape):.2f}"
        draw.text((x + 2, y + h * scale + 1), f"{Path(name).name[:18]}  {label}", fill="black")
    return sheet
