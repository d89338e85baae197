"""The Cycles PBR set: path-traced images with ground-truth intrinsics (imports bpy).

Same scene rules, draws and AOV graph as the intrinsics set, so sample i of a PBR recipe
shows the car, paint, environment and camera that sample i of an intrinsics recipe with
the same options would, and its `normal`/`albedo`/`reflection`/`mask` layers match. The
image adds physically based materials (clear-coated paint, transmissive glass, emissive
lights, metals), the environment as light and background, and the car's shadow on a
shadow-catcher ground plane.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import scene as S
from .conversions import preview_srgb8
from .dataset import LIGHT_LAYERS, save_png
from .quiet import without_lines
from .recipe import Recipe
from .render import SampleRenderer


# Cycles' passes behind the light layers (dataset.LIGHT_LAYERS)
LIGHT_PASSES = ("diffuse_color", "diffuse_direct", "diffuse_indirect", "glossy_color", "glossy_direct",
                "glossy_indirect", "transmission_color", "transmission_direct", "transmission_indirect", "emit",
                "environment")


class PbrRenderer(SampleRenderer):
    physical = True

    def _configure(self, threads: int) -> None:
        # Denoiser settings make Cycles probe for CUDA; on a machine without it every worker printed
        # "WARNING CUEW initialization failed", which reads as an error. Other messages go through.
        with without_lines("CUEW initialization failed"):
            self._configure_cycles(threads)

    def _configure_cycles(self, threads: int) -> None:
        S.configure_cycles(self.scene, self.recipe.width, self.recipe.height, self.recipe.samples, threads)
        cy = self.scene.cycles
        cy.use_adaptive_sampling = self.recipe.noise_threshold > 0
        cy.adaptive_threshold = self.recipe.noise_threshold or Recipe.noise_threshold  # unused when off
        cy.adaptive_min_samples = min(4, self.recipe.samples)
        cy.use_denoising = True
        cy.denoiser = "OPENIMAGEDENOISE"
        cy.denoising_quality = "FAST"  # about 2 s less per frame on 2 cores than HIGH
        cy.denoising_prefilter = "FAST"
        cy.use_light_tree = False  # few lights: the tree costs more than it saves here
        cy.max_bounces = 6
        cy.diffuse_bounces = 2
        cy.glossy_bounces = 3  # a car is mostly reflections
        cy.transmission_bounces = 4
        cy.transparent_max_bounces = 4
        cy.caustics_reflective = False
        cy.caustics_refractive = False
        cy.sample_clamp_indirect = 10.0  # tames fireflies from the HDR sun
        layer = self.scene.view_layers[0]
        layer.use_pass_combined = True
        self.scene.render.film_transparent = False
        if set(LIGHT_LAYERS) & set(self.recipe.extras()):  # Cycles' light passes, and the image they add up to
            for p in LIGHT_PASSES:
                setattr(layer, f"use_pass_{p}", True)
            layer.cycles.denoising_store_passes = True  # "Noisy Image": the passes sum to it, not to the denoised one

    def _setup_lighting(self) -> None:
        self.world_env, self.world_turn = S.environment_world(self.scene, self.env_node.image)
        self.ground = S.shadow_catcher(self.scene)
        # Lamps glow and show in reflections; sampling them as lights costs more than it adds.
        self.shader.cycles.emission_sampling = "NONE"

    def _read_passes(self) -> dict[str, np.ndarray]:
        layers = super()._read_passes()
        ch = self._channels

        def get(name: str) -> np.ndarray:
            return np.stack([ch[f"ViewLayer.{name}.{c}"] for c in "RGB"], axis=-1).astype(np.float32)

        rgb = get("Combined")
        wanted = set(self.recipe.extras())
        if wanted & set(LIGHT_LAYERS):
            light = {
                "rgb_noisy": get("Noisy Image"), "diffuse_color": get("Diffuse Color"),
                "diffuse_shading": get("Diffuse Direct") + get("Diffuse Indirect"),
                "glossy": get("Glossy Color") * (get("Glossy Direct") + get("Glossy Indirect")),
                "transmission": get("Transmission Color") * (get("Transmission Direct") + get("Transmission Indirect")),
                "emission": get("Emission"), "environment": get("Environment"),
            }
            layers.update({k: v for k, v in light.items() if k in wanted})
        return {"rgb": np.maximum(rgb, 0.0), **layers}

    def _write_preview(self, layers: dict, out_dir: Path, index: int) -> None:
        previews = out_dir / "previews"
        previews.mkdir(exist_ok=True)
        save_png(previews / f"{index:06d}.png", preview_srgb8("rgb", layers["rgb"]))
