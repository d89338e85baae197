"""CycleGAN and MUNIT baselines: shapes, loss wiring, style seeds, pool, checkpoint/resume, overfit."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from train.baselines import CycleGAN, ImagePool, MUNIT
from train.config import load_config
from train.loop import fit
from train.model import build_model

from .conftest import ROOT
from .train_helpers import tiny_fit, tiny_intrinsics, tiny_overrides, tiny_photos


def cfg_for(kind: str, *extra: str):
    return load_config(kind, tiny_overrides(kind) + list(extra))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("base")
    return tiny_intrinsics(root / "intr"), tiny_photos(root / "photos")


@pytest.mark.parametrize("kind, cls", [("cyclegan", CycleGAN), ("munit", MUNIT)])
@pytest.mark.parametrize("h, w", [(32, 64), (64, 128)])
def test_shapes(kind, cls, h, w):
    model = build_model(cfg_for(kind, f"data.height={h}", f"data.width={w}"))
    assert isinstance(model, cls)
    m, x = torch.randn(2, 9, h, w).tanh(), torch.randn(2, 3, h, w).tanh()
    assert model.render(m).shape == (2, 3, h, w) and model.decompose(x).shape == (2, 9, h, w)
    out = model.forward_all(m, x)
    for k, c in (("fake_I", 3), ("rec_I", 3), ("fake_M", 9), ("rec_M", 9)):
        assert out[k].shape == (2, c, h, w)


def test_cyclegan_loss_wiring_and_pool():
    model = build_model(cfg_for("cyclegan"))
    m, x = torch.randn(2, 9, 32, 64).tanh(), torch.randn(2, 3, 32, 64).tanh()
    out = model.forward_all(m, x)
    _, logs = model.generator_loss(out)
    assert set(logs) == {"G/adv_img", "G/adv_intr", "G/cycle_intr", "G/cycle_img", "G/total"}
    expected = logs["G/adv_img"] + logs["G/adv_intr"] + 10 * (logs["G/cycle_intr"] + logs["G/cycle_img"])
    assert logs["G/total"] == pytest.approx(expected, rel=1e-5)
    assert torch.allclose(out["rec_M"], model.G_decomp(out["fake_I"]))  # cycle through both generators
    pool = ImagePool(3, (1, 1, 1))
    first = pool.query(torch.arange(3.0).reshape(3, 1, 1, 1))
    assert torch.equal(first.flatten(), torch.arange(3.0)) and int(pool.count) == 3
    torch.manual_seed(0)
    later = pool.query(torch.full((40, 1, 1, 1), 9.0)).flatten()
    from_history = (later != 9.0).sum().item()
    assert 0 < from_history < 40, "about half the fakes come from the history once it is full"


def test_munit_style_codes_are_seeded_and_decomposition_is_deterministic():
    model = build_model(cfg_for("munit")).eval()
    m, x = torch.randn(1, 9, 32, 64).tanh(), torch.randn(1, 3, 32, 64).tanh()
    with torch.no_grad():
        a = model.render(m, generator=torch.Generator().manual_seed(3))
        b = model.render(m, generator=torch.Generator().manual_seed(3))
        c = model.render(m, generator=torch.Generator().manual_seed(4))
        assert torch.equal(a, b) and not torch.equal(a, c)
        assert torch.equal(model.decompose(x), model.decompose(x))
    _, logs = model.generator_loss(model.forward_all(m, x))
    assert {"G/recon_x_a", "G/recon_s_b", "G/recon_c_a", "G/adv_a", "G/adv_b"} <= set(logs)


@pytest.mark.parametrize("kind", ["cyclegan", "munit"])
def test_checkpoint_and_exact_resume(kind, data, tmp_path):
    intr, photos = data
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    # the uninterrupted run and the first half in this process; the resume, the subject, from the
    # command line in a fresh one (nothing but the run folder carries the state over)
    tiny_fit(whole, intr, photos, 4, preset=kind)
    tiny_fit(parts, intr, photos, 3, preset=kind)
    subprocess.run([sys.executable, "-m", "train.cli", "fit", "--run-dir", str(parts), "--max-steps", "4", "--quiet"],
                   cwd=ROOT, check=True)
    a = [json.loads(x) for x in (whole / "stats.jsonl").read_text().splitlines()]
    b = [json.loads(x) for x in (parts / "stats.jsonl").read_text().splitlines()]
    assert len(a) == len(b) == 4
    for ra, rb in zip(a, b):
        assert ra == pytest.approx(rb, rel=1e-5, abs=1e-7)
    rendered = tmp_path / "r"
    subprocess.run([sys.executable, "-m", "train.cli", "render", "--run", str(whole), "--intrinsics", str(intr),
                    "--out", str(rendered), "--style-seed", "1", "--quiet"], cwd=ROOT, check=True)
    assert len(list(rendered.glob("*.png"))) == 4


@pytest.mark.parametrize("kind, key", [("cyclegan", "G/cycle_intr"), ("munit", "G/recon_x_a")])
def test_short_overfit(kind, key, data, tmp_path):
    intr, photos = data
    torch.manual_seed(0)
    cfg = cfg_for(kind, "optim.lr=1e-3", "run.checkpoint_every=1000", "run.grid_every=1000")
    fit(tmp_path / kind, cfg, str(intr), str(photos), max_steps=40, progress=False)
    vals = [json.loads(x)[key] for x in (tmp_path / kind / "stats.jsonl").read_text().splitlines()]
    assert np.mean(vals[-8:]) < 0.6 * np.mean(vals[:4]), (vals[:4], vals[-8:])


def test_reference_initialisation():
    torch.manual_seed(0)
    iae = build_model(load_config("paper", ["model.r_local_enhancers=0", "model.r_ngf=64"]))
    convs = [m for m in iae.modules() if isinstance(m, torch.nn.Conv2d) and m.weight.numel() > 100_000]
    assert convs and all(abs(float(c.weight.detach().std()) - 0.02) < 0.002 for c in convs)
    assert all(float(m.bias.abs().max()) == 0 for m in iae.modules() if isinstance(m, torch.nn.Conv2d))
    cyc = build_model(load_config("cyclegan"))
    assert abs(float(cyc.G_render.model[1].weight.detach().std()) - 0.02) < 0.002
    munit = build_model(load_config("munit"))
    conv = munit.gen_a.content.model[1]  # 9 -> 64, 7x7: He-normal std sqrt(2 / fan_in)
    assert abs(float(conv.weight.detach().std()) / (2 / (9 * 49)) ** 0.5 - 1) < 0.05
    assert abs(float(munit.D_b.nets[0][1].weight.detach().std()) - 0.02) < 0.003


def test_munit_discriminator_is_the_reference_layout_and_its_loss_sums_scales():
    model = build_model(load_config("munit"))
    net = model.D_b.nets[0]
    convs = [m for m in net if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (3, 64, (4, 4), (2, 2)), (64, 128, (4, 4), (2, 2)), (128, 256, (4, 4), (2, 2)), (256, 512, (4, 4), (2, 2)),
        (512, 1, (1, 1), (1, 1))]
    assert sum(isinstance(m, torch.nn.ReflectionPad2d) for m in net) == 4
    assert not any(isinstance(m, (torch.nn.InstanceNorm2d, torch.nn.BatchNorm2d)) for m in model.D_b.modules())
    assert len(model.D_b.nets) == 3
    small = build_model(cfg_for("munit"))
    m, x = torch.randn(1, 9, 32, 64).tanh(), torch.randn(1, 3, 32, 64).tanh()
    out = small.forward_all(m, x)
    _, logs = small.discriminator_loss(out)
    real = small.D_b(x)
    assert len(real) == 3
    expected = sum(float(((d - 1) ** 2).mean()) for d in real)
    assert logs["D/D_b_real"] == pytest.approx(expected, rel=1e-5)


def test_munit_adain_takes_the_mlp_outputs_as_scale_and_bias():
    model = build_model(cfg_for("munit")).eval()
    dec = model.gen_b.decoder
    style = torch.randn(2, 8)
    with torch.no_grad():
        params = dec.mlp(style)
        dec(torch.randn(2, dec.adains[0].channels, 8, 16), style)
    c = dec.adains[0].channels
    assert torch.equal(dec.adains[0].bias, params[:, :c]) and torch.equal(dec.adains[0].weight, params[:, c:2 * c])


def test_munit_optimiser_has_weight_decay_and_the_step_policy():
    from train.loop import lr_factor

    cfg = load_config("munit")
    assert (cfg.optim.weight_decay, cfg.optim.lr_policy, cfg.optim.step_size, cfg.optim.step_gamma) == (1e-4, "step",
                                                                                                        100000, 0.5)
    f = lr_factor(cfg.optim)
    assert [f(0), f(99_999), f(100_000), f(250_000)] == [1.0, 1.0, 0.5, 0.25]
    g = lr_factor(load_config("paper").optim)
    assert [g(0), g(100_000), g(150_000), g(200_000)] == [1.0, 1.0, 0.5, 0.0]


@pytest.mark.parametrize("kind", ["iae", "cyclegan", "munit", "oracle"])
def test_every_model_kind_implements_the_protocol(kind):
    from train.model import ModelKind

    cfg = load_config("cpu-small", ["model.kind=oracle"]) if kind == "oracle" else \
        load_config("cpu-small") if kind == "iae" else cfg_for(kind)
    model = build_model(cfg)
    assert isinstance(model, ModelKind)
    assert all(isinstance(m, torch.nn.Module) for m in model.generator_modules().values())
