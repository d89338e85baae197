"""Making the model learn: probe figures, the loss options, the training-size cache, the
gradient diagnosis, the sanity sets and the environment background of intrinsics."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from blender_gen.dataset import sha256_file
from train.config import load_config
from train.data import CachedTensors, IntrinsicsData, RealImages, flip_stack
from train.losses import chroma_loss
from train.model import build_model
from train.probe import ProbeSet, decomposition_scores, evaluate_probe, input_sensitivity, training_means
from train.colour import srgb_decode, srgb_encode
from train.sanity import LIGHT, shade_network

from .conftest import invoke_here
from .train_helpers import TINY, tiny_intrinsics, tiny_overrides

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("learn")
    return {"intr": tiny_intrinsics(base / "intr", n=6, seed=0),
            "pbr": tiny_intrinsics(base / "pbr", n=4, seed=5, kind="pbr")}


def _probe(n=4, h=16, w=32, seed=0) -> ProbeSet:
    g = torch.Generator().manual_seed(seed)
    maps = torch.rand(n, 9, h, w, generator=g) * 2 - 1
    maps[:, :3] = torch.nn.functional.normalize(maps[:, :3], dim=1)
    masks = torch.zeros(n, 1, h, w)
    masks[:, :, 4:12, 8:24] = 1
    return ProbeSet(torch.rand(n, 3, h, w, generator=g) * 2 - 1, maps, masks)


def test_probe_scores_are_zero_for_the_truth_and_known_for_a_constant():
    p = _probe()
    perfect = decomposition_scores(p.maps, p)
    assert perfect["normal_deg"] == pytest.approx(0, abs=0.05)
    assert perfect["albedo_l1"] == pytest.approx(0) and perfect["reflection_l1"] == pytest.approx(0)
    # one albedo channel off by 0.2 network units everywhere: 0.2 * 127.5 / 3 on the 0-255 scale
    off = p.maps.clone()
    off[:, 3] += 0.2
    assert decomposition_scores(off, p)["albedo_l1"] == pytest.approx(0.2 * 127.5 / 3, rel=1e-4)
    # a normal turned by 90 degrees on every pixel
    turned = p.maps.clone()
    n = p.maps[:, :3]
    turned[:, :3] = torch.nn.functional.normalize(torch.cross(n, torch.roll(n, 1, dims=1), dim=1), dim=1)
    assert decomposition_scores(turned, p)["normal_deg"] == pytest.approx(90, abs=0.1)


def test_input_sensitivity_is_zero_for_a_constant_renderer_and_one_for_a_perfect_one():
    p = _probe()
    on = p.masks[:, 0] >= 0.5
    assert input_sensitivity(p.images, p.images, on) == pytest.approx(1.0)
    same = p.images[:1].expand_as(p.images)
    assert input_sensitivity(same, p.images, on) == 0.0
    assert input_sensitivity(0.5 * p.images, p.images, on) == pytest.approx(0.5)


def test_colour_correlation_is_one_for_the_truth_and_zero_for_one_colour_everywhere():
    from train.probe import colour_correlation

    p = _probe()
    on = p.masks[:, 0] >= 0.5
    assert colour_correlation(p.images, p.images, on) == pytest.approx(1.0)
    # brightness and exposure do not count: a darker, offset copy keeps its colours
    assert colour_correlation(0.5 * p.images - 0.2, p.images, on) == pytest.approx(1.0)
    # the same coloured car drawn for every input: the chroma never varies with the true one
    one = torch.zeros_like(p.images)
    one[:, 0], one[:, 2] = 0.4, -0.4
    assert colour_correlation(one, p.images, on) == pytest.approx(0.0, abs=1e-6)
    swapped = p.images[:, [2, 1, 0]]  # red for blue: anti-correlated where the colours differ
    assert colour_correlation(swapped, p.images, on) < 0.5


def test_training_means_average_object_pixels_in_linear_light():
    maps = torch.zeros(2, 9, 4, 4)
    maps[:, 2, :, :2] = 1.0  # object on the left half
    maps[0, 3:6, :, :2] = srgb_encode(torch.tensor(0.2)) * 2 - 1
    maps[1, 3:6, :, :2] = srgb_encode(torch.tensor(0.6)) * 2 - 1
    maps[:, 3:6, :, 2:] = 1.0  # background values must not count
    albedo, _ = training_means(maps)
    assert float(srgb_decode((albedo[0] + 1) / 2)) == pytest.approx(0.4, abs=1e-4)


def test_evaluate_probe_reports_every_figure_and_restores_train_mode():
    cfg = load_config("cpu-small", tiny_overrides())
    model = build_model(cfg)
    model.train()
    p = _probe(h=32, w=64)
    p.const_albedo, p.const_reflection = training_means(p.maps)
    figs = evaluate_probe(model, p)
    assert model.training
    for key in ("normal_deg", "albedo_l1", "reflection_l1", "normal_corr_x", "normal_corr_y", "normal_corr_z",
                "const_normal_deg", "const_albedo_l1", "const_reflection_l1", "render_l1", "r_sensitivity",
                "r_colour_corr", "h_colour_corr"):
        assert np.isfinite(figs[f"probe/{key}"]), key
    assert figs["probe/r_gain"] == pytest.approx(cfg.model.shader_gain_start)  # the shared gain, untrained
    per_image = build_model(load_config("cpu-small", tiny_overrides() + ["model.shader_gain=per_image"]))
    assert "probe/r_gain" not in evaluate_probe(per_image, p)


def test_s0_shader_is_the_stated_formula():
    maps = torch.zeros(1, 9, 2, 2)
    maps[0, 0:3, 0, 0] = LIGHT  # facing the light, white albedo, no reflection: linear 1.0
    maps[0, 3:6, 0, 0] = 1.0
    maps[0, 0:3, 0, 1] = -LIGHT  # facing away: ambient 0.3 of albedo 0.5, plus 0.5 x reflection 0.2
    maps[0, 3:6, 0, 1] = srgb_encode(torch.tensor(0.5)) * 2 - 1
    maps[0, 6:9, 0, 1] = srgb_encode(torch.tensor(0.2)) * 2 - 1
    maps[0, 3:9, 1, :] = -1.0  # background: black everything, zero normal
    img = shade_network(maps)
    lin = srgb_decode((img + 1) / 2)
    assert torch.allclose(lin[0, :, 0, 0], torch.ones(3), atol=1e-5)
    assert torch.allclose(lin[0, :, 0, 1], torch.full((3,), 0.3 * 0.5 + 0.5 * 0.2), atol=1e-5)
    assert torch.all(img[0, :, 1, :] == -1)


def test_normal_length_on_the_car_never_touches_the_background():
    cfg = load_config("cpu-small", tiny_overrides() + ["loss.normal_length_on=car"])
    model = build_model(cfg)
    m_s = torch.zeros(1, 9, 32, 64)
    m_s[:, 2, 8:24, 16:48] = 1.0
    rec = (torch.randn(1, 9, 32, 64) * 0.5).requires_grad_()
    fake = (torch.randn(1, 9, 32, 64) * 0.5).requires_grad_()
    loss = model._normal_length({"M_s": m_s, "rec_M": rec, "fake_M": fake})
    loss.backward()
    assert fake.grad is None  # H(I_r) has no known mask: untouched
    assert torch.all(rec.grad[:, :, :8] == 0) and rec.grad[:, :3, 8:24, 16:48].abs().sum() > 0
    # the paper's threshold rule acts wherever a prediction is long, background included
    cfg2 = load_config("cpu-small", tiny_overrides() + ["loss.normal_length_on=threshold"])
    rec2 = torch.zeros(1, 9, 32, 64)
    rec2[:, 2] = 0.8
    rec2.requires_grad_()
    build_model(cfg2)._normal_length({"M_s": m_s, "rec_M": rec2}).backward()
    assert rec2.grad[:, 2, :8].abs().sum() > 0


def test_gan_terms_averaged_over_scales_and_fakes():
    torch.manual_seed(0)
    sets = tiny_overrides() + ["loss.w_adv_m=1", "loss.w_adv_rec=1"]  # the paper's shared terms
    out_sum = build_model(load_config("cpu-small", sets + ["loss.gan_reduce=sum"]))
    torch.manual_seed(0)
    out_mean = build_model(load_config("cpu-small", sets + ["loss.gan_reduce=mean"]))
    m, i = torch.rand(2, 9, 32, 64) * 2 - 1, torch.rand(2, 3, 32, 64) * 2 - 1
    t_sum = out_sum.loss_terms(out_sum.forward_all(m, i))
    t_mean = out_mean.loss_terms(out_mean.forward_all(m, i))
    scales = 2  # model.d_scales
    for k in t_sum:
        if k.startswith("G/adv_"):
            assert float(t_mean[k][1].detach()) == pytest.approx(float(t_sum[k][1].detach()) / scales, rel=1e-5)
            assert t_mean[k][0] == pytest.approx(t_sum[k][0] / 2)  # two fakes per shared discriminator


def test_reconstructions_train_the_discriminators_but_not_the_generators_by_default():
    m, i = torch.rand(2, 9, 32, 64) * 2 - 1, torch.rand(2, 3, 32, 64) * 2 - 1
    model = build_model(load_config("cpu-small", tiny_overrides() + ["loss.w_adv_m=1"]))
    out = model.forward_all(m, i)
    w = {k: wt for k, (wt, _) in model.loss_terms(out).items() if k.startswith("G/adv_")}
    # the direct translations weigh as without sharing (a weighted mean), the reconstructions 0
    assert w == {"G/adv_D_I_fake_I": 1.0, "G/adv_D_I_rec_I": 0.0, "G/adv_D_M_fake_M": 1.0, "G/adv_D_M_rec_M": 0.0}
    assert model.discriminator_inputs(out)["D_M"][1] == ["fake_M", "rec_M"]  # D still learns from both
    # with one cycle off, a discriminator's only fake (a reconstruction) keeps its full weight
    no_dec = build_model(load_config("cpu-small", tiny_overrides() + ["loss.w_adv_m=1", "loss.decomposition_cycle=false"]))
    w = {k: wt for k, (wt, _) in no_dec.loss_terms(no_dec.forward_all(m, i)).items() if k.startswith("G/adv_")}
    assert w == {"G/adv_D_I_fake_I": 1.0, "G/adv_D_M_rec_M": 1.0}


def test_generator_loss_is_the_weighted_sum_of_its_terms():
    model = build_model(load_config("cpu-small", tiny_overrides()))
    out = model.forward_all(torch.rand(2, 9, 32, 64) * 2 - 1, torch.rand(2, 3, 32, 64) * 2 - 1)
    total, logs = model.generator_loss(out)
    terms = model.loss_terms(out)
    assert float(total) == pytest.approx(sum(w * float(v) for w, v in terms.values()), rel=1e-5)
    assert set(logs) == set(terms) | {"G/total"}


def test_chroma_loss_ignores_brightness_and_sees_a_hue_change():
    g = torch.Generator().manual_seed(0)
    albedo = torch.rand(2, 3, 16, 32, generator=g) * 2 - 1
    mask = torch.zeros(2, 1, 16, 32)
    mask[:, :, 4:12, 8:24] = 1
    assert float(chroma_loss(albedo, albedo, mask)) == 0.0
    darker = (albedo + 1) * 0.5 * 0.8 * 2 - 1  # shading dims the car, its colour stays
    rotated = albedo[:, [1, 2, 0]]  # the same brightness, another hue
    assert float(chroma_loss(darker, albedo, mask)) < 0.2 * float(chroma_loss(rotated, albedo, mask))
    outside = albedo.clone()
    outside[:, :, :4] = -albedo[:, :, :4]  # the background never counts
    assert float(chroma_loss(outside, albedo, mask)) == 0.0
    # a default term weighted as configured; not in the paper's objective, nor without albedo input
    m, i = torch.rand(2, 9, 32, 64) * 2 - 1, torch.rand(2, 3, 32, 64) * 2 - 1
    for sets, weight in (([], 10.0), (["loss.w_chroma=3"], 3.0), (["loss.w_chroma=0"], None), (["model.inputs=NF"], None)):
        model = build_model(load_config("cpu-small", tiny_overrides() + sets))
        assert model.loss_terms(model.forward_all(m, i)).get("G/chroma", (None,))[0] == weight, sets
    paper = build_model(load_config("paper", tiny_overrides()))
    assert "G/chroma" not in paper.loss_terms(paper.forward_all(m, i))


def test_albedo_level_term_moves_a_too_bright_population_and_is_off_by_default():
    from train.losses import level_bias_loss, linear_mean

    mask = torch.ones(1, 1, 4, 4)
    level = linear_mean(torch.zeros(1, 3, 4, 4), mask)  # mid-grey in network space
    assert torch.allclose(level, torch.full((3,), 0.2140), atol=1e-3)  # sRGB 0.5 in linear light
    # a population too bright in green: the batch's green is pushed down, red and blue untouched
    x = level.clone().requires_grad_(True)
    loss = level_bias_loss(x, torch.tensor([0.2, 0.3, 0.2]), torch.tensor([0.2, 0.2, 0.2]))
    assert float(loss.detach()) == pytest.approx(math.log(1.5) ** 2, rel=1e-4)
    loss.backward()
    assert x.grad[1] > 0 and x.grad[0] == 0 and x.grad[2] == 0
    # in the model: absent by default (no buffer, old checkpoints load), a running level when on
    m, i = torch.rand(2, 9, 32, 64) * 2 - 1, torch.rand(2, 3, 32, 64) * 2 - 1
    m[:, 0:3] = torch.nn.functional.normalize(m[:, 0:3], dim=1)
    off = build_model(load_config("cpu-small", tiny_overrides()))
    assert off.albedo_levels is None and "albedo_levels" not in off.state_dict()
    assert "G/albedo_level" not in off.loss_terms(off.forward_all(m, i))
    on = build_model(load_config("cpu-small", tiny_overrides() + ["loss.w_albedo_level=3"])).train()
    w, v = on.loss_terms(on.forward_all(m, i))["G/albedo_level"]
    assert w == 3.0 and torch.isfinite(v) and "albedo_levels" in on.state_dict()
    assert float(on.albedo_levels[1].min()) > 0  # the training intrinsics' level was recorded
    v.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in on.H.parameters())


def test_cache_gives_the_decoded_tensors_and_rebuilds_when_the_data_changes(data, tmp_path):
    ds = IntrinsicsData(data["intr"], 32, 64)
    cache = CachedTensors(ds, tmp_path / "c" / "intr.npy", stack=True)
    for i in range(len(ds)):
        assert torch.equal(cache[(i, False)], ds[(i, False)])
        assert torch.equal(cache[(i, True)], flip_stack(ds[(i, False)]))
    reals = RealImages(data["pbr"], 32, 64)
    rc = CachedTensors(reals, tmp_path / "c" / "real.npy", stack=False)
    assert torch.equal(rc[(1, True)], reals[(1, True)])
    # a stale key (another dataset content) is rebuilt, a half-written file without its key is never used
    meta = tmp_path / "c" / "intr.json"
    key = json.loads(meta.read_text())
    meta.write_text(json.dumps({**key, "content": "0" * 64}))
    np.save(tmp_path / "c" / "intr.npy", np.zeros((len(ds), 9, 32, 64), np.float32))
    again = CachedTensors(ds, tmp_path / "c" / "intr.npy", stack=True)
    assert torch.equal(again[(0, False)], ds[(0, False)])
    meta.unlink()
    assert torch.equal(CachedTensors(ds, tmp_path / "c" / "intr.npy", stack=True)[(2, False)], ds[(2, False)])
    # derived data: a damaged key, a truncated array and a killed build's temporary cost a rebuild
    meta.write_text("{not json")
    assert torch.equal(CachedTensors(ds, tmp_path / "c" / "intr.npy", stack=True)[(1, False)], ds[(1, False)])
    npy = tmp_path / "c" / "intr.npy"
    npy.write_bytes(npy.read_bytes()[: npy.stat().st_size // 2])
    (tmp_path / "c" / ".intr.npy.tmp999").write_bytes(b"\0" * 4096)
    assert torch.equal(CachedTensors(ds, npy, stack=True)[(3, False)], ds[(3, False)])
    assert not list((tmp_path / "c").glob(".intr.npy.tmp*"))
    # a photo replaced by another of the same size and modification time is not served from the cache
    import os
    import shutil

    from PIL import Image

    from .train_helpers import tiny_photos

    photos = tiny_photos(tmp_path / "photos", n=2)
    first = RealImages(photos, 32, 64)
    CachedTensors(first, tmp_path / "c" / "photos.npy", stack=False)
    target = photos / "photo_1.png"
    st = target.stat()
    swapped = tmp_path / "swap.png"
    Image.new("RGB", (90, 60), (250, 10, 10)).save(swapped)
    swapped.write_bytes(swapped.read_bytes()[: st.st_size].ljust(st.st_size, b"\0"))  # same size
    shutil.copyfile(swapped, tmp_path / "same_size.png")
    os.replace(tmp_path / "same_size.png", target)
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))  # same modification time
    reread = RealImages(photos, 32, 64)
    assert torch.equal(CachedTensors(reread, tmp_path / "c" / "photos.npy", stack=False)[(1, False)], reread[(1, False)])


def _fit(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "train.cli", "fit", *args], capture_output=True, text=True, cwd=ROOT)


def test_diagnose_names_a_run_of_another_kind(data, tmp_path):
    from train.config import load_config

    run = tmp_path / "cyclegan_run"
    run.mkdir()
    (run / "training_options.json").write_text(json.dumps({"config": load_config("cyclegan").to_dict(),
                                                           "intrinsics": str(data["pbr"]), "real": str(data["pbr"])}))
    proc = subprocess.run([sys.executable, "-m", "train.cli", "diagnose", "--run", str(run), "--probe", str(data["pbr"])],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert f"--run {run}: a cyclegan run; diagnose measures" in proc.stderr, proc.stderr


def test_fit_probe_logs_curves_and_diagnose_reads_the_run(data, tmp_path):
    run = tmp_path / "run"
    proc = _fit("--config", "cpu-small", "--intrinsics", str(data["intr"]), "--real", str(data["pbr"]),
                "--probe", str(data["pbr"]), "--run-dir", str(run), "--max-steps", "4", "--quiet", *TINY,
                "--set", "run.probe_every=2")
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(x) for x in (run / "stats.jsonl").read_text().splitlines()]
    probed = [r["step"] for r in rows if "probe/normal_deg" in r]
    assert probed == [2, 4]
    # every run folder has a model card of its newest weights
    card = (run / "MODEL_CARD.md").read_text()
    assert "Trained for 4 of" in card and "64x32 (width x height)" in card and "| H | Decomposer |" in card
    assert "| per-pixel prior (no image) |" in card and "## Limits" in card
    assert str(data["intr"]) in card or str(data["intr"].resolve()) in card
    assert (run / "probe.png").stat().st_size > 1000
    assert json.loads((run / "training_options.json").read_text())["probe"] == str(data["pbr"].resolve())
    assert (run / "cache" / "intrinsics_32x64.npy").exists()
    # resumed without --probe: the saved probe goes on
    proc = _fit("--run-dir", str(run), "--max-steps", "6", "--quiet")
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(x) for x in (run / "stats.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "probe/normal_deg" in r] == [2, 4, 6]

    out = tmp_path / "diag.json"
    proc = subprocess.run([sys.executable, "-m", "train.cli", "diagnose", "--run", str(run), "--probe", str(data["pbr"]),
                           "--batch", "2", "--json", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "ren_cycle" in proc.stdout and "H_N |g|" in proc.stdout
    terms = json.loads(out.read_text())["terms"]
    assert all(-1 <= row[net]["cosine"] <= 1 for row in terms.values() for net in ("H_N", "H_A", "H_F", "R"))
    # D_I's term on R(M_s) cannot reach H; the normal-length term (car only) cannot reach H_A or H_F
    assert terms["G/adv_D_I_fake_I"]["H_N"]["grad_norm"] == 0
    assert terms["G/normal_length"]["H_A"]["grad_norm"] == 0 and terms["G/normal_length"]["H_F"]["grad_norm"] == 0
    assert terms["G/ren_cycle"]["H_N"]["grad_norm"] > 0

    def diagnose(*args):  # the error paths, in this process
        from train.cli import main

        return invoke_here(main, "diagnose", "--run", run, "--batch", "2", *args)

    other = tmp_path / "other_run" / "checkpoints"  # another run's checkpoint under this run's name: refused
    shutil.copytree(run / "checkpoints", other)
    proc = diagnose("--probe", str(data["pbr"]), "--checkpoint", str(next(other.glob("*.safetensors"))))
    assert proc.returncode == 1 and "not a checkpoint of --run" in proc.stderr and "Traceback" not in proc.stderr
    # a NaN in a probe sample: a one-line error naming the sample, not a table of nan
    from blender_gen.dataset import read_exr, write_exr

    bad = tmp_path / "bad_probe"
    shutil.copytree(data["pbr"], bad)
    layers = read_exr(bad / "samples" / "000001.exr")
    layers["albedo"][3, 3] = np.nan
    write_exr(bad / "samples" / "000001.exr", layers)
    rows = [json.loads(x) for x in (bad / "manifest.jsonl").read_text().splitlines()]
    rows[1]["sha256"] = sha256_file(bad / "samples" / "000001.exr")
    (bad / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    proc = diagnose("--probe", str(bad))
    assert proc.returncode == 1 and "000001.exr: layer 'albedo' holds NaN" in proc.stderr, proc.stderr


def test_diagnose_of_a_baseline_is_a_one_line_error(data, tmp_path):
    run = tmp_path / "cg"
    proc = _fit("--config", "cyclegan", "--intrinsics", str(data["intr"]), "--real", str(data["pbr"]),
                "--run-dir", str(run), "--max-steps", "1", "--quiet",
                *[a for s in tiny_overrides("cyclegan") for a in ("--set", s)])
    assert proc.returncode == 0, proc.stderr
    from train.cli import main

    proc = invoke_here(main, "diagnose", "--run", run, "--probe", data["pbr"])
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr and "model.kind = 'iae'" in proc.stderr


def test_sanity_sets_shade_and_mask_what_they_derive(data, tmp_path):
    from blender_gen.dataset import open_dataset
    from eval.sanity import _masked, _shade, derive

    s0 = derive(data["pbr"], tmp_path / "s0", "pbr", [0, 2], _shade, "S0 shading")
    s1 = derive(data["pbr"], tmp_path / "s1", "pbr", [1], _masked, "S1 mask")
    src = open_dataset(data["pbr"])
    a, b = open_dataset(s0), open_dataset(s1)
    assert len(a) == 2 and len(b) == 1 and a.info["complete"]
    got = a.load(1, ["rgb", "normal"])
    want = _shade(src.load(2))
    assert np.allclose(got["rgb"], want["rgb"], atol=2e-3)  # half-float EXR
    assert np.array_equal(got["normal"], src.load(2, ["normal"])["normal"])
    m = b.load(0, ["rgb", "mask"])
    assert np.all(m["rgb"][m["mask"][..., 0] < 0.5] == 0)
    # an existing complete set of the same derivation is kept; another derivation is rebuilt
    stamp = (s0 / "dataset.json").stat().st_mtime_ns
    derive(data["pbr"], tmp_path / "s0", "pbr", [0, 2], _shade, "S0 shading")
    assert (s0 / "dataset.json").stat().st_mtime_ns == stamp
    derive(data["pbr"], tmp_path / "s0", "pbr", [0], _shade, "S0 shading")
    assert len(open_dataset(s0)) == 1


def test_environment_background_shows_what_the_pbr_image_shows_behind_the_car(tmp_path):
    """The reflection layer's background is the environment seen directly (Cycles' Environment
    pass); the PBR image of the same recipe shows the same sky and ground, plus the car's shadow."""
    from blender_gen.dataset import open_dataset

    from .conftest import run_gen

    common = ["--count", "2", "--resolution", "96x48", "--seed", "4", "--cars", "procedural:train", "--envmap",
              "procedural", "--quiet"]
    run_gen("intrinsics", "--out", str(tmp_path / "env"), "--background", "environment", *common)
    run_gen("intrinsics", "--out", str(tmp_path / "black"), "--background", "black", *common)
    run_gen("pbr", "--out", str(tmp_path / "pbr"), "--samples", "16", *common)
    env, black, pbr = (open_dataset(tmp_path / k) for k in ("env", "black", "pbr"))
    assert "background" in env.info["recipe"] and "background" not in black.info["recipe"]
    for i in range(2):
        e, b, p = env.load(i), black.load(i), pbr.load(i)
        car = e["mask"][..., 0] >= 1.0
        bg = e["mask"][..., 0] <= 0.0
        # car and camera turn instead of the environment: the same layers up to rounding
        assert np.array_equal(e["mask"], b["mask"])
        assert np.abs(e["normal"] - b["normal"]).max() < 5e-3
        diff = np.abs(e["reflection"][car] - b["reflection"][car])
        assert diff.mean() < 1e-3 and diff.max() < 0.02
        assert np.all(b["reflection"][bg] == 0) and e["reflection"][bg].mean() > 0.05
        rel = np.abs(e["reflection"][bg] - p["rgb"][bg]).mean() / p["rgb"][bg].mean()
        assert rel < 0.2, rel  # what differs is the car's shadow on the ground and sampling noise


def test_environment_lookup_matches_cycles_environment_pass():
    """The environment background looked up along the view rays in NumPy is what Cycles'
    Environment pass shows there (sets made before the lookup keep the pass); the car is unchanged."""
    from blender_gen.recipe import Recipe
    from blender_gen.render import SampleRenderer

    from .conftest import TEST_THREADS

    got = {}
    for method in ("lookup", "cycles"):
        r = SampleRenderer(Recipe(kind="intrinsics", seed=4, width=96, height=48, background="environment",
                                  environment_pass=method), threads=TEST_THREADS)
        assert (r.world_env is None) == (method == "lookup")
        got[method] = [r.render_layers(i)[0] for i in range(3)]
        r.close()
    rel = []
    for a, b in zip(got["lookup"], got["cycles"]):
        assert np.array_equal(a["mask"], b["mask"]) and np.abs(a["normal"] - b["normal"]).max() < 5e-3
        car, bg = a["mask"][..., 0] >= 1.0, a["mask"][..., 0] <= 0.0
        assert np.abs(a["reflection"][car] - b["reflection"][car]).mean() < 1e-3
        ref = b["reflection"][bg]
        assert ref.mean() > 0.05  # the pass shows a sky and a ground
        rel.append(np.abs(a["reflection"][bg] - ref).max(axis=-1) / np.maximum(ref.max(axis=-1), 0.05))
    rel = np.concatenate(rel)
    # one jittered sample per pixel against the pixel centre: equal up to the skyline's texels
    assert np.median(rel) < 0.02 and (rel < 0.1).mean() > 0.95, (np.median(rel), (rel < 0.1).mean())


def test_an_environment_set_made_with_the_cycles_pass_resumes_with_it(tmp_path):
    """A set whose recipe predates the lookup (no `environment_pass` in its identity) is resumed
    and extended with Cycles' Environment pass, so its samples stay byte-identical."""
    from blender_gen.generate import legacy_recipe
    from blender_gen.recipe import Recipe

    new = Recipe(kind="intrinsics", seed=4, width=96, height=48, background="environment")
    assert new.identity()["environment_pass"] == "lookup"
    old = Recipe(kind="intrinsics", seed=4, width=96, height=48, background="environment", environment_pass="cycles")
    assert "environment_pass" not in old.identity()
    (tmp_path / "dataset.json").write_text(json.dumps({"recipe": old.identity()}))
    assert legacy_recipe(new, tmp_path).identity() == old.identity()
    (tmp_path / "dataset.json").write_text(json.dumps({"recipe": new.identity()}))
    assert legacy_recipe(new, tmp_path) == new
    assert "environment_pass" not in Recipe(kind="intrinsics", seed=4, width=96, height=48).identity()


def test_the_background_option_does_not_hide_a_shared_sample_recipe(tmp_path):
    """An evaluation PBR set with the training intrinsics' recipe shows their poses, whichever
    background the intrinsics' reflection layer has: the protocol check still refuses it."""
    from eval.protocol import ProtocolError, check_sets, describe

    def with_recipe(root, **recipe):
        info = json.loads((root / "dataset.json").read_text())
        (root / "dataset.json").write_text(json.dumps({**info, "seed": recipe["seed"], "recipe": recipe}))
        return root

    base = {"seed": 4, "cars": ["procedural:train"], "envmaps": ["procedural"], "camera": {"radius_max": 8}}
    train = with_recipe(tiny_intrinsics(tmp_path / "train", n=2), kind="intrinsics", samples=1,
                        background="environment", **base)
    evaluation = with_recipe(tiny_intrinsics(tmp_path / "eval", n=2, kind="pbr"), kind="pbr", samples=8, **base)
    with pytest.raises(ProtocolError, match="shows the poses of the training intrinsics"):
        check_sets(describe("train", train), None, describe("eval", evaluation), None)


@pytest.mark.parametrize("mode", ["1", "L", "I;16", "I", "P", "RGB", "RGBA", "CMYK", "RGB16"])
def test_photos_of_every_pillow_mode_load_at_their_own_scale(tmp_path, mode):
    """A mid-grey photo (white for 1-bit) loads as mid-grey whatever its mode; 16-bit grey PNGs
    used to load as nearly all white through convert("RGB")."""
    from PIL import Image

    from train.data import read_photo

    h, w = 6, 8
    if mode == "I;16":
        img, want = Image.fromarray(np.full((h, w), 32896, np.uint16)), 0.502
    elif mode == "I":
        img, want = Image.fromarray(np.full((h, w), 32896, np.int32)), 0.502
    elif mode == "RGB16":  # 16-bit RGB PNG: Pillow reads it as 8-bit RGB
        import zlib
        import struct

        raw = b"".join(b"\x00" + struct.pack(">HHH", 32896, 32896, 32896) * w for _ in range(h))
        chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))  # noqa: E731
        png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)) \
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
        (tmp_path / "x.png").write_bytes(png)
        img, want = None, 0.502
    elif mode == "1":
        img, want = Image.new("1", (w, h), 1), 1.0
    elif mode == "CMYK":
        img, want = Image.new("RGB", (w, h), (128, 128, 128)).convert("CMYK"), 0.502
    elif mode == "P":
        img, want = Image.new("RGB", (w, h), (128, 128, 128)).convert("P", palette=Image.ADAPTIVE), 0.502
    else:
        img, want = Image.new("RGB", (w, h), (128, 128, 128)).convert(mode), 0.502
    path = tmp_path / {"CMYK": "x.jpg", "I": "x.tif"}.get(mode, "x.png")  # PNG cannot store 32-bit integers
    if img is not None:
        img.save(path, quality=100) if mode == "CMYK" else img.save(path)
    got = read_photo(path)
    assert got.shape == (h, w, 3) and got.dtype == np.float32
    assert np.allclose(got, want, atol=0.02), (mode, float(got.mean()))


def test_webp_bmp_and_tiff_photos_are_read_and_heic_ones_named(tmp_path):
    from PIL import Image

    from blender_gen.dataset import DatasetError
    from train.data import RealImages, image_files, read_photo, unread_photos_note

    grey = Image.new("RGB", (8, 6), (128, 128, 128))
    for name in ("a.webp", "b.BMP", "c.tif", "sub/d.jpg"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        grey.save(tmp_path / name, **({"lossless": True} if name.endswith("webp") else {}))
    (tmp_path / "notes.txt").write_text("not a photo")
    assert unread_photos_note(tmp_path, "--real") is None
    (tmp_path / "e.HEIC").write_bytes(b"\0" * 64)
    (tmp_path / "f.dng").write_bytes(b"\0" * 64)
    files = image_files(tmp_path)
    assert [f.relative_to(tmp_path).as_posix() for f in files] == ["a.webp", "b.BMP", "c.tif", "sub/d.jpg"]
    for f in files:
        assert np.allclose(read_photo(f), 0.502, atol=0.02), f
    note = unread_photos_note(tmp_path, "--real")
    assert note == (f"note: --real {tmp_path}: 2 photo(s) in formats not read here (.dng, .heic; first e.HEIC) are "
                    "left out; convert them to JPG or PNG to use them")
    only_heic = tmp_path / "phone"
    only_heic.mkdir()
    (only_heic / "IMG_0001.heic").write_bytes(b"\0" * 64)
    with pytest.raises(DatasetError, match=r"no images found .*1 photo\(s\) in formats not read here \(\.heic"):
        RealImages(only_heic, 4, 8)


def test_an_oversized_photo_is_a_one_line_error(tmp_path, monkeypatch):
    from PIL import Image

    from blender_gen.dataset import DatasetError
    from train.data import read_photo

    Image.new("L", (64, 64)).save(tmp_path / "big.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # 64x64 is then over twice the limit: a bomb
    with pytest.raises(DatasetError, match="big.png: cannot read image"):
        read_photo(tmp_path / "big.png")
