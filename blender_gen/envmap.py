"""Environment maps: the built-in procedural HDR sky, and the equirectangular lookup.

Arrays here are (H, W, 3) float32, row 0 at the top (zenith), linear HDR. The lookup
follows Blender's Environment Texture convention exactly, so `reflection_reference`
reproduces what the renderer's shader computes (tests compare the two).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

PROCEDURAL_PREFIX = "procedural:"
DEFAULT_SKY_VARIANTS = 8  # "procedural" (= "procedural:train"): variants 0..7, the training skies
HELDOUT_SKY_VARIANTS = 4  # "procedural:heldout": variants 8..11, skies no training intrinsics reflect
PROCEDURAL_SETS = ("procedural", "procedural:train", "procedural:heldout")


def direction_to_uv(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blender's equirectangular mapping; u right, v up (v = 1 at the zenith)."""
    d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    u = 0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2.0 * np.pi)
    v = 0.5 + np.arcsin(np.clip(d[..., 2], -1.0, 1.0)) / np.pi
    return u, v


def uv_to_direction(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, v = np.broadcast_arrays(u, v)
    phi = (0.5 - u) * 2.0 * np.pi
    theta = (v - 0.5) * np.pi
    return np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], axis=-1)


def sample_equirect(env: np.ndarray, d: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """Bilinear lookup of `env` along world directions `d` (..., 3).

    The map is turned by `rotation_deg` about +Z (content at azimuth a moves to a + rotation).
    Pixel centres sit at (i + 0.5) / W as in Blender; u wraps, v clamps.
    """
    h, w, _ = env.shape
    d = np.asarray(d)
    u, v = direction_to_uv(d if d.dtype == np.float32 else d.astype(np.float64))
    u = u + rotation_deg / 360.0  # the map turned by +rotation about +Z: azimuth a reads a - rotation
    x = (u * w - 0.5).ravel()
    y = ((1.0 - v) * h - 0.5).ravel()  # rows run top-down here
    xf, yf = np.floor(x), np.floor(y)
    fx, fy = (x - xf).astype(np.float32)[:, None], (y - yf).astype(np.float32)[:, None]
    x0, y0 = xf.astype(np.intp), yf.astype(np.intp)
    xa, xb = x0 % w, (x0 + 1) % w
    ya, yb = np.clip(y0, 0, h - 1) * w, np.clip(y0 + 1, 0, h - 1) * w
    flat = np.asarray(env, dtype=np.float32).reshape(h * w, -1)
    texel = lambda i: np.take(flat, i, axis=0)  # noqa: E731  (3x faster than fancy indexing)
    top = texel(ya + xa)
    top += (texel(ya + xb) - top) * fx
    bot = texel(yb + xa)
    bot += (texel(yb + xb) - bot) * fx
    top += (bot - top) * fy
    return top.reshape(*d.shape[:-1], flat.shape[-1])


def reflect(view: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror the view ray (camera -> surface) about the unit normal."""
    return view - 2.0 * np.sum(view * normal, axis=-1, keepdims=True) * normal


def _periodic_noise(rng: np.random.Generator, h: int, w: int, cells_x: int, cells_y: int) -> np.ndarray:
    """Smooth value noise, periodic in azimuth, in [0, 1]."""
    grid = rng.random((cells_y + 1, cells_x))
    y = np.linspace(0, cells_y, h, endpoint=False) + 0.5 * cells_y / h
    x = np.linspace(0, cells_x, w, endpoint=False)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    y1, x1 = np.minimum(y0 + 1, cells_y), (x0 + 1) % cells_x
    g = grid
    top = g[y0][:, x0] * (1 - fx) + g[y0][:, x1] * fx
    bot = g[y1][:, x0] * (1 - fx) + g[y1][:, x1] * fx
    return top * (1 - fy[:, None]) + bot * fy[:, None]


def _fbm(rng: np.random.Generator, h: int, w: int, base: int, octaves: int = 4) -> np.ndarray:
    out, amp, total = np.zeros((h, w)), 1.0, 0.0
    for o in range(octaves):
        cells = base * 2**o
        out += amp * _periodic_noise(rng, h, w, cells, max(cells // 2, 2))
        total += amp
        amp *= 0.5
    return out / total


def procedural_sky(variant: int, width: int = 1024, height: int = 512) -> np.ndarray:
    """A deterministic outdoor HDR sky: sun, sky gradient, clouds, skyline and ground.

    The skyline (buildings and trees around the horizon) and cloud structure give the
    reflections something to show; the sun makes highlights. Same variant, same pixels.
    """
    rng = np.random.default_rng([20201125, variant])
    v = 1.0 - (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    d = uv_to_direction(u[None, :], v[:, None])
    elev = np.arcsin(np.clip(d[..., 2], -1, 1))
    azim = np.arctan2(d[..., 1], d[..., 0])

    sun_az = rng.uniform(-np.pi, np.pi)
    sun_el = np.deg2rad(rng.uniform(12.0, 60.0))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    cos_sun = np.clip(d @ sun, -1.0, 1.0)
    ang = np.arccos(cos_sun)

    warm = rng.uniform(0.0, 1.0)
    zenith = np.array([0.18, 0.32, 0.75]) * rng.uniform(0.7, 1.2)
    horizon = np.array([0.85, 0.85, 0.9]) + warm * np.array([0.25, 0.05, -0.2])
    t = np.clip(elev / (np.pi / 2), 0, 1)[..., None] ** 0.5
    sky = horizon * (1 - t) + zenith * t
    sky = sky + (np.exp(-ang / 0.35) * 1.5)[..., None] * np.array([1.0, 0.9, 0.7])  # glow
    cover = rng.uniform(0.2, 0.7)
    clouds = np.clip((_fbm(rng, height, width, 6) - (1 - cover)) * 3.0, 0, 1)[..., None]
    sky = sky * (1 - clouds) + clouds * np.array([1.1, 1.1, 1.12]) * (0.6 + 0.6 * np.clip(cos_sun, 0, 1))[..., None]
    disk = (ang < np.deg2rad(1.6)).astype(np.float64)
    sky = sky + disk[..., None] * 400.0 * np.array([1.0, 0.95, 0.85])

    # Skyline: blocks of buildings and tree lines with a random height per azimuth step.
    steps = rng.integers(40, 90)
    heights = np.deg2rad(rng.uniform(1.0, 16.0, steps)) * (rng.random(steps) < 0.8)
    idx = ((azim + np.pi) / (2 * np.pi) * steps).astype(int) % steps
    shade = rng.uniform(0.05, 0.35, steps)[idx]
    tint = np.array([0.9, 1.0, 0.85]) if rng.random() < 0.5 else np.array([1.0, 0.95, 0.9])
    texture = 0.7 + 0.6 * _fbm(rng, height, width, 64, 2)
    blocks = (elev >= 0) & (elev < heights[idx])
    sky = np.where(blocks[..., None], (shade * texture)[..., None] * tint, sky)

    ground_col = np.array([0.16, 0.15, 0.14]) if rng.random() < 0.6 else np.array([0.10, 0.16, 0.07])
    ground = ground_col * (0.6 + 0.8 * _fbm(rng, height, width, 32, 3))[..., None]
    ground = ground * (1.0 + 1.5 * max(np.sin(sun_el), 0.1))
    sky = np.where((elev < 0)[..., None], ground, sky)
    return sky.astype(np.float32)


def sky_cache_dir() -> Path | None:
    """Where built skies are kept between processes and runs: $IAE_CACHE_DIR (``none`` turns the
    cache off), else $XDG_CACHE_HOME or ~/.cache, under intrinsic-autoencoders/skies."""
    root = os.environ.get("IAE_CACHE_DIR")
    if root is not None and root.strip().lower() in ("", "none", "off"):
        return None
    if root is None:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "intrinsic-autoencoders")
    return Path(root) / "skies"


# the cache key: this module's source, so a change to the sky (or the lookup) never reads old pixels
_SOURCE_KEY = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]


def _remove_dead_temporaries(folder: Path) -> None:
    """Delete the temporaries of writers that died before their rename (a sky is 6 MB); a live
    writer's file stays, and one deleted by mistake only costs that writer its cache entry."""
    for tmp in folder.glob(".sky*.tmp"):
        try:
            pid = int(tmp.name.split(".")[-2])
        except ValueError:  # not a name this module writes
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except (PermissionError, OverflowError):  # another user's live process; not a pid
            pass


def cached_procedural_sky(variant: int, width: int = 1024, height: int = 512) -> np.ndarray:
    """`procedural_sky`, built once per machine rather than once per worker process (about 1 s
    each, 8 per worker otherwise): the same array, bit for bit. A missing, unreadable or wrong-shaped
    cache file is rebuilt; a cache that cannot be written is skipped."""
    folder = sky_cache_dir()
    path = folder / f"sky{variant}_{width}x{height}_{_SOURCE_KEY}.npy" if folder is not None else None
    if path is not None:
        try:
            arr = np.load(path, allow_pickle=False)
            if arr.shape == (height, width, 3) and arr.dtype == np.float32:
                return arr
        except (OSError, ValueError, EOFError):
            pass
    arr = procedural_sky(variant, width, height)
    if path is not None:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _remove_dead_temporaries(folder)
            with open(tmp, "wb") as fh:
                np.save(fh, arr, allow_pickle=False)
            os.replace(tmp, path)  # readers see the whole file or none
        except OSError:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
    return arr


def view_rays(cam_to_world: np.ndarray, focal_px: float, height: int, width: int,
              dtype: type = np.float64) -> np.ndarray:
    """(H, W, 3) unit world directions of a pinhole camera's rays through the pixel centres;
    `cam_to_world` is the 3x3 rotation whose columns are the camera's right, up and back axes."""
    xs = (np.arange(width) + 0.5) - 0.5 * width
    ys = 0.5 * height - (np.arange(height) + 0.5)
    ray_cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], -focal_px), axis=-1).astype(dtype)
    ray_cam /= np.linalg.norm(ray_cam, axis=-1, keepdims=True)
    return ray_cam @ np.asarray(cam_to_world, dtype=dtype).T


def background_lookup(cam_to_world: np.ndarray, focal_px: float, height: int, width: int,
                      env: np.ndarray, rotation_deg: float) -> np.ndarray:
    """(H, W, 3) the environment seen directly along each pixel's view ray: what Cycles'
    Environment pass shows, without a world to render (the intrinsics' environment background)."""
    return sample_equirect(env, view_rays(cam_to_world, focal_px, height, width, np.float32), rotation_deg)


def reflection_reference(normal_cam: np.ndarray, cam_to_world: np.ndarray, focal_px: float,
                         env: np.ndarray, rotation_deg: float, gloss: np.ndarray) -> np.ndarray:
    """NumPy reference of the `reflection` layer for a pinhole camera.

    `normal_cam` (H, W, 3) is in camera space (OpenGL: +Z toward the camera) as stored in the
    dataset; `cam_to_world` is the 3x3 rotation whose columns are the camera's right, up and
    back axes in world space; `gloss` (H, W) the glossiness per pixel.
    """
    h, w, _ = normal_cam.shape
    view = view_rays(cam_to_world, focal_px, h, w)
    n = normal_cam.astype(np.float64) @ cam_to_world.T
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    r = reflect(view, n)
    return sample_equirect(env, r, rotation_deg) * gloss[..., None]
