"""Split textured triangles along their texture's edges, so that faces can be labelled by colour.

Older game and simulator models (Gazebo's SUV, hatchback, ambulance) paint windows, lamps and
trim into one body texture over a few large triangles: one triangle of a door can carry the
door, its window and the sill. A part is one colour per face, so the labeller and palette rules
can only be as fine as the faces. Here a triangle whose texture varies strongly and covers many
texels is cut in four (midpoints of its corners, normals and UVs), recursively, until each piece
sees one colour or is a few texels small (faces whose name already decides their part, such as
wheels, only twice: enough to part tyre from rim). Palette models (Kenney's: every face inside one flat
swatch) are left untouched. Pure numpy; deterministic.
"""
from __future__ import annotations

import numpy as np

MIN_TEXELS = 24.0  # a piece covering fewer texels than this is not split further
CONTRAST = 0.3  # sRGB range (largest channel) within a piece above which it is split
MAX_DEPTH = 5  # at most 4**5 pieces per authored triangle
NAMED_DEPTH = 2  # for faces whose name decides their part (wheels, glass): tyre from rim, not the tread
# at most this many pieces per call: a noise texture over a fine mesh would otherwise split every
# triangle to the full depth (2,000 triangles under 1024x1024 noise: 2 million faces, 5.6 GB)
MAX_PIECES = 200_000

# barycentric sample points: near the corners, the edge midpoints, the centre and between
_B = np.array([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8], [0.45, 0.45, 0.1], [0.1, 0.45, 0.45],
               [0.45, 0.1, 0.45], [1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.2, 0.6, 0.2], [0.2, 0.2, 0.6]])


def sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel of an (h, w, c) image (row 0 at v = 0, as Blender stores pixels) at UVs (..., 2)."""
    h, w = img.shape[:2]
    x = np.minimum(w - 1, ((uv[..., 0] % 1.0) * w).astype(int))
    y = np.minimum(h - 1, ((uv[..., 1] % 1.0) * h).astype(int))
    return img[y, x]


def _mixed(cuv: np.ndarray, img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    texels = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) * w * h
    big = texels > MIN_TEXELS
    out = np.zeros(len(cuv), bool)
    if big.any():
        pts = np.einsum("sk,nkd->nsd", _B, cuv[big])  # (n, samples, 2)
        col = sample(img, pts)[..., :3]
        out[big] = (col.max(1) - col.min(1)).max(-1) > CONTRAST
    return out


def _split4(a: np.ndarray) -> np.ndarray:
    """(n, 3, d) corners -> (4n, 3, d): the three corner triangles and the middle one, per input."""
    m01, m12, m20 = (a[:, 0] + a[:, 1]) / 2, (a[:, 1] + a[:, 2]) / 2, (a[:, 2] + a[:, 0]) / 2
    out = np.stack([np.stack([a[:, 0], m01, m20], 1), np.stack([m01, a[:, 1], m12], 1),
                    np.stack([m20, m12, a[:, 2]], 1), np.stack([m01, m12, m20], 1)], 1)
    return out.reshape(-1, 3, a.shape[-1])


def split_by_texture(pos: np.ndarray, nrm: np.ndarray, cuv: np.ndarray, img: np.ndarray,
                     max_depth: int = MAX_DEPTH, max_pieces: int = MAX_PIECES
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Triangles (n, 3, 3) positions, corner normals and (n, 3, 2) corner UVs over an image ->
    the same for the pieces, plus each piece's source triangle index (pieces of one source are
    adjacent and in a fixed order; a source left whole is one piece), and whether splitting stopped
    early at the level that would have exceeded `max_pieces`."""
    src = np.arange(len(pos))
    keep_p, keep_n, keep_uv, keep_src = [], [], [], []
    kept, capped = 0, False
    for level in range(max_depth + 1):
        split = _mixed(cuv, img) if level < max_depth else np.zeros(len(cuv), bool)
        if kept + (~split).sum() + 4 * split.sum() > max_pieces and split.any():
            split, capped = np.zeros(len(cuv), bool), True
        kept += int((~split).sum())
        keep_p.append(pos[~split]), keep_n.append(nrm[~split]), keep_uv.append(cuv[~split]), keep_src.append(src[~split])
        if not split.any():
            break
        pos, cuv, src = _split4(pos[split]), _split4(cuv[split]), np.repeat(src[split], 4)
        nrm = _split4(nrm[split])
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    src = np.concatenate(keep_src)
    order = np.argsort(src, kind="stable")
    return (np.concatenate(keep_p)[order], np.concatenate(keep_n)[order], np.concatenate(keep_uv)[order], src[order],
            capped)
