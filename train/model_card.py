"""MODEL_CARD.md in every run folder: what the networks are, what they were trained on, how well
they did on the run's probe, and what they are not for (Mitchell et al., "Model Cards for Model
Reporting", 2019). Rewritten at every checkpoint from the run's own files, so it always describes
the newest weights."""
from __future__ import annotations

from pathlib import Path

from blender_gen.dataset import atomic_write_bytes

from .config import Config
from .run_folder import RunFolder

LIMITS = """\
- Trained on synthetic cars rendered by `iae-gen` (and the real images named above). Other objects,
  scenes or camera set-ups are outside what it has seen.
- H's maps are estimates: read the probe figures above against the constant predictor and the
  per-pixel prior, which use no image at all. Where H is not clearly better than the prior, its
  normals carry little information about the image.
- H runs at the training size shown above; `iae-train decompose` resizes photos to about that pixel
  count (aspect kept) and its maps back to the photo's size.
- Not for safety-relevant uses (driving, inspection, measurement)."""


def _count(params) -> str:
    n = sum(p.numel() for p in params)
    return f"{n / 1e6:.2f} M" if n >= 1e5 else f"{n:,}"


def _sets(opts: dict) -> list[str]:
    ids = opts.get("data_identity") or {}
    lines = []
    for key, what in (("intrinsics", "M_s, synthetic intrinsics"), ("real", "I_r, real images")):
        d = ids.get(key, {})
        res = "x".join(map(str, d.get("resolution") or [])) or "various"
        lines.append(f"| {what} | `{opts[key]}` | {d.get('kind', '?')} | {d.get('count', '?')} | {res} | "
                     f"`{str(d.get('manifest_sha256', '?'))[:16]}` |")
    return lines


def _probe(rows: list[dict]) -> list[str]:
    probed = [r for r in rows if "probe/normal_deg" in r]
    if not probed:
        return ["No probe set was given (`iae-train fit --probe PBR_SET`): no decomposition figures."]
    r = probed[-1]
    pre = "probe_ema/" if "probe_ema/normal_deg" in r else "probe/"
    weights = "moving-average" if pre == "probe_ema/" else "raw"
    f = lambda k: f"{r[k]:.1f}" if isinstance(r.get(k), (int, float)) else "-"  # noqa: E731
    return [f"Step {r['step']}, {weights} weights, on the probe set at the training size (lower is better):", "",
            "| | normals (deg) | albedo L1 | reflection L1 |", "|---|---|---|---|",
            f"| H | {f(pre + 'normal_deg')} | {f(pre + 'albedo_l1')} | {f(pre + 'reflection_l1')} |",
            f"| constant predictor (no image) | {f('probe/const_normal_deg')} | {f('probe/const_albedo_l1')} | "
            f"{f('probe/const_reflection_l1')} |",
            f"| per-pixel prior (no image) | {f('probe/prior_normal_deg')} | {f('probe/prior_albedo_l1')} | "
            f"{f('probe/prior_reflection_l1')} |"]


def _compute(c: dict | None) -> str:
    if not c:
        return "- Compute: not recorded (a run folder from before the record)."
    threads = f", {c['threads']} CPU thread(s)" if c.get("threads") else ""
    return (f"- Compute: torch {c['torch']} on {c['device']}{threads}, {c['processes']} process(es); the same seed "
            "and data give the same weights byte for byte only with the same compute.")


def write_model_card(run: RunFolder, cfg: Config, opts: dict, model, step: int) -> Path:
    """Write RUN/MODEL_CARD.md for the weights of `step`."""
    m = cfg.model
    nets = "".join(f"| {name} | {type(net).__name__} | {_count(net.parameters())} |\n"
                   for name, net in {**model.generator_modules(), **model.discriminator_modules()}.items())
    init = opts.get("init_from")
    lines = [
        f"# Model card: {run.root.name}", "",
        "Written by `iae-train fit` at every checkpoint; it describes the newest one.", "",
        "## Model", "",
        f"- Kind: `{m.kind}`, config `{cfg.name}`; R: `{m.renderer}`"
        + (f" (lighting `{m.shader_lighting}`, gain `{m.shader_gain}`)" if m.renderer == "shader" else "")
        + f"; inputs `{m.inputs}`.",
        f"- Trained for {step} of {cfg.optim.max_steps} steps at {cfg.data.width}x{cfg.data.height} (width x height), "
        f"batch {cfg.data.batch_size}, seed {cfg.run.seed}; moving average of the weights: "
        + (f"decay {cfg.run.ema_decay} (used by inference)" if cfg.run.ema_decay else "off") + ".",
        f"- Started from: `{init['run']}` step {init['step']}" if init else "- Started from: random initialisation.",
        _compute(opts.get("compute")),
        "", "| network | class | parameters |", "|---|---|---|", nets.rstrip("\n"), "",
        "## Data", "",
        "| role | path | kind | samples | resolution | content digest |", "|---|---|---|---|---|---|",
        *_sets(opts), "",
        "## How well (the run's probe)", "", *_probe(run.stats()), "",
        "## Use", "",
        "```sh",
        f"iae-train decompose --run {run.root} --images PHOTOS/ --out dec/    # H: normal, albedo, reflection",
        f"iae-train render --run {run.root} --intrinsics DATASET --out frames/   # R: images from intrinsics",
        f"iae-train export --run {run.root} --net H --out H.onnx                # for other runtimes",
        "```", "",
        "```python",
        "import train",
        f"run = train.load_run({str(run.root)!r})",
        "maps = run.decompose(photo)   # an (H, W, 3) array or PIL image -> normal, albedo, reflection at its size",
        "image = run.render(maps)      # (H, W, 3) sRGB in [0, 1]",
        "```", "",
        "## Limits", "", LIMITS, "",
        "Full configuration: `training_options.json`; curves: `stats.jsonl`, `probe.png`, TensorBoard.", ""]
    path = run.root / "MODEL_CARD.md"
    atomic_write_bytes(path, "\n".join(lines).encode())
    return path
