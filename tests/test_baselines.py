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
from .train_helpers import TINY, tiny_intrinsics, tiny_overrides, tiny_photos


def cfg_for(kind: str, *extra: str):
    return load_config(kind, tiny_overrides() + list(extra))


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
    base = [sys.executable, "-m", "train.cli", "fit", "--intrinsics", str(intr), "--real", str(photos), "--quiet"]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    subprocess.run(base + ["--config", kind, "--run-dir", str(whole), "--max-steps", "4", *TINY], cwd=ROOT, check=True)
    subprocess.run(base + ["--config", kind, "--run-dir", str(parts), "--max-steps", "3", *TINY], cwd=ROOT, check=True)
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
