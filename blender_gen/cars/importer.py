"""Import real car models (glTF/GLB, OBJ+MTL, .blend) as catalogue-like part meshes (bpy).

The model is read into Blender, every face is given a part by the rules (see `rules.py`),
and the result is normalised: forward axis to +X, up to +Z, centred on the origin, ground
at z = 0, scaled to the rules' length. The imported objects are then removed again; the
renderer builds its own part objects from the returned meshes, exactly as for
procedural cars. A .blend is appended through the library API, which never runs the
scripts or drivers a file may carry.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ..geometry import Mesh
from ..quiet import quiet_stdout
from ..cli_errors import first_line
from .rules import MODEL_SUFFIXES, SPLIT_PARTS, Rules, RulesError, face_part
_AXIS = {"+X": (0, 1.0), "-X": (0, -1.0), "+Y": (1, 1.0), "-Y": (1, -1.0), "+Z": (2, 1.0), "-Z": (2, -1.0)}


@dataclass
class ImportedModel:
    name: str
    category: str
    parts: dict[str, Mesh]
    face_counts: dict[str, int]
    unmatched: int  # faces that fell to the default part



BLEND_MAGICS = (b"BLENDER", b"\x1f\x8b", b"\x28\xb5\x2f\xfd")  # plain, gzip, zstd

def _read_objects(path: Path) -> list[bpy.types.Object]:
    before = set(bpy.data.objects)
    suffix = path.suffix.lower()
    bpy.context.preferences.filepaths.use_scripts_auto_execute = False
    with quiet_stdout(python_too=True):  # the glTF importer logs every node
        if suffix in (".glb", ".gltf"):
            bpy.ops.import_scene.gltf(filepath=str(path))
        elif suffix == ".obj":
            bpy.ops.wm.obj_import(filepath=str(path))
        elif suffix == ".blend":
            with open(path, "rb") as fh:
                magic = fh.read(7)
            if not magic.startswith(BLEND_MAGICS):
                raise RulesError(f"{path}: not a .blend file (no BLENDER header, nor a gzip/zstd-compressed one)")
            # Appending data blocks never executes text blocks, drivers or handlers.
            with bpy.data.libraries.load(str(path), link=False) as (src, dst):
                dst.objects = list(src.objects)
            coll = bpy.data.collections.new(f"import_{path.stem}")
            bpy.context.scene.collection.children.link(coll)
            for obj in dst.objects:
                if obj is not None:
                    coll.objects.link(obj)
        else:
            raise RulesError(f"{path}: unsupported model format; expected one of {MODEL_SUFFIXES}")
    return [o for o in bpy.data.objects if o not in before]


def _base_colour_image(mat) -> tuple[np.ndarray, int, int] | None:
    """The image feeding a material's base colour, as (H, W, 3) sRGB-encoded floats, v up."""
    if mat is None or mat.node_tree is None:
        return None
    for node in mat.node_tree.nodes:
        if node.type == "BSDF_PRINCIPLED" and node.inputs["Base Color"].is_linked:
            src = node.inputs["Base Color"].links[0].from_node
            if src.type == "TEX_IMAGE" and src.image is not None and src.image.size[0] > 0:
                img = src.image
                w, h = img.size
                px = np.empty(w * h * img.channels, dtype=np.float32)
                img.pixels.foreach_get(px)
                return px.reshape(h, w, img.channels)[..., :3], w, h
    return None


def _rotation(forward: str, up: str) -> np.ndarray:
    """Rows map model axes to the car frame: forward -> +X, up -> +Z, left = up x forward -> +Y."""
    f = np.zeros(3)
    f[_AXIS[forward][0]] = _AXIS[forward][1]
    u = np.zeros(3)
    u[_AXIS[up][0]] = _AXIS[up][1]
    return np.stack([f, np.cross(u, f), u])


def import_model(path: str | Path, rules: Rules) -> ImportedModel:
    path = Path(path)
    if not path.is_file():
        raise RulesError(f"--cars {path}: no such model file")
    settings = rules.settings_for(path)
    try:
        objects = _read_objects(path)
    except RuntimeError as exc:  # Blender's importers report a bad file as RuntimeError
        raise RulesError(f"{path}: cannot be imported ({first_line(exc)})") from None
    try:
        meshes = [o for o in objects if o.type == "MESH"]
        if not meshes:
            raise RulesError(f"{path}: no mesh objects in the file")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        tris, normals, labels, rule_hits = [], [], [], Counter()
        for obj in meshes:
            ev = obj.evaluated_get(depsgraph)
            me = ev.to_mesh()
            try:
                me.calc_loop_triangles()
                mw = np.array(obj.matrix_world)
                nm = np.linalg.inv(mw[:3, :3]).T
                co = np.empty(len(me.vertices) * 3, np.float32)
                me.vertices.foreach_get("co", co)
                co = co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]
                lnorm = np.empty(len(me.loops) * 3, np.float32)
                me.corner_normals.foreach_get("vector", lnorm)
                lnorm = lnorm.reshape(-1, 3) @ nm.T
                uv_layer = me.uv_layers.active
                uvs = None
                if uv_layer is not None:
                    uvs = np.empty(len(me.loops) * 2, np.float32)
                    uv_layer.data.foreach_get("uv", uvs)
                    uvs = uvs.reshape(-1, 2)
                images = [_base_colour_image(m) for m in me.materials]
                n_tri = len(me.loop_triangles)
                tri_loops = np.empty(n_tri * 3, np.int32)
                me.loop_triangles.foreach_get("loops", tri_loops)
                tri_loops = tri_loops.reshape(-1, 3)
                tri_verts = np.empty(n_tri * 3, np.int32)
                me.loop_triangles.foreach_get("vertices", tri_verts)
                tri_verts = tri_verts.reshape(-1, 3)
                tri_poly = np.empty(n_tri, np.int32)
                me.loop_triangles.foreach_get("polygon_index", tri_poly)
                poly_mat = np.empty(len(me.polygons), np.int32)
                me.polygons.foreach_get("material_index", poly_mat)
                poly_start = np.empty(len(me.polygons), np.int32)
                me.polygons.foreach_get("loop_start", poly_start)
                poly_total = np.empty(len(me.polygons), np.int32)
                me.polygons.foreach_get("loop_total", poly_total)
                decided: dict[int, object] = {}
                for t in range(n_tri):
                    p = int(tri_poly[t])
                    if p not in decided:
                        mi = int(poly_mat[p])
                        mat = me.materials[mi] if mi < len(me.materials) else None
                        uv = colour = None
                        if uvs is not None:
                            uv = uvs[poly_start[p]:poly_start[p] + poly_total[p]].mean(axis=0)
                            img = images[mi] if mi < len(images) else None
                            if img is not None:
                                arr, w, h = img
                                x = min(w - 1, int((uv[0] % 1.0) * w))
                                y = min(h - 1, int((uv[1] % 1.0) * h))
                                colour = arr[y, x]
                        decided[p] = face_part(rules, obj.name, mat.name if mat else None, uv, colour)
                    rule = decided[p]
                    rule_hits[rule.index if rule else 0] += 1
                    labels.append(rule.part if rule else settings.default_part)
                    tris.append(co[tri_verts[t]])
                    normals.append(lnorm[tri_loops[t]])
            finally:
                ev.to_mesh_clear()
    finally:
        _remove(objects)
    if sum(n for idx, n in rule_hits.items() if idx) == 0:
        raise RulesError(f"{path}: no rule of {rules.path} matched any face (all {len(labels)} faces would be "
                         f"'{settings.default_part}'); check the object names, materials or palette ranges")
    return _normalise(path, settings, np.array(tris), np.array(normals), np.array(labels, dtype=object),
                      rule_hits.get(0, 0))


def _normalise(path: Path, settings, tris: np.ndarray, normals: np.ndarray, labels: np.ndarray,
               unmatched: int) -> ImportedModel:
    rot = _rotation(settings.forward, settings.up)
    pts = tris.reshape(-1, 3) @ rot.T
    nrm = normals.reshape(-1, 3) @ rot.T
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = settings.length / max(hi[0] - lo[0], 1e-9)
    pts = (pts - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])) * scale
    pts = pts.reshape(-1, 3, 3)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-9)
    nrm = nrm.reshape(-1, 3, 3)
    # split parts that the rules leave to position and facing (windows, bumpers)
    centres = pts.mean(axis=1)
    face_n = np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0])
    face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-12)
    labels = labels.copy()
    win = labels == "windows"
    labels[win & (face_n[:, 0] > 0.35)] = "windshield"
    labels[win & (face_n[:, 0] < -0.35)] = "window_rear"
    labels[labels == "windows"] = "window_side"
    bump = labels == "bumpers"
    labels[bump & (centres[:, 0] >= 0)] = "bumper_front"
    labels[labels == "bumpers"] = "bumper_rear"
    parts = {}
    for part in sorted(set(labels)):
        ids = np.nonzero(labels == part)[0]
        faces = np.arange(3 * len(ids)).reshape(-1, 3)
        parts[part] = Mesh(pts[ids].reshape(-1, 3).astype(np.float64), faces, nrm[ids])
    counts = {k: int((labels == k).sum()) for k in parts}
    assert not set(parts) & set(SPLIT_PARTS)
    return ImportedModel(path.stem, settings.category, parts, counts, unmatched)


def _remove(objects: list[bpy.types.Object]) -> None:
    data = {o.data for o in objects if o.data is not None}
    for o in objects:
        bpy.data.objects.remove(o, do_unlink=True)
    for d in data:
        if isinstance(d, bpy.types.Mesh) and d.users == 0:
            bpy.data.meshes.remove(d)
    for coll in [c for c in bpy.data.collections if c.name.startswith("import_") and not c.objects]:
        bpy.data.collections.remove(coll)

