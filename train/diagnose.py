"""`iae-train diagnose`: the gradient of every loss term on each network, against the supervised direction.

For whoever tunes the objective. On one batch (M_s from the run's intrinsics, I_r from a probe
set with ground truth) it takes each generator term of Eq. 7 (weighted as in training) and
measures its gradient on H_N, H_A, H_F and R: the norm, and the cosine with the direction a
supervised learner would take on the same batch (H: L1 to I_r's true maps on object pixels;
R: L1 of R(true maps of I_r) to I_r on object pixels). A term that is large and points away
from the supervised direction is the one to look at (docs/experiment_log.md "Making it learn").
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F

NETS = ("H_N", "H_A", "H_F", "R")


def _net_params(model) -> dict[str, list[torch.nn.Parameter]]:
    return {"H_N": list(model.H.h_n.parameters()), "H_A": list(model.H.h_a.parameters()),
            "H_F": list(model.H.h_f.parameters()), "R": list(model.R.parameters())}


def _flat_grad(loss: torch.Tensor, params: list[torch.nn.Parameter]) -> torch.Tensor:
    if not loss.requires_grad:  # e.g. the shader R lit by fitted lightings: no parameter reaches it
        return torch.cat([torch.zeros_like(p).flatten() for p in params])
    grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return torch.cat([(g if g is not None else torch.zeros_like(p)).flatten() for g, p in zip(grads, params)])


def supervised_losses(model, out: dict, maps: torch.Tensor, masks: torch.Tensor) -> dict[str, torch.Tensor]:
    """The supervised direction per network: object-pixel L1 of H(I_r) to the true maps, per map,
    and of R(true maps) to I_r."""
    on = (masks >= 0.5).float()
    denom = 3 * on.sum().clamp_min(1)
    fake = out["fake_M"]
    sup = {net: ((fake[:, sl] - maps[:, sl]).abs() * on).sum() / denom
           for net, sl in (("H_N", slice(0, 3)), ("H_A", slice(3, 6)), ("H_F", slice(6, 9)))}
    sup["R"] = ((model.render(maps) - out["I_r"]).abs() * on).sum() / denom
    return sup


def diagnose(model, m_s: torch.Tensor, i_r: torch.Tensor, maps: torch.Tensor, masks: torch.Tensor) -> dict:
    """{term: {"weight", "loss", net: {"grad_norm", "cosine"}}} for every generator term and the total, of an
    Intrinsic Autoencoder (`diagnose_run` refuses runs of other kinds by name)."""
    model.train()  # the gradient training sees (instance norm behaves the same either way)
    out = model.forward_all(m_s, i_r, everything=True)
    terms = model.loss_terms(out)
    params = _net_params(model)
    sup = {net: _flat_grad(loss, params[net]) for net, loss in supervised_losses(model, out, maps, masks).items()}
    total = sum(w * v for w, v in terms.values())
    rows = {}
    for name, (weight, value) in [*terms.items(), ("G/total", (1.0, total))]:
        row = {"weight": weight, "loss": float(value.detach())}
        for net in NETS:
            g = _flat_grad(weight * value, params[net])
            norm = float(g.norm())
            cos = float(F.cosine_similarity(g, sup[net], dim=0)) if norm > 0 and sup[net].norm() > 0 else 0.0
            row[net] = {"grad_norm": norm, "cosine": cos}
        rows[name] = row
    model.zero_grad(set_to_none=True)
    return rows


def diagnose_run(run_dir: Path, probe: Path, checkpoint: Path | None = None, batch: int = 8, seed: int = 0,
                 device: str = "cpu") -> dict:
    """Load a run (newest checkpoint or `checkpoint`) and diagnose it on `batch` probe images."""
    from .data import IntrinsicsData
    from .inference import load_run_checkpoint, load_run_options
    from .probe import load_probe
    from .run_folder import RunFolder

    opts, cfg = load_run_options(run_dir)
    if cfg.model.kind != "iae":  # before any weights or data are read
        raise ValueError(f"--run {run_dir}: a {cfg.model.kind} run; diagnose measures the Intrinsic Autoencoder's "
                         "loss terms (model.kind = 'iae')")
    own = RunFolder(run_dir).checkpoints.resolve()
    if checkpoint is not None and Path(checkpoint).resolve().parent != own:  # its figures would carry this run's name
        raise ValueError(f"--checkpoint {checkpoint}: not a checkpoint of --run {run_dir} (those are in {own})")
    cfg, model, step, path = load_run_checkpoint(run_dir, device, checkpoint, raw=True)
    model.step = step  # the terms weighed as at that step (loss.adv_m_from)
    gen = torch.Generator().manual_seed(seed)
    intr = IntrinsicsData(Path(opts["intrinsics"]), cfg.data.height, cfg.data.width)
    p = load_probe(Path(probe), cfg.data.height, cfg.data.width, limit=None)
    pick_m = torch.randint(0, len(intr), (batch,), generator=gen)
    pick_i = torch.randperm(len(p.images), generator=gen)[:batch]
    m_s = torch.stack([intr[(int(i), False)] for i in pick_m]).to(device)
    rows = diagnose(model, m_s, p.images[pick_i].to(device), p.maps[pick_i].to(device), p.masks[pick_i].to(device))
    return {"run": str(Path(run_dir).resolve()), "step": step, "checkpoint": str(path), "probe": str(Path(probe).resolve()),
            "batch": int(len(pick_i)), "seed": seed, "terms": rows}


def format_diagnosis(result: dict) -> str:
    head = f"{'term':<22}{'weight':>7}{'loss':>9}" + "".join(f"{net + ' |g|':>11}{'cos':>7}" for net in NETS)
    lines = [f"{result['run']} step {result['step']}, {result['batch']} probe images of {result['probe']}",
             "gradient norm of each weighted term on each network, cosine with the supervised direction", head]
    for name, row in result["terms"].items():
        cells = "".join(f"{row[net]['grad_norm']:>11.3g}{row[net]['cosine']:>7.2f}" for net in NETS)
        lines.append(f"{name[2:]:<22}{row['weight']:>7.3g}{row['loss']:>9.4f}{cells}")
    return "\n".join(lines)
