"""The paper's baselines on the 9-channel intrinsics stack: CycleGAN and MUNIT.

Both expose the Intrinsic Autoencoder's interface (forward_all, generator_loss,
discriminator_loss, render, decompose, visuals) so they train, log, checkpoint, resume and
run inference through the same loop and commands, and they reuse its building blocks:
ResNet generators, PatchGAN discriminators, GAN losses and the data pipeline. Each reads
its own config section ([cyclegan], [munit]) with the reference implementation's defaults.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import Config
from .losses import discriminator_terms, finish_logs, gan_loss
from .networks import MultiscaleDiscriminator, ResnetBlock, ResnetGenerator, init_weights, norm_layer


class ImagePool(nn.Module):
    """CycleGAN's history of 50 generated images for the discriminator update.

    The history is a buffer, so checkpoints hold it and a resumed run sees the same pool.
    """

    def __init__(self, size: int, shape: tuple[int, int, int]):
        super().__init__()
        self.size = size
        self.register_buffer("images", torch.zeros((size, *shape)))
        self.register_buffer("count", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def query(self, batch: torch.Tensor) -> torch.Tensor:
        if self.size == 0:
            return batch
        out = []
        for img in batch:
            n = int(self.count)
            if n < self.size:
                self.images[n] = img.to(self.images.dtype)
                self.count += 1
                out.append(img)
            elif torch.rand(()) < 0.5:
                k = int(torch.randint(0, self.size, ()))
                out.append(self.images[k].clone().to(img.dtype))
                self.images[k] = img.to(self.images.dtype)
            else:
                out.append(img)
        return torch.stack(out)


class CycleGAN(nn.Module):
    """Reference defaults: ResNet generators (9 blocks at 256 px), 70x70 PatchGAN, LSGAN,
    L1 cycle weight 10 both ways, pool of 50, identity loss off (channel counts differ)."""

    def __init__(self, cfg: Config):
        super().__init__()
        c = self.cfg = cfg.cyclegan
        self.G_render = ResnetGenerator(9, 3, c.ngf, c.n_down, c.n_blocks, c.norm)
        self.G_decomp = ResnetGenerator(3, 9, c.ngf, c.n_down, c.n_blocks, c.norm)
        self.D_img = MultiscaleDiscriminator(3, c.ndf, c.d_layers, 1, c.norm)  # one scale: the 70x70 PatchGAN
        self.D_intr = MultiscaleDiscriminator(9, c.ndf, c.d_layers, 1, c.norm)
        init_weights(self, "normal")  # the reference's init_type = normal, gain 0.02
        hw = (cfg.data.height, cfg.data.width)
        self.pool_img = ImagePool(c.pool, (3, *hw))
        self.pool_intr = ImagePool(c.pool, (9, *hw))

    def generator_modules(self):
        return {"G_render": self.G_render, "G_decomp": self.G_decomp}

    def discriminator_modules(self):
        return {"D_img": self.D_img, "D_intr": self.D_intr}

    def render(self, m, generator=None):
        return self.G_render(m)

    def decompose(self, img):
        return self.G_decomp(img)

    def forward_all(self, m_s, i_r, everything: bool = False):
        fake_I, fake_M = self.G_render(m_s), self.G_decomp(i_r)
        return {"M_s": m_s, "I_r": i_r, "fake_I": fake_I, "fake_M": fake_M,
                "rec_M": self.G_decomp(fake_I), "rec_I": self.G_render(fake_M)}

    def generator_loss(self, out):
        c = self.cfg
        logs = {
            "G/adv_img": gan_loss(self.D_img(out["fake_I"]), True, c.gan),
            "G/adv_intr": gan_loss(self.D_intr(out["fake_M"]), True, c.gan),
            "G/cycle_intr": F.l1_loss(out["rec_M"], out["M_s"]),
            "G/cycle_img": F.l1_loss(out["rec_I"], out["I_r"]),
        }
        total = c.w_adv * (logs["G/adv_img"] + logs["G/adv_intr"]) \
            + c.w_cycle * (logs["G/cycle_intr"] + logs["G/cycle_img"])
        return finish_logs(total, logs, "G")

    def discriminator_loss(self, out):
        c = self.cfg
        logs = {}
        total = 0.0
        for name, d, real, fake, pool in (("D_img", self.D_img, out["I_r"], out["fake_I"], self.pool_img),
                                          ("D_intr", self.D_intr, out["M_s"], out["fake_M"], self.pool_intr)):
            logs[f"D/{name}_real"], logs[f"D/{name}_fake"] = discriminator_terms(d, real, pool.query(fake.detach()), c.gan)
            total = total + 0.5 * (logs[f"D/{name}_real"] + logs[f"D/{name}_fake"])
        return finish_logs(total, logs, "D")

    def visuals(self, out):
        return {k: out[k] for k in ("M_s", "fake_I", "rec_M", "I_r", "fake_M", "rec_I")}


# ----------------------------------------------------------------------------- MUNIT

class AdaptiveInstanceNorm2d(nn.Module):
    """Instance norm whose scale and bias are set per sample from a style code.

    As in the reference, the MLP's outputs are the scale and bias themselves (no offset of 1).
    """

    def __init__(self, channels: int):
        super().__init__()
        self.channels = channels
        self.weight: torch.Tensor | None = None
        self.bias: torch.Tensor | None = None

    def forward(self, x):
        x = F.instance_norm(x, eps=1e-5)
        return x * self.weight[:, :, None, None] + self.bias[:, :, None, None]


class LayerNorm2d(nn.Module):
    """MUNIT's layer norm: per sample over (C, H, W), divided by the unbiased std plus eps,
    then a per-channel affine transform whose scale starts uniform in [0, 1) (the reference's)."""

    def __init__(self, channels: int, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.gamma = nn.Parameter(torch.rand(channels))
        self.beta = nn.Parameter(torch.zeros(channels))

    def forward(self, x):
        flat = x.flatten(1)
        mean = flat.mean(1).view(-1, 1, 1, 1)
        std = flat.std(1).view(-1, 1, 1, 1)
        x = (x - mean) / (std + self.eps)
        return x * self.gamma[None, :, None, None] + self.beta[None, :, None, None]


class AdaINResBlock(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.conv1, self.conv2 = nn.Conv2d(dim, dim, 3), nn.Conv2d(dim, dim, 3)
        self.n1, self.n2 = AdaptiveInstanceNorm2d(dim), AdaptiveInstanceNorm2d(dim)

    def forward(self, x):
        y = F.relu(self.n1(self.conv1(F.pad(x, (1, 1, 1, 1), mode="reflect"))))
        return x + self.n2(self.conv2(F.pad(y, (1, 1, 1, 1), mode="reflect")))


class ContentEncoder(nn.Module):
    def __init__(self, in_ch: int, dim: int, n_down: int, n_res: int):
        super().__init__()
        layers = [nn.ReflectionPad2d(3), nn.Conv2d(in_ch, dim, 7), norm_layer("instance", dim), nn.ReLU(True)]
        for _ in range(n_down):
            layers += [nn.ReflectionPad2d(1), nn.Conv2d(dim, dim * 2, 4, stride=2), norm_layer("instance", dim * 2),
                       nn.ReLU(True)]
            dim *= 2
        layers += [ResnetBlock(dim, "instance") for _ in range(n_res)]
        self.model, self.out_dim = nn.Sequential(*layers), dim

    def forward(self, x):
        return self.model(x)


class StyleEncoder(nn.Module):
    def __init__(self, in_ch: int, dim: int, style_dim: int, n_down: int = 4):
        super().__init__()
        layers = [nn.ReflectionPad2d(3), nn.Conv2d(in_ch, dim, 7), nn.ReLU(True)]
        for i in range(n_down):
            nxt = dim * 2 if i < 2 else dim
            layers += [nn.ReflectionPad2d(1), nn.Conv2d(dim, nxt, 4, stride=2), nn.ReLU(True)]
            dim = nxt
        layers += [nn.AdaptiveAvgPool2d(1), nn.Conv2d(dim, style_dim, 1)]
        self.model = nn.Sequential(*layers)

    def forward(self, x):
        return self.model(x).flatten(1)


class MunitDecoder(nn.Module):
    def __init__(self, dim: int, out_ch: int, n_up: int, n_res: int, style_dim: int, mlp_dim: int):
        super().__init__()
        self.res = nn.ModuleList(AdaINResBlock(dim) for _ in range(n_res))
        up = []
        for _ in range(n_up):
            up += [nn.Upsample(scale_factor=2), nn.ReflectionPad2d(2), nn.Conv2d(dim, dim // 2, 5), LayerNorm2d(dim // 2),
                   nn.ReLU(True)]
            dim //= 2
        up += [nn.ReflectionPad2d(3), nn.Conv2d(dim, out_ch, 7), nn.Tanh()]
        self.up = nn.Sequential(*up)
        self.adains = [m for m in self.res.modules() if isinstance(m, AdaptiveInstanceNorm2d)]
        n_params = sum(2 * a.channels for a in self.adains)
        self.mlp = nn.Sequential(nn.Linear(style_dim, mlp_dim), nn.ReLU(True), nn.Linear(mlp_dim, mlp_dim),
                                 nn.ReLU(True), nn.Linear(mlp_dim, n_params))

    def forward(self, content, style):
        params = self.mlp(style)
        k = 0
        for a in self.adains:
            a.bias = params[:, k:k + a.channels]
            a.weight = params[:, k + a.channels:k + 2 * a.channels]
            k += 2 * a.channels
        x = content
        for block in self.res:
            x = block(x)
        return self.up(x)


class MunitAutoEncoder(nn.Module):
    def __init__(self, in_ch: int, cfg: Config):
        super().__init__()
        m = cfg.munit
        self.content = ContentEncoder(in_ch, m.dim, m.n_down, m.n_res)
        self.style = StyleEncoder(in_ch, m.dim, m.style_dim, m.style_down)
        self.decoder = MunitDecoder(self.content.out_dim, in_ch, m.n_down, m.n_res, m.style_dim, m.mlp_dim)


class MunitDiscriminator(MultiscaleDiscriminator):
    """The reference's MsImageDis: per scale, a 4x4 stride-2 reflect-padded conv with LeakyReLU,
    n_layers - 1 more doubling the width, then a 1x1 conv to one logit map; no norm. Scales
    are 3x3 average pools (stride 2, padding 1, padding not counted), as in the parent class."""

    def __init__(self, in_ch: int, ndf: int, n_layers: int, scales: int):
        nn.Module.__init__(self)  # the parent's per-scale PatchGANs are replaced by the reference's nets

        def net() -> nn.Sequential:
            layers, ch = [], in_ch
            for i in range(n_layers):
                nxt = ndf * 2 ** i
                layers += [nn.ReflectionPad2d(1), nn.Conv2d(ch, nxt, 4, 2), nn.LeakyReLU(0.2, True)]
                ch = nxt
            return nn.Sequential(*layers, nn.Conv2d(ch, 1, 1))

        self.nets = nn.ModuleList(net() for _ in range(scales))


class MUNIT(nn.Module):
    """MUNIT with domain a = the 9-channel intrinsics (input_dim 9), b = images.

    Reference configuration: LSGAN, image reconstruction weight 10, style and content
    reconstruction weight 1, cycle reconstruction 0, 8-d style codes; multi-scale
    discriminators without normalisation. Rendering draws a random style code (seeded by
    --style-seed); decomposition uses the prior's mean style, so it is deterministic.
    """

    def __init__(self, cfg: Config):
        super().__init__()
        m = self.cfg = cfg.munit
        self.style_dim = m.style_dim
        self.gen_a, self.gen_b = MunitAutoEncoder(9, cfg), MunitAutoEncoder(3, cfg)
        self.D_a = MunitDiscriminator(9, m.d_ndf, m.d_layers, m.d_scales)
        self.D_b = MunitDiscriminator(3, m.d_ndf, m.d_layers, m.d_scales)
        for gen in (self.gen_a, self.gen_b):
            init_weights(gen, "kaiming")  # the reference's init: kaiming (generators) ...
        for dis in (self.D_a, self.D_b):
            init_weights(dis, "normal")  # ... and gaussian N(0, 0.02) (discriminators)

    def generator_modules(self):
        return {"gen_a": self.gen_a, "gen_b": self.gen_b}

    def discriminator_modules(self):
        return {"D_a": self.D_a, "D_b": self.D_b}

    def _style(self, n: int, like: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        s = torch.randn(n, self.style_dim, generator=generator)
        return s.to(like.device, like.dtype)

    def render(self, m, generator: torch.Generator | None = None):
        return self.gen_b.decoder(self.gen_a.content(m), self._style(m.shape[0], m, generator))

    def decompose(self, img):
        zero = torch.zeros(img.shape[0], self.style_dim, device=img.device, dtype=img.dtype)
        return self.gen_a.decoder(self.gen_b.content(img), zero)

    def forward_all(self, m_s, i_r, everything: bool = False):
        c_a, s_a_prime = self.gen_a.content(m_s), self.gen_a.style(m_s)
        c_b, s_b_prime = self.gen_b.content(i_r), self.gen_b.style(i_r)
        s_a, s_b = self._style(m_s.shape[0], m_s), self._style(i_r.shape[0], i_r)
        out = {"M_s": m_s, "I_r": i_r, "s_a": s_a, "s_b": s_b, "c_a": c_a, "c_b": c_b,
               "rec_M": self.gen_a.decoder(c_a, s_a_prime), "rec_I": self.gen_b.decoder(c_b, s_b_prime),
               "fake_M": self.gen_a.decoder(c_b, s_a), "fake_I": self.gen_b.decoder(c_a, s_b)}
        out["c_b_recon"], out["s_a_recon"] = self.gen_a.content(out["fake_M"]), self.gen_a.style(out["fake_M"])
        out["c_a_recon"], out["s_b_recon"] = self.gen_b.content(out["fake_I"]), self.gen_b.style(out["fake_I"])
        return out

    def generator_loss(self, out):
        lc = self.cfg
        logs = {
            "G/recon_x_a": F.l1_loss(out["rec_M"], out["M_s"]),
            "G/recon_x_b": F.l1_loss(out["rec_I"], out["I_r"]),
            "G/recon_s_a": F.l1_loss(out["s_a_recon"], out["s_a"]),
            "G/recon_s_b": F.l1_loss(out["s_b_recon"], out["s_b"]),
            "G/recon_c_a": F.l1_loss(out["c_a_recon"], out["c_a"]),
            "G/recon_c_b": F.l1_loss(out["c_b_recon"], out["c_b"]),
            "G/adv_a": gan_loss(self.D_a(out["fake_M"]), True, lc.gan),
            "G/adv_b": gan_loss(self.D_b(out["fake_I"]), True, lc.gan),
        }
        total = lc.w_adv * (logs["G/adv_a"] + logs["G/adv_b"]) \
            + lc.w_recon_x * (logs["G/recon_x_a"] + logs["G/recon_x_b"]) \
            + lc.w_recon_s * (logs["G/recon_s_a"] + logs["G/recon_s_b"]) \
            + lc.w_recon_c * (logs["G/recon_c_a"] + logs["G/recon_c_b"])
        if lc.w_cyc:
            cyc_a = self.gen_a.decoder(out["c_a_recon"], self.gen_a.style(out["M_s"]))
            cyc_b = self.gen_b.decoder(out["c_b_recon"], self.gen_b.style(out["I_r"]))
            logs["G/cycle"] = F.l1_loss(cyc_a, out["M_s"]) + F.l1_loss(cyc_b, out["I_r"])
            total = total + lc.w_cyc * logs["G/cycle"]
        return finish_logs(total, logs, "G")

    def discriminator_loss(self, out):
        lc = self.cfg
        logs = {}
        total = 0.0
        for name, d, real, fake in (("D_a", self.D_a, out["M_s"], out["fake_M"]), ("D_b", self.D_b, out["I_r"], out["fake_I"])):
            logs[f"D/{name}_real"], logs[f"D/{name}_fake"] = discriminator_terms(d, real, fake, lc.gan)
            total = total + logs[f"D/{name}_real"] + logs[f"D/{name}_fake"]
        return finish_logs(total, logs, "D")

    def visuals(self, out):
        return {k: out[k] for k in ("M_s", "fake_I", "rec_M", "I_r", "fake_M", "rec_I")}


def build(cfg: Config) -> nn.Module:
    if cfg.model.kind == "cyclegan":
        return CycleGAN(cfg)
    if cfg.model.kind == "munit":
        return MUNIT(cfg)
    raise ValueError(f"model.kind {cfg.model.kind!r}")
