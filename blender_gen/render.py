"""One Blender process that renders samples of a recipe (imports bpy).

`SampleRenderer(recipe).render(index, out_dir)` draws sample `index`'s car, paint,
environment and camera from its own seed, renders all intrinsic layers in one Cycles
pass, and writes the sample's EXR atomically. Cars and environment images are built on
first use and kept, so a worker pays for each model once.
"""
from __future__ import annotations

import math
import os
import tempfile
import time
import weakref
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import scene as S
from .camera import CameraError, orbit_focal, orbit_pose, sample_camera
from .cars import RandomCars, load_catalogue, load_part_materials, select_cars
from .dataset import read_exr_channels, sample_filename, sha256_file, write_exr
from .envmap import PROCEDURAL_PREFIX, background_lookup, cached_procedural_sky
from .materials import load_materials
from .quiet import quiet_stdout
from .recipe import Recipe, block_seed, sample_seed
from .cars.rules import ImportedSpec, imported_specs, is_model_file, load_rules

import bpy  # noqa: E402  (after the project imports so their errors surface first)


def _rz(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _scratch_dir() -> str:
    return "/dev/shm" if os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()


SCRATCH_PREFIX = "iae_render_"
STALE_SCRATCH_S = 600  # a live renderer rewrites its scratch file with every sample


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def sweep_stale_scratch(directory: str) -> int:
    """Delete scratch files that killed renderers left behind (in /dev/shm they hold RAM until a
    reboot): those whose process is gone and that nothing wrote for STALE_SCRATCH_S. Returns how many."""
    removed = 0
    now = time.time()
    for entry in os.scandir(directory):
        if not (entry.name.startswith(SCRATCH_PREFIX) and entry.name.endswith(".exr")):
            continue
        pid = entry.name[len(SCRATCH_PREFIX):].split("_", 1)[0]
        try:
            if not pid.isdigit() or now - entry.stat().st_mtime < STALE_SCRATCH_S:
                continue
            os.kill(int(pid), 0)  # raises if no such process
            continue
        except ProcessLookupError:
            pass
        except OSError:  # alive under another user (PermissionError) or gone already (stat)
            continue
        _unlink(entry.path)
        removed += 1
    return removed


class SampleRenderer:
    """One per process at a time: a new one resets Blender and retires the one before it."""

    _current: "SampleRenderer | None" = None

    def __init__(self, recipe: Recipe, threads: int = 0):
        if SampleRenderer._current is not None:
            SampleRenderer._current.close()
        SampleRenderer._current = self
        self.recipe = recipe
        self.scene = S.reset_scene()
        self._configure(threads)
        self.table = load_materials()
        self.paints = list(self.table.paints.values())
        self.materials = {**self.table.parts}
        self.env_names = recipe.envmap_names()
        self._env_images: dict[str, bpy.types.Image] = {}
        self._env_arrays: dict[str, np.ndarray] = {}
        self.shader, self.env_node = S.car_material(self.env_image(self.env_names[0]), physical=self.physical)
        self._setup_lighting()
        self._part_materials, self._tinted = load_part_materials()
        self.car_specs = self._resolve_cars()
        self._cars: dict[str, S.CarInstance] = {}
        self._visible: str | None = None
        self._orbit_focal: float | None = None
        scratch_dir = _scratch_dir()
        sweep_stale_scratch(scratch_dir)
        # named by process, so a later renderer can tell a dead one's leftover from a live one's
        fd, self._scratch = tempfile.mkstemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}_", suffix=".exr", dir=scratch_dir)
        os.close(fd)
        self._finalizer = weakref.finalize(self, _unlink, self._scratch)  # also at interpreter exit
        self.scene.render.filepath = self._scratch

    physical = False  # the PBR renderer shades with Principled BSDFs

    def _configure(self, threads: int) -> None:
        S.configure_cycles(self.scene, self.recipe.width, self.recipe.height, self.recipe.samples, threads)

    world_env = None  # the world's environment texture node, where the world shows the environment

    def _setup_lighting(self) -> None:
        """Intrinsics need no light: AOVs only. The environment background is looked up along the
        view rays after the render (`environment_pass = "lookup"`), or, for sets made before that,
        the world shows the environment, read back through Cycles' Environment pass."""
        if self.recipe.background == "environment" and self.recipe.environment_pass == "cycles":
            self.world_env, self.world_turn = S.environment_world(self.scene, self.env_node.image)
            self.scene.view_layers[0].use_pass_environment = True

    def set_environment(self, img) -> None:
        if self.env_node.image != img:
            self.env_node.image = img
        if self.world_env is not None and self.world_env.image != img:
            self.world_env.image = img  # Cycles rebuilds its light-sampling map: once per block

    def place(self, d: dict) -> None:
        """Paint, environment rotation and camera of a sample.

        With no world, the rotation is a shader attribute. With a world (PBR, or the environment
        background) car and camera turn by -rotation instead of the world by +rotation: the same
        picture and camera-space layers, but a changed world would make Cycles rebuild the
        environment's importance map (over a second per frame).
        """
        if self.world_env is None:
            S.set_sample_state(d["car"], d["paint"], d["rotation"])
            S.set_camera(self.scene, d["pose"])
            return
        rot = _rz(-d["rotation"])
        S.set_sample_state(d["car"], d["paint"], 0.0)
        d["car"].root.rotation_euler = (0.0, 0.0, -math.radians(d["rotation"]))
        pose = d["pose"]
        turned = replace(pose, location=tuple(rot @ np.asarray(pose.location)),
                         rotation=tuple(map(tuple, rot @ pose.matrix())), target=tuple(rot @ np.asarray(pose.target)))
        S.set_camera(self.scene, turned)

    # ------------------------------------------------------------------ resources
    def _resolve_cars(self) -> list:
        """Catalogue selectors and model files, in the recipe's order."""
        files = [c for c in self.recipe.cars if is_model_file(c)]
        names = [c for c in self.recipe.cars if c not in files]
        specs = select_cars(load_catalogue(), ",".join(names)) if names else []
        if files:
            self._rules = load_rules(self.recipe.car_rules)
            specs += imported_specs(files, self._rules)
        return specs

    def env_image(self, name: str) -> bpy.types.Image:
        img = self._env_images.get(name)
        if img is None:
            if name.startswith(PROCEDURAL_PREFIX):
                variant = int(name.rsplit("_", 1)[1])
                img = S.image_from_array(name, cached_procedural_sky(variant))
            else:
                img = S.load_envmap_image(name)
            self._env_images[name] = img
        return img

    @property
    def cars(self) -> dict[str, S.CarInstance]:
        """The car models built so far, by name."""
        return self._cars

    def forget_cars(self) -> None:
        """Delete every built car, so the next sample builds its model again (for benchmarks)."""
        for name in list(self._cars):
            self._forget(name)

    def _forget(self, name: str) -> None:
        car = self._cars.pop(name)
        meshes = {o.data for o in car.objects.values()}
        for o in list(car.collection.objects):
            bpy.data.objects.remove(o, do_unlink=True)
        for m in meshes:
            bpy.data.meshes.remove(m)
        bpy.data.collections.remove(car.collection)
        if self._visible == name:
            self._visible = None  # the shown car is gone

    # Random cars are built per block of views and rarely seen again: keep only the latest few.
    KEEP_RANDOM = 4

    def _resolve_random(self, spec, k: int):
        """Car k of a `procedural:random` pool (a catalogue or imported spec passes through)."""
        return spec.car(self.recipe.seed, k) if isinstance(spec, RandomCars) else spec

    def env_pixels(self, name: str) -> np.ndarray:
        """The environment map exactly as the shader sees it (for reference checks)."""
        return S.image_to_array(self.env_image(name))

    def env_array(self, name: str) -> np.ndarray:
        """`env_pixels`, read from Blender once per environment."""
        arr = self._env_arrays.get(name)
        if arr is None:
            arr = self._env_arrays[name] = self.env_pixels(name)
        return arr

    def car(self, spec) -> S.CarInstance:
        car = self._cars.get(spec.name)
        if car is None:
            from .cars import build_car

            if spec.split == "random":
                built = [n for n, c in self._cars.items() if c.split == "random"]
                for name in built[: max(0, len(built) - self.KEEP_RANDOM + 1)]:
                    self._forget(name)
            part_mat = self._part_materials
            if spec.tinted_rear:
                part_mat = {**part_mat, "window_side": self._tinted}
            if isinstance(spec, ImportedSpec):
                from .cars.importer import import_model

                parts, source = import_model(spec.path, self._rules).parts, f"import:{Path(spec.path).name}"
            else:
                parts, source = build_car(spec), "procedural"
            car = S.add_car(spec.name, spec.category, parts, part_mat, self.materials, self.shader, self.scene)
            car.source = source
            car.split = spec.split
            self._cars[spec.name] = car
        return car

    # ------------------------------------------------------------------ samples
    def draw(self, index: int) -> dict:
        """The random choices of sample `index` (deterministic in seed and index)."""
        if self.recipe.orbit is not None:
            return self._draw_orbit(index)
        seed = sample_seed(self.recipe.seed, index)
        rng = np.random.default_rng(seed)
        block = np.random.default_rng(block_seed(self.recipe.seed, index, self.recipe.views_per_car))
        spec = self.car_specs[int(block.integers(len(self.car_specs)))]
        spec = self._resolve_random(spec, index // self.recipe.views_per_car)  # a new random car per block
        paint = self.paints[int(rng.integers(len(self.paints)))]
        env = self.env_names[int(block.integers(len(self.env_names)))]
        rotation = float(rng.uniform(0.0, 360.0))
        car = self.car(spec)
        try:
            pose = sample_camera(rng, car.points, self.recipe.width, self.recipe.height, self.recipe.camera)
        except CameraError as e:  # name the car: with several --cars, one model may be too large for the ranges
            extent = np.ptp(np.asarray(car.points)[:, :3], axis=0)
            raise CameraError(f"car {spec.name!r} ({extent[0]:.1f} x {extent[1]:.1f} x {extent[2]:.1f} m): {e}") from None
        return {"seed": seed, "spec": spec, "car": car, "paint": paint, "env": env, "rotation": rotation, "pose": pose}

    def _draw_orbit(self, frame: int) -> dict:
        """Frame `frame` of a turntable: one car, paint and environment for every frame, and one
        Cycles seed (Blender's default), so only the camera changes between frames."""
        orbit = self.recipe.orbit
        seed = sample_seed(self.recipe.seed, 0)
        rng = np.random.default_rng(seed)
        spec = self._resolve_random(self.car_specs[0], 0)
        drawn_paint = self.paints[int(rng.integers(len(self.paints)))]
        paint = self.table.paints[orbit.paint] if orbit.paint else drawn_paint
        env = self.env_names[int(rng.integers(len(self.env_names)))]
        drawn_rotation = float(rng.uniform(0.0, 360.0))
        rotation = drawn_rotation if orbit.env_rotation_deg is None else float(orbit.env_rotation_deg)
        car = self.car(spec)
        if orbit.focal is None:  # fitted to the car once per process (a pure function: every worker agrees)
            if self._orbit_focal is None:
                self._orbit_focal = orbit_focal(car.points, orbit, self.recipe.width, self.recipe.height,
                                                self.recipe.camera)
            orbit = replace(orbit, focal=self._orbit_focal)
        pose = orbit_pose(car.points, orbit, frame, self.recipe.width, self.recipe.height, self.recipe.camera)
        return {"seed": seed, "spec": spec, "car": car, "paint": paint, "env": env, "rotation": rotation, "pose": pose}

    def show(self, car: S.CarInstance | None) -> None:
        """Make `car` the only visible car (None hides all)."""
        if self._visible != (car.name if car else None):
            for other in self._cars.values():
                other.set_visible(other is car)
            self._visible = car.name if car else None

    @property
    def alive(self) -> bool:
        """False once a newer renderer has reset Blender's scene under this one."""
        return SampleRenderer._current is self

    def render_current(self) -> dict[str, np.ndarray]:
        """Render the scene as it is set up now and return its layers."""
        if not self.alive:
            raise RuntimeError("this SampleRenderer was replaced by a newer one: Blender holds one scene per "
                               "process, so make a new renderer")
        with quiet_stdout():
            bpy.ops.render.render(write_still=True)
        return self._read_passes()

    # A persistent Cycles session (BVH and shaders kept between renders) keeps the integrator seed
    # of its first render and ignores later changes to `scene.cycles.seed` (measured: a sample
    # rendered after another one used that one's seed, so a resumed run re-rendered it with other
    # noise). The frame number does reach a persistent session: with an animated seed Cycles
    # hashes it with one recipe-wide seed, so each sample gets its own noise, a function of
    # (recipe, index) alone. A turntable keeps one seed for every frame (frame 1 throughout).
    MAX_FRAME = 1_000_000  # below Blender's frame limit; noise patterns repeat after a million samples

    def set_up(self, index: int) -> dict:
        """Put sample `index`'s car, paint, environment, camera and noise seed in the scene; returns its draws."""
        d = self.draw(index)
        self.show(d["car"])
        self.set_environment(self.env_image(d["env"]))
        self.place(d)
        cy = self.scene.cycles
        orbit = self.recipe.orbit is not None
        cy.use_animated_seed = not orbit
        cy.seed = sample_seed(self.recipe.seed, 0)
        frame = 1 if orbit else index % self.MAX_FRAME + 1
        if self.scene.frame_current != frame:
            self.scene.frame_current = frame
        return d

    def render_layers(self, index: int) -> tuple[dict[str, np.ndarray], dict]:
        d = self.set_up(index)
        layers = self.render_current()
        if self.recipe.kind == "intrinsics" and self.recipe.background == "environment" and self.world_env is None:
            w, h = self.recipe.width, self.recipe.height
            behind = 1.0 - layers["mask"]
            env = background_lookup(d["pose"].matrix(), d["pose"].focal_px(w), h, w, self.env_array(d["env"]),
                                    d["rotation"])
            # the AOV covers the car, the environment the rest: edges blend by coverage
            layers["reflection"] = layers["reflection"] + behind * env
        return layers, d

    def _read_passes(self) -> dict[str, np.ndarray]:
        ch = read_exr_channels(self._scratch)

        def get(layer: str, comps: str) -> np.ndarray:
            return np.stack([ch[f"ViewLayer.{layer}.{c}"] for c in comps], axis=-1).astype(np.float32)

        self._channels = ch
        mask = np.clip(get("mask", "X"), 0.0, 1.0)
        normal = get("normal", "RGB")
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        on = mask > 0
        normal = np.where(on & (length > 1e-6), normal / np.maximum(length, 1e-6), 0.0)
        reflection = get("reflection", "RGB")
        if self.recipe.kind == "intrinsics" and self.world_env is not None:
            # the AOV covers the car, the Environment pass the rest: edges blend by coverage
            reflection = reflection + np.maximum(get("Environment", "RGB"), 0.0)
        layers = {
            "normal": normal, "albedo": get("albedo", "RGB"), "reflection": reflection,
            "mask": mask, "material": np.round(get("material", "X")),
        }
        if self.recipe.extras():
            # AOVs average over a pixel's samples: depth per unit of coverage (the car's own distance
            # at its edges), ids rounded as the material's, gloss weighted by coverage as albedo is
            depth = get("depth", "X") / np.maximum(mask, 1e-6)
            extra = {"depth": np.where(on, depth, 0.0).astype(np.float32), "part": np.round(get("part", "X")),
                     "gloss": get("gloss", "X")}
            layers.update({k: extra[k] for k in self.recipe.extras() if k in extra})
        return layers

    def render(self, index: int, out_dir: Path) -> dict:
        """Render sample `index` into `out_dir` and return its manifest row."""
        layers, d = self.render_layers(index)
        rel = sample_filename(index)
        path = Path(out_dir) / rel
        write_exr(path, layers)
        self._write_preview(layers, Path(out_dir), index)
        return {
            "index": index,
            "file": rel,
            "sha256": sha256_file(path),
            "seed": d["seed"],
            "car": {"name": d["spec"].name, "category": d["spec"].category, "source": d["car"].source},
            "paint": d["paint"].name,
            "envmap": {"name": Path(d["env"]).name if not d["env"].startswith(PROCEDURAL_PREFIX) else d["env"],
                       "rotation_deg": round(d["rotation"], 6)},
            "camera": {**d["pose"].to_json(), "resolution": [self.recipe.width, self.recipe.height]},
        }

    def _write_preview(self, layers: dict, out_dir: Path, index: int) -> None:
        """Intrinsics sets write no per-sample previews (`iae-gen inspect` makes a grid)."""

    def close(self) -> None:
        self._finalizer()

