"""Mesh primitives in NumPy: lofts, lathes and superellipsoids.

Kept free of `bpy` so car shapes can be built, measured and tested without Blender;
`blender_gen.scene` turns the result into objects.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Mesh:
    """Vertices (N, 3) in metres and faces (F, k) as vertex indices (quads or triangles).

    `loop_normals` (F, k, 3), when set, are the normals a model's author gave each corner
    (imported models keep their own shading); otherwise shading is smooth.
    """

    verts: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    loop_normals: np.ndarray | None = None

    def extend(self, other: "Mesh") -> "Mesh":
        offset = len(self.verts)
        if len(self.faces) and self.faces.shape[1] != other.faces.shape[1]:
            raise ValueError("cannot join meshes of triangles and quads")
        if len(self.faces) == 0:
            self.loop_normals = other.loop_normals
        elif (self.loop_normals is None) != (other.loop_normals is None):
            raise ValueError("cannot join meshes with and without loop normals")
        elif self.loop_normals is not None:
            self.loop_normals = np.concatenate([self.loop_normals, other.loop_normals])
        self.verts = np.concatenate([self.verts, other.verts])
        self.faces = np.concatenate([self.faces, other.faces + offset]) if len(self.faces) else other.faces + offset
        return self

    def subset(self, face_ids: np.ndarray) -> "Mesh":
        """The faces `face_ids` with only the vertices they use."""
        faces = self.faces[face_ids]
        used, inverse = np.unique(faces, return_inverse=True)
        normals = None if self.loop_normals is None else self.loop_normals[face_ids]
        return Mesh(self.verts[used].copy(), inverse.reshape(faces.shape), normals)

    def flipped(self, mask: np.ndarray | None = None) -> "Mesh":
        """Reverse the winding of all faces, or of those where `mask` is true."""
        faces = self.faces.copy()
        sel = slice(None) if mask is None else mask
        faces[sel] = faces[sel][:, ::-1]
        return Mesh(self.verts, faces)

    def face_centroids(self) -> np.ndarray:
        return self.verts[self.faces].mean(axis=1)

    def face_normals(self) -> np.ndarray:
        """Area-weighted (Newell) normals, unit length; zero for degenerate faces."""
        p = self.verts[self.faces]
        q = np.roll(p, -1, axis=1)
        n = np.stack([
            np.sum((p[..., 1] - q[..., 1]) * (p[..., 2] + q[..., 2]), axis=1),
            np.sum((p[..., 2] - q[..., 2]) * (p[..., 0] + q[..., 0]), axis=1),
            np.sum((p[..., 0] - q[..., 0]) * (p[..., 1] + q[..., 1]), axis=1),
        ], axis=1)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.where(length > 1e-12, n / np.maximum(length, 1e-12), 0.0)


def loft(rings: np.ndarray) -> Mesh:
    """Quads between consecutive closed rings (S, K, 3); ring k wraps to 0.

    Rings that shrink to a point or a line at the ends close the surface without caps.
    Vertex order makes normals point outward for rings ordered counter-clockwise when
    seen from the direction the sections advance toward.
    """
    s, k, _ = rings.shape
    i, j = np.meshgrid(np.arange(s - 1), np.arange(k), indexing="ij")
    a = (i * k + j).ravel()
    b = (i * k + (j + 1) % k).ravel()
    faces = np.stack([a, b, b + k, a + k], axis=1)
    return Mesh(rings.reshape(-1, 3).astype(np.float64), faces)


def superellipse(k: int, exponent: float) -> np.ndarray:
    """K points (y, z) on the unit superellipse |y|^n + |z|^n = 1, counter-clockwise."""
    theta = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    e = 2.0 / exponent
    return np.stack([np.sign(c) * np.abs(c) ** e, np.sign(s) * np.abs(s) ** e], axis=1)


def superellipsoid(center, size, exponent: float = 4.0, segments: int = 12) -> Mesh:
    """A rounded box: |x/a|^n + |y/b|^n + |z/c|^n <= 1, with half sizes `size`/2."""
    cx, cy, cz = center
    a, b, c = (0.5 * float(v) for v in size)
    lat = np.linspace(-np.pi / 2, np.pi / 2, segments + 1)
    e = 2.0 / exponent

    def sp(t):
        return np.sign(t) * np.abs(t) ** e

    rings = []
    for phi in lat:
        ring = superellipse(2 * segments, exponent)  # (y, z) profile reused as (x, y) around
        scale = sp(np.cos(phi))
        rings.append(np.stack([
            cx + a * scale * ring[:, 0],
            cy + b * scale * ring[:, 1],
            np.full(len(ring), cz + c * sp(np.sin(phi))),
        ], axis=1))
    return loft(np.asarray(rings))


def lathe(profile: np.ndarray, segments: int, center, axis_sign: float = 1.0) -> Mesh:
    """Revolve a (radius, axial) profile about the Y axis through `center`.

    `axis_sign` mirrors the axial coordinate, so one profile serves left and right wheels.
    """
    cx, cy, cz = center
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    rings = []
    for r, a in profile:
        rings.append(np.stack([
            cx + r * np.cos(angles),
            np.full(segments, cy + axis_sign * a),
            cz + r * np.sin(angles),
        ], axis=1))
    mesh = loft(np.asarray(rings))
    return mesh.flipped() if axis_sign < 0 else mesh  # mirroring flips the winding


def smooth_profile(xs: np.ndarray, points: list[tuple[float, float]], passes: int = 2, width: int = 3) -> np.ndarray:
    """Piecewise-linear profile through `points`, evaluated at `xs` and box-filtered.

    The filter rounds the kinks (cowl, roof edges) so that smooth shading has no creases.
    """
    px, pz = zip(*points)
    z = np.interp(xs, px, pz)
    kernel = np.ones(2 * width + 1) / (2 * width + 1)
    for _ in range(passes):
        padded = np.pad(z, width, mode="edge")
        z = np.convolve(padded, kernel, mode="valid")
    return z
