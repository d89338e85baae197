"""The Intrinsic Autoencoder (Section 3 of the paper) and its ablation switches.

R renders intrinsics to images, H decomposes images into intrinsics; two cycles
(rendering M_s -> R -> H, decomposition I_r -> H -> R) and the *shared* adversarial
losses: D_I sees R(M_s) and R(H(I_r)) as fakes, D_M sees H(I_r) and H(R(M_s)).
The ablations switch a whole cycle off: without the decomposition cycle no real image
reaches R or H (D_I compares I_r with R(M_s) only, D_M compares M_s with H(R(M_s))), and
without the rendering cycle no synthetic intrinsics reach them (the mirror case).
Each discriminator runs once per step on one concatenated batch (instance norm keeps
samples independent), which keeps the multi-process gradient all-reduce simple.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import nn

from .config import Config
from .losses import (chroma_loss, cycle_loss, finish_logs, gan_loss, level_bias_loss, linear_mean, masked_mean,
                     normal_length_loss, object_mask, update_running)
from .networks import CHANNELS, Decomposer, MultiscaleDiscriminator, ShaderRenderer, init_weights, make_renderer_net
from .shading import fit_lighting, render_sh, shading_loss



@runtime_checkable
class ModelKind(Protocol):
    """What every model kind implements (the Intrinsic Autoencoder, CycleGAN, MUNIT, the oracle).

    The training loop, inference commands, grids and the report use nothing else, so a new
    baseline is a class with these methods and a config section of its own (train.config).
    """

    def generator_modules(self) -> dict[str, nn.Module]:
        """Networks updated by the generator step (one optimiser)."""

    def discriminator_modules(self) -> dict[str, nn.Module]:
        """Networks updated by the discriminator step; empty for a model without one."""

    def forward_all(self, m_s: torch.Tensor, i_r: torch.Tensor, everything: bool = False) -> dict[str, torch.Tensor]:
        """All outputs one training step needs; `everything` adds those only pictures show."""

    def generator_loss(self, out: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """The generators' loss and its logged terms ("G/...")."""

    def discriminator_loss(self, out: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """The discriminators' loss on detached fakes and its logged terms ("D/...")."""

    def visuals(self, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """M_s, R(M_s), H(R(M_s)), I_r, H(I_r), R(H(I_r)) where the model has them (for grids)."""

    def render(self, m: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """9-channel intrinsics (network space) -> image; `generator` seeds random style codes."""

    def decompose(self, img: torch.Tensor) -> torch.Tensor:
        """Image -> 9-channel intrinsics (network space)."""


class IntrinsicAutoencoder(nn.Module):
    def __init__(self, cfg: Config):
        super().__init__()
        m, self.loss_cfg = cfg.model, cfg.loss
        self.inputs = [c for c in "NAF" if c in m.inputs]  # canonical order
        self.shader = m.renderer == "shader"
        if self.shader:
            self.R = ShaderRenderer(self.inputs, m.r_ngf, m.r_downsample, m.r_blocks, m.r_local_enhancers, m.norm,
                                    m.shader_residual, m.shader_residual_on,
                                    m.lighting_bank if m.shader_lighting == "per_image" else 0,
                                    m.shader_gain_start if m.shader_gain == "shared" else 0.0,
                                    m.shader_background, m.bank_level, m.shader_gain_min)
        else:
            self.R = make_renderer_net(3 * len(self.inputs), m.r_ngf, m.r_downsample, m.r_blocks,
                                       m.r_local_enhancers, m.norm)
        self.H = Decomposer(m.h_ngf, m.h_downsample, m.h_blocks, m.norm, m.normal_output, m.h_upsample)
        self.D_I = MultiscaleDiscriminator(3, m.d_ndf, m.d_layers, m.d_scales, m.norm)
        self.cond_m = cfg.loss.adv_m_cond == "image"
        self.D_M = MultiscaleDiscriminator(9 + 3 * self.cond_m, m.d_ndf, m.d_layers, m.d_scales, m.norm)
        self.normal_output = m.normal_output
        self.step = 0  # training steps done, set by the training loop; only loss.adv_m_from reads it
        # running albedo levels (loss.w_albedo_level): H's on real images, the training intrinsics';
        # None (not part of the weights) when the term is off, so older checkpoints load as before
        self.register_buffer("albedo_levels", torch.zeros(2, 3) if cfg.loss.w_albedo_level else None)
        init_weights(self, "normal")  # pix2pixHD / CycleGAN: N(0, 0.02)

    # -------------------------------------------------------------- groups for optimisers
    def generator_modules(self) -> dict[str, nn.Module]:
        return {"R": self.R, "H": self.H}

    def discriminator_modules(self) -> dict[str, nn.Module]:
        return {"D_I": self.D_I, "D_M": self.D_M}

    # -------------------------------------------------------------- inference
    def select(self, m: torch.Tensor) -> torch.Tensor:
        """The channels of a 9-channel stack that R takes (ablation `model.inputs`)."""
        return torch.cat([m[:, CHANNELS[c]] for c in self.inputs], dim=1)

    def render(self, m: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        return self.R(m) if self.shader else self.R(self.select(m))

    def decompose(self, img: torch.Tensor) -> torch.Tensor:
        return self.H(img)

    def reconstruct(self, img: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
        """R(H(img)) as in the decomposition cycle: `maps` = H(img), lit as the image is (the
        shader's per-image lighting fit) where the renderer has one."""
        if self.shader and self.R.bank is not None:
            return self.R(maps, self.real_lighting(img, maps)[0])
        return self.render(maps)

    # -------------------------------------------------------------- training
    def forward_all(self, m_s: torch.Tensor, i_r: torch.Tensor, everything: bool = False) -> dict[str, torch.Tensor]:
        """The outputs the losses need; `everything` also computes those an ablation does not
        train on (for pictures only: H(I_r) shows what an ablated H makes of real images)."""
        lc = self.loss_cfg
        out = {"M_s": m_s, "I_r": i_r}
        per_image = self.shader and self.R.bank is not None
        if lc.rendering_cycle or everything:
            # R(M_s), under a real image's lighting when the bank has one (training only: pictures
            # and inference use the bank's mean)
            light = self.R.draw(len(m_s)) if per_image and self.training else None
            out["fake_I"] = self.R(m_s, light) if self.shader else self.render(m_s)
            out["rec_M"] = self.H(self._into_cycle(out["fake_I"]))  # H(R(M_s))
        else:
            light = None
        if lc.decomposition_cycle or everything:
            out["fake_M"] = self.H(i_r)  # H(I_r)
            if light is not None:  # model.bank_level: the real images' car level beside R(M_s)'s
                self._update_levels(m_s, light, i_r, out["fake_M"])
            light, fitted = self.real_lighting(i_r, out["fake_M"]) if per_image else (None, None)
            rec_in = self._into_cycle(out["fake_M"])
            out["rec_I"] = self.R(rec_in, light) if self.shader else self.render(rec_in)  # R(H(I_r))
            if light is not None and self.training:
                self.R.push(light[fitted])
        return out

    @torch.no_grad()
    def _update_levels(self, m_s: torch.Tensor, drawn: torch.Tensor, i_r: torch.Tensor, fake_m: torch.Tensor) -> None:
        """Running car levels for model.bank_level "images": the real images' on H's car mask, and
        R(M_s)'s (its shaded car, linear) under the drawn lightings as fitted (the scale taken out)."""
        if self.R.levels is None:
            return
        fitted = drawn / self.R.level_scale().view(1, 3, 1)
        lin = render_sh(m_s[:, 0:3], m_s[:, 3:6], m_s[:, 6:9], fitted[..., :9], fitted[..., 9])
        car = object_mask(m_s)
        self.R.update_levels(linear_mean(i_r, object_mask(fake_m.detach())), masked_mean(lin, car))

    @torch.no_grad()
    def real_lighting(self, i_r: torch.Tensor, fake_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(n, 3, 10) SH lighting and reflection gain that explain each real image through H's maps, on
        H's object mask, and (n,) whether each was fitted: an image where H finds (almost) no object
        gets the default lighting instead."""
        mask = object_mask(fake_m)
        light, gain = fit_lighting(i_r, fake_m[:, 0:3], fake_m[:, 3:6], fake_m[:, 6:9], mask,
                                   gain=self.R.shared_gain())
        fitted = torch.cat([light, gain.unsqueeze(-1)], dim=-1).clamp(-10, 10)
        d_light, d_gain = self.R.default_lighting()
        default = torch.cat([d_light, d_gain.unsqueeze(-1)], dim=-1).expand_as(fitted)
        ok = mask.flatten(1).sum(1) >= 16
        return torch.where(ok.view(-1, 1, 1), fitted, default.to(fitted.dtype)), ok

    def _into_cycle(self, x: torch.Tensor) -> torch.Tensor:
        """A first network's output on its way into the second: `loss.cycle_detach` cuts its
        gradient, `loss.cycle_noise` (training only) perturbs it; discriminators see it unchanged."""
        if self.loss_cfg.cycle_detach:
            x = x.detach()
        if self.training and self.loss_cfg.cycle_noise > 0:
            return x + self.loss_cfg.cycle_noise * torch.randn_like(x)
        return x

    def discriminator_inputs(self, out: dict[str, torch.Tensor]) -> dict[str, tuple[torch.Tensor, list[str]]]:
        """Which tensors each discriminator sees: (real, names of fakes).

        Shared: every generated image (R(M_s), R(H(I_r))) is a fake for D_I and every generated
        stack (H(I_r), H(R(M_s))) for D_M. Not shared: only the direct translations.
        """
        candidates = {"D_I": ("fake_I", "rec_I"), "D_M": ("fake_M", "rec_M")}
        if not self.loss_cfg.shared_discriminator:
            candidates = {"D_I": ("fake_I",), "D_M": ("fake_M",)}
        reals = {"D_I": out["I_r"], "D_M": self._beside("D_M", "M_s", out, out["M_s"])}
        return {d: (reals[d], [k for k in names if k in out]) for d, names in candidates.items()}

    # the image each stack goes with, for a D_M that judges maps beside their image (loss.adv_m_cond)
    _IMAGE_OF = {"M_s": "fake_I", "fake_M": "I_r", "rec_M": "fake_I"}

    def _beside(self, dname: str, key: str, out: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """x (out[key], possibly detached) as the named discriminator sees it: with a conditioned D_M,
        the maps beside their (detached) image, so D_M's gradient reaches the maps only."""
        if dname != "D_M" or not self.cond_m:
            return x
        return torch.cat([x, out[self._IMAGE_OF[key]].detach()], dim=1)

    def _mismatched(self, out: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """M_s beside the next sample's R(M_s): real maps with an image they do not fit, one more fake
        for a conditioned D_M (None with a batch of one, where there is no other sample)."""
        if not self.cond_m or len(out["M_s"]) < 2:
            return None
        return torch.cat([out["M_s"], out["fake_I"].detach().roll(1, dims=0)], dim=1)

    def _disc(self, name: str) -> nn.Module:
        return self.D_I if name == "D_I" else self.D_M

    def _judge(self, name: str, x: torch.Tensor) -> list[torch.Tensor]:
        """A discriminator's logits on x; D_M sees maps masked to the car (loss.adv_m_on) and pooled
        by loss.adv_m_pool."""
        if name == "D_M" and self.loss_cfg.adv_m_on == "car":
            x = x * object_mask(x.detach())
        elif name == "D_M" and self.loss_cfg.adv_m_on == "reflection":
            x = torch.cat([torch.zeros_like(x[:, :6]), x[:, 6:]], dim=1)
        k = self.loss_cfg.adv_m_pool
        if name == "D_M" and k > 1:
            x = nn.functional.avg_pool2d(x, k)
        return self._disc(name)(x)

    def loss_terms(self, out: dict[str, torch.Tensor]) -> dict[str, tuple[float, torch.Tensor]]:
        """Every generator loss term as (weight, unweighted value); Eq. 7 is their weighted sum.
        `iae-train diagnose` measures each term's gradient from this."""
        lc = self.loss_cfg
        terms: dict[str, tuple[float, torch.Tensor]] = {}
        if "rec_M" in out:
            terms["G/ren_cycle"] = (lc.w_ren, cycle_loss(self.select(out["rec_M"]), self.select(out["M_s"]),
                                                         lc.smooth_l1_beta))
        if "rec_I" in out:
            terms["G/dec_cycle"] = (lc.w_dec, cycle_loss(out["rec_I"], out["I_r"], lc.smooth_l1_beta))
        if self.normal_output == "tanh" and lc.w_norm:
            norm = self._normal_length(out)
            if norm is not None:
                terms["G/normal_length"] = (lc.w_norm, norm)
        if lc.w_chroma and "fake_I" in out and "A" in self.inputs:
            a = out["M_s"][:, CHANNELS["A"]]
            terms["G/chroma"] = (lc.w_chroma, chroma_loss(out["fake_I"], a, object_mask(out["M_s"])))
        if lc.w_shading_ren and "fake_I" in out:  # R shades by the normals it is given
            m = out["M_s"]
            terms["G/shading_ren"] = (lc.w_shading_ren, shading_loss(out["fake_I"], m[:, 0:3], m[:, 3:6], m[:, 6:9],
                                                                     object_mask(m), gain=self.shared_gain()))
        if lc.w_shading_dec and "fake_M" in out:  # H's normals explain the real image's shading
            h = out["fake_M"]
            terms["G/shading_dec"] = (lc.w_shading_dec, shading_loss(out["I_r"], h[:, 0:3], h[:, 3:6], h[:, 6:9],
                                                                     object_mask(h.detach()), gain=self.shared_gain()))
        if lc.w_albedo_level and "fake_M" in out and self.albedo_levels is not None:
            terms["G/albedo_level"] = (lc.w_albedo_level, self._albedo_level(out["fake_M"], out["M_s"]))
        mean = lc.gan_reduce == "mean"
        for dname, (_, fakes) in self.discriminator_inputs(out).items():
            logits = self._judge(dname, torch.cat([self._beside(dname, f, out, out[f]) for f in fakes]))
            chunks = [torch.chunk(l, len(fakes)) for l in logits]
            rel = self._adv_weights(fakes)
            norm = sum(rel) if mean else 1.0
            scale = (lc.w_adv_m * (self.step >= lc.adv_m_from)) if dname == "D_M" else 1.0
            for k, f in enumerate(fakes):
                w = lc.w_adv * scale * rel[k] / norm
                terms[f"G/adv_{dname}_{f}"] = (w, gan_loss([c[k] for c in chunks], True, lc.gan, lc.gan_reduce))
        return terms

    def _albedo_level(self, fake_m: torch.Tensor, m_s: torch.Tensor) -> torch.Tensor:
        """loss.w_albedo_level: H's albedo level on real images (its own car mask) against the training
        intrinsics', both as running means updated while training (about 100 steps' memory)."""
        level = linear_mean(fake_m[:, 3:6], object_mask(fake_m.detach()))
        if self.training:
            train_level = linear_mean(m_s[:, 3:6], object_mask(m_s))
            update_running(self.albedo_levels, torch.stack([level.detach(), train_level]))
        return level_bias_loss(level, self.albedo_levels[0], self.albedo_levels[1])

    def shared_gain(self) -> torch.Tensor | None:
        """(3,) the shader R's shared reflection gain, which the shading fits hold fixed
        (model.shader_gain = "shared"); None for a fitted gain or the paper's R."""
        return self.R.shared_gain() if self.shader else None

    def _adv_weights(self, fakes: list[str]) -> list[float]:
        """Relative generator weights of one discriminator's fakes: the cycle reconstructions at
        loss.w_adv_rec beside a direct translation; alone (one cycle off) they keep weight 1."""
        direct = any(not f.startswith("rec_") for f in fakes)
        return [self.loss_cfg.w_adv_rec if direct and f.startswith("rec_") else 1.0 for f in fakes]

    def generator_loss(self, out: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        terms = self.loss_terms(out)
        total = out["M_s"].new_zeros((), dtype=torch.float32)
        for weight, value in terms.values():
            total = total + weight * value
        return finish_logs(total, {k: v for k, (_, v) in terms.items()}, "G")

    def _normal_length(self, out: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """L_norm. "threshold" (the paper, as read here): on H_N(I_r) and H_N(R(M_s)) wherever the
        prediction is longer than loss.normal_threshold. "car": on H_N(R(M_s)) where M_s has an
        object (the one output whose object mask is known), so it never acts on the background."""
        lc = self.loss_cfg
        if lc.normal_length_on == "car":
            if "rec_M" not in out:
                return None
            return normal_length_loss(out["rec_M"][:, :3], lc.normal_threshold, mask=object_mask(out["M_s"]))
        terms = [normal_length_loss(out[k][:, :3], lc.normal_threshold) for k in ("fake_M", "rec_M") if k in out]
        return sum(terms) if terms else None

    def discriminator_loss(self, out: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """Real vs the (detached) fakes; halved as in pix2pixHD so D learns at half G's pace."""
        lc = self.loss_cfg
        logs: dict[str, torch.Tensor] = {}
        total = out["M_s"].new_zeros((), dtype=torch.float32)
        for dname, (real, fakes) in self.discriminator_inputs(out).items():
            fake_in = [self._beside(dname, f, out, out[f].detach()) for f in fakes]
            wrong = self._mismatched(out) if dname == "D_M" else None
            fake_in += [wrong] if wrong is not None else []
            batch = torch.cat([real.detach()] + fake_in)
            chunks = [torch.chunk(l, 1 + len(fake_in)) for l in self._judge(dname, batch)]
            loss_real = gan_loss([c[0] for c in chunks], True, lc.gan, lc.gan_reduce)
            loss_fake = sum(gan_loss([c[k + 1] for c in chunks], False, lc.gan, lc.gan_reduce)
                            for k in range(len(fake_in))) / len(fake_in)
            logs[f"D/{dname}_real"], logs[f"D/{dname}_fake"] = loss_real, loss_fake
            total = total + 0.5 * (loss_real + loss_fake)
            if dname == "D_M" and lc.r1_m > 0:
                logs["D/D_M_r1"] = self._r1(dname, real)
                total = total + 0.5 * lc.r1_m * logs["D/D_M_r1"]
        return finish_logs(total, logs, "D")

    def _r1(self, dname: str, real: torch.Tensor) -> torch.Tensor:
        """Mean over the batch of the squared gradient of a discriminator's summed logits (every
        scale) at the real inputs; its own forward pass, so the penalty's graph holds only D."""
        x = real.detach().requires_grad_(True)
        score = sum(l.float().sum() for l in self._judge(dname, x))
        (grad,) = torch.autograd.grad(score, x, create_graph=True)
        return grad.float().pow(2).flatten(1).sum(1).mean()

    def visuals(self, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: out[k] for k in ("M_s", "fake_I", "rec_M", "I_r", "fake_M", "rec_I") if k in out}


class SupervisedOracle(IntrinsicAutoencoder):
    """Not in the paper: the same R and H trained with paired data (PBR images and their own
    intrinsics), by L1 in network space. Run with the same budget, it separates what the unpaired
    setting costs from what the budget costs. Training pairs come from the --real PBR set."""

    paired = True

    def __init__(self, cfg: Config):
        super().__init__(cfg)
        del self.D_I, self.D_M

    def discriminator_modules(self) -> dict[str, nn.Module]:
        return {}

    def forward_all(self, m_s: torch.Tensor, i_r: torch.Tensor, everything: bool = False) -> dict[str, torch.Tensor]:
        """`m_s` are the intrinsics of the images `i_r` here."""
        return {"M_s": m_s, "I_r": i_r, "fake_I": self.render(m_s), "fake_M": self.H(i_r)}

    def generator_loss(self, out: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        logs = {"G/render_l1": (out["fake_I"] - out["I_r"]).abs().mean(),
                "G/decompose_l1": (out["fake_M"] - out["M_s"]).abs().mean()}
        return finish_logs(logs["G/render_l1"] + logs["G/decompose_l1"], logs, "G")

    def discriminator_loss(self, out):
        raise RuntimeError("the supervised oracle has no discriminators")


def build_model(cfg: Config) -> ModelKind:
    if cfg.model.kind == "iae":
        return IntrinsicAutoencoder(cfg)
    if cfg.model.kind == "oracle":
        return SupervisedOracle(cfg)
    from . import baselines

    return baselines.build(cfg)
