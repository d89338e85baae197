"""Textured triangles cut along their texture's edges (blender_gen/cars/texsplit.py), and what
that gives the labeller on a car whose windows are painted into one body texture."""
from __future__ import annotations

import numpy as np

from blender_gen.cars.labeller import FaceTable, agreement, face_normals, infer
from blender_gen.cars.texsplit import MIN_TEXELS, sample, split_by_texture


def _area(t: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=-1)


def _one(uv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv = np.array([uv], float)
    pos = np.concatenate([uv * 4.0, np.zeros((1, 3, 1))], axis=-1)  # a triangle in the xy plane
    return pos, np.tile([0.0, 0.0, 1.0], (1, 3, 1)), uv


def test_uniform_texture_and_small_triangles_are_left_whole():
    img = np.full((64, 64, 3), 0.7, np.float32)
    pos, nrm, uv = _one([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    p, n, u, src, _ = split_by_texture(pos, nrm, uv, img)
    assert len(p) == 1 and (src == 0).all() and np.array_equal(p, pos)
    img[:, 32:] = 0.0  # an edge, but under a triangle of fewer texels than the limit
    side = np.sqrt(2 * MIN_TEXELS * 0.5) / 64
    pos, nrm, uv = _one([[0.49, 0.2], [0.49 + side, 0.2], [0.49, 0.2 + side]])
    assert len(split_by_texture(pos, nrm, uv, img)[0]) == 1


def test_pieces_follow_the_edge_and_tile_the_triangle():
    img = np.full((64, 64, 3), 0.9, np.float32)
    img[:, :24] = 0.05  # black left of u = 0.375
    pos, nrm, uv = _one([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    p, n, u, src, _ = split_by_texture(pos, nrm, uv, img)
    assert len(p) > 16 and (src == 0).all()
    assert np.isclose(_area(p).sum(), _area(pos).sum())  # the pieces tile the triangle
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0)
    # a piece either sees one colour or is small: the mixed ones hug the edge
    col = sample(img, u.mean(1))[:, 0]
    centre_u = u.mean(1)[:, 0]
    assert (col[centre_u < 0.3] < 0.5).all() and (col[centre_u > 0.45] > 0.5).all()
    mixed = (u[:, :, 0].min(1) < 0.375 - 1e-9) & (u[:, :, 0].max(1) > 0.375 + 1e-9)  # straddle the edge
    assert _area(p[~mixed]).sum() > 0.9 * _area(pos).sum()
    again = split_by_texture(pos, nrm, uv, img)
    assert all(np.array_equal(a, b) for a, b in zip((p, n, u, src), again))  # deterministic


def _painted_box_car(split: bool, lower=None):
    """A box car (x along, z up) whose sides carry their windows in one body texture: white paint
    with a black band (the side windows) over the upper third of each side, mapped onto two large
    triangles per side as old game models do. Returns the table and the true windows mask."""
    img = np.full((128, 128, 3), 0.92, np.float32)
    # side region u in [0, 0.5]; the windows from v 0.62 to 0.92, pillars at the ends
    img[int(0.62 * 128):int(0.92 * 128), int(0.05 * 128):int(0.45 * 128)] = 0.04
    if lower is not None:  # the lower 30% of each side in another colour
        img[:int(0.3 * 128), :64] = lower
    lo, hi = np.array([-2.0, -0.9, 0.3]), np.array([2.0, 0.9, 1.5])
    tris, uvs = [], []
    for axis in range(3):
        for sign in (-1, 1):
            u_ax, v_ax = [k for k in range(3) if k != axis]
            if sign < 0:
                u_ax, v_ax = v_ax, u_ax
            base = np.where(np.arange(3) == axis, hi if sign > 0 else lo, 0.0)
            corners, cuv = [], []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                q = base.copy()
                q[u_ax], q[v_ax] = (lo, hi)[a][u_ax], (lo, hi)[b][v_ax]
                corners.append(q)
                # sides (normal along y): u from x, v from height; everything else in the plain half
                cuv.append([(q[0] - lo[0]) / 4.0 * 0.5, (q[2] - lo[2]) / 1.2] if axis == 1 else [0.75, 0.5])
            for i, j, k in ((0, 1, 2), (0, 2, 3)):
                tris.append([corners[i], corners[j], corners[k]])
                uvs.append([cuv[i], cuv[j], cuv[k]])
    tris, uvs = np.array(tris), np.array(uvs)
    fn = face_normals(tris)
    nrm = np.repeat(fn[:, None], 3, axis=1)
    if split:
        tris, nrm, uvs, _, _ = split_by_texture(tris, nrm, uvs, img)
    uv = uvs.mean(1)
    n = len(tris)
    table = FaceTable(tris=tris, normals=nrm, objects=np.full(n, "body", dtype=object),
                      materials=np.full(n, "atlas", dtype=object), uv=uv, colour=sample(img, uv).astype(float),
                      textured=np.ones(n, bool), alpha=np.ones(n), transmission=np.zeros(n), emission=np.zeros(n))
    z = tris[:, :, 2].mean(1)
    x = tris[:, :, 0].mean(1)
    truth = (np.abs(face_normals(tris)[:, 1]) > 0.9) & (z > 1.05) & (z < 1.4) & (np.abs(x) < 1.5)
    return table, truth


def test_windows_painted_into_a_body_texture_are_found_once_faces_are_cut():
    whole, _ = _painted_box_car(split=False)
    # two triangles per side cannot follow the band: whichever part a side's triangle gets, it
    # spans paint below the belt and glass above it
    called = whole.tris[infer(whole, forward="+X", up="+Z").labels == "windows"]
    assert len(called) == 0 or (called[:, :, 2].min(1) < 0.95).all()
    table, truth = _painted_box_car(split=True)
    lab = infer(table, forward="+X", up="+Z")
    areas = table.areas()
    win = lab.labels == "windows"
    assert agreement(win[truth], np.ones(truth.sum(), bool), areas[truth]) > 0.9  # the band is glass
    z = table.tris[:, :, 2].mean(1)
    assert not win[z < 0.95].any()  # and nothing below the belt is
    assert (lab.labels[(face_normals(table.tris)[:, 2] > 0.9)] == "body").all()  # the roof stays paint


def test_a_light_paints_baked_shading_is_paint_and_tinted_plastic_is_bumpers():
    for lower, part in (((0.55, 0.55, 0.55), "body"), ((0.45, 0.46, 0.54), "bumpers")):
        table, _ = _painted_box_car(split=True, lower=lower)
        lab = infer(table, forward="+X", up="+Z")
        z = table.tris[:, :, 2].mean(1)
        side_low = (np.abs(face_normals(table.tris)[:, 1]) > 0.9) & (z < 0.6)
        areas = table.areas()
        assert agreement(lab.labels[side_low], np.full(side_low.sum(), part, dtype=object), areas[side_low]) > 0.9, lower


def test_a_noise_texture_cannot_split_without_bound():
    rng = np.random.default_rng(0)
    img = rng.random((1024, 1024, 3))  # every texel another colour
    n = 200
    corners = rng.random((n, 3, 2))
    pos = np.concatenate([corners, np.zeros((n, 3, 1))], axis=-1)
    nrm = np.tile([0.0, 0.0, 1.0], (n, 3, 1))
    p, _, _, src, capped = split_by_texture(pos, nrm, corners, img, max_pieces=20_000)
    assert capped and len(p) <= 20_000 and set(src) == set(range(n))  # every source kept, fewer pieces
    _, _, _, _, capped = split_by_texture(pos[:2], nrm[:2], corners[:2], np.zeros((8, 8, 3)))
    assert not capped
