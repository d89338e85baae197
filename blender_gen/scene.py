"""Blender scene building: render settings, the intrinsics material, cars, camera.

The only module (with `render.py` and `importer.py`) that imports `bpy`.

All intrinsic layers come from one Cycles render as shader AOVs. One material serves
every part: it reads the part's albedo, glossiness and material id, and the environment
rotation, from *object* attributes, so a new paint or rotation per sample changes object
data only and never recompiles shaders.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import bpy
import mathutils
import numpy as np

from .camera import CameraPose
from .cars.spec import PARTS
from .geometry import Mesh
from .materials import Material

AOVS = (("normal", "COLOR"), ("albedo", "COLOR"), ("reflection", "COLOR"), ("mask", "VALUE"), ("material", "VALUE"),
        ("depth", "VALUE"), ("part", "VALUE"), ("gloss", "VALUE"))
ATTR_ALBEDO, ATTR_GLOSS, ATTR_MATERIAL, ATTR_ENV_ROT = "iae_albedo", "iae_gloss", "iae_material", "iae_env_rot"
ATTR_PART = "iae_part"  # 1 + the part's position in cars.spec.PARTS
# Physical parameters for the PBR shader, also object attributes (see `set_material_attrs`).
PBR_ATTRS = {
    "iae_metallic": "Metallic", "iae_roughness": "Roughness", "iae_transmission": "Transmission Weight",
    "iae_ior": "IOR", "iae_emission": "Emission Strength", "iae_coat": "Coat Weight",
}


def reset_scene() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def configure_cycles(scene: bpy.types.Scene, width: int, height: int, samples: int, threads: int,
                     bounces: int = 0) -> None:
    """Cycles on the CPU with persistent data; AOV passes for the intrinsic layers."""
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = samples
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.max_bounces = bounces
    cy.use_animated_seed = False
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.use_persistent_data = True  # keep BVH and shaders between samples
    scene.render.threads_mode = "FIXED" if threads > 0 else "AUTO"
    if threads > 0:
        scene.render.threads = threads
    scene.render.use_compositing = False
    scene.render.use_sequencer = False
    layer = scene.view_layers[0]
    layer.use_pass_z = False
    for name, kind in AOVS:
        if name not in layer.aovs:
            aov = layer.aovs.add()
            aov.name, aov.type = name, kind
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "NONE"  # a scratch file read back at once: no time spent compressing


def image_from_array(name: str, pixels: np.ndarray) -> bpy.types.Image:
    """A float image from an (H, W, 3) top-down array (Blender stores rows bottom-up)."""
    h, w, _ = pixels.shape
    img = bpy.data.images.new(name, w, h, float_buffer=True, alpha=False)
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :3] = pixels[::-1]
    img.pixels.foreach_set(rgba.ravel())
    img.pack()  # keep the pixels with the image so Cycles never looks for a file
    return img


def image_to_array(img: bpy.types.Image) -> np.ndarray:
    """(H, W, 3) top-down float32 pixels of a Blender image."""
    w, h = img.size
    buf = np.empty(w * h * img.channels, dtype=np.float32)
    img.pixels.foreach_get(buf)
    return buf.reshape(h, w, img.channels)[::-1, :, :3].copy()


def load_envmap_image(path: str) -> bpy.types.Image:
    """Load an equirectangular .hdr/.exr; a clear error if Blender cannot decode it."""
    try:
        img = bpy.data.images.load(path, check_existing=True)
    except RuntimeError as exc:
        raise ValueError(f"--envmap {path}: cannot be read as an image ({exc})") from exc
    w, h = img.size
    if w == 0 or h == 0 or not img.has_data and len(img.pixels) == 0:
        raise ValueError(f"--envmap {path}: cannot be decoded as an image (expected an equirectangular .hdr or .exr)")
    if abs(w - 2 * h) > 2:
        raise ValueError(f"--envmap {path}: {w}x{h} is not equirectangular (expected width = 2 x height)")
    img.colorspace_settings.name = "Linear Rec.709"
    return img


def _attr(nt, name: str, x: float, y: float):
    node = nt.nodes.new("ShaderNodeAttribute")
    node.attribute_type = "OBJECT"
    node.attribute_name = name
    node.location = (x, y)
    return node


def _aov(nt, name: str, socket, x: float, y: float):
    node = nt.nodes.new("ShaderNodeOutputAOV")
    node.aov_name = name
    node.location = (x, y)
    nt.links.new(socket, node.inputs["Value" if dict(AOVS)[name] == "VALUE" else "Color"])
    return node


def add_intrinsic_aovs(nt: bpy.types.NodeTree, env_node: bpy.types.Node) -> None:
    """AOV outputs for normal, albedo, reflection, mask, material id, part index, gloss and depth.

    normal: shading normal in Cycles' camera space (+Z forward), turned to OpenGL (+Z back).
    reflection: the environment along the view ray mirrored about the normal, times gloss.
    """
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    to_cam = nt.nodes.new("ShaderNodeVectorTransform")
    to_cam.vector_type, to_cam.convert_from, to_cam.convert_to = "NORMAL", "WORLD", "CAMERA"
    nt.links.new(geo.outputs["Normal"], to_cam.inputs["Vector"])
    flip = nt.nodes.new("ShaderNodeVectorMath")
    flip.operation = "MULTIPLY"
    flip.inputs[1].default_value = (1.0, 1.0, -1.0)
    nt.links.new(to_cam.outputs["Vector"], flip.inputs[0])
    _aov(nt, "normal", flip.outputs["Vector"], 600, 300)

    view = nt.nodes.new("ShaderNodeVectorMath")
    view.operation = "SCALE"
    view.inputs["Scale"].default_value = -1.0
    nt.links.new(geo.outputs["Incoming"], view.inputs[0])
    mirror = nt.nodes.new("ShaderNodeVectorMath")
    mirror.operation = "REFLECT"
    nt.links.new(view.outputs["Vector"], mirror.inputs[0])
    nt.links.new(geo.outputs["Normal"], mirror.inputs[1])
    turn = nt.nodes.new("ShaderNodeMapping")
    turn.vector_type = "VECTOR"
    nt.links.new(mirror.outputs["Vector"], turn.inputs["Vector"])
    nt.links.new(_attr(nt, ATTR_ENV_ROT, -400, -200).outputs["Vector"], turn.inputs["Rotation"])
    nt.links.new(turn.outputs["Vector"], env_node.inputs["Vector"])
    scale = nt.nodes.new("ShaderNodeVectorMath")
    scale.operation = "SCALE"
    nt.links.new(env_node.outputs["Color"], scale.inputs[0])
    nt.links.new(_attr(nt, ATTR_GLOSS, 0, -300).outputs["Fac"], scale.inputs["Scale"])
    _aov(nt, "reflection", scale.outputs["Vector"], 600, -100)

    _aov(nt, "albedo", _attr(nt, ATTR_ALBEDO, 0, 100).outputs["Color"], 600, 100)
    _aov(nt, "material", _attr(nt, ATTR_MATERIAL, 0, -500).outputs["Fac"], 600, -300)
    _aov(nt, "part", _attr(nt, ATTR_PART, 0, -700).outputs["Fac"], 600, -700)
    _aov(nt, "gloss", _attr(nt, ATTR_GLOSS, 0, -900).outputs["Fac"], 600, -900)
    cam = nt.nodes.new("ShaderNodeCameraData")  # distance along the camera's view axis
    _aov(nt, "depth", cam.outputs["View Z Depth"], 600, -1100)
    one = nt.nodes.new("ShaderNodeValue")
    one.outputs[0].default_value = 1.0
    _aov(nt, "mask", one.outputs[0], 600, -500)


def car_material(env_image: bpy.types.Image, physical: bool = False) -> tuple[bpy.types.Material, bpy.types.Node]:
    """The one material every car part shares; returns it and its environment node.

    Intrinsics: AOVs over an opaque Holdout (without a closure the ray would pass through
    and AOVs would add up over hits). PBR (`physical`): the same AOVs over a Principled
    BSDF whose parameters are object attributes, so both sets see identical ground truth.
    """
    mat = bpy.data.materials.new("iae_pbr" if physical else "iae_intrinsics")
    nt = mat.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = env_image
    env.interpolation = "Linear"
    add_intrinsic_aovs(nt, env)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if not physical:
        surface = nt.nodes.new("ShaderNodeHoldout")
    else:
        surface = nt.nodes.new("ShaderNodeBsdfPrincipled")
        nt.links.new(_attr(nt, ATTR_ALBEDO, -300, 300).outputs["Color"], surface.inputs["Base Color"])
        for k, (attr, socket) in enumerate(PBR_ATTRS.items()):
            nt.links.new(_attr(nt, attr, -300, 200 - 100 * k).outputs["Fac"], surface.inputs[socket])
        nt.links.new(_attr(nt, "iae_emission_color", -300, -500).outputs["Color"], surface.inputs["Emission Color"])
        surface.inputs["Coat Roughness"].default_value = 0.03
    nt.links.new(surface.outputs[0], out.inputs["Surface"])
    return mat, env


def mesh_from_numpy(name: str, mesh: Mesh) -> bpy.types.Mesh:
    """A Blender mesh built with foreach_set (fast): smooth-shaded, or with the mesh's own
    per-corner normals when it carries them (imported models)."""
    me = bpy.data.meshes.new(name)
    n_faces, k = mesh.faces.shape
    me.vertices.add(len(mesh.verts))
    me.vertices.foreach_set("co", mesh.verts.astype(np.float32).ravel())
    me.loops.add(n_faces * k)
    me.loops.foreach_set("vertex_index", mesh.faces.astype(np.int32).ravel())
    me.polygons.add(n_faces)
    me.polygons.foreach_set("loop_start", np.arange(0, k * n_faces, k, dtype=np.int32))
    me.update(calc_edges=True)
    me.shade_smooth()
    if mesh.loop_normals is not None:
        me.normals_split_custom_set(mesh.loop_normals.reshape(-1, 3).tolist())
    return me


@dataclass
class CarInstance:
    """A car in the scene: its collection, part objects and sample points for framing."""

    name: str
    category: str
    collection: bpy.types.Collection
    objects: dict[str, bpy.types.Object]
    part_material: dict[str, str]  # part -> material name ("paint" = body paint)
    points: np.ndarray  # (N, 3) world-space vertices, subsampled
    root: bpy.types.Object | None = None  # parent of all parts
    source: str = "procedural"
    split: str = "train"  # "random" cars are dropped again after a few blocks

    def set_visible(self, visible: bool) -> None:
        self.collection.hide_render = not visible


def set_material_attrs(obj: bpy.types.Object, material: Material, paint: bool = False) -> None:
    """Intrinsic and physical parameters of a part as object attributes.

    Paints are modelled as a base coat under a clear coat; a "metallic" paint gets a
    partly metallic base (full metal would make it a tinted mirror).
    """
    obj[ATTR_ALBEDO] = tuple(material.albedo)
    obj[ATTR_GLOSS] = float(material.gloss)
    obj[ATTR_MATERIAL] = float(material.id)
    obj["iae_metallic"] = 0.55 * material.metallic if paint else material.metallic
    obj["iae_roughness"] = (0.35 if material.metallic else 0.3) if paint else material.roughness
    obj["iae_transmission"] = material.transmission
    obj["iae_ior"] = material.ior
    obj["iae_emission"] = material.emission
    obj["iae_emission_color"] = tuple(material.emission_color)
    obj["iae_coat"] = 1.0 if paint else 0.0


def add_car(name: str, category: str, parts: dict[str, Mesh], part_material: dict[str, str],
            materials: dict[str, Material], shader: bpy.types.Material, scene: bpy.types.Scene) -> CarInstance:
    """Create one object per part, all sharing the intrinsics shader."""
    coll = bpy.data.collections.new(name)
    scene.collection.children.link(coll)
    root = bpy.data.objects.new(f"{name}.root", None)  # turns the whole car (PBR rotation)
    coll.objects.link(root)
    objects = {}
    for part, mesh in parts.items():
        me = mesh_from_numpy(f"{name}.{part}", mesh)
        me.materials.append(shader)
        obj = bpy.data.objects.new(f"{name}.{part}", me)
        obj.parent = root
        coll.objects.link(obj)
        obj[ATTR_PART] = float(PARTS.index(part) + 1)
        mat_name = part_material[part]
        if mat_name != "paint":
            set_material_attrs(obj, materials[mat_name])
        objects[part] = obj
    pts = np.concatenate([m.verts for m in parts.values()])
    step = max(1, len(pts) // 4000)
    return CarInstance(name, category, coll, objects, dict(part_material), pts[::step].copy(), root)


def environment_world(scene: bpy.types.Scene, env_image: bpy.types.Image) -> tuple[bpy.types.Node, bpy.types.Node]:
    """World lit by the environment map; returns its texture and mapping nodes."""
    world = bpy.data.worlds.new("iae_world")
    scene.world = world
    nt = world.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    coord = nt.nodes.new("ShaderNodeTexCoord")
    turn = nt.nodes.new("ShaderNodeMapping")
    turn.vector_type = "VECTOR"
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = env_image
    env.interpolation = "Linear"
    bg = nt.nodes.new("ShaderNodeBackground")
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(coord.outputs["Generated"], turn.inputs["Vector"])
    nt.links.new(turn.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return env, turn


def shadow_catcher(scene: bpy.types.Scene, size: float = 60.0) -> bpy.types.Object:
    """A ground plane at z = 0 that shows only the car's shadow over the environment."""
    me = bpy.data.meshes.new("iae_ground")
    h = 0.5 * size
    me.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    mat = bpy.data.materials.new("iae_ground")
    nt = mat.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    me.materials.append(mat)
    obj = bpy.data.objects.new("iae_ground", me)
    obj.is_shadow_catcher = True
    scene.collection.objects.link(obj)
    return obj


def set_camera(scene: bpy.types.Scene, pose: CameraPose) -> bpy.types.Object:
    cam = scene.camera
    if cam is None:
        data = bpy.data.cameras.new("iae_camera")
        cam = bpy.data.objects.new("iae_camera", data)
        scene.collection.objects.link(cam)
        scene.camera = cam
    m = np.eye(4)
    m[:3, :3] = pose.matrix()
    m[:3, 3] = pose.location
    cam.matrix_world = mathutils.Matrix([list(map(float, row)) for row in m])  # rows
    cam.data.lens = pose.focal_length
    cam.data.sensor_width = pose.sensor_width
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.clip_start = 0.05
    cam.data.clip_end = 200.0
    return cam


def set_sample_state(car: CarInstance, paint: Material, env_rotation_deg: float) -> None:
    """Per-sample object attributes: body paint and environment rotation on every part."""
    rot = (0.0, 0.0, -math.radians(env_rotation_deg))  # the shader looks up Rz(-rotation) r
    for part, obj in car.objects.items():
        if car.part_material[part] == "paint":
            set_material_attrs(obj, paint, paint=True)
        obj[ATTR_ENV_ROT] = rot
        obj.update_tag()
