"""Networks of the paper: pix2pixHD generator R, ResNet decomposers H, multi-scale PatchGANs.

Written here (no torchvision): they are a few conv blocks. Layouts follow pix2pixHD's
`GlobalGenerator`/`LocalEnhancer`/`MultiscaleDiscriminator` and CycleGAN's ResNet generator.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


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


def _decoder(ch: int, n_up: int, norm: str) -> tuple[list[nn.Module], int]:
    layers: list[nn.Module] = []
    for _ in range(n_up):
        layers += [nn.ConvTranspose2d(ch, ch // 2, 3, stride=2, padding=1, output_padding=1),
                   norm_layer(norm, ch // 2), nn.ReLU(True)]
        ch //= 2
    return layers, ch


class ResnetGenerator(nn.Module):
    """c7s1-ngf, n_down stride-2 convs, n_blocks residual blocks, n_down transposed convs, c7s1-out, tanh.

    pix2pixHD's GlobalGenerator is this with n_down=4, n_blocks=9; the paper's H nets use 5 blocks.
    """

    def __init__(self, in_ch: int, out_ch: int, ngf: int = 64, n_down: int = 2, n_blocks: int = 9,
                 norm: str = "instance", final: bool = True):
        super().__init__()
        enc, ch = _encoder(in_ch, ngf, n_down, norm)
        blocks = [ResnetBlock(ch, norm) for _ in range(n_blocks)]
        dec, ch = _decoder(ch, n_down, norm)
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
                 normal_output: str = "tanh"):
        super().__init__()
        self.h_n = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm)
        self.h_a = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm)
        self.h_f = ResnetGenerator(3, 3, ngf, n_down, n_blocks, norm)
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
