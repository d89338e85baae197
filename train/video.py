"""Frames to a video file: MP4 (H.264 through imageio's bundled ffmpeg) or an animated GIF (Pillow)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from blender_gen.dataset import atomic_target

VIDEO_SUFFIXES = (".mp4", ".gif")


class VideoError(ValueError):
    """A video that cannot be written; names the option or file."""


def check_video_path(path: Path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise VideoError(f"--video {path}: expected a file ending in {' or '.join(VIDEO_SUFFIXES)}")
    return path


def display(t: torch.Tensor) -> np.ndarray:
    """A network-space (3, H, W) tensor in [-1, 1] -> (H, W, 3) uint8; sRGB colours stay as they are,
    normals show as (n + 1) / 2."""
    x = ((t.detach().float().clamp(-1, 1) + 1.0) * 127.5 + 0.5).to(torch.uint8)
    return x.permute(1, 2, 0).cpu().numpy()


def side_by_side(panels: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Panels of one height next to each other, separated by white columns."""
    h = panels[0].shape[0]
    sep = np.full((h, gap, 3), 255, np.uint8)
    out = []
    for k, p in enumerate(panels):
        out += [sep, p] if k else [p]
    return np.concatenate(out, axis=1)


def write_video(frames: list[np.ndarray], path: Path, fps: float = 12.0) -> Path:
    """Write uint8 (H, W, 3) frames atomically (a temporary name, then renamed)."""
    path = check_video_path(path)
    if not frames:
        raise VideoError(f"--video {path}: no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_target(path) as tmp:
        if path.suffix.lower() == ".gif":
            images = [Image.fromarray(f) for f in frames]
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                           duration=max(20, round(1000 / fps)), loop=0)
        else:
            import imageio_ffmpeg

            # H.264 in yuv420p needs even sides: pad by one row/column where needed
            h, w = frames[0].shape[:2]
            pad = ((0, h % 2), (0, w % 2), (0, 0))
            writer = imageio_ffmpeg.write_frames(str(tmp), (w + w % 2, h + h % 2), fps=fps, codec="libx264",
                                                 quality=8, pix_fmt_out="yuv420p", macro_block_size=1,
                                                 output_params=["-f", "mp4"])  # the temporary has no .mp4 suffix
            writer.send(None)
            try:
                for f in frames:
                    writer.send(np.ascontiguousarray(np.pad(f, pad, mode="edge")))
            finally:
                writer.close()
    return path
