"""The trainer: networks, losses, wiring of the shared discriminators, steps, checkpoints, resume, DDP."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from train.config import ConfigError, load_config, set_value
from train.data import RealImages, StepSampler, flip_stack
from train.losses import cycle_loss, gan_loss, normal_length_loss
from train.loop import discriminator_step, fit, generator_step
from train.model import IntrinsicAutoencoder, build_model
from train.networks import Decomposer, LocalEnhancer, MultiscaleDiscriminator, ResnetGenerator

from .conftest import ROOT
from .train_helpers import TINY, tiny_intrinsics, tiny_overrides, tiny_photos


def tiny_cfg(**sets):
    cfg = load_config("cpu-small", tiny_overrides())
    for k, v in sets.items():
        set_value(cfg, k.replace("__", "."), v)
    return cfg


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    return tiny_intrinsics(root / "intr"), tiny_photos(root / "photos")


@pytest.mark.parametrize("h, w", [(32, 64), (64, 128)])
def test_network_shapes(h, w):
    x9, x3 = torch.randn(2, 9, h, w), torch.randn(2, 3, h, w)
    assert ResnetGenerator(9, 3, 8, n_down=4, n_blocks=2)(x9).shape == (2, 3, h, w)  # pix2pixHD global
    assert LocalEnhancer(9, 3, 8, 3, 1, "instance")(x9).shape == (2, 3, h, w)
    assert Decomposer(8, 2, 5)(x3).shape == (2, 9, h, w)
    outs = MultiscaleDiscriminator(9, 8, 3, 2)(x9)
    assert len(outs) == 2 and outs[0].shape[:2] == (2, 1) and outs[1].shape[-1] < outs[0].shape[-1]
    cfg = tiny_cfg(data__height=h, data__width=w, model__inputs="NA")
    model = IntrinsicAutoencoder(cfg)
    out = model.forward_all(x9.tanh(), x3.tanh())
    assert out["fake_I"].shape == (2, 3, h, w) and out["fake_M"].shape == (2, 9, h, w)
    assert out["rec_M"].shape == (2, 9, h, w) and out["rec_I"].shape == (2, 3, h, w)
    assert model.R.model[1].in_channels == 6


def test_losses_against_hand_computed_values():
    d = [torch.tensor([[0.5, 1.0]]), torch.tensor([[0.0]])]
    # lsgan, real: ((0.5-1)^2 + 0)/2 = 0.125 at scale 1; (0-1)^2 = 1 at scale 2; mean = 0.5625
    assert gan_loss(d, True, "lsgan").item() == pytest.approx(0.5625)
    assert gan_loss(d, False, "lsgan").item() == pytest.approx(((0.25 + 1.0) / 2 + 0.0) / 2)
    # bce, real: -log(sigmoid(x)) = softplus(-x)
    sp = lambda x: math.log1p(math.exp(-x))  # noqa: E731
    assert gan_loss(d, True, "bce").item() == pytest.approx(((sp(0.5) + sp(1.0)) / 2 + sp(0.0)) / 2, rel=1e-6)
    # smooth L1 with beta 0.5: |0.2| < beta -> 0.5*0.04/0.5 = 0.04; |1.0| -> 1.0 - 0.25 = 0.75
    assert cycle_loss(torch.tensor([0.2, 1.0]), torch.zeros(2), 0.5).item() == pytest.approx((0.04 + 0.75) / 2)
    # normal length: |(0.6, 0, 0)| = 0.6 -> 0.4; |(0, 2, 0)| = 2 -> 1.0; (0.1, 0, 0) below threshold: ignored
    n = torch.tensor([[0.6, 0.0, 0.1], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]]).reshape(1, 3, 1, 3)
    assert normal_length_loss(n, 0.5).item() == pytest.approx((0.4 + 1.0) / 2)


def test_which_fakes_reach_which_discriminator():
    x9, x3 = torch.randn(1, 9, 32, 64).tanh(), torch.randn(1, 3, 32, 64).tanh()
    shared = IntrinsicAutoencoder(tiny_cfg())
    wiring = {k: v[1] for k, v in shared.discriminator_inputs(shared.forward_all(x9, x3)).items()}
    assert wiring == {"D_I": ["fake_I", "rec_I"], "D_M": ["fake_M", "rec_M"]}
    separate = IntrinsicAutoencoder(tiny_cfg(loss__shared_discriminator=False))
    wiring = {k: v[1] for k, v in separate.discriminator_inputs(separate.forward_all(x9, x3)).items()}
    assert wiring == {"D_I": ["fake_I"], "D_M": ["fake_M"]}
    ren_only = IntrinsicAutoencoder(tiny_cfg(loss__decomposition_cycle=False))
    out = ren_only.forward_all(x9, x3)
    assert "rec_I" not in out and "rec_M" in out
    _, logs = ren_only.generator_loss(out)
    assert "G/dec_cycle" not in logs and "G/ren_cycle" in logs
    reals = shared.discriminator_inputs(shared.forward_all(x9, x3))
    assert reals["D_I"][0] is x3 and reals["D_M"][0] is x9


def test_discriminator_step_never_moves_generators_and_vice_versa():
    torch.manual_seed(0)
    model = IntrinsicAutoencoder(tiny_cfg())
    g_params = [p for m in model.generator_modules().values() for p in m.parameters()]
    d_params = [p for m in model.discriminator_modules().values() for p in m.parameters()]
    opt_g, opt_d = torch.optim.Adam(g_params, lr=1e-2), torch.optim.Adam(d_params, lr=1e-2)
    x9, x3 = torch.randn(2, 9, 32, 64).tanh(), torch.randn(2, 3, 32, 64).tanh()
    snap = lambda ps: [p.detach().clone() for p in ps]  # noqa: E731
    same = lambda a, b: all(torch.equal(x, y) for x, y in zip(a, b))  # noqa: E731
    g0, d0 = snap(g_params), snap(d_params)
    out, _ = generator_step(model, opt_g, g_params, x9, x3)
    assert same(d0, d_params) and not same(g0, g_params)
    g1 = snap(g_params)
    discriminator_step(model, opt_d, d_params, out)
    assert same(g1, g_params) and not same(d0, d_params)


def test_flip_negates_normal_x_and_sampler_is_a_pure_function():
    m = torch.arange(9 * 2 * 3, dtype=torch.float32).reshape(9, 2, 3)
    f = flip_stack(m.clone())
    assert torch.equal(f[0], -m[0].flip(-1)) and torch.equal(f[1:], m[1:].flip(-1))
    a = StepSampler(10, 3, seed=1, stream=0)
    b = StepSampler(10, 3, seed=1, stream=0, start_step=5)
    assert a.batch_at(5) == next(iter(b))
    r0 = StepSampler(10, 2, 1, 0, rank=0, world=2).batch_at(0)
    r1 = StepSampler(10, 2, 1, 0, rank=1, world=2).batch_at(0)
    assert not {i for i, _ in r0} & {i for i, _ in r1}


def test_real_images_from_photos_are_resized_and_centre_cropped(data):
    _, photos = data
    reals = RealImages(photos, 32, 64)
    x = reals[(0, False)]
    assert x.shape == (3, 32, 64) and -1.0 <= x.min() and x.max() <= 1.0
    assert torch.equal(reals[(0, True)], x.flip(-1))


def _run(*args, env=None, check=True):
    proc = subprocess.run([sys.executable, "-m", "train.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, **(env or {})})
    if check and proc.returncode:
        raise AssertionError(proc.stdout + proc.stderr)
    return proc


def _stats(run):
    return [json.loads(line) for line in (run / "stats.jsonl").read_text().splitlines()]


def test_run_folder_checkpoint_round_trip_and_exact_resume(data, tmp_path):
    intr, photos = data
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(whole),
         "--max-steps", "6", "--quiet", *TINY)
    _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(parts),
         "--max-steps", "4", "--quiet", *TINY)
    # a run stopped after its step-3 checkpoint: stats logged after it are dropped on resume
    _run("fit", "--run-dir", str(parts), "--max-steps", "6", "--quiet")
    a, b = _stats(whole), _stats(parts)
    assert [r["step"] for r in a] == [r["step"] for r in b] == [1, 2, 3, 4, 5, 6]
    for ra, rb in zip(a, b):
        for k in ra:
            assert ra[k] == pytest.approx(rb[k], rel=1e-5, abs=1e-7), (ra["step"], k)
    opts = json.loads((whole / "training_options.json").read_text())
    assert opts["config"]["data"]["height"] == 32 and opts["intrinsics"] == str(intr.resolve())
    assert (whole / "grids" / "step_00000005.png").exists() and list(whole.glob("events.out.tfevents.*"))
    from train.checkpoint import latest_checkpoint, load_weights

    ckpt = latest_checkpoint(whole / "checkpoints")
    assert ckpt.name == "step_00000006.safetensors"
    model = build_model(load_config("cpu-small", tiny_overrides()))
    load_weights(ckpt, model)  # safetensors: no pickle involved
    with pytest.raises(ValueError, match="does not match|shape"):
        load_weights(ckpt, build_model(load_config("cpu-small")))


def test_render_and_decompose_commands(data, tmp_path):
    intr, photos = data
    run = tmp_path / "run"
    _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(run),
         "--max-steps", "2", "--quiet", *TINY)
    _run("render", "--run", str(run), "--intrinsics", str(intr), "--out", str(tmp_path / "r"), "--quiet")
    assert sorted(p.name for p in (tmp_path / "r").glob("*.png")) == [f"{i:06d}.png" for i in range(4)]
    _run("decompose", "--run", str(run), "--images", str(photos), "--out", str(tmp_path / "d"), "--quiet")
    from blender_gen.dataset import open_dataset

    preds = open_dataset(tmp_path / "d", kinds=("predictions",))
    assert len(preds) == 4 and set(preds.load(0)) == {"normal", "albedo", "reflection"}
    assert len(list((tmp_path / "d" / "previews").glob("*.png"))) == 4
    bad = _run("decompose", "--run", str(run), "--images", str(intr), "--out", str(tmp_path / "x"), check=False)
    assert bad.returncode and "dataset of kind 'intrinsics', expected pbr" in bad.stderr
    bad = _run("render", "--run", str(tmp_path / "nothing"), "--intrinsics", str(intr), "--out", str(tmp_path / "y"),
               check=False)
    assert bad.returncode and "not a run folder" in bad.stderr


def test_config_errors_name_the_key_and_the_nearest_valid_one(data, tmp_path):
    with pytest.raises(ConfigError, match=r"unknown config key 'loss.w_rem'; did you mean 'loss.w_ren'"):
        load_config("paper", ["loss.w_rem=3"])
    with pytest.raises(ConfigError, match="model.inputs"):
        load_config("paper", ["model.inputs=NX"])
    with pytest.raises(ConfigError, match="no such preset"):
        load_config("papr")
    intr, photos = data
    bad = _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir",
               str(tmp_path / "r"), "--set", "optim.lrate=1", check=False)
    assert bad.returncode and "did you mean 'optim.lr'" in bad.stderr and "Traceback" not in bad.stderr


def test_nan_loss_stops_with_the_last_good_checkpoint(data, tmp_path, monkeypatch):
    intr, photos = data
    real = IntrinsicAutoencoder.generator_loss
    calls = {"n": 0}

    def poisoned(self, out):
        calls["n"] += 1
        loss, logs = real(self, out)
        if calls["n"] == 5:
            return loss * float("nan"), {**logs, "G/total": float("nan")}
        return loss, logs

    monkeypatch.setattr(IntrinsicAutoencoder, "generator_loss", poisoned)
    from train.loop import NonFiniteLoss

    with pytest.raises(NonFiniteLoss, match="step 5.*step_00000003"):
        fit(tmp_path / "run", tiny_cfg(), str(intr), str(photos), max_steps=8, progress=False)
    assert json.loads((tmp_path / "run" / "checkpoints" / "latest.json").read_text())["step"] == 3


def test_rendering_cycle_loss_falls_when_overfitting(data, tmp_path):
    intr, photos = data
    torch.manual_seed(0)
    cfg = tiny_cfg(optim__lr=1e-3, run__log_every=1, run__checkpoint_every=1000, run__grid_every=1000)
    fit(tmp_path / "of", cfg, str(intr), str(photos), max_steps=60, progress=False)
    ren = [r["G/ren_cycle"] for r in _stats(tmp_path / "of")]
    assert np.mean(ren[-10:]) < 0.5 * np.mean(ren[:5]), (ren[:5], ren[-10:])


def test_ddp_two_cpu_processes_gloo(data, tmp_path):
    intr, photos = data
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29517",
           "-m", "train.cli", "fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos),
           "--run-dir", str(run), "--max-steps", "3", "--device", "cpu", "--quiet", *TINY]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _stats(run)
    assert [r["step"] for r in rows] == [1, 2, 3] and all(math.isfinite(r["G/total"]) for r in rows)
    assert json.loads((run / "checkpoints" / "latest.json").read_text())["step"] == 3
