"""Read a car model's faces into plain arrays (bpy): geometry plus the evidence parts are told by.

One row per triangle: its corners and corner normals (model space, after the importer's own
axis conversion), the object and material it belongs to, the material's transparency,
transmission and emission, its base colour, the UV centroid and the texture colour under it.
The rules (`rules.py`) and the automatic labeller (`labeller.py`) both work on this table,
so a rules file and `--car-rules auto` see exactly the same faces.
"""
from __future__ import annotations

import sys
from pathlib import Path

import bpy
import numpy as np

from ..cli_errors import first_line
from ..quiet import quiet_stdout, without_lines
from ..recipe import texture_by_name
from .labeller import FaceTable, infer, named_part
from .rules import MODEL_SUFFIXES, RulesError, base_name
from .texsplit import MAX_DEPTH, MAX_PIECES, NAMED_DEPTH, sample, split_by_texture
from .wheels import place_wheel_files, take

BLEND_MAGICS = (b"BLENDER", b"\x1f\x8b", b"\x28\xb5\x2f\xfd")  # plain, gzip, zstd


def read_objects(path: Path) -> list[bpy.types.Object]:
    before = set(bpy.data.objects)
    suffix = path.suffix.lower()
    bpy.context.preferences.filepaths.use_scripts_auto_execute = False
    with quiet_stdout(python_too=True):  # the glTF importer logs every node
        if suffix in (".glb", ".gltf"):
            try:
                bpy.ops.import_scene.gltf(filepath=str(path))
            except RuntimeError as exc:  # the operator reports a Ctrl-C inside its Python as a failed import
                if "KeyboardInterrupt" in str(exc):
                    raise KeyboardInterrupt from None
                raise
        elif suffix == ".obj":
            # The importer says "Failed to open dir" for each texture it cannot find beside the .mtl
            # (Gazebo packages keep them in ../materials/textures/, or name them model://...);
            # `_find_texture` looks them up, and `_read_files` names any that stay missing.
            with without_lines("Failed to open dir"):
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


def remove_objects(objects: list[bpy.types.Object]) -> None:
    data = {o.data for o in objects if o.data is not None}
    for o in objects:
        bpy.data.objects.remove(o, do_unlink=True)
    for d in data:
        if isinstance(d, bpy.types.Mesh) and d.users == 0:
            bpy.data.meshes.remove(d)
    for coll in [c for c in bpy.data.collections if c.name.startswith("import_") and not c.objects]:
        bpy.data.collections.remove(coll)


def _file_name(img) -> str:
    """The file name an image datablock names (its path may be relative to the .blend, '//')."""
    return Path(bpy.path.abspath(img.filepath)).name


def _find_texture(img, model: Path):
    """The image itself, or, where the importer could not find its file, the file of that name that
    `recipe.texture_by_name` finds (the one the recipe's identity hashes)."""
    if img.packed_file is not None or img.source != "FILE" or img.size[0] > 0:
        return img
    found = texture_by_name(_file_name(img), model)
    return bpy.data.images.load(str(found), check_existing=True) if found else img


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def _material_info(mat, model: Path) -> dict:
    """Base colour (sRGB), texture pixels, alpha, transmission and emission of a material."""
    info = {"name": base_name(mat.name) if mat else "", "image": None, "base": np.full(3, np.nan),
            "alpha": 1.0, "transmission": 0.0, "emission": 0.0}
    if mat is None:
        return info
    info["alpha"] = float(getattr(mat, "alpha", 1.0)) if not mat.use_nodes else 1.0
    if mat.node_tree is None:
        info["base"] = _linear_to_srgb(np.array(mat.diffuse_color[:3], dtype=np.float64))
        return info
    for node in mat.node_tree.nodes:
        if node.type != "BSDF_PRINCIPLED":
            continue
        inp = node.inputs
        info["base"] = _linear_to_srgb(np.array(inp["Base Color"].default_value[:3], dtype=np.float64))
        # an alpha linked to a texture (OBJ importers wire every RGBA map so) says nothing by itself
        info["alpha"] = float(inp["Alpha"].default_value) if not inp["Alpha"].is_linked else 1.0
        if "Transmission Weight" in inp:
            info["transmission"] = float(inp["Transmission Weight"].default_value)
        if "Emission Strength" in inp and "Emission Color" in inp:
            col = np.array(inp["Emission Color"].default_value[:3])
            info["emission"] = float(inp["Emission Strength"].default_value) * float(col @ [0.2126, 0.7152, 0.0722])
        if inp["Base Color"].is_linked:
            src = inp["Base Color"].links[0].from_node
            if src.type == "TEX_IMAGE" and src.image is not None:
                img = _find_texture(src.image, model)
                if img.size[0] == 0:
                    info["missing"] = _file_name(img) or img.name
                else:
                    w, h = img.size
                    px = np.empty(w * h * img.channels, dtype=np.float32)
                    img.pixels.foreach_get(px)
                    info["image"] = px.reshape(h, w, img.channels)[..., :3]  # 8-bit images: as encoded (sRGB)
        break
    return info


def read_car(paths: list[Path], forward: str | None = None, up: str | None = None) -> tuple[FaceTable, list[str]]:
    """The faces of one car (one file, or a body and its wheel files), imported objects removed.
    Wheel files modelled at the origin are put into the body's arches (`wheels.py`), in the frame
    given or, failing that, the body's inferred one. Returns the table and what was placed."""
    table, objects, file_index = _read_files(paths)
    remove_objects(objects)
    if len(paths) == 1:
        return table, []
    body = np.nonzero(file_index == 0)[0]
    if len(body) == 0:
        raise RulesError(f"{paths[0]}: the body file (the first of '+') has no mesh faces")
    sizes = []
    for k, p in enumerate(paths):
        own = table.tris[file_index == k].reshape(-1, 3)
        if len(own) == 0:
            raise RulesError(f"{p}: a wheel file (after '+') with no mesh faces")
        sizes.append(float(np.prod(np.ptp(own, axis=0) + 1e-9)))
    if max(sizes[1:]) > sizes[0]:
        big = paths[1 + int(np.argmax(sizes[1:]))]
        raise RulesError(f"{'+'.join(str(p) for p in paths)}: {big} is larger than the first file, {paths[0]}; the "
                         "body comes first, then its wheel files")
    if forward is None or up is None:
        lab = infer(take(table, body), forward=forward, up=up)
        forward, up = lab.forward, lab.up
    return place_wheel_files(table, file_index, [p.name for p in paths], forward, up)


def read_faces(paths: list[Path]) -> tuple[FaceTable, list[bpy.types.Object]]:
    """Import every file (one car, possibly several files) and tabulate its triangles as they are
    authored. Returns the imported objects too; the caller removes them (`remove_objects`)."""
    table, objects, _ = _read_files(paths)
    return table, objects


def _read_files(paths: list[Path]) -> tuple[FaceTable, list[bpy.types.Object], np.ndarray]:
    objects: list[bpy.types.Object] = []
    rows: dict[str, list] = {k: [] for k in ("tris", "normals", "objects", "materials", "uv", "colour", "textured",
                                             "alpha", "transmission", "emission")}
    file_index: list[np.ndarray] = []
    try:
        for k, path in enumerate(paths):
            try:
                new = read_objects(path)
            except RuntimeError as exc:  # Blender's importers report a bad file as RuntimeError
                raise RulesError(f"{path}: cannot be imported ({first_line(exc)})") from None
            objects += new
            depsgraph = bpy.context.evaluated_depsgraph_get()
            before = sum(len(t) for t in rows["tris"])
            missing: set[str] = set()
            for obj in (o for o in new if o.type == "MESH"):
                missing |= _read_mesh(obj, depsgraph, path, rows)
            if missing:
                print(f"warning: {path}: texture(s) {', '.join(sorted(missing))} not found below the model's folder "
                      f"or the one above it; those faces keep their material's base colour", file=sys.stderr)
            file_index.append(np.full(sum(len(t) for t in rows["tris"]) - before, k))
    except BaseException:
        remove_objects(objects)
        raise
    if not rows["tris"]:
        remove_objects(objects)
        raise RulesError(f"{', '.join(map(str, paths))}: no mesh objects in the file")
    cat = {k: np.concatenate(v) for k, v in rows.items()}
    return FaceTable(**cat), objects, np.concatenate(file_index)


def _read_mesh(obj, depsgraph, path: Path, rows: dict[str, list]) -> set[str]:
    """Appends the object's triangles to `rows`; returns the names of textures its materials name but
    that could not be found."""
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        me.calc_loop_triangles()
        n_tri = len(me.loop_triangles)
        if n_tri == 0:
            return set()
        mw = np.array(obj.matrix_world)
        nm = np.linalg.inv(mw[:3, :3]).T
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]
        lnorm = np.empty(len(me.loops) * 3, np.float32)
        me.corner_normals.foreach_get("vector", lnorm)
        lnorm = lnorm.reshape(-1, 3) @ nm.T
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
        pos, nrm = co[tri_verts], lnorm[tri_loops]
        # the polygon's UV centroid (as the rules have always used), per triangle
        uv = np.full((n_tri, 2), np.nan)
        cuv = None
        uv_layer = me.uv_layers.active
        if uv_layer is not None:
            uvs = np.empty(len(me.loops) * 2, np.float32)
            uv_layer.data.foreach_get("uv", uvs)
            uvs = uvs.reshape(-1, 2).astype(np.float64)
            cuv = uvs[tri_loops]
            csum = np.concatenate([np.zeros((1, 2)), np.cumsum(uvs, axis=0)])
            p = tri_poly
            uv = (csum[poly_start[p] + poly_total[p]] - csum[poly_start[p]]) / poly_total[p][:, None]
        infos = [_material_info(m, path) for m in me.materials] or [_material_info(None, path)]
        mi = np.minimum(poly_mat[tri_poly], len(infos) - 1)
        if cuv is not None:  # textured triangles cut along their texture's edges (texsplit.py)
            pos, nrm, uv, mi = _cut_textured(pos, nrm, cuv, uv, mi, infos, base_name(obj.name))
            n_tri = len(pos)
        colour = np.full((n_tri, 3), np.nan)
        textured = np.zeros(n_tri, bool)
        for k, info in enumerate(infos):
            sel = mi == k
            if not sel.any():
                continue
            colour[sel] = info["base"]
            img = info["image"]
            if img is not None:
                ok = sel & np.isfinite(uv[:, 0])
                colour[ok] = sample(img, uv[ok])
                textured[ok] = True
        rows["tris"].append(pos)
        rows["normals"].append(nrm)
        rows["objects"].append(np.full(n_tri, base_name(obj.name), dtype=object))
        rows["materials"].append(np.array([infos[k]["name"] for k in mi], dtype=object))
        rows["uv"].append(uv)
        rows["colour"].append(colour)
        rows["textured"].append(textured)
        for key in ("alpha", "transmission", "emission"):
            rows[key].append(np.array([infos[k][key] for k in mi], dtype=np.float64))
        return {infos[k]["missing"] for k in set(mi.tolist()) if "missing" in infos[k]}
    finally:
        ev.to_mesh_clear()


def _cut_textured(pos: np.ndarray, nrm: np.ndarray, cuv: np.ndarray, uv: np.ndarray, mi: np.ndarray,
                  infos: list[dict], obj_name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A mesh's triangles with the textured ones cut along their texture's edges: positions, corner
    normals, UV per face (a whole triangle keeps its polygon's UV centroid, a piece its own) and
    material index, pieces in their source triangle's place."""
    n_tri = len(pos)
    textured = np.zeros(n_tri, bool)
    for k, info in enumerate(infos):
        if info["image"] is not None:
            textured |= (mi == k) & np.isfinite(uv[:, 0])
    plain = np.nonzero(~textured)[0]
    out_p, out_n, out_uv, out_src = [pos[plain]], [nrm[plain]], [cuv[plain]], [plain]
    for k, info in enumerate(infos):
        sel = np.nonzero(textured & (mi == k))[0]
        if len(sel):
            # where a name decides the part (wheels, glass) only a little: enough to tell a wheel's
            # tyre from its rim, not to follow its tread
            depth = NAMED_DEPTH if named_part(obj_name, info["name"]) else MAX_DEPTH
            p, n, u, src, capped = split_by_texture(pos[sel], nrm[sel], cuv[sel], info["image"], depth)
            if capped:
                print(f"warning: {obj_name}: the texture of material {info['name']!r} varies too finely to follow; "
                      f"its faces were split less ({len(p)} pieces, at most {MAX_PIECES})", file=sys.stderr)
            out_p.append(p), out_n.append(n), out_uv.append(u), out_src.append(sel[src])
    src = np.concatenate(out_src)
    order = np.argsort(src, kind="stable")
    src = src[order]
    whole = np.bincount(src, minlength=n_tri)[src] == 1
    piece_uv = np.concatenate(out_uv)[order].mean(1)
    return (np.concatenate(out_p)[order], np.concatenate(out_n)[order],
            np.where(whole[:, None], uv[src], piece_uv), mi[src])
