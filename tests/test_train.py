"""The trainer: networks, losses, wiring of the shared discriminators, steps, checkpoints, resume, DDP."""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch import nn

from train.config import ConfigError, load_config, set_value
from train.data import RealImages, StepSampler, flip_stack
from train.losses import cycle_loss, gan_loss, normal_length_loss
from train.loop import discriminator_step, fit, generator_step
from train.model import IntrinsicAutoencoder, build_model
from train.networks import Decomposer, LocalEnhancer, MultiscaleDiscriminator, ResnetGenerator

from .conftest import ROOT, invoke_here
from .train_helpers import TINY, tiny_fit, tiny_intrinsics, tiny_overrides, tiny_photos


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
    cfg = tiny_cfg(data__height=h, data__width=w, model__inputs="NA", model__renderer="shader",
                   model__shader_residual=0.25)
    model = IntrinsicAutoencoder(cfg)
    out = model.forward_all(x9.tanh(), x3.tanh())
    assert out["fake_I"].shape == (2, 3, h, w) and out["fake_M"].shape == (2, 9, h, w)
    assert out["rec_M"].shape == (2, 9, h, w) and out["rec_I"].shape == (2, 3, h, w)
    assert model.R.net.model[1].in_channels == 6 + 3  # the selected maps and the shaded image (renderer "shader")
    paper_r = IntrinsicAutoencoder(tiny_cfg(data__height=h, data__width=w, model__inputs="NA", model__renderer="net"))
    assert paper_r.R.model[1].in_channels == 6


def test_resize_and_subpixel_upsampling_start_without_checkerboard_and_older_runs_keep_transposed_layers():
    """On a constant input a stride-2 transposed 3x3 convolution gives even and odd pixels different
    numbers of kernel taps (a 2x2 checkerboard); nearest upsampling + a 3x3 convolution gives one value,
    and so does the sub-pixel layer as initialised (its four phase filters equal), until training
    teaches the phases apart."""
    from train.config import Config, config_from_dict, validate
    from train.networks import SubPixelUpsample, init_weights, upsample_layer

    torch.manual_seed(0)
    flat = torch.ones(1, 8, 8, 8)
    phases = {}
    for kind in ("transposed", "resize", "subpixel"):
        layer = init_weights(nn.Sequential(*upsample_layer(8, 4, kind)))
        out = layer(flat)[0, :, 2:-2, 2:-2]  # away from the borders' padding
        assert out.shape[-2:] == (12, 12)
        phases[kind] = torch.stack([out[:, i::2, j::2] for i in (0, 1) for j in (0, 1)])  # the four 2x2 phases
    assert phases["resize"].std(dim=(0, 2, 3)).max() < 1e-6
    assert phases["subpixel"].std(dim=(0, 2, 3)).max() < 1e-6
    assert phases["transposed"].mean(dim=(2, 3)).std(dim=0).min() > 1e-3
    sub = SubPixelUpsample(8, 4)
    with torch.no_grad():
        sub.conv.weight[1::4] += 0.1  # one phase's filters changed, as training may change them
    out = sub(flat)[0, :, 2:-2, 2:-2]
    assert (out[:, 0::2, 1::2] - out[:, 0::2, 0::2]).abs().min() > 1e-3  # the phase (row 0, column 1) differs
    x3 = torch.randn(2, 3, 32, 64)
    for kind in ("resize", "subpixel"):
        assert Decomposer(8, 2, 2, upsample=kind)(x3).shape == (2, 9, 32, 64)
    old = Config().to_dict()
    del old["model"]["h_upsample"]
    assert config_from_dict(old).model.h_upsample == "transposed"  # what every run before the option had
    # the default is subpixel; the paper preset keeps the paper's (CycleGAN's) transposed layers
    assert Config().model.h_upsample == "subpixel" and load_config("paper").model.h_upsample == "transposed"
    with pytest.raises(ConfigError, match="model.h_upsample"):
        validate(tiny_cfg(model__h_upsample="bilinear"))


def test_losses_against_hand_computed_values():
    d = [torch.tensor([[0.5, 1.0]]), torch.tensor([[0.0]])]
    # lsgan, real: ((0.5-1)^2 + 0)/2 = 0.125 at scale 1; (0-1)^2 = 1 at scale 2; summed over scales (pix2pixHD)
    assert gan_loss(d, True, "lsgan").item() == pytest.approx(1.125)
    assert gan_loss(d, False, "lsgan").item() == pytest.approx((0.25 + 1.0) / 2 + 0.0)
    # bce, real: -log(sigmoid(x)) = softplus(-x)
    sp = lambda x: math.log1p(math.exp(-x))  # noqa: E731
    assert gan_loss(d, True, "bce").item() == pytest.approx((sp(0.5) + sp(1.0)) / 2 + sp(0.0), rel=1e-6)
    # smooth L1 with beta 0.5: |0.2| < beta -> 0.5*0.04/0.5 = 0.04; |1.0| -> 1.0 - 0.25 = 0.75
    assert cycle_loss(torch.tensor([0.2, 1.0]), torch.zeros(2), 0.5).item() == pytest.approx((0.04 + 0.75) / 2)
    # normal length: |(0.6, 0, 0)| = 0.6 -> 0.4; |(0, 2, 0)| = 2 -> 1.0; (0.1, 0, 0) below threshold: ignored
    n = torch.tensor([[0.6, 0.0, 0.1], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]]).reshape(1, 3, 1, 3)
    assert normal_length_loss(n, 0.5).item() == pytest.approx((0.4 + 1.0) / 2)


WIRING = {  # switches -> (outputs computed, D_I fakes, D_M fakes, normal-length inputs)
    (): ({"fake_I", "rec_M", "fake_M", "rec_I"}, ["fake_I", "rec_I"], ["fake_M", "rec_M"]),
    (("loss__shared_discriminator", False),): ({"fake_I", "rec_M", "fake_M", "rec_I"}, ["fake_I"], ["fake_M"]),
    # w/o decomposition cycle: only M_s -> R -> H; D_I: I_r vs R(M_s); D_M: M_s vs H(R(M_s))
    (("loss__decomposition_cycle", False),): ({"fake_I", "rec_M"}, ["fake_I"], ["rec_M"]),
    # the mirror: only I_r -> H -> R; D_I: I_r vs R(H(I_r)); D_M: M_s vs H(I_r)
    (("loss__rendering_cycle", False),): ({"fake_M", "rec_I"}, ["rec_I"], ["fake_M"]),
}


@pytest.mark.parametrize("switches", list(WIRING))
def test_which_tensors_reach_which_discriminator_and_loss(switches):
    computed, d_i, d_m = WIRING[switches]
    x9, x3 = torch.randn(1, 9, 32, 64).tanh(), torch.randn(1, 3, 32, 64).tanh()
    model = IntrinsicAutoencoder(tiny_cfg(**dict(switches)))
    out = model.forward_all(x9, x3)
    assert set(out) - {"M_s", "I_r"} == computed
    wiring = model.discriminator_inputs(out)
    assert wiring["D_I"][0] is x3 and wiring["D_M"][0] is x9
    assert (wiring["D_I"][1], wiring["D_M"][1]) == (d_i, d_m)
    _, logs = model.generator_loss(out)
    assert ("G/ren_cycle" in logs) == ("rec_M" in computed) and ("G/dec_cycle" in logs) == ("rec_I" in computed)
    assert {k for k in logs if k.startswith("G/adv_")} == {f"G/adv_D_I_{f}" for f in d_i} | {f"G/adv_D_M_{f}" for f in d_m}
    # pictures still show every output, so an ablated H can be judged on real images
    assert set(model.forward_all(x9, x3, everything=True)) == {"M_s", "I_r", "fake_I", "rec_M", "fake_M", "rec_I"}


def _generator_grads(model, x9, x3):
    model.zero_grad(set_to_none=True)
    loss, _ = model.generator_loss(model.forward_all(x9, x3))
    loss.backward()
    return {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("switch, unseen", [("loss__decomposition_cycle", "real"), ("loss__rendering_cycle", "synthetic")])
def test_an_ablated_cycle_lets_no_input_of_its_domain_reach_the_generators(switch, unseen):
    torch.manual_seed(0)
    model = IntrinsicAutoencoder(tiny_cfg(**{switch: False}))
    x9, x3 = torch.randn(2, 9, 32, 64).tanh(), torch.randn(2, 3, 32, 64).tanh()
    other9, other3 = torch.randn(2, 9, 32, 64).tanh(), torch.randn(2, 3, 32, 64).tanh()
    a = _generator_grads(model, x9, x3)
    b = _generator_grads(model, x9, other3) if unseen == "real" else _generator_grads(model, other9, x3)
    h_grads = [n for n in a if n.startswith("H.")]
    assert h_grads, "H must still learn from the other cycle"
    for name in a:  # the generators' gradients do not depend on the unseen domain's images at all
        assert torch.equal(a[name], b[name]), name
    full = IntrinsicAutoencoder(tiny_cfg())
    full.load_state_dict(model.state_dict())
    c = _generator_grads(full, x9, x3)
    d = _generator_grads(full, x9, other3) if unseen == "real" else _generator_grads(full, other9, x3)
    assert any(not torch.equal(c[n], d[n]) for n in c if n.startswith("H.")), "the full model does see both domains"


@pytest.mark.parametrize("detach", [False, True])
def test_cycle_detach_trains_only_the_second_network_of_each_cycle(detach):
    torch.manual_seed(0)
    # the paper's R: the shader R lit by fitted lightings has no parameter of its own in either cycle
    model = IntrinsicAutoencoder(tiny_cfg(loss__cycle_detach=detach, model__renderer="net"))
    x9, x3 = torch.randn(2, 9, 32, 64).tanh(), torch.randn(2, 3, 32, 64).tanh()
    for loss_name, first, second in (("dec", "H.", "R."), ("ren", "R.", "H.")):
        model.zero_grad(set_to_none=True)
        out = model.forward_all(x9, x3)
        key, target = ("rec_I", "I_r") if loss_name == "dec" else ("rec_M", "M_s")
        cycle_loss(out[key], out[target], 1 / 16).backward()
        grads = {n: p.grad for n, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
        assert any(n.startswith(second) for n in grads), loss_name
        assert any(n.startswith(first) for n in grads) != detach, loss_name  # detached: the first gets nothing


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


def test_photos_of_another_aspect_are_covered_then_centre_cropped(tmp_path):
    from PIL import Image

    img = np.zeros((20, 100, 3), np.uint8)
    img[:, :25] = (255, 0, 0)  # a red left quarter: outside the centre 2:1 window of a 5:1 photo
    img[:, 25:] = (0, 0, 255)
    (tmp_path / "p").mkdir()
    Image.fromarray(img).save(tmp_path / "p" / "wide.png")
    x = RealImages(tmp_path / "p", 32, 64)[(0, False)]
    assert x.shape == (3, 32, 64)
    assert float(x[0].max()) < -0.9 and float(x[2].min()) > 0.9, "only the blue centre survives, undistorted"


def _run(*args, env=None, check=True):
    """`iae-train ARGS` in a fresh process; an expected failure (check=False) in this one."""
    if not check:
        from train.cli import main

        return invoke_here(main, *args, env=env)
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
    tiny_fit(parts, intr, photos, 4)
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
    # photos come back whole, at their own size, named after them, with a labelled panel each
    from PIL import Image

    shots = tmp_path / "shots"
    shutil.copytree(photos, shots / "street")
    Image.new("RGB", (300, 300), (120, 90, 60)).save(shots / "square.jpg")
    Image.new("RGB", (200, 100), (60, 90, 120)).save(shots / "square.webp")  # the same name, another photo
    (shots / "broken.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    (shots / "IMG_0001.HEIC").write_bytes(b"\0" * 64)  # not read here: named, not silently dropped
    res = _run("decompose", "--run", str(run), "--images", str(shots), "--out", str(tmp_path / "p"), "--quiet",
               check=False)
    assert res.returncode == 0 and "warning: 1 photo(s) could not be read and were skipped (broken.jpg)" in res.stderr
    assert "Traceback" not in res.stderr
    assert "1 photo(s) in formats not read here (.heic; first IMG_0001.HEIC) are left out" in res.stderr
    gallery = tmp_path / "p" / "photos"
    assert Image.open(gallery / "square_jpg_normal.png").size == (300, 300)  # no crop to 2:1
    assert Image.open(gallery / "square_webp_normal.png").size == (200, 100)  # neither overwrites the other
    assert Image.open(gallery / "street__photo_1_albedo.png").size == (90, 60)
    from blender_gen.dataset import read_exr

    maps = read_exr(gallery / "square_jpg.exr")  # the maps in full precision, the datasets' units
    assert {k: v.shape for k, v in maps.items()} == {k: (300, 300, 3) for k in ("normal", "albedo", "reflection")}
    png = np.asarray(Image.open(gallery / "square_jpg_albedo.png"), dtype=np.float64)
    from blender_gen.conversions import linear_to_srgb

    assert np.abs(linear_to_srgb(maps["albedo"]) * 255 - png).max() <= 1.5  # half floats, 8-bit rounding
    strict = _run("decompose", "--run", str(run), "--images", str(shots), "--out", str(tmp_path / "s"), "--quiet",
                  "--strict", "--size", "64", check=False)
    assert strict.returncode == 1 and "broken.jpg" in strict.stderr and "Traceback" not in strict.stderr
    assert Image.open(tmp_path / "s" / "photos" / "square_jpg_normal.png").size == (64, 64)  # the longer side
    assert Image.open(tmp_path / "s" / "photos" / "square_webp_normal.png").size == (64, 32)
    sized = _run("decompose", "--run", str(run), "--images", str(photos), "--out", str(tmp_path / "z"), "--quiet",
                 "--size", "40x30")
    assert Image.open(tmp_path / "z" / "photos" / "photo_0_render.png").size == (40, 30)
    # the predictions dataset does not depend on --size
    assert np.array_equal(open_dataset(tmp_path / "z", kinds=("predictions",)).load(0)["albedo"], preds.load(0)["albedo"])
    for bad_size in ("0", "12xx", "big"):
        bad = _run("decompose", "--run", str(run), "--images", str(photos), "--out", str(tmp_path / "q"), "--quiet",
                   "--size", bad_size, check=False)
        assert bad.returncode == 1 and f"--size {bad_size!r}: expected photo, a longer side" in bad.stderr
    panel = Image.open(gallery / "square_jpg.png")
    assert panel.size == (5 * 256, 18 + 256)  # photo, normal, albedo, reflection, R(H(photo)); a title row
    assert "street/photo_0.jpg" in (gallery / "index.html").read_text()
    info = json.loads((tmp_path / "p" / "dataset.json").read_text())
    assert info["complete"] and info["count"] == 6 and info["skipped"][0]["file"].endswith("broken.jpg")
    bad = _run("decompose", "--run", str(run), "--images", str(intr), "--out", str(tmp_path / "x"), check=False)
    assert bad.returncode and "dataset of kind 'intrinsics', expected pbr" in bad.stderr
    bad = _run("render", "--run", str(tmp_path / "nothing"), "--intrinsics", str(intr), "--out", str(tmp_path / "y"),
               check=False)
    assert bad.returncode and "not a run folder" in bad.stderr
    heic = tmp_path / "heic"
    heic.mkdir()
    (heic / "IMG_1.HEIC").write_bytes(b"not read here")
    bad = _run("decompose", "--run", str(tmp_path / "nothing"), "--images", str(heic), "--out", str(tmp_path / "w"),
               check=False)  # a mistyped run is named before the photos are scanned
    assert bad.returncode == 1 and bad.stderr.strip().splitlines() == [
        f"Error: --run {tmp_path / 'nothing'}: not a run folder (no training_options.json)"]


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
    # GAN training is chaotic: 1 and 2 threads sum in other orders and end at 0.60x and < 0.5x
    assert np.mean(ren[-10:]) < 0.7 * np.mean(ren[:5]), (ren[:5], ren[-10:])


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


@pytest.mark.parametrize("preset, setting, message", [
    ("cyclegan", "model.d_scales=3", "model.d_scales does not apply to model.kind = 'cyclegan'"),
    ("cyclegan", "loss.w_ren=3", "loss.w_ren does not apply"),
    ("munit", "cyclegan.pool=10", "cyclegan.pool does not apply to model.kind = 'munit'"),
    ("paper", "munit.dim=8", "munit.dim does not apply to model.kind = 'iae'"),
    ("paper", "data.batch_size=0", "data.batch_size: expected at least 1"),
    ("paper", "optim.lr=0", "optim.lr: expected a learning rate"),
    ("paper", "run.log_every=0", "run.log_every: expected at least 1"),
    ("paper", "data.workers=-1", "data.workers: expected at least 0"),
    ("paper", "optim.lr_policy=cosine", "optim.lr_policy: expected one of"),
])
def test_settings_a_model_kind_ignores_or_out_of_range_are_refused(preset, setting, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_config(preset, [setting])


def test_a_size_the_generators_bottleneck_cannot_pad_is_refused_by_name():
    # the paper's R downsamples by 32: at 32x64 its bottleneck is 1x2, which a reflection pad cannot pad
    for kind in ("iae", "oracle"):
        with pytest.raises(ConfigError, match=r"data.height/width \(32x64\) must be at least 64"):
            load_config("paper", [f"model.kind={kind}", "data.height=32", "data.width=64"])
    with pytest.raises(ConfigError, match=r"data.height/width \(8x16\) must be at least 16"):
        load_config("cyclegan", ["cyclegan.n_down=3", "data.height=8", "data.width=16"])
    # the shader R runs no generator at that size unless it has a residual: the same size is accepted
    assert load_config("paper", ["model.renderer=shader", "data.height=32", "data.width=64"]).data.height == 32
    with pytest.raises(ConfigError, match=r"data.height/width \(32x64\) must be at least 64"):
        load_config("paper", ["model.renderer=shader", "model.shader_residual=0.5", "data.height=32", "data.width=64"])
    cfg = load_config("paper", ["model.kind=oracle", "data.height=64", "data.width=128"])
    model = IntrinsicAutoencoder(cfg)
    assert model.R(torch.zeros(1, 9, 64, 128)).shape == (1, 3, 64, 128)


def test_the_paper_preset_trains_the_oracle_and_the_baselines():
    """`reproduce --budget gpu|paper` builds the oracle as `--config paper --set model.kind=oracle`:
    the preset's own [loss] values are dropped for a kind that never reads them, while a --set
    that names one is still refused."""
    oracle = load_config("paper", ["model.kind=oracle"])
    assert oracle.model.kind == "oracle" and oracle.model.h_ngf == 64 and oracle.data.height == 256
    assert load_config("paper", ["model.kind=cyclegan"]).model.kind == "cyclegan"
    with pytest.raises(ConfigError, match="loss.w_ren does not apply"):
        load_config("paper", ["model.kind=oracle", "loss.w_ren=3"])


def test_sections_a_model_kind_never_reads_are_named():
    from train.config import unread_sections

    assert unread_sections(load_config("cyclegan")) == ["model (all but model.kind)", "loss", "munit"]
    assert unread_sections(load_config("munit")) == ["model (all but model.kind)", "loss", "cyclegan"]
    assert unread_sections(load_config("paper")) == ["cyclegan", "munit"]


def test_every_section_a_model_kind_reads_is_a_config_section():
    # MODEL_SECTIONS (derived from KIND_SECTIONS) is what validate and unread_sections walk, in
    # the order their messages name the sections; each must be a real section of Config
    from dataclasses import fields

    from train.config import MODEL_SECTIONS, Config

    assert MODEL_SECTIONS == ("model", "loss", "cyclegan", "munit")
    assert set(MODEL_SECTIONS) <= {f.name for f in fields(Config)}


def test_every_value_of_the_paper_preset_says_where_it_comes_from():
    from train.config import PRESETS_DIR

    lines = [ln for ln in (PRESETS_DIR / "paper.toml").read_text().splitlines() if "=" in ln and not ln.startswith("#")]
    assert len(lines) > 30
    for line in lines:
        assert "# paper:" in line or "# chosen:" in line, line
    cfg = load_config("paper")
    assert (cfg.loss.gan, cfg.loss.w_ren, cfg.loss.w_dec, cfg.model.d_scales, cfg.model.h_blocks) == ("bce", 1, 1, 2, 5)


def _fit_args(data, run, *extra):
    intr, photos = data
    return ("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(run),
            "--quiet", *TINY, *extra)


def test_a_failed_start_does_not_poison_the_run_folder(data, tmp_path):
    run = tmp_path / "r"
    bad = _run(*_fit_args(data, run, "--max-steps", "2", "--set", "data.batch_size=0"), check=False)
    assert bad.returncode == 1 and "data.batch_size: expected at least 1" in bad.stderr and not run.exists()
    intr, photos = data
    missing = _run("fit", "--config", "cpu-small", "--intrinsics", str(tmp_path / "nope"), "--real", str(photos),
                   "--run-dir", str(run), "--max-steps", "2", "--quiet", *TINY, check=False)
    assert missing.returncode == 1 and "Traceback" not in missing.stderr
    assert f"--intrinsics {tmp_path / 'nope'}: no such dataset directory" in missing.stderr  # names the option
    assert not (run / "training_options.json").exists()
    # a start that wrote its options but never reached a checkpoint takes a corrected config
    run.mkdir()
    (run / "training_options.json").write_text(json.dumps({"config": tiny_cfg().to_dict(), "intrinsics": str(intr),
                                                           "real": str(photos)}))
    _run(*_fit_args(data, run, "--max-steps", "2", "--set", "optim.lr=1e-3"))
    opts = json.loads((run / "training_options.json").read_text())
    assert opts["config"]["optim"]["lr"] == 1e-3 and opts["sections_not_read"] == ["cyclegan", "munit"]


def test_resume_survives_torn_stats_and_truncated_checkpoints(data, tmp_path):
    run = tmp_path / "r"
    _run(*_fit_args(data, run, "--max-steps", "6"))  # checkpoints at steps 3 and 6
    ckpts = run / "checkpoints"
    with open(run / "stats.jsonl", "a") as fh:
        fh.write('{"step": 7, "G/tot')  # a torn last line
    (ckpts / "latest.json").write_text('{"step": 6, "na')
    newest = ckpts / "step_00000006.safetensors"
    newest.write_bytes(newest.read_bytes()[:1000])  # truncated by a crash or a full disk
    (ckpts / ".step_00000009.safetensors.tmp999").write_bytes(b"\0" * 1000)  # a save killed mid-write
    proc = _run("fit", "--run-dir", str(run), "--max-steps", "8", "--quiet")
    assert not list(ckpts.glob(".*.tmp*"))
    assert "skipped an unreadable checkpoint" in proc.stderr and "step_00000006.safetensors" in proc.stderr
    assert "step 8 (5 steps" in proc.stdout  # resumed from step 3
    steps = [r["step"] for r in _stats(run)]
    assert steps == list(range(1, 9))
    (run / "training_options.json").write_text('{"config": {"da')
    broken = _run("fit", "--run-dir", str(run), "--max-steps", "9", "--quiet", check=False)
    assert broken.returncode == 1 and "training_options.json: truncated or corrupt" in broken.stderr
    assert "Traceback" not in broken.stderr


def test_sigterm_saves_a_checkpoint_and_the_run_resumes_from_it(data, tmp_path):
    import signal
    import time

    run = tmp_path / "r"
    cmd = [sys.executable, "-m", "train.cli", *_fit_args(data, run, "--max-steps", "100000", "--set",
                                                          "run.checkpoint_every=100000")]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not ((run / "stats.jsonl").exists() and len(_stats(run)) >= 3):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM and "interrupted at step" in err and "Traceback" not in err
    saved = sorted((run / "checkpoints").glob("step_*.safetensors"))
    assert len(saved) == 1
    step = int(saved[0].stem.split("_")[1])
    assert step >= 3
    again = _run("fit", "--run-dir", str(run), "--max-steps", str(step + 2), "--quiet")
    assert f"step {step + 2} (2 steps" in again.stdout


def test_objective_puts_the_paper_s_objective_on_a_preset_s_networks(data, tmp_path):
    """`fit --config cpu-small --objective paper` trains the paper's R and Eq. 7 at cpu-small widths;
    --set still goes on top."""
    import json

    run = tmp_path / "r"
    _run(*_fit_args(data, run, "--max-steps", "1", "--objective", "paper", "--set", "loss.w_ren=2"))
    cfg = json.loads((run / "training_options.json").read_text())["config"]
    assert cfg["model"]["renderer"] == "net" and cfg["loss"]["w_dec"] == 1.0 and cfg["loss"]["adv_m_on"] == "all"
    assert cfg["loss"]["w_ren"] == 2.0 and cfg["model"]["h_blocks"] != 5  # --set on top; widths stay small


def test_set_without_config_and_a_non_empty_out_are_one_line_errors(data, tmp_path):
    run = tmp_path / "r"
    _run(*_fit_args(data, run, "--max-steps", "3"))
    nocfg = _run("fit", "--run-dir", str(run), "--set", "optim.lr=1", check=False)
    assert nocfg.returncode == 2 and "--set needs --config" in nocfg.stderr and "Traceback" not in nocfg.stderr
    noobj = _run("fit", "--run-dir", str(run), "--objective", "paper", check=False)
    assert noobj.returncode == 2 and "--objective needs --config" in noobj.stderr
    intr, photos = data
    new = _run("fit", "--run-dir", str(tmp_path / "new"), "--intrinsics", str(intr), "--real", str(photos), check=False)
    assert new.returncode == 1 and "Traceback" not in new.stderr
    assert "no run there to resume" in new.stderr and "(--config not given)" in new.stderr
    mine = tmp_path / "my_photos"
    mine.mkdir()
    (mine / "holiday.jpg").write_bytes(b"not touched")
    for cmd in (("render", "--intrinsics", str(intr)), ("decompose", "--images", str(photos))):
        proc = _run(cmd[0], "--run", str(run), *cmd[1:], "--out", str(mine), "--quiet", check=False)
        assert proc.returncode == 1 and "is not an empty folder" in proc.stderr, proc.stderr
    assert [p.name for p in mine.iterdir()] == ["holiday.jpg"]


def test_the_supervised_oracle_learns_from_pbr_pairs_and_needs_a_pbr_set(data, tmp_path):
    intr, photos = data
    pbr = tiny_intrinsics(tmp_path / "pbr", n=4, kind="pbr", seed=3)
    torch.manual_seed(0)
    # the paper's R: both networks start from noise and must fall far
    cfg = tiny_cfg(model__kind="oracle", model__renderer="net", optim__lr=1e-3, run__checkpoint_every=1000,
                   run__grid_every=1000)
    model = build_model(cfg)
    assert model.discriminator_modules() == {} and set(model.generator_modules()) == {"R", "H"}
    fit(tmp_path / "o", cfg, str(intr), str(pbr), max_steps=40, progress=False)
    rows = _stats(tmp_path / "o")
    for key in ("G/render_l1", "G/decompose_l1"):
        vals = [r[key] for r in rows]
        assert np.mean(vals[-5:]) < 0.7 * np.mean(vals[:3]), (key, vals[:3], vals[-5:])
    with pytest.raises(ConfigError, match="needs a PBR dataset"):
        fit(tmp_path / "o2", cfg, str(intr), str(photos), max_steps=2, progress=False)
    with pytest.raises(ConfigError, match="loss.gan does not apply to model.kind = 'oracle'"):
        load_config("cpu-small", ["model.kind=oracle", "loss.gan=lsgan"])


def test_training_refuses_a_set_being_written_or_incomplete_and_a_set_that_changed_on_resume(tmp_path):
    from blender_gen.dataset import DatasetError, locked_folder

    intr, photos = tiny_intrinsics(tmp_path / "intr", n=4), tiny_photos(tmp_path / "photos")
    run = tmp_path / "run"
    with locked_folder(intr):  # a generator still writing the set
        with pytest.raises(DatasetError, match=r"--intrinsics .* is being written by pid"):
            fit(run, tiny_cfg(), str(intr), str(photos), max_steps=1, progress=False)
    info = json.loads((intr / "dataset.json").read_text())
    (intr / "dataset.json").write_text(json.dumps({**info, "count_requested": 6}))  # stopped at 4 of 6
    with pytest.raises(DatasetError, match=r"incomplete \(4 of 6 samples\)"):
        fit(run, tiny_cfg(), str(intr), str(photos), max_steps=1, progress=False)
    assert not run.exists()
    (intr / "dataset.json").write_text(json.dumps(info))
    fit(run, tiny_cfg(), str(intr), str(photos), max_steps=1, progress=False)
    recorded = json.loads((run / "training_options.json").read_text())["data_identity"]
    assert recorded["intrinsics"]["count"] == 4 and recorded["real"]["count"] == 4
    tiny_intrinsics(intr, n=6)  # the set grew (regenerated with more samples) before the resume
    with pytest.raises(ConfigError, match=r"--intrinsics .* changed since .* \(4 -> 6 samples\).*--accept-changed-data"):
        fit(run, max_steps=2, progress=False)
    result = fit(run, max_steps=2, progress=False, accept_changed_data=True)
    assert result["step"] == 2
    opts = json.loads((run / "training_options.json").read_text())
    assert opts["data_identity"]["intrinsics"]["count"] == 6
    assert opts["data_changes"][0]["step"] == 1 and opts["data_changes"][0]["was"]["intrinsics"]["count"] == 4


def test_init_from_starts_a_new_run_from_another_runs_weights(data, tmp_path):
    from safetensors.torch import load_file

    intr, photos = data
    source = tmp_path / "source"
    fit(source, tiny_cfg(), str(intr), str(photos), max_steps=3, progress=False)
    tuned = tmp_path / "tuned"
    res = _run("fit", "--init-from", str(source), "--intrinsics", str(intr), "--real", str(photos), "--run-dir",
               str(tuned), "--max-steps", "1", "--quiet", "--set", "optim.lr=1e-5")
    assert res.returncode == 0, res.stderr
    opts = json.loads((tuned / "training_options.json").read_text())
    assert opts["init_from"]["step"] == 3 and opts["init_from"]["checkpoint"].endswith("step_00000003.safetensors")
    assert opts["config"]["optim"]["lr"] == 1e-5 and opts["config"]["model"]["h_ngf"] == tiny_cfg().model.h_ngf
    start = load_file(str(source / "checkpoints" / "step_00000003.safetensors"))
    after = load_file(str(tuned / "checkpoints" / "step_00000001.safetensors"))
    fresh = tmp_path / "fresh"
    fit(fresh, tiny_cfg(**{"optim__lr": 1e-5, "run__seed": 5}), str(intr), str(photos), max_steps=1, progress=False)
    scratch = load_file(str(fresh / "checkpoints" / "step_00000001.safetensors"))
    key = next(k for k in start if k.startswith("model.H.") and k.endswith("weight") and start[k].dim() == 4)
    assert (after[key] - start[key]).abs().max() < 1e-3 < (scratch[key] - start[key]).abs().max()
    bad = _run("fit", "--init-from", str(source), "--intrinsics", str(intr), "--real", str(photos), "--run-dir",
               str(tmp_path / "wider"), "--max-steps", "1", "--quiet", "--config", "cpu-small", *TINY,
               "--set", "model.h_ngf=16", check=False)
    assert bad.returncode == 1 and "do not fit this run's config" in bad.stderr and "Traceback" not in bad.stderr


def test_training_grids_are_titled_and_reach_tensorboard(data, tmp_path):
    from train.loop import sample_grid

    g = torch.Generator().manual_seed(0)
    vis = {k: torch.rand(2, c, 32, 64, generator=g) * 2 - 1
           for k, c in (("M_s", 9), ("fake_I", 3), ("rec_M", 9), ("I_r", 3), ("fake_M", 9), ("rec_I", 3))}
    grid = sample_grid(vis)
    assert grid.shape == (26 + 4 * 32, 84 + 7 * 64, 3)  # a title band, a legend margin, 7 columns, 2 rows per sample
    head, legend = grid[:26, 84:], grid[26:, :84]
    assert (head[..., 2] > head[..., 0] + 60).any() and (head[..., 0] > head[..., 2] + 60).any()  # both title rows
    assert (legend < 128).any()
    intr, photos = data
    run = tmp_path / "run"
    fit(run, tiny_cfg(run__grid_every=1), str(intr), str(photos), max_steps=1, progress=False)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(next(run.rglob("events.out.tfevents.*")).parent))
    events.Reload()
    assert "samples" in events.Tags()["images"]


def test_a_run_records_its_compute_and_a_resume_on_other_compute_says_so(data, tmp_path, capsys):
    """The order of float sums follows the CPU thread count, so a run records it: the same seed and
    data give the same bytes only on the same compute, and a resume on other compute says so."""
    intr, photos = data
    run = tmp_path / "run"
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        tiny_fit(run, intr, photos, 2)
        opts = json.loads((run / "training_options.json").read_text())
        assert opts["compute"] == {"torch": torch.__version__, "device": "cpu", "processes": 1, "threads": 1}
        assert "torch " + torch.__version__ + " on cpu, 1 CPU thread(s)" in (run / "MODEL_CARD.md").read_text()
        fit(run, max_steps=3, progress=False)  # the same compute: no note
        assert "other compute" not in capsys.readouterr().err
        torch.set_num_threads(2)
        fit(run, max_steps=4, progress=False)
        err = capsys.readouterr().err
        assert "resumes with other compute than it started with (threads 1 -> 2)" in err and str(run) in err
        # what the run started with stays recorded
        assert json.loads((run / "training_options.json").read_text())["compute"]["threads"] == 1
    finally:
        torch.set_num_threads(before)


def test_python_api_decomposes_and_renders_numpy_images_as_the_cli_does(data, tmp_path, monkeypatch):
    """`train.load_run(RUN)`: decompose takes uint8 / float / PIL pictures of any size and returns the
    maps at that size, the same maps `iae-train decompose` writes; render takes those maps (or a
    dataset sample, or an HxWx9 array); the guide's example runs as written."""
    import re

    from PIL import Image

    import train
    from blender_gen.conversions import linear_to_srgb
    from blender_gen.dataset import open_dataset

    intr, photos = data
    run_dir = tmp_path / "runs" / "paper"
    _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(run_dir),
         "--max-steps", "2", "--quiet", *TINY)
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (200, 300, 3), dtype=np.uint8)
    (tmp_path / "shots").mkdir()
    Image.fromarray(pixels).save(tmp_path / "shots" / "my_car.png")
    run = train.load_run(run_dir)
    assert run.step == 2 and run.weights == "moving average" and run.checkpoint.name.endswith(".safetensors")
    maps = run.decompose(pixels)
    assert set(maps) == {"normal", "albedo", "reflection"}
    assert all(v.shape == (200, 300, 3) and v.dtype == np.float32 for v in maps.values())
    for same in (Image.fromarray(pixels), pixels / 255.0, pixels.astype(np.uint16) * 257):
        again = run.decompose(same)
        assert max(np.abs(again[k] - maps[k]).max() for k in maps) < 1e-5
    # what the command writes for the same photo (an 8-bit sRGB picture of the same albedo)
    _run("decompose", "--run", str(run_dir), "--images", str(tmp_path / "shots"), "--out", str(tmp_path / "d"),
         "--quiet")
    written = np.asarray(Image.open(tmp_path / "d" / "photos" / "my_car_albedo.png"), dtype=np.float64)
    assert np.abs(linear_to_srgb(maps["albedo"]) * 255 - written).max() <= 1.0
    image = run.render(maps)
    assert image.shape == (200, 300, 3) and image.dtype == np.float32 and 0 <= image.min() <= image.max() <= 1
    stack = np.concatenate([maps[k] for k in ("normal", "albedo", "reflection")], axis=-1)
    assert np.array_equal(run.render(stack), image)
    sample = next(open_dataset(intr).samples(["normal", "albedo", "reflection"]))
    assert run.render(sample).shape == (32, 64, 3) and run.render(sample, size=(128, 64)).shape == (64, 128, 3)
    assert run.decompose(pixels, size=(64, 32))["albedo"].shape == (32, 64, 3)
    assert run.reconstruct(pixels).shape == (200, 300, 3)
    with pytest.raises(ValueError, match=r"expected an \(H, W, 3\) array.*got shape \(5, 5, 2\)"):
        run.decompose(np.zeros((5, 5, 2)))
    with pytest.raises(ValueError, match="float values must be sRGB in"):
        run.decompose(np.full((8, 8, 3), 200.0))
    with pytest.raises(ValueError, match="missing reflection"):
        run.render({"normal": maps["normal"], "albedo": maps["albedo"]})
    # the guide's example, as written, where runs/paper and my_car.jpg exist
    page = (ROOT / "docs" / "dataset_format.md").read_text()
    example = re.search(r"## Trained networks from Python\n\n```python\n(.*?)```", page, re.S).group(1)
    Image.fromarray(pixels).save(tmp_path / "my_car.jpg")
    monkeypatch.chdir(tmp_path)
    exec(compile(example, "docs/dataset_format.md", "exec"), {})
    assert Image.open(tmp_path / "my_car_render.png").size == (300, 200)
