"""Normals from shading: the SH shading fit, the shader renderer, the honest bars (per-pixel prior,
speckle figure) and the moving average of the weights."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from train.config import ConfigError, load_config
from train.model import build_model
from train.networks import ShaderRenderer
from train.probe import ProbeSet, evaluate_probe, high_frequency, pixel_prior, speckle_scores, training_means
from train.sanity import shade_network
from train.shading import fit_shading, render_sh, sh_basis, shading_loss

from .conftest import bench_module
from .train_helpers import tiny_fit, tiny_intrinsics, tiny_overrides

ROOT = Path(__file__).resolve().parent.parent


def _blobs(n: int = 3, h: int = 32, w: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 9, h, w) network-space stacks of ellipsoids with smooth normals and flat paint, and masks."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-2, 2, w), indexing="ij")
    stacks, masks = [], []
    for _ in range(n):
        sx, sy = 1.2 + 0.5 * torch.rand(1, generator=g), 0.7 + 0.2 * torch.rand(1, generator=g)
        u, v = xs / sx, ys / sy
        on = (u ** 2 + v ** 2) < 0.97
        z = (1 - u ** 2 - v ** 2).clamp_min(0).sqrt()
        normal = F.normalize(torch.stack([u, -v, z]), dim=0) * on
        paint = (torch.rand(3, 1, 1, generator=g) * 1.6 - 0.8).expand(3, h, w)
        albedo = torch.where(on, paint, torch.full_like(paint, -1.0))
        refl = torch.where(on, torch.full((3, h, w), -0.6), torch.full((3, h, w), -1.0))
        stacks.append(torch.cat([normal, albedo, refl]))
        masks.append(on[None].float())
    return torch.stack(stacks), torch.stack(masks)


def test_sh_basis_spans_the_clamped_cosine_of_one_light():
    n = F.normalize(torch.randn(1, 3, 40, 40), dim=1)
    basis = sh_basis(n).flatten(2)[0].T  # (p, 9)
    light = torch.tensor([0.3, 0.6, 0.7]) / torch.tensor([0.3, 0.6, 0.7]).norm()
    target = (n[0].flatten(1).T @ light).clamp_min(0)
    coef = torch.linalg.lstsq(basis, target[:, None]).solution
    # second-order SH reproduce a clamped cosine to within a few percent of its range (Ramamoorthi and Hanrahan)
    assert (basis @ coef - target[:, None]).abs().mean() < 0.05


def test_shading_fit_explains_an_exactly_shaded_image_and_not_noise():
    stacks, masks = _blobs()
    image = shade_network(stacks)  # the S0 formula: albedo x (ambient + one light) + reflection
    res, coeffs = fit_shading(image, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], masks)
    assert coeffs.shape == (3, 10) and res.max() < 0.05
    noise = torch.rand(image.shape, generator=torch.Generator().manual_seed(1)) * 2 - 1
    res_noise, _ = fit_shading(noise, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], masks)
    assert res_noise.min() > 0.3
    # flat normals cannot explain the shading; a rotation of all normals can (the lighting turns
    # with them: the one ambiguity a per-image lighting fit leaves)
    flat = torch.zeros_like(stacks[:, 0:3])
    flat[:, 2] = 1
    res_flat, _ = fit_shading(image, flat, stacks[:, 3:6], stacks[:, 6:9], masks)
    assert (res_flat > 3 * res).all()
    turned = stacks[:, 0:3] * torch.tensor([-1.0, -1.0, 1.0]).view(1, 3, 1, 1)
    assert torch.allclose(fit_shading(image, turned, stacks[:, 3:6], stacks[:, 6:9], masks)[0], res, atol=1e-3)


def test_shading_loss_moves_normals_and_ignores_images_without_an_object():
    stacks, masks = _blobs(2)
    image = shade_network(stacks)
    normals = stacks[:, 0:3].clone().requires_grad_(True)
    loss = shading_loss(image, normals + 0.3 * torch.randn_like(normals), stacks[:, 3:6], stacks[:, 6:9], masks)
    loss.backward()
    assert loss > 0 and normals.grad.abs().sum() > 0
    empty = shading_loss(image, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], torch.zeros_like(masks))
    assert empty.item() == 0.0


def test_the_shader_renderer_shades_by_its_normals_and_replaces_ablated_maps():
    stacks, masks = _blobs(2)
    r = ShaderRenderer(list("NAF"), 8, 2, 1, 0, "instance", residual=0.0)
    out = r(stacks)
    assert out.shape == (2, 3, 32, 64) and out.min() >= -1 and out.max() <= 1
    # without a residual it is exactly the SH formula, so another normal map gives another image
    from train.colour import srgb_encode

    ref = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], r.light, r.gain)) * 2 - 1
    assert torch.allclose(out, ref, atol=1e-6)
    turned = stacks.clone()
    turned[:, 0:3] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1) * masks
    assert (r(turned) - out).abs()[masks.expand(-1, 3, -1, -1) > 0].mean() > 0.01
    # w/o N: the normals no longer reach the image
    r_no_n = ShaderRenderer(list("AF"), 8, 2, 1, 0, "instance", residual=0.0)
    assert torch.allclose(r_no_n(turned), r_no_n(stacks))
    # the residual generator sees the selected maps and the shaded image
    r_res = ShaderRenderer(list("NA"), 8, 2, 1, 0, "instance", residual=0.25)
    assert r_res.net.model[1].in_channels == 9
    assert (r_res(stacks) - ref).abs().max() <= 0.25 + 1e-6 or r_res.light is not r.light


def test_the_shader_draws_the_environment_behind_the_car_as_stored_or_scaled_by_the_gain():
    stacks, masks = _blobs(2)
    sky = torch.linspace(-0.6, 0.8, 64).view(1, 1, 1, 64).expand(2, 3, 32, 64)
    stacks[:, 6:9] = torch.where(masks > 0, stacks[:, 6:9], sky)  # an environment in the reflection layer
    light = torch.zeros(2, 3, 10)
    light[..., 0], light[..., 9] = 1.0, 0.3  # ambient, and a reflection gain of 0.3
    env = ShaderRenderer(list("NAF"), 8, 2, 1, 0, "instance", residual=0.0, background="environment")
    gain = ShaderRenderer(list("NAF"), 8, 2, 1, 0, "instance", residual=0.0)
    a, b = env(stacks, light), gain(stacks, light)
    bg, car = (masks == 0).expand(-1, 3, -1, -1), (masks > 0).expand(-1, 3, -1, -1)
    assert torch.allclose(a[bg], sky.expand(2, 3, 32, 64)[bg], atol=1e-5)  # the stored environment, at unit gain
    assert (b[bg] < a[bg] - 0.05).float().mean() > 0.9  # "gain": the car's gain dims it
    assert torch.equal(a[car], b[car])  # the car is shaded alike
    with pytest.raises(ConfigError, match="model.shader_background"):
        load_config("cpu-small", ["model.shader_background=sky"])


def test_shading_terms_are_logged_and_the_shader_is_chosen_by_config():
    cfg = load_config("cpu-small", tiny_overrides() + ["model.renderer=shader", "loss.w_shading_ren=3",
                                                        "loss.w_shading_dec=1"])
    model = build_model(cfg)
    stacks, _ = _blobs(2)
    out = model.forward_all(stacks, shade_network(stacks))
    terms = model.loss_terms(out)
    assert terms["G/shading_ren"][0] == 3 and terms["G/shading_dec"][0] == 1
    assert all(torch.isfinite(v) for _, v in terms.values())
    assert isinstance(model.R, ShaderRenderer)
    # the paper's preset keeps the paper's R and no shading terms
    paper = load_config("paper")
    assert (paper.model.renderer, paper.loss.w_shading_ren, paper.loss.w_shading_dec) == ("net", 0, 0)
    with pytest.raises(ConfigError, match="model.renderer"):
        load_config("cpu-small", ["model.renderer=raytracer"])
    with pytest.raises(ConfigError, match="run.ema_decay"):
        load_config("cpu-small", ["run.ema_decay=1.5"])


def _d_m_input(stacks: torch.Tensor, setting: str) -> torch.Tensor:
    """The one batch D_M judges in a discriminator step of a tiny model with `setting`."""
    model = build_model(load_config("cpu-small", tiny_overrides() + [setting]))
    seen = []
    hook = model.D_M.register_forward_pre_hook(lambda mod, args: seen.append(args[0].detach()))
    model.discriminator_loss(model.forward_all(stacks, shade_network(stacks)))
    hook.remove()
    (batch,) = seen
    return batch


def test_d_m_judges_pooled_or_car_only_maps_when_asked_and_the_paper_keeps_the_whole_maps():
    stacks, _ = _blobs(2)
    for pool in (1, 2):
        torch.manual_seed(0)
        model = build_model(load_config("cpu-small", tiny_overrides() + [f"loss.adv_m_pool={pool}"]))
        seen = []
        hook = model.D_M.register_forward_pre_hook(lambda mod, args: seen.append(args[0].shape[-2:]))
        out = model.forward_all(stacks, shade_network(stacks))
        model.discriminator_loss(out)
        model.generator_loss(out)
        hook.remove()
        assert seen and all(tuple(s) == (stacks.shape[-2] // pool, stacks.shape[-1] // pool) for s in seen), (pool, seen)
    assert load_config("paper").loss.adv_m_pool == 1
    with pytest.raises(ConfigError, match="loss.adv_m_pool"):
        load_config("cpu-small", ["loss.adv_m_pool=0"])
    # on the car only: every stack D_M sees is zero where its own normals are short (no object)
    batch = _d_m_input(stacks, "loss.adv_m_on=car")
    inside = batch[:, :3].norm(dim=1, keepdim=True) > 0.5
    assert inside.any() and (~inside).any() and batch.masked_select(~inside.expand_as(batch)).abs().max() == 0
    assert torch.equal(batch[: len(stacks)], stacks * (stacks[:, :3].norm(dim=1, keepdim=True) > 0.5))  # the real ones
    assert load_config("paper").loss.adv_m_on == "all"
    # the reflection map only: normals and albedo reach D_M as zeros, the reflection map as it is
    batch = _d_m_input(stacks, "loss.adv_m_on=reflection")
    assert batch[:, :6].abs().max() == 0 and torch.equal(batch[: len(stacks), 6:], stacks[:, 6:])
    assert load_config("cpu-small").loss.adv_m_on == "reflection"  # the measured default
    # so D_M's generator terms reach H's reflection map and never its normals or albedo
    torch.manual_seed(0)
    model = build_model(load_config("cpu-small", tiny_overrides()))
    out = model.forward_all(stacks, shade_network(stacks))
    out["fake_M"].retain_grad()
    model.loss_terms(out)["G/adv_D_M_fake_M"][1].backward()
    g = out["fake_M"].grad
    assert g[:, :6].abs().max() == 0 and g[:, 6:].abs().max() > 0


def test_r1_penalty_on_d_m_is_the_squared_gradient_at_the_real_maps_and_smooths_d_m():
    stacks, _ = _blobs(2)
    torch.manual_seed(0)
    model = build_model(load_config("cpu-small", tiny_overrides() + ["loss.r1_m=4"]))
    out = model.forward_all(stacks, shade_network(stacks))
    total, logs = model.discriminator_loss(out)
    # by hand: the gradient of D_M's summed logits (both scales) at M_s, as D_M sees it (by default
    # the reflection map only: no gradient reaches the normals and albedo)
    x = stacks.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(sum(l.sum() for l in model._judge("D_M", x)), x)
    assert g[:, :6].abs().max() == 0 and g[:, 6:].abs().max() > 0
    expected = float(g.pow(2).flatten(1).sum(1).mean())
    assert logs["D/D_M_r1"] == pytest.approx(expected, rel=1e-4) and expected > 0
    model.loss_cfg.r1_m = 0.0
    plain, plain_logs = model.discriminator_loss(out)
    assert "D/D_M_r1" not in plain_logs
    assert float(total.detach()) == pytest.approx(float(plain.detach()) + 0.5 * 4 * expected, rel=1e-4)
    # a few D steps on the penalty shrink D_M's gradient at the real maps
    model.loss_cfg.r1_m = 4.0
    opt = torch.optim.Adam(model.D_M.parameters(), lr=1e-3)
    first = last = None
    for _ in range(8):
        opt.zero_grad()
        loss, logs = model.discriminator_loss(out)
        loss.backward()
        opt.step()
        first = logs["D/D_M_r1"] if first is None else first
        last = logs["D/D_M_r1"]
    assert last < 0.5 * first, (first, last)
    assert load_config("paper").loss.r1_m == 0 and load_config("cpu-small").loss.r1_m == 0
    with pytest.raises(ConfigError, match="loss.r1_m"):
        load_config("cpu-small", ["loss.r1_m=-1"])


def test_a_conditioned_d_m_judges_each_stack_beside_its_image_and_real_maps_beside_a_wrong_image_as_fake():
    stacks, _ = _blobs(3)
    torch.manual_seed(0)
    # on the whole maps (the default judges the reflection map only, so the batch's first 6 would be 0)
    model = build_model(load_config("cpu-small", tiny_overrides() + ["loss.adv_m_cond=image", "loss.adv_m_on=all"]))
    out = model.forward_all(stacks, shade_network(stacks))
    seen = []
    hook = model.D_M.register_forward_pre_hook(lambda mod, args: seen.append(args[0]))
    model.discriminator_loss(out)
    (batch,) = seen
    n = len(stacks)
    # real, H(I_r), H(R(M_s)), then M_s beside the previous sample's render
    assert batch.shape == (4 * n, 12) + stacks.shape[-2:]
    assert torch.equal(batch[:n], torch.cat([stacks, out["fake_I"].detach()], 1))
    assert torch.equal(batch[n:2 * n], torch.cat([out["fake_M"].detach(), out["I_r"]], 1))
    assert torch.equal(batch[2 * n:3 * n], torch.cat([out["rec_M"].detach(), out["fake_I"].detach()], 1))
    assert torch.equal(batch[3 * n:, :9], stacks) and torch.equal(batch[3 * n:, 9:], out["fake_I"].detach().roll(1, 0))
    hook.remove()
    # the generator's D_M terms reach H through the maps, never R through the conditioning image
    model.zero_grad()
    terms = model.loss_terms(out)
    terms["G/adv_D_M_fake_M"][1].backward(retain_graph=True)
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.H.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.R.parameters())
    # a batch of one has no other sample's render: no mismatched fake
    one = model.forward_all(stacks[:1], shade_network(stacks[:1]))
    assert model._mismatched(one) is None and model.discriminator_loss(one)[0].isfinite()
    assert load_config("paper").loss.adv_m_cond == "none" and load_config("cpu-small").loss.adv_m_cond == "none"
    with pytest.raises(ConfigError, match="loss.adv_m_cond"):
        load_config("cpu-small", ["loss.adv_m_cond=pairs"])
    with pytest.raises(ConfigError, match="loss.rendering_cycle"):
        load_config("cpu-small", ["loss.adv_m_cond=image", "loss.rendering_cycle=false"])


def test_d_m_terms_start_at_adv_m_from_while_d_m_learns_from_the_first_step():
    stacks, _ = _blobs(2)
    torch.manual_seed(0)
    model = build_model(load_config("cpu-small", tiny_overrides() + ["loss.adv_m_from=100"]))
    out = model.forward_all(stacks, shade_network(stacks))
    weights = lambda: {k: w for k, (w, _) in model.loss_terms(out).items() if "D_M" in k}  # noqa: E731
    assert model.step == 0 and weights() and all(w == 0 for w in weights().values())
    assert "D/D_M_real" in model.discriminator_loss(out)[1]  # D_M learns meanwhile
    model.step = 100
    assert weights()["G/adv_D_M_fake_M"] > 0  # (the reconstructions' terms weigh loss.w_adv_rec, 0 here)
    model.step = 0
    assert model.loss_terms(out)["G/adv_D_I_fake_I"][0] > 0  # D_I is not held back
    # the training loop tells the model its step
    from train.loop import build_optimisation, generator_step
    g_params, _, opts, _ = build_optimisation(load_config("cpu-small", tiny_overrides()), model)
    generator_step(model, opts["G"], g_params, stacks, shade_network(stacks), step=7)
    assert model.step == 7
    assert load_config("paper").loss.adv_m_from == 0 and load_config("cpu-small").loss.adv_m_from == 0
    with pytest.raises(ConfigError, match="loss.adv_m_from"):
        load_config("cpu-small", ["loss.adv_m_from=-1"])


def test_the_per_pixel_prior_knows_the_frame_and_beats_the_constant_on_its_own_data():
    stacks, masks = _blobs(6, seed=3)
    prior = pixel_prior(stacks)
    assert prior.shape == (9, 32, 64)
    # where no sample has an object: the camera-facing normal
    assert torch.allclose(prior[0:3, 0, 0], torch.tensor([0.0, 0.0, 1.0]))
    # the left side of a car faces left: the prior's normal points left there
    assert prior[0, 16, 12] < -0.3
    p = ProbeSet(shade_network(stacks), stacks, masks)
    p.const_albedo, p.const_reflection = training_means(stacks)
    p.prior = prior
    model = build_model(load_config("cpu-small", tiny_overrides()))
    figs = evaluate_probe(model, p)
    assert figs["probe/prior_normal_deg"] < figs["probe/const_normal_deg"] - 5
    for key in ("prior_albedo_l1", "prior_reflection_l1", "normal_hf_ratio", "albedo_hf"):
        assert np.isfinite(figs[f"probe/{key}"]), key


def test_the_speckle_figure_is_one_for_the_truth_and_large_for_noise():
    stacks, masks = _blobs(3)
    p = ProbeSet(shade_network(stacks), stacks, masks)
    truth = speckle_scores(stacks, p)
    assert truth["normal_hf_ratio"] == pytest.approx(1.0)
    assert np.isnan(truth["albedo_hf_ratio"])  # flat paint has no high frequencies to compare with
    noisy = stacks + 0.2 * torch.randn(stacks.shape, generator=torch.Generator().manual_seed(0))
    assert speckle_scores(noisy, p)["normal_hf_ratio"] > 5
    # the silhouette's edge does not count: a flat map cut by the mask scores 0
    flat = torch.ones(1, 3, 32, 64)
    assert high_frequency(flat, masks[:1, 0] > 0).item() == 0.0


def test_report_speckle_and_prior_agree_with_the_training_figures(tmp_path):
    from eval.decomposition import high_frequency as hf_np
    from eval.reference_rows import pixel_prior as prior_np

    stacks, masks = _blobs(2)
    n = stacks[0, 0:3].permute(1, 2, 0).numpy()
    on = masks[0, 0].numpy() > 0.5
    assert hf_np(n, on) == pytest.approx(high_frequency(stacks[:1, 0:3], masks[:1, 0] > 0.5).item(), rel=1e-5)
    intr = tiny_intrinsics(tmp_path / "intr", n=5, h=32, w=64)
    prior = prior_np(intr, (32, 16))
    assert prior["normal"].shape == (16, 32, 3)
    lengths = np.linalg.norm(prior["normal"], axis=-1)
    assert np.allclose(lengths, 1, atol=1e-4)


def _fit(args, cwd=ROOT):
    proc = subprocess.run([sys.executable, "-m", "train.cli", *args], cwd=cwd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def test_moving_average_is_probed_saved_and_resumed_exactly(tmp_path):
    intr = tiny_intrinsics(tmp_path / "intr", n=4)
    pbr = tiny_intrinsics(tmp_path / "pbr", n=4, seed=5, kind="pbr")
    sets = ["run.probe_every=3", "model.renderer=shader", "loss.w_shading_ren=1", "loss.w_shading_dec=1"]
    # the uninterrupted run and the first half here, the resume from the command line in a fresh process
    tiny_fit(tmp_path / "whole", intr, pbr, 6, *sets, probe=pbr)
    tiny_fit(tmp_path / "parts", intr, pbr, 3, *sets, probe=pbr)
    _fit(["fit", "--run-dir", str(tmp_path / "parts"), "--max-steps", "6", "--quiet"])
    rows = {}
    for name in ("whole", "parts"):
        rows[name] = [json.loads(line) for line in (tmp_path / name / "stats.jsonl").read_text().splitlines()]
    last = rows["whole"][-1]
    assert "probe_ema/normal_deg" in last and "probe/prior_normal_deg" in last
    assert last["probe_ema/normal_deg"] != last["probe/normal_deg"]  # another set of weights
    for key, value in last.items():
        assert rows["parts"][-1][key] == pytest.approx(value, rel=1e-5, abs=1e-7, nan_ok=True), key
    from safetensors.torch import load_file

    tensors = load_file(str(tmp_path / "whole" / "checkpoints" / "step_00000006.safetensors"))
    assert any(k.startswith("ema.R.") for k in tensors) and any(k.startswith("ema.H.") for k in tensors)


def test_lighting_fitted_to_an_image_renders_it_and_fills_the_bank():
    from train.colour import srgb_encode
    from train.shading import fit_lighting

    stacks, masks = _blobs(3)
    light = torch.zeros(3, 9)
    light[:, 0], light[:, 3] = 2.5, 0.8  # ambient and a light from the side
    image = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], light, torch.full((3,), 0.4))) * 2 - 1
    l_fit, g_fit = fit_lighting(image, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], masks)
    again = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], l_fit, g_fit)) * 2 - 1
    on = masks.expand(-1, 3, -1, -1) > 0
    assert (again - image).abs()[on].mean() < 0.02
    # the model: R(H(I_r)) is lit by the fit, R(M_s) by a drawn real lighting, the bank keeps the last ones
    cfg = load_config("cpu-small", tiny_overrides() + ["model.renderer=shader", "model.lighting_bank=4",
                                                       "model.shader_gain=per_image"])
    model = build_model(cfg).train()
    r = model.R
    assert int(r.bank_filled) == 0 and r.draw(2) is None
    fake = torch.cat([stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9]], 1)
    fitted, ok = model.real_lighting(image, fake)
    assert ok.all() and torch.allclose(fitted[..., :9], l_fit.clamp(-10, 10), atol=1e-4)
    for _ in range(2):
        model.forward_all(stacks, image)
    assert int(r.bank_filled) == 4 and int(r.bank_pos) == 2  # 6 pushed into 4 places, oldest out first
    assert r.draw(5).shape == (5, 3, 10)
    mean_light, mean_gain = r.default_lighting()
    assert torch.allclose(mean_light, r.bank.mean(0)[:, :9])
    # an image where H sees no object keeps the default lighting and is not banked
    empty = fake.clone()
    empty[:, 0:3] = 0
    _, ok = model.real_lighting(image, empty)
    assert not ok.any()


def test_a_run_trained_before_these_settings_loads_as_it_trained():
    from train.config import Config, config_from_dict

    old = Config().to_dict()
    for section, name in (("model", "renderer"), ("model", "shader_residual_on"), ("model", "shader_lighting"),
                          ("model", "shader_gain"), ("model", "shader_gain_min"), ("loss", "w_shading_ren"),
                          ("loss", "w_shading_dec"), ("run", "ema_decay")):
        del old[section][name]
    cfg = config_from_dict(old)
    assert (cfg.model.renderer, cfg.loss.w_shading_ren, cfg.loss.w_shading_dec, cfg.run.ema_decay) == ("net", 0, 0, 0)
    assert cfg.model.shader_gain == "per_image"  # the gain was fitted per image before the option
    assert cfg.model.shader_gain_min == 0.0  # and a shared gain had no floor
    # a run that names them keeps its values
    new = config_from_dict(Config().to_dict())
    assert new.model.renderer == Config().model.renderer and new.run.ema_decay == Config().run.ema_decay


def test_bank_level_images_scales_the_banked_lightings_to_the_real_images_car_level():
    """model.bank_level "images": lightings fitted too dim (as through a too-bright albedo) are given
    out at the real images' level, for R(M_s) and for inference; "fit" keeps them and saves no levels."""
    from train.colour import srgb_encode

    stacks, masks = _blobs(3)
    light = torch.zeros(3, 9)
    light[:, 0], light[:, 3] = 2.5, 0.8
    gain = torch.full((3,), 0.4)
    image = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], light, gain)) * 2 - 1
    dim = torch.cat([light * 0.5, (gain * 0.5).unsqueeze(-1)], dim=-1)  # (3, 10): half as bright
    for level, factor in (("fit", 1.0), ("images", 2.0)):
        cfg = load_config("cpu-small", tiny_overrides() + ["model.renderer=shader", "model.lighting_bank=4",
                                                           f"model.bank_level={level}", "model.shader_gain=per_image"])
        model = build_model(cfg).train()
        r = model.R
        assert ("R.levels" in model.state_dict()) == (level == "images")
        r.push(dim.expand(4, 3, 10))
        for _ in range(2):  # H's maps stand in as the true ones: its car mask is the images'
            model._update_levels(stacks, r.draw(3), image, stacks)
        assert torch.allclose(r.level_scale(), torch.full((3,), factor), rtol=1e-3)
        mean_light, mean_gain = r.default_lighting()
        assert torch.allclose(mean_light, factor * dim[:, :9], rtol=1e-3) and torch.allclose(mean_gain, factor * dim[:, 9], rtol=1e-3)
        on = masks.expand(-1, 3, -1, -1) > 0
        err = (r(stacks, r.draw(3)) - image).abs()[on].mean()
        assert (err < 0.01) == (level == "images")


def test_the_shader_learns_the_lighting_of_shaded_images_by_gradient():
    stacks, masks = _blobs(4, seed=7)
    target = shade_network(stacks)  # S0's light: ambient 0.3 and a light from above-right
    r = ShaderRenderer(list("NAF"), 8, 2, 1, 0, "instance", residual=0.0)
    opt = torch.optim.Adam(r.parameters(), lr=0.05)
    on = masks.expand(-1, 3, -1, -1) > 0

    def err() -> torch.Tensor:
        return (r(stacks) - target).abs()[on].mean()

    before = err().item()
    for _ in range(150):
        opt.zero_grad()
        loss = err()
        loss.backward()
        opt.step()
    assert err().item() < 0.3 * before


def test_gap_closed_starts_from_the_stronger_bar_per_column():
    from eval.report import PRIOR, _gap_closed

    def dec(n, a, f):
        return {"normal_mean_deg": n, "albedo_l1_srgb255": a, "reflection_l1_srgb255": f}

    entries = [{"label": "Constant predictor", "dec": dec(40, 70, 50)}, {"label": PRIOR, "dec": dec(34, 72, 40)},
               {"label": "Supervised oracle (paired PBR)", "dec": dec(18, 22, 24)}]
    # normals from the prior (34), albedo from the constant (70), reflection from the prior (40)
    assert _gap_closed(dec(26, 46, 32), entries) == "0.50 / 0.50 / 0.50"
    worse_oracle = entries[:2] + [{"label": "Supervised oracle (paired PBR)", "dec": dec(60, 22, 24)}]
    assert _gap_closed(dec(26, 46, 32), worse_oracle).startswith("- / ")



def test_a_shared_reflection_gain_leaves_no_room_for_copying_the_image_into_the_reflection_map():
    """With a gain fitted per image, maps that put the whole image into the reflection layer (no
    albedo) explain it exactly; with the gain shared at the data's value they cannot, while the
    true maps still fit. The shared gain is learned (log space) and reaches the renderer's output."""
    from train.colour import srgb_encode
    from train.shading import fit_lighting

    stacks, masks = _blobs(3)
    light = torch.zeros(3, 9)
    light[:, 0], light[:, 3] = 2.5, 0.8
    true_gain = torch.full((3,), 0.15)
    image = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], light, true_gain)) * 2 - 1
    copy = stacks.clone()
    copy[:, 3:6] = -1.0  # black albedo
    copy[:, 6:9] = torch.where(masks > 0, image, copy[:, 6:9])  # the image as its reflection map
    n, a, f = (lambda s: (s[:, 0:3], s[:, 3:6], s[:, 6:9]))(copy)
    fitted_res, fitted = fit_shading(image, n, a, f, masks)
    shared_res, shared = fit_shading(image, n, a, f, masks, gain=true_gain)
    truth_res, _ = fit_shading(image, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], masks, gain=true_gain)
    assert fitted_res.max() < 0.01 and shared_res.min() > 0.5 and truth_res.max() < 0.05
    assert torch.allclose(shared[:, 9], torch.full((3,), float((torch.tensor([0.2126, 0.7152, 0.0722]) * 0.15).sum())))
    light_fit, gain = fit_lighting(image, stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], masks, gain=true_gain)
    assert gain.shape == (3, 3) and torch.allclose(gain, true_gain.expand(3, 3))
    again = srgb_encode(render_sh(stacks[:, 0:3], stacks[:, 3:6], stacks[:, 6:9], light_fit, gain)) * 2 - 1
    assert (again - image).abs()[masks.expand(-1, 3, -1, -1) > 0].mean() < 0.02
    cfg = load_config("cpu-small", tiny_overrides() + ["model.renderer=shader", "model.shader_gain=shared",
                                                       "model.shader_gain_start=0.2"])
    model = build_model(cfg)
    assert torch.allclose(model.R.shared_gain(), torch.full((3,), 0.2))
    out = model.R(stacks)
    out.mean().backward()
    assert model.R.log_gain.grad is not None and model.R.log_gain.grad.abs().sum() > 0
    plain = build_model(load_config("cpu-small", tiny_overrides() + ["model.renderer=shader", "model.shader_gain=per_image"]))
    assert plain.R.shared_gain() is None and "R.log_gain" not in plain.state_dict()  # older checkpoints still load
    with pytest.raises(ConfigError, match="model.shader_gain_start"):
        load_config("cpu-small", tiny_overrides() + ["model.shader_gain_start=nan"])
    # a floor: the gain starts where asked and never falls below the floor, however far it is pushed
    floored = build_model(load_config("cpu-small", tiny_overrides() + ["model.renderer=shader",
                                                                      "model.shader_gain_min=0.1"]))
    assert torch.allclose(floored.R.shared_gain(), torch.full((3,), 0.25))
    with torch.no_grad():
        floored.R.log_gain.fill_(-100.0)
    assert torch.allclose(floored.R.shared_gain(), torch.full((3,), 0.1))
    with pytest.raises(ConfigError, match="model.shader_gain_min"):
        load_config("cpu-small", tiny_overrides() + ["model.shader_gain_min=0.3"])  # above the start


def test_the_shading_budget_takes_a_cycles_image_apart():
    """bench/shading_budget.py: a diffuse shading that is exactly second-order SH of the normals
    fits to ~0; the layers' shares of the car's luminance add up to the image's."""
    budget = bench_module("shading_budget").budget

    from train.shading import sh_basis

    rng = np.random.default_rng(0)
    h, w = 24, 40
    yy, xx = np.mgrid[0:h, 0:w]
    u, v = (xx - w / 2) / (w / 2.2), (yy - h / 2) / (h / 2.2)
    inside = u**2 + v**2 < 1
    n = np.stack([u, -v, np.sqrt(np.clip(1 - u**2 - v**2, 1e-4, 1))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    basis = sh_basis(torch.from_numpy(n.transpose(2, 0, 1).copy()).float()[None])[0].numpy().transpose(1, 2, 0)
    shading = np.repeat((basis @ np.array([1.0, 0.3, 0.5, 0.2, 0.05, 0.1, 0.1, 0.0, 0.05]))[..., None], 3, -1)
    albedo = np.full((h, w, 3), 0.5) * inside[..., None]
    glossy = rng.uniform(0, 0.2, (h, w, 3)) * inside[..., None]
    zero = np.zeros((h, w, 3))
    sample = {"normal": n * inside[..., None], "albedo": albedo, "reflection": glossy * 2, "mask": inside[..., None] * 1.0,
              "diffuse_shading": shading, "diffuse_color": albedo, "glossy": glossy, "transmission": zero,
              "emission": zero, "environment": zero, "rgb_noisy": albedo * shading + glossy}
    row = budget(sample)
    assert row["residual_diffuse_shading"] < 1e-4 and row["residual_diffuse_image"] < 1e-4
    assert row["residual_image"] < 1e-3  # gloss = 0.5 x the reflection layer: the model draws it exactly
    shares = sum(row[k] for k in row if k.startswith("share_"))
    assert shares == pytest.approx(1.0, abs=1e-6)
    sample["diffuse_shading"] = shading * rng.uniform(0.5, 1.5, (h, w, 1))  # noise the SH cannot draw
    assert budget(sample)["residual_diffuse_shading"] > 0.1


def test_the_probe_plot_draws_the_moving_average_beside_both_no_image_bars_and_the_speckle():
    from train.probe import probe_figure, probe_plot

    def row(step: int, ema: bool) -> dict:
        r = {"step": step, "probe/normal_deg": 40.0 - step / 100, "probe/const_normal_deg": 40.0,
             "probe/prior_normal_deg": 35.0, "probe/albedo_l1": 50.0, "probe/const_albedo_l1": 70.0,
             "probe/prior_albedo_l1": 67.0, "probe/reflection_l1": 40.0, "probe/const_reflection_l1": 52.0,
             "probe/prior_reflection_l1": 37.0, "probe/normal_hf_ratio": 2.0, "probe/albedo_hf_ratio": 1.5}
        if ema:
            r.update({"probe_ema/normal_deg": 39.0 - step / 100, "probe_ema/normal_hf_ratio": 0.4,
                      "probe_ema/albedo_hf_ratio": 1.1})
        return r

    assert probe_figure([{"step": 10, "G/total": 1.0}]) is None  # no probe rows: nothing to draw
    fig = probe_figure([row(100, True), {"step": 150, "G/total": 1.0}, row(200, True)], "full")
    labels = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes]
    assert {"H normals (moving avg.)", "H normals (raw)", "no image, constant",
            "no image, per-pixel prior"} <= set(labels[0])
    assert "albedo, per-pixel prior" in labels[1] and "reflection, constant" in labels[1]
    ema_curve = [ln for ln in fig.axes[0].get_lines() if ln.get_label() == "H normals (moving avg.)"][0]
    assert list(ema_curve.get_ydata()) == [38.0, 37.0]  # the moving average's figures, one per probe row
    speckle = [ln for ln in fig.axes[2].get_lines() if ln.get_label() == "normals"][0]
    assert list(speckle.get_ydata()) == [0.4, 0.4]  # read from the moving average where the rows have it
    # a run probed before the moving average and the prior existed: raw curve and constant only
    old = [{k: v for k, v in row(s, False).items() if "prior" not in k} for s in (100, 200)]
    labels = [t.get_text() for t in probe_figure(old).axes[0].get_legend().get_texts()]
    assert labels == ["H normals", "no image, constant"]
    assert probe_plot(old)[:8] == b"\x89PNG\r\n\x1a\n"
    # after the first probe every curve is one point: drawn as a marker, as a line would draw nothing
    first = probe_figure([row(100, True)])
    drawn = [ln for ax in first.axes for ln in ax.get_lines() if len(ln.get_xdata()) == 1]
    assert len(drawn) >= 8 and all(ln.get_marker() not in ("None", "", None) for ln in drawn)
    assert all(ln.get_marker() in ("None", "", None) for ln in fig.axes[0].get_lines())  # lines once there are two
