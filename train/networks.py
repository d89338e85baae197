"""Networks of the paper: pix2pixHD generator R, ResNet decomposers H, multi-scale PatchGANs.

Written here (no torchvision): they are a few conv blocks. Layouts follow pix2pixHD's
`GlobalGenerator`/`LocalEnhancer`/`MultiscaleDiscriminator` and CycleGAN's ResNet generator.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .colour import srgb_encode
from .losses import object_mask, update_running
from .shading import _C0, _C1, linear, render_sh

# Adam moves a parameter by about lr per step; the shared gain's log moves this many times faster
# (an equalised learning rate, as StyleGAN's), so it can travel from its start to the data's in a run
GAIN_LR_SCALE = 10.0

# where each intrinsic map sits in a 9-channel stack
CHANNELS = {"N": slice(0, 3), "A": slice(3, 6), "F": slice(6, 9)}


def init_weights(module: nn.Module, scheme: str = "normal") -> nn.Module:
    """The references' initialisation, applied to every conv and linear layer of `module`.

    "normal": N(0, 0.02) weights, zero biases, batch-norm scales N(1, 0.02) (pix2pixHD, CycleGAN,
    and MUNIT's discriminators); "kaiming": He-normal fan-in weights, zero biases (MUNIT's generators).
    """
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            if scheme == "normal":
                nn.init.normal_(m.weight, 0.0, 0.02)
            elif scheme == "kaiming":
                nn.init.kaiming_normal_(m.weight, a=0, mode="fan_in")
            else:
                raise ValueError(f"unknown init scheme {scheme!r}")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d) and scheme == "normal":
            nn.init.normal_(m.weight, 1.0, 0.02)
            nn.init.zeros_(m.bias)
    for m in module.modules():
        if isinstance(m, SubPixelUpsample):
            m.tie_phases()
    return module


def norm_layer(kind: str, channels: int) -> nn.Module:
    if kind == "instance":
        return nn.InstanceNorm2d(channels, affine=False)
    if kind == "none":
        return nn.Identity()
    return nn.BatchNorm2d(channels)


class ResnetBlock(nn.Module):
    def __init__(self, dim: int, norm: str):
        super().__init__()
        self.block = nn.Sequential(
            nn.ReflectionPad2d(1), nn.Conv2d(dim, dim, 3), norm_layer(norm, dim), nn.ReLU(True),
            nn.ReflectionPad2d(1), nn.Conv2d(dim, dim, 3), norm_layer(norm, dim),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x)


def _encoder(in_ch: int, ngf: int, n_down: int, norm: str) -> tuple[list[nn.Module], int]:
    layers: list[nn.Module] = [nn.ReflectionPad2d(3), nn.Conv2d(in_ch, ngf, 7), norm_layer(norm, ngf), nn.ReLU(True)]
    ch = ngf
    for _ in range(n_down):
        layers += [nn.Conv2d(ch, ch * 2, 3, stride=2, padding=1), norm_layer(norm, ch * 2), nn.ReLU(True)]
        ch *= 2
    return layers, ch


class SubPixelUpsample(nn.Module):
    """A 3x3 convolution to four times the channels, then a pixel shuffle (Shi et al., 2016): each
    output pixel of a 2x2 cell has its own filter, as in a transposed convolution, but every phase
    sees the same 3x3 neighbourhood. The phases start equal (ICNR, Aitken et al., 2017), so the
    layer starts as nearest-neighbour upsampling after a convolution, free of a checkerboard;
    training may still teach the phases apart."""

    def __init__(self, ch_in: int, ch_out: int):
        super().__init__()
        self.pad = nn.ReflectionPad2d(1)
        self.conv = nn.Conv2d(ch_in, 4 * ch_out, 3)
        self.shuffle = nn.PixelShuffle(2)
        self.tie_phases()

    @torch.no_grad()
    def tie_phases(self) -> None:
        """Copy each output channel's first phase filter to its other three (ICNR); `init_weights`
        calls it again after drawing new weights."""
        w, b = self.conv.weight, self.conv.bias
        w.copy_(w[0::4].repeat_interleave(4, dim=0))  # PixelShuffle reads channel 4c + k as phase k of c
        b.copy_(b[0::4].repeat_interleave(4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.shuffle(self.conv(self.pad(x)))


def upsample_layer(ch_in: int, ch_out: int, kind: str = "transposed") -> list[nn.Module]:
    """Twice the resolution. "transposed": pix2pixHD's and CycleGAN's 3x3 stride-2 transposed
    convolution, whose uneven kernel overlap stamps a 2x2 checkerboard on each level (Odena et al.,
    2016, "Deconvolution and Checkerboard Artifacts"); "resize": nearest-neighbour upsampling, then a
    3x3 convolution, which has no such pattern; "subpixel": `SubPixelUpsample`, a filter per phase
    like the transposed layer's, started without the pattern."""
    if kind == "resize":
        return [nn.Upsample(scale_factor=2, mode="nearest"), nn.ReflectionPad2d(1), nn.Conv2d(ch_in, ch_out, 3)]
    if kind == "subpixel":
        return [SubPixelUpsample(ch_in, ch_out)]
    return [nn.ConvTranspose2d(ch_in, ch_out, 3, stride=2, padding=1, output_padding=1)]


def _decoder(ch: int, n_up: int, norm: str, upsample: str = "transposed") -> tuple[list[nn.Module], int]:
    layers: list[nn.Module] = []
    for _ in range(n_up):
        layers += [*upsample_layer(ch, ch // 2, upsample), norm_layer(norm, ch // 2), nn.ReLU(True)]
        ch //= 2
    return layers, ch


class ResnetGenerator(nn.Module):
    """c7s1-ngf, n_down stride-2 convs, n_blocks residual blocks, n_down upsamplings (`upsample_layer`:
    transposed convs by default), c7s1-out, tanh.

    pix2pixHD's GlobalGenerator is this with n_down=4, n_blocks=9; the paper's H nets use 5 blocks.
    """

    def __init__(self, in_ch: int, out_ch: int, ngf: int = 64, n_down: int = 2, n_blocks: int = 9,
                 norm: str = "instance", final: bool = True, upsample: str = "transposed"):
        super().__init__()
        enc, ch = _encoder(in_ch, ngf, n_down, norm)
        blocks = [ResnetBlock(ch, norm) for _ in range(n_blocks)]
        dec, ch = _decoder(ch, n_down, norm, upsample)
        head = [nn.ReflectionPad2d(3), nn.Conv2d(ch, out_ch, 7), nn.Tanh()] if final else []
        self.model = nn.Sequential(*enc, *blocks, *dec, *head)
        self.out_features = ch

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class LocalEnhancer(nn.Module):
    """pix2pixHD's coarse-to-fine generator: a global generator on the half-resolution input,
    its last features added to a full-resolution front-end, then residual blocks and a head."""

    def __init__(self, in_ch: int, out_ch: int, ngf: int, n_down: int, n_blocks: int, norm: str):
        super().__init__()
        self.global_net = ResnetGenerator(in_ch, out_ch, ngf * 2, n_down, n_blocks, norm, final=False)
        self.front = nn.Sequential(
            nn.ReflectionPad2d(3), nn.Conv2d(in_ch, ngf, 7), norm_layer(norm, ngf), nn.ReLU(True),
            nn.Conv2d(ngf, ngf * 2, 3, stride=2, padding=1), norm_layer(norm, ngf * 2), nn.ReLU(True))
        self.back = nn.Sequential(
            ResnetBlock(ngf * 2, norm), ResnetBlock(ngf * 2, norm), ResnetBlock(ngf * 2, norm),
            nn.ConvTranspose2d(ngf * 2, ngf, 3, stride=2, padding=1, output_padding=1), norm_layer(norm, ngf),
            nn.ReLU(True), nn.ReflectionPad2d(3), nn.Conv2d(ngf, out_ch, 7), nn.Tanh())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        coarse = self.global_net(F.avg_pool2d(x, 3, stride=2, padding=1, count_include_pad=False))
        return self.back(self.front(x) + coarse)


def make_renderer_net(in_ch: int, ngf: int, n_down: int, n_blocks: int, local: int, norm: str) -> nn.Module:
    """R: intrinsics (3 per input map) -> RGB."""
    if local:
        return LocalEnhancer(in_ch, 3, ngf, n_down, n_blocks, norm)
    return ResnetGenerator(in_ch, 3, ngf, n_down, n_blocks, norm)


class Decomposer(nn.Module):
    """H = {H_N, H_A, H_F}: three ResNet generators, image -> 9 channels (normal, albedo, reflection)."""

    def __init__(self, ngf: int = 64, n_down: int = 2, n_blocks: int = 5, norm: str = "instance",
                 normal_output: str = "tanh", upsample: str = "transposed"):
        super().__init__()
        self.h_n = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm, upsample=upsample)
        self.h_a = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm, upsample=upsample)
        self.h_f = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm, upsample=upsample)
        self.normal_output = normal_output

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        n = self.h_n(img)
        if self.normal_output == "normalize":
            n = F.normalize(n, dim=1, eps=1e-6)
        return torch.cat([n, self.h_a(img), self.h_f(img)], dim=1)


class NLayerDiscriminator(nn.Module):
    """PatchGAN: 4x4 convs, LeakyReLU 0.2, one realism score per patch (logits)."""

    def __init__(self, in_ch: int, ndf: int = 64, n_layers: int = 3, norm: str = "instance"):
        super().__init__()
        pad = 2  # pix2pixHD's ceil((4 - 1) / 2)
        layers: list[nn.Module] = [nn.Conv2d(in_ch, ndf, 4, stride=2, padding=pad), nn.LeakyReLU(0.2, True)]
        ch = ndf
        for n in range(1, n_layers + 1):
            nxt = min(ch * 2, 512)
            stride = 2 if n < n_layers else 1
            layers += [nn.Conv2d(ch, nxt, 4, stride=stride, padding=pad), norm_layer(norm, nxt), nn.LeakyReLU(0.2, True)]
            ch = nxt
        layers.append(nn.Conv2d(ch, 1, 4, stride=1, padding=pad))
        self.model = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class MultiscaleDiscriminator(nn.Module):
    """PatchGANs at full, half, ... resolution; returns one logit map per scale."""

    def __init__(self, in_ch: int, ndf: int = 64, n_layers: int = 3, scales: int = 2, norm: str = "instance"):
        super().__init__()
        self.nets = nn.ModuleList(NLayerDiscriminator(in_ch, ndf, n_layers, norm) for _ in range(scales))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, net in enumerate(self.nets):
            if i:
                x = F.avg_pool2d(x, 3, stride=2, padding=1, count_include_pad=False)
            out.append(net(x))
        return out


class ShaderRenderer(nn.Module):
    """R as a deferred shader (not in the paper): linear RGB = lin(A) x SH(N; lighting) + gain x lin(F),
    9 SH coefficients and a gain per colour channel, then sRGB. R's image follows the normals from the
    first step, so the rendering cycle shows H images whose shading comes from the normals.

    Lighting: given per sample (fitted to a real image, `train.shading.fit_lighting`), else the mean
    of the bank of recent fits, else a learned global one. `residual` > 0 adds a generator's output
    of that amplitude for what the shading model lacks, on the background only by default; both
    placements measured worse (docs/normals_from_shading.md): on the car R and H agreed on a hidden
    code again, on the background its noise told H which images were R's.

    Background (`background`): "gain" scales the reflection layer by the car's gain there too;
    "environment" shows it as stored (the scene behind the car), apart from the car's fit.

    Takes the full 9-channel stack; a map outside `inputs` (an ablation) is replaced by what carries
    no information: a camera-facing normal, mid-grey albedo, no reflection."""

    def __init__(self, inputs: list[str], ngf: int, n_down: int, n_blocks: int, local: int, norm: str,
                 residual: float, residual_on: str = "background", bank: int = 0, shared_gain: float = 0.0,
                 background: str = "gain", bank_level: str = "fit", gain_min: float = 0.0):
        super().__init__()
        self.inputs = inputs
        self.background = background
        self.residual = residual
        self.residual_on = residual_on
        # lightings fitted to real images (9 SH coefficients and a reflection gain per colour channel),
        # most recent `bank` of them: drawn for R(M_s), their mean used where no lighting is given
        for name, value in (("bank", torch.zeros(bank, 3, 10)), ("bank_filled", torch.zeros((), dtype=torch.long)),
                            ("bank_pos", torch.zeros((), dtype=torch.long))):
            self.register_buffer(name, value if bank else None)  # None: not part of the weights
        # bank_level "images": running (3,) car levels of the real images and of R(M_s) under the bank's
        # lightings as fitted; their ratio scales every lighting the bank gives out (`level_scale`)
        self.register_buffer("levels", torch.zeros(2, 3) if bank and bank_level == "images" else None)
        light = torch.zeros(3, 9)
        light[:, 0] = 0.55 / _C0  # ambient
        light[:, 2] = 0.45 / _C1  # a light from the camera's side
        self.light = nn.Parameter(light)
        self.gain = nn.Parameter(torch.full((3,), 0.5))
        self.net = make_renderer_net(3 * len(inputs) + 3, ngf, n_down, n_blocks, local, norm) if residual > 0 else None
        # one reflection gain per colour channel for every image (model.shader_gain = "shared"), learned
        # in log space with a GAIN_LR_SCALE times larger step, above gain_min (model.shader_gain_min);
        # absent (not a weight) when gains are fitted
        self.gain_min = gain_min
        self.log_gain = (nn.Parameter(torch.full((3,), math.log(shared_gain - gain_min) / GAIN_LR_SCALE))
                         if shared_gain else None)

    def shared_gain(self) -> torch.Tensor | None:
        """(3,) the shared reflection gain, or None where each lighting carries its own."""
        return None if self.log_gain is None else self.gain_min + torch.exp(GAIN_LR_SCALE * self.log_gain)

    @torch.no_grad()
    def push(self, lighting: torch.Tensor) -> None:
        """Add (n, 3, 10) fitted lightings to the bank, oldest out first."""
        size = 0 if self.bank is None else len(self.bank)
        for row in lighting.detach()[-size:] if size else []:
            self.bank[self.bank_pos] = row.to(self.bank.dtype)
            self.bank_pos.fill_((int(self.bank_pos) + 1) % size)
            self.bank_filled.fill_(min(size, int(self.bank_filled) + 1))

    def draw(self, n: int) -> torch.Tensor | None:
        """(n, 3, 10) lightings drawn from the bank with the global RNG (at the bank's level,
        `level_scale`); None while it is empty."""
        filled = 0 if self.bank is None else int(self.bank_filled)
        if filled == 0:
            return None
        return self.bank[torch.randint(filled, (n,)).to(self.bank.device)] * self.level_scale().view(1, 3, 1)

    def level_scale(self) -> torch.Tensor:
        """(3,) per-channel factor on the bank's lightings (model.bank_level): the real images' running
        car level over R(M_s)'s under the lightings as fitted; 1 as fitted or before the first update."""
        ones = torch.ones(3, device=self.light.device)
        if self.levels is None or not bool(self.levels[1].gt(0).all()):
            return ones
        return (self.levels[0] / self.levels[1]).clamp(0.1, 10)

    @torch.no_grad()
    def update_levels(self, real: torch.Tensor, render_fitted: torch.Tensor, momentum: float = 0.99) -> None:
        """Fold this batch's (3,) linear car levels into the running ones: the real images' and R(M_s)'s
        under the drawn lightings as fitted (unscaled). No-op unless model.bank_level is "images"."""
        if self.levels is not None:
            update_running(self.levels, torch.stack([real, render_fitted]), momentum)

    def default_lighting(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(3, 9) lighting and (3,) gain for a render without a given lighting: the bank's mean where
        it has entries (the typical real lighting), else the learned global one."""
        filled = 0 if self.bank is None else int(self.bank_filled)
        if filled:
            mean = self.bank[:filled].mean(0) * self.level_scale().view(3, 1)
            return mean[:, :9], mean[:, 9]
        return self.light, self.gain

    def forward(self, m: torch.Tensor, lighting: torch.Tensor | None = None) -> torch.Tensor:
        """`lighting`: (n, 3, 10) per-sample SH lighting and reflection gain (`fit_lighting`), or None."""
        n, a, f = m[:, 0:3], m[:, 3:6], m[:, 6:9]
        if "N" not in self.inputs:
            n = torch.zeros_like(n)
            n[:, 2] = 1.0
        if "A" not in self.inputs:
            a = torch.zeros_like(a)
        if "F" not in self.inputs:
            f = torch.full_like(f, -1.0)
        light, gain = (lighting[..., :9], lighting[..., 9]) if lighting is not None else self.default_lighting()
        if self.log_gain is not None:
            gain = self.shared_gain()
        lin = render_sh(n, a, f, light, gain)
        if self.background == "environment":  # no object: the scene behind the car, at unit gain
            lin = torch.where(object_mask(m) > 0, lin, linear(f.float()))
        base = srgb_encode(lin) * 2 - 1
        if self.net is None:
            return base
        sel = torch.cat([m[:, CHANNELS[c]] for c in self.inputs] + [base.to(m.dtype)], dim=1)
        res = self.residual * self.net(sel)
        if self.residual_on == "background":  # on the car the image is the shading alone: no room for a code
            res = res * (1 - object_mask(m)).to(res.dtype)
        return (base + res).clamp(-1, 1)
