"""Inference with a trained run: R as a renderer, H as a decomposer writing datasets."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from blender_gen.conversions import from_network, preview_srgb8
from blender_gen.dataset import INTRINSIC_LAYERS, DatasetError, DatasetWriter, folder_is_empty, save_png
from .checkpoint import CheckpointError, load_ema, load_newest, load_weights, read_state
from .config import Config, config_from_dict
from .data import IntrinsicsData, RealImages
from .loop import _save_png, to_display
from .model import build_model
from .run_folder import RunFolder


def load_run_options(run_dir: Path) -> tuple[dict, Config]:
    """training_options.json of a run folder and its config, or a one-line error."""
    run = RunFolder(run_dir)
    opts = run.options()
    return opts, config_from_dict(opts["config"])


def load_run(run_dir: Path, device: str = "cpu", checkpoint: Path | None = None) -> tuple[Config, torch.nn.Module, int]:
    """Config and weights of a run folder (the newest checkpoint unless one is named)."""
    cfg, model, step, _ = load_run_checkpoint(run_dir, device, checkpoint)
    return cfg, model, step


def load_run_checkpoint(run_dir: Path, device: str = "cpu", checkpoint: Path | None = None, raw: bool = False
                        ) -> tuple[Config, torch.nn.Module, int, Path]:
    """`load_run` and the checkpoint file the weights came from.

    The generators' moving-average weights are used where the checkpoint has them (run.ema_decay;
    they probe better and steadier than the raw ones, docs/normals_from_shading.md), as StyleGAN
    uses G_ema; `raw` takes the weights the optimiser was training (for gradient diagnosis)."""
    run_dir = Path(run_dir)
    _, cfg = load_run_options(run_dir)
    model = build_model(cfg)
    if checkpoint:
        state, path = read_state(Path(checkpoint)), Path(checkpoint)
        load_weights(path, model)
    else:
        state, path, skipped = load_newest(RunFolder(run_dir).checkpoints, model)
        for why in skipped:
            print(f"skipped an unreadable checkpoint: {why}", file=sys.stderr)
        if state is None:
            raise CheckpointError(f"--run {run_dir}: no readable checkpoint yet (train it with `iae-train fit` first)")
    model.weights = "moving average" if not raw and load_ema(path, model) else "raw"
    return cfg, model.to(device).eval(), int(state["step"]), path


def _srgb_png(path: Path, t: torch.Tensor) -> None:
    """R's output is sRGB-encoded network space: write it as it is."""
    _save_png(path, to_display(t))


def fresh_output(out: Path) -> Path:
    """An output folder that is new or empty: results never mix with files already there."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or not folder_is_empty(out)):
        raise DatasetError(f"--out {out}: exists and is not an empty folder; choose a new folder")
    out.mkdir(parents=True, exist_ok=True)
    return out


@torch.no_grad()
def render_dataset(run_dir: Path, intrinsics: Path, out: Path, device: str = "cpu", batch: int = 4,
                   style_seed: int = 0, limit: int | None = None, progress: bool = True,
                   video: Path | None = None, side_by_side: bool = False, fps: float = 12.0,
                   force_video: bool = False, checkpoint: Path | None = None) -> list[Path]:
    """R applied to every sample of an intrinsics dataset: one sRGB PNG per sample.

    `checkpoint` pins the weights (default: the run's newest checkpoint). `video` also assembles the frames in sample order (a turntable's path) into an MP4 or GIF;
    `side_by_side` puts the intrinsics (normal, albedo, reflection) left of R's frame and, for a
    PBR dataset, Cycles' image right of it.
    """
    from .video import check_video_path, display, side_by_side as join, write_video

    if video is not None:
        from blender_gen.outputs import refuse_output

        check_video_path(video)
        refuse_output(video, "--video", force_video)  # checked before any frame is rendered
    cfg, model, _ = load_run(run_dir, device, checkpoint)
    data = IntrinsicsData(intrinsics, cfg.data.height, cfg.data.width)
    cycles = RealImages(intrinsics, cfg.data.height, cfg.data.width) if side_by_side and data.ds.kind == "pbr" else None
    n = len(data) if limit is None else min(limit, len(data))
    out = fresh_output(out)
    gen = torch.Generator().manual_seed(style_seed)
    written, frames = [], []
    for start in tqdm(range(0, n, batch), desc="render", unit="batch", disable=not progress):
        idx = list(range(start, min(n, start + batch)))
        m = torch.stack([data[(i, False)] for i in idx]).to(device)
        if video is None:
            imgs = model.render(m, generator=gen)
        else:  # one style code for every frame (MUNIT), so a video changes only with the camera
            imgs = torch.cat([model.render(x[None], generator=torch.Generator().manual_seed(style_seed)) for x in m])
        for i, img, stack in zip(idx, imgs, m):
            path = out / f"{data.ds.rows[i]['index']:06d}.png"
            _srgb_png(path, img)
            written.append(path)
            if video is not None:
                panels = [display(img)]
                if side_by_side:
                    panels = [display(stack[k:k + 3]) for k in (0, 3, 6)] + panels
                    if cycles is not None:
                        panels.append(display(cycles[(i, False)]))
                frames.append(join(panels) if len(panels) > 1 else panels[0])
    if video is not None:
        write_video(frames, video, fps)
    return written


@torch.no_grad()
def decompose_images(run_dir: Path, images: Path, out: Path, device: str = "cpu", batch: int = 4,
                     limit: int | None = None, progress: bool = True, checkpoint: Path | None = None,
                     h_at: str = "train", size: int | tuple[int, int] | None = None) -> Path:
    """H applied to photos or a PBR dataset, written as a `predictions` dataset (EXR + PNG previews).

    Predictions of a PBR dataset are resized back to its resolution and keep its sample
    indices, so `iae-eval decomposition --predictions` compares them pixel by pixel. `h_at`:
    "train" runs H on the images resized to its training size (the default: what it learned on),
    "native" at the PBR set's own resolution (H is fully convolutional; cars then appear larger
    than in training). `size` (photos only): the maps' size in photos/, as `train.photos.output_size`.
    """
    if h_at not in ("train", "native"):
        raise ValueError(f"h_at {h_at!r}: expected 'train' or 'native'")
    cfg, model, step = load_run(run_dir, device, checkpoint)
    reals = RealImages(images, cfg.data.height, cfg.data.width)
    if size is not None and reals.ds is not None:
        raise DatasetError(f"--size: {images} is a PBR set, whose predictions keep its resolution; --size is for photos")
    if h_at == "native" and reals.ds is not None:
        w, h = reals.ds.resolution
        reals = RealImages(images, h, w)
    n = len(reals) if limit is None else min(limit, len(reals))
    out = fresh_output(out)
    try:
        return _decompose_into(out, run_dir, images, cfg, model, step, reals, n, device, batch, limit, progress, size)
    except PhotosSkipped:  # the readable photos are written and complete; the error names the others
        raise
    except BaseException:  # a bad image mid-way: no half-written predictions that look like a result
        import shutil

        shutil.rmtree(out, ignore_errors=True)
        raise


@torch.no_grad()
def _decompose_photos(out: Path, writer: DatasetWriter, images: Path, cfg, model, reals, n: int, device: str,
                      progress: bool, size: int | tuple[int, int] | None) -> Path:
    """Photos one by one (their sizes differ): H on the whole photo, aspect kept (train.photos); the
    dataset's EXR sample is the training-size centre crop of those maps (what the dataset format
    and the scorer read); photos/ holds the maps at the photo's size, named after it, and a
    labelled panel per photo. An unreadable photo is skipped and named; the others go on."""
    from .data import cover_crop, resize
    from .photos import at_network_size, output_size, photo_names, write_gallery, write_photo_outputs

    gallery = out / "photos"
    gallery.mkdir()
    done = []
    # photos whose header could not be read (RealImages left them out), up to the last one used
    skipped = [{"file": str(p), "reason": why} for p, why in reals.unreadable
               if n == len(reals.files) or p < reals.files[n]]
    for s in skipped:
        tqdm.write(f"skipped: {s['reason']}", file=sys.stderr)
    names = photo_names(reals.files[:n], Path(images))
    for i in tqdm(range(n), desc="decompose", unit="photo", disable=not progress):
        path = reals.files[i]
        try:
            photo = torch.from_numpy(reals.load_photo(path)).permute(2, 0, 1).contiguous().float()
        except DatasetError as exc:
            skipped.append({"file": str(path), "reason": str(exc)})
            tqdm.write(f"skipped: {exc}", file=sys.stderr)
            continue
        img = at_network_size(photo, cfg.data.height, cfg.data.width).to(device)
        maps = model.decompose(img).float()
        rerender = model.reconstruct(img, maps) if hasattr(model, "reconstruct") else model.render(maps)
        name = names[i]
        native = resize(maps[0].cpu(), *output_size(*photo.shape[-2:]))  # the photo's size: the dataset's crop
        full = native if size is None else resize(maps[0].cpu(), *output_size(*photo.shape[-2:], size))
        write_photo_outputs(gallery, name, photo, full, rerender[0].cpu())
        crop = cover_crop(native, cfg.data.height, cfg.data.width)  # the same whatever --size asks for
        arr = crop.permute(1, 2, 0).cpu().numpy()
        layers = {k: from_network(k, arr[..., 3 * j:3 * j + 3]) for j, k in enumerate(INTRINSIC_LAYERS)}
        save_png(out / "previews" / f"{i:06d}.png",
                 np.concatenate([preview_srgb8(k, layers[k]) for k in INTRINSIC_LAYERS], axis=1))
        writer.add(i, layers, source=reals.source_name(i), photo=name)
        done.append((name, str(Path(path).relative_to(images) if Path(images).is_dir() else Path(path).name)))
    if not done:  # nothing to show: no folder that looks like a result
        raise DatasetError(f"--images {images}: none of its {len(skipped)} photo(s) could be read "
                           f"({skipped[0]['reason']})")
    write_gallery(gallery, done, f"H's decompositions of {Path(images).name}")
    writer.info.update(skipped=skipped, count_requested=len(done))
    writer.finish()
    if skipped:
        raise PhotosSkipped(out, skipped, len(done))
    return out


class PhotosSkipped(DatasetError):
    """Some photos could not be read: the others are decomposed and written; this names the rest."""

    def __init__(self, out: Path, skipped: list[dict], done: int):
        self.out, self.skipped, self.done = out, skipped, done
        names = ", ".join(Path(s["file"]).name for s in skipped[:3]) + (" ..." if len(skipped) > 3 else "")
        super().__init__(f"{len(skipped)} photo(s) could not be read and were skipped ({names}); the other {done} "
                         f"are in {out}")


@torch.no_grad()
def _decompose_into(out: Path, run_dir: Path, images: Path, cfg, model, step: int, reals, n: int, device: str,
                    batch: int, limit: int | None, progress: bool, size: int | tuple[int, int] | None = None) -> Path:
    (out / "previews").mkdir(exist_ok=True)
    if reals.ds is not None:
        src_w, src_h = reals.ds.resolution
    else:
        src_w, src_h = cfg.data.width, cfg.data.height
    # provenance: the scorer refuses predictions of another source set (recipe, and each image's checksum)
    writer = DatasetWriter(out, {
        "kind": "predictions", "resolution": [src_w, src_h], "count_requested": n, "source": str(Path(images).resolve()),
        "source_recipe": reals.ds.info.get("recipe") if reals.ds is not None else None, "limit": limit,
        "run": str(Path(run_dir).resolve()), "step": step, "model": cfg.model.kind, "config_name": cfg.name,
        "weights": getattr(model, "weights", "raw"), "layers": list(INTRINSIC_LAYERS),
        # H is fully convolutional; by default it runs at the size it trained at and its maps are resized back
        "network_size": [reals.w, reals.h]})
    if reals.ds is None:
        return _decompose_photos(out, writer, images, cfg, model, reals, n, device, progress, size)
    for start in tqdm(range(0, n, batch), desc="decompose", unit="batch", disable=not progress):
        idx = list(range(start, min(n, start + batch)))
        img = torch.stack([reals[(i, False)] for i in idx]).to(device)
        pred = model.decompose(img).float()
        if pred.shape[-2:] != (src_h, src_w):
            pred = F.interpolate(pred, size=(src_h, src_w), mode="bilinear", align_corners=False)
        for i, p in zip(idx, pred):
            arr = p.permute(1, 2, 0).cpu().numpy()
            layers = {k: from_network(k, arr[..., 3 * j:3 * j + 3]) for j, k in enumerate(INTRINSIC_LAYERS)}
            index = reals.ds.rows[i]["index"] if reals.ds is not None else i
            preview = np.concatenate([preview_srgb8(k, layers[k]) for k in INTRINSIC_LAYERS], axis=1)
            save_png(out / "previews" / f"{index:06d}.png", preview)
            source = {"source_sha256": reals.ds.rows[i]["sha256"]} if reals.ds is not None else {}
            writer.add(index, layers, source=reals.source_name(i), **source)
    writer.finish()
    return out
