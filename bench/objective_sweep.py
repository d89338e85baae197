"""A/B of training objectives on in-memory data, with the probe curves of `train.probe`.

The measurement behind the "Making it learn" tables (docs/experiment_log.md). It trains the project's own
model, losses, optimisers and steps (`train.model`, `train.loop.generator_step`,
`discriminator_step`) on tensors packed once from datasets, so many variants and seeds run
at once on one GPU (or, slowly, on the CPU) without EXR decoding.

  pack   datasets -> one .npz at training size, for a setting:
           protocol  "real" = PBR images with their backgrounds (the paper's protocol)
           s1        "real" = PBR images, background masked to black (every pixel expressible)
           s0        "real" = the analytic shading (train.sanity.shade) of other intrinsics
  run    one variant and seed -> a JSON-lines curve of probe figures
  grid   variants x seeds as parallel processes (one thread each); --runs-dir keeps a run folder
         per run (as `iae-train fit`'s), resumed by a rerun and read by `iae-eval report`
  slim   those run folders -> their generators' weights in tars small enough to leave a GPU lease
  unslim the tars' folders -> run folders `iae-eval report` reads
  picture  saved weights of several runs on the first probe images, labelled

  python bench/objective_sweep.py pack --setting s0 --intrinsics I --probe P --out s0.npz
  python bench/objective_sweep.py grid --data s0.npz --variants bench/variants.toml --seeds 0 1 --steps 8000
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from train.run_folder import RunFolder  # noqa: E402


def pack(args) -> None:
    import torch

    from train.probe import load_probe
    from train.sanity import load_pbr, load_stacks, masked_black, shade_network

    h, w = args.height, args.width
    ms = load_stacks(Path(args.intrinsics), h, w, args.n_intrinsics) if args.setting != "protocol_env" else None
    probe = load_probe(Path(args.probe), h, w, limit=args.n_probe)
    if args.setting == "s0":  # half the intrinsics are M_s, the other half shaded are the "real" images
        half = len(ms) // 2
        ms, yr = ms[:half], ms[half:]
        xr = shade_network(yr)
        probe.images = shade_network(probe.maps)
    elif args.setting == "protocol_env":  # M_s = PBR intrinsics whose background reflection is the scene behind the car
        xs, ms, mk = load_pbr(Path(args.intrinsics), h, w, args.n_intrinsics)
        ms[:, 6:9] = torch.where(mk >= 0.5, ms[:, 6:9], xs)
        xr, yr, mr = load_pbr(Path(args.real), h, w, args.n_real)
    else:
        xr, yr, mr = load_pbr(Path(args.real), h, w, args.n_real)
        if args.setting == "s1":
            xr = masked_black(xr, mr)
            probe.images = masked_black(probe.images, probe.masks)
    u8 = lambda t: np.round((t.numpy().clip(-1, 1) + 1) * 127.5).astype(np.uint8)  # noqa: E731
    enc_mask = lambda t: np.round(t.numpy().clip(0, 1) * 255).astype(np.uint8)  # noqa: E731
    arrays = {"MS": ms, "XR": xr, "YR": yr, "PX": probe.images, "PY": probe.maps}
    if args.dtype == "uint8":  # 4x smaller than float32: a 64x128 protocol set fits a device transfer
        packed = {k: u8(v) for k, v in arrays.items()}
    elif args.dtype == "jpeg":  # lossy, about 10x smaller again: a 256x512 set fits a device transfer
        packed = {}  # the probe stays lossless (8-bit), so its figures are scored against exact maps
        for k, v in arrays.items():
            if k in ("PX", "PY"):
                packed[k] = u8(v)
                continue
            buf, off = jpeg_encode(u8(v), args.quality)
            packed.update({f"{k}__jpg": buf, f"{k}__off": off, f"{k}__shape": np.array(v.shape)})
    else:
        packed = {k: v.numpy().astype(np.float16) for k, v in arrays.items()}
        enc_mask = lambda t: t.numpy().astype(np.float16)  # noqa: E731
    from train.data import set_identity

    # the sets a pack came from, so a run trained on it (`run --run-dir`) records them as `fit` does
    sources = {k: {"path": str(Path(v).resolve()), "identity": set_identity(Path(v))}
               for k, v in (("intrinsics", args.intrinsics), ("real", args.real), ("probe", args.probe)) if v}
    np.savez_compressed(args.out, **packed, PM=enc_mask(probe.masks), setting=args.setting,
                        sources=json.dumps(sources))
    print(f"{args.out}: M_s {tuple(ms.shape)}, real {tuple(xr.shape)}, probe {tuple(probe.images.shape)}")


def jpeg_encode(a: np.ndarray, quality: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, c, h, w) uint8 with c a multiple of 3 -> one buffer of 4:4:4 JPEGs (three channels
    each; no chroma subsampling, which would blur normals) and their end offsets."""
    import io

    from PIL import Image

    parts = []
    for sample in a:
        for c in range(0, a.shape[1], 3):
            b = io.BytesIO()
            Image.fromarray(np.ascontiguousarray(sample[c:c + 3].transpose(1, 2, 0))).save(
                b, "JPEG", quality=quality, subsampling=0)
            parts.append(np.frombuffer(b.getvalue(), dtype=np.uint8))
    return np.concatenate(parts), np.cumsum([len(p) for p in parts])


def jpeg_decode(buf: np.ndarray, off: np.ndarray, shape: np.ndarray) -> np.ndarray:
    import io

    from PIL import Image

    n, c, h, w = (int(x) for x in shape)
    out = np.empty((n, c, h, w), dtype=np.uint8)
    starts = np.concatenate([[0], off[:-1]])
    for j, (a, b) in enumerate(zip(starts, off)):
        i, k = divmod(j, c // 3)
        out[i, 3 * k:3 * k + 3] = np.asarray(Image.open(io.BytesIO(buf[a:b].tobytes()))).transpose(2, 0, 1)
    return out


def load_packed(z, key: str) -> np.ndarray:
    """One array of a pack, as stored (JPEG packs decoded to uint8)."""
    if f"{key}__jpg" in z.files:
        return jpeg_decode(z[f"{key}__jpg"], z[f"{key}__off"], z[f"{key}__shape"])
    return z[key]


def unpack(a: np.ndarray, mask: bool = False) -> np.ndarray:
    """A packed array as float32: uint8 packs hold network space [-1, 1] (masks [0, 1]) in 255
    steps, float16 packs the values themselves."""
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0 if mask else a.astype(np.float32) / 127.5 - 1.0
    return a.astype(np.float32)


def run(args) -> None:
    import torch

    torch.set_num_threads(args.threads)
    from train.config import load_config
    from train.data import flip_stack
    from train.loop import build_optimisation, discriminator_step, generator_step, make_ema, update_ema
    from train.model import build_model
    from train.probe import EMA_PREFIX, ProbeSet, evaluate_probe, pixel_prior, training_means

    dev = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    z = np.load(args.data)
    def dec(k: str) -> torch.Tensor:
        return torch.from_numpy(unpack(load_packed(z, k), mask=k == "PM")).to(dev)

    t = {k: dec(k) for k in ("MS", "XR", "YR", "PX", "PY", "PM")}
    h, w = t["MS"].shape[2:]
    sets = [f"data.height={h}", f"data.width={w}", f"data.batch_size={args.batch}", f"run.seed={args.seed}",
            f"optim.max_steps={args.steps}"]
    if args.decay > 0:  # MUNIT keeps its own step policy (as in `reproduce`): --decay 0
        sets.append(f"optim.decay_start={int(args.steps * args.decay)}")
    sets += args.set
    cfg = load_config(args.config, sets)
    torch.manual_seed(args.seed)
    model = build_model(cfg).to(dev)
    g_params, d_params, opts, scheds = build_optimisation(cfg, model)
    ema = make_ema(model, cfg.run.ema_decay)  # probed beside the raw weights, as `fit --probe` does
    ca, cr = training_means(t["MS"])
    probe = ProbeSet(t["PX"], t["PY"], t["PM"], ca, cr, pixel_prior(t["MS"]))
    paired = getattr(model, "paired", False)
    gen = torch.Generator(device="cpu").manual_seed(args.seed)
    start = 0
    run_dir = RunFolder(args.run_dir) if args.run_dir else None
    if run_dir is not None:
        start = open_run(run_dir, z, args, cfg, model, opts, scheds, ema, gen)
    out = open(args.out, "a" if start else "w") if args.out else sys.stdout

    def draw(x: torch.Tensor, idx: torch.Tensor, flips: torch.Tensor, stack: bool) -> torch.Tensor:
        b = x[idx.to(dev)].clone()
        for j in torch.nonzero(flips).flatten().tolist():
            b[j] = flip_stack(b[j]) if stack else b[j].flip(-1)
        return b

    t0 = time.time()
    step = start
    for step in range(start + 1, min(args.steps, args.stop_at or args.steps) + 1):
        ir = torch.randint(0, len(t["XR"]), (args.batch,), generator=gen)
        im = ir if paired else torch.randint(0, len(t["MS"]), (args.batch,), generator=gen)
        f_m, f_i = torch.rand(args.batch, generator=gen) < 0.5, torch.rand(args.batch, generator=gen) < 0.5
        if paired:
            f_m = f_i
        m_s = draw(t["YR"] if paired else t["MS"], im, f_m, True)
        i_r = draw(t["XR"], ir, f_i, False)
        model.train()
        o, g_logs = generator_step(model, opts["G"], g_params, m_s, i_r, step=step - 1)
        d_logs = discriminator_step(model, opts["D"], d_params, o) if "D" in opts else {}
        for s in scheds.values():
            s.step()
        if ema is not None:
            update_ema(ema, model, cfg.run.ema_decay, step)
        late = (args.minutes is not None and time.time() - t0 > args.minutes * 60) or step == args.stop_at
        if step % args.every == 0 or step == args.steps or late:
            row = {"step": step, "t": round(time.time() - t0, 1), "variant": args.name, "seed": args.seed,
                   **{k: round(v, 4) for k, v in evaluate_probe(model, probe).items()},
                   **({k: round(v, 4) for k, v in evaluate_probe(ema, probe, prefix=EMA_PREFIX, references=False).items()}
                      if ema is not None else {}),
                   **{k: round(v, 4) for k, v in {**g_logs, **d_logs}.items()}}
            line = json.dumps(row) + "\n"
            out.write(line)
            out.flush()
            if run_dir is not None:
                with open(run_dir.stats_path, "a") as fh:
                    fh.write(line)
        if late:
            break
    if run_dir is not None and step > start:
        from train.checkpoint import save_checkpoint

        save_checkpoint(run_dir.checkpoints, step, model, opts, scheds, ema=ema,
                        extra={"sweep_generator": gen.get_state().tolist()})
    if args.save:
        from safetensors.torch import save_file

        dtype = torch.float16 if args.half else None  # half the bytes: enough to render pictures from
        save_file({k: (v.to(dtype) if dtype and v.is_floating_point() else v).contiguous().cpu()
                   for k, v in model.state_dict().items()}, args.save)


def open_run(run: "RunFolder", z, args, cfg, model, opts, scheds, ema, gen) -> int:
    """A run folder for a sweep run, as `iae-train fit` writes one (config, the pack's source sets and
    their identities, checkpoints with the EMA), so `iae-eval report` reads it; its newest checkpoint
    resumes the run (weights, optimisers, schedules, EMA, the batch sampler's state). The step to go on from."""
    import torch

    from blender_gen.dataset import atomic_write_json
    from train.checkpoint import load_checkpoint, load_ema, newest_state
    from train.config import config_from_dict, differing_sections

    if "sources" not in z.files:
        sys.exit(f"--run-dir needs a pack that records its sets; repack {args.data} with this version")
    sources = json.loads(str(z["sources"]))
    if "real" not in sources:
        sys.exit(f"--run-dir: {args.data} has no real set (an s0 pack); a run folder needs one")
    if run.exists():
        diff = differing_sections(cfg, config_from_dict(run.options()["config"]))
        if diff:
            sys.exit(f"--run-dir {run.root}: a run with another config (section(s) {diff} differ)")
        newest = newest_state(run.checkpoints)
        if newest is None:
            return 0
        state = load_checkpoint(newest[0], model, opts, scheds)
        if ema is not None:
            load_ema(newest[0], ema)
        gen.set_state(torch.tensor(state["extra"]["sweep_generator"], dtype=torch.uint8))
        return int(state["step"])
    run.root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(run.options_path, {
        "config": cfg.to_dict(), "intrinsics": sources["intrinsics"]["path"], "real": sources["real"]["path"],
        "probe": sources.get("probe", {}).get("path"),
        "data_identity": {k: sources[k]["identity"] for k in ("intrinsics", "real")},
        "trained_by": {"tool": "bench/objective_sweep.py run", "pack": Path(args.data).name,
                       "setting": str(z["setting"]), "batch": args.batch}})
    return 0


def slim(args) -> None:
    """Run folders (`grid --runs-dir`) -> what a report needs of each, small enough to come back from
    a GPU lease: the generators' moving-average weights in float16, the options, stats and step,
    in tar files of at most 15 MiB (runs1.tar, runs2.tar, ...)."""
    import tarfile
    import tempfile

    from safetensors.torch import load_file, save_file

    from train.checkpoint import newest_state

    stage = Path(tempfile.mkdtemp())
    folders = []
    for run in sorted(p for p in Path(args.runs_dir).iterdir() if (p / "training_options.json").exists()):
        newest = newest_state(run / "checkpoints")
        if newest is None:
            continue
        tensors = load_file(str(newest[0]))
        prefix = "ema." if any(k.startswith("ema.") for k in tensors) else "model."
        keep = {k[len(prefix):]: v.half() if v.is_floating_point() else v for k, v in tensors.items()
                if k.startswith((prefix + "R.", prefix + "H."))}
        d = stage / run.name
        d.mkdir()
        save_file({k: v.contiguous() for k, v in keep.items()}, str(d / "generators.safetensors"))
        (d / "state.json").write_text(json.dumps({"step": newest[1], "weights": prefix.rstrip(".")}))
        for f in ("training_options.json", "stats.jsonl"):
            if (run / f).exists():
                shutil.copyfile(run / f, d / f)
        folders.append(d)
        print(f"{run.name}: step {newest[1]}, {sum(v.numel() for v in keep.values())} weights")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    k, size, tar = 0, 0, None
    for d in folders:
        n = sum(f.stat().st_size for f in d.iterdir())
        if tar is None or size + n > 15 * 2**20:
            if tar is not None:
                tar.close()
            k, size = k + 1, 0
            tar = tarfile.open(Path(args.out) / f"runs{k}.tar", "w")
        tar.add(d, arcname=d.name)
        size += n
    if tar is not None:
        tar.close()


def unslim(args) -> None:
    """`slim`'s folders -> run folders `iae-eval report` reads: a checkpoint whose generators (raw and
    moving average) are the kept weights. The discriminators were not kept (no figure uses them):
    they are the fresh initialisation, and the state says so; such a run cannot resume training."""
    import copy

    import torch
    from safetensors.torch import load_file

    from blender_gen.dataset import atomic_write_json
    from train.checkpoint import save_checkpoint
    from train.config import config_from_dict
    from train.model import build_model

    for d in sorted(p for p in Path(args.slim).iterdir() if (p / "generators.safetensors").exists()):
        run = RunFolder(Path(args.runs_dir) / d.name)
        if run.exists():
            sys.exit(f"--runs-dir: {run.root} exists; unslim writes new run folders only")
        opts = json.loads((d / "training_options.json").read_text())
        state = json.loads((d / "state.json").read_text())
        cfg = config_from_dict(opts["config"])
        torch.manual_seed(cfg.run.seed)
        model = build_model(cfg)
        kept = {k: v.float() for k, v in load_file(str(d / "generators.safetensors")).items()}
        model.load_state_dict({**model.state_dict(), **kept})
        run.root.mkdir(parents=True)
        atomic_write_json(run.options_path, {**opts, "slim": "generators only, float16 (objective_sweep.py slim)"})
        if (d / "stats.jsonl").exists():
            shutil.copyfile(d / "stats.jsonl", run.stats_path)
        save_checkpoint(run.checkpoints, state["step"], model, {}, {}, ema=copy.deepcopy(model),
                        extra={"slim": f"generators' {state['weights']} weights only (float16); discriminators freshly "
                                        "initialised; not resumable"})
        print(f"{run.root}: step {state['step']}")


def picture(args) -> None:
    """Saved weights of several runs (`grid --save-dir`) on the first probe images of a pack: one row
    per image (the image, then each layer's ground truth and every run's H), labelled, enlarged."""
    import torch
    from PIL import Image, ImageDraw
    from safetensors.torch import load_file

    from train.config import load_config
    from train.model import build_model

    z = np.load(args.data)
    px, py = (torch.from_numpy(unpack(load_packed(z, k))[: args.samples]) for k in ("PX", "PY"))
    h, w = px.shape[2:]
    preds = []
    for spec in args.runs:
        label, rest = spec.split("=", 1)
        path, *sets = rest.split(",")
        cfg = load_config(args.config, [f"data.height={h}", f"data.width={w}", *sets])
        model = build_model(cfg).eval()
        model.load_state_dict({k: v.float() for k, v in load_file(path).items()})
        with torch.no_grad():
            preds.append((label, model.decompose(px)))
    tile = lambda t: ((t.clamp(-1, 1) + 1) * 127.5 + 0.5).byte().permute(1, 2, 0).numpy()  # noqa: E731
    titles, rows = ["image"], []
    for c, layer in ((0, "normal"), (3, "albedo"), (6, "reflection")):
        titles += [f"{layer}: truth"] + [f"{layer}: {label}" for label, _ in preds]
    for i in range(len(px)):
        cells = [tile(px[i])]
        for c in (0, 3, 6):
            cells += [tile(py[i, c:c + 3])] + [tile(p[i, c:c + 3]) for _, p in preds]
        rows.append(np.concatenate(cells, axis=1))
    body = np.concatenate(rows, axis=0).repeat(args.scale, 0).repeat(args.scale, 1)
    tw = w * args.scale
    sheet = Image.new("RGB", (body.shape[1], body.shape[0] + 14), (255, 255, 255))
    sheet.paste(Image.fromarray(body), (0, 14))
    draw = ImageDraw.Draw(sheet)
    for k, t in enumerate(titles):
        draw.text((k * tw + 2, 1), t, fill=(0, 0, 0))
    sheet.save(args.out)
    print(args.out)


def load_variants(path: str | Path) -> dict[str, dict]:
    """A variants file's variants, each with its full `set` list. A file's top-level `base` list holds
    --set values every variant of it starts from (the defaults its runs were measured under, so a
    later change of the defaults does not change what they mean); a variant of another kind (oracle,
    baselines) opts out with `base = false`."""
    variants = tomllib.loads(Path(path).read_text())
    base = variants.pop("base", [])
    return {name: {**v, "set": [*(base if v.get("base", True) else []), *v.get("set", [])]}
            for name, v in variants.items()}


def grid(args) -> None:
    variants = load_variants(args.variants)
    names = args.only or list(variants)
    unknown = [n for n in names if n not in variants]
    if unknown:
        sys.exit(f"{args.variants}: no variant {', '.join(unknown)} (it has {', '.join(variants)})")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if args.save_dir:
        Path(args.save_dir).mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    procs = []
    for name in names:
        v = variants[name]
        for seed in args.seeds:
            cmd = [sys.executable, __file__, "run", "--data", args.data, "--name", name, "--seed", str(seed),
                   "--steps", str(args.steps), "--every", str(args.every), "--config", v.get("config", "cpu-small"),
                   "--device", args.device, "--batch", str(args.batch), "--decay", str(v.get("decay", args.decay)),
                   *(["--minutes", str(args.minutes)] if args.minutes else []),
                   *(["--stop-at", str(args.stop_at)] if args.stop_at else []),
                   "--out", str(Path(args.out) / f"{name}_s{seed}.jsonl")]
            if args.save_dir:
                cmd += ["--save", str(Path(args.save_dir) / f"{name}_s{seed}.safetensors"), "--half"]
            if args.runs_dir:
                cmd += ["--run-dir", str(Path(args.runs_dir) / f"{name}_s{seed}")]
            cmd += [a for s in v["set"] for a in ("--set", s)]
            procs.append((name, seed, subprocess.Popen(cmd, env=env, stderr=open(Path(args.out) / f"{name}_s{seed}.err", "w"))))
    from train.checkpoint import newest_state

    bad = 0
    for name, seed, p in procs:
        failed = p.wait() != 0
        bad += failed
        out = Path(args.out) / f"{name}_s{seed}.jsonl"
        if args.runs_dir:  # the step a rerun goes on from (a run complete before adds no row to OUT)
            newest = newest_state(Path(args.runs_dir) / f"{name}_s{seed}" / "checkpoints")
            step = newest[1] if newest else 0
        else:
            rows = out.read_text().splitlines() if out.exists() else []
            step = json.loads(rows[-1])["step"] if rows else 0
        # a run stopped by --minutes or --stop-at ends without error short of its schedule
        state = ("failed, see " + str(out.with_suffix(".err")) if failed else
                 "complete" if step >= args.steps else
                 "stopped" + ("; the same command with this --runs-dir goes on" if args.runs_dir else ""))
        print(f"{name}_s{seed}: step {step} of {args.steps}, {state}")
    print(f"{len(procs) - bad}/{len(procs)} runs ended without error in {args.out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("--setting", choices=("protocol", "protocol_env", "s1", "s0"), required=True)
    p.add_argument("--intrinsics", required=True)
    p.add_argument("--real", default=None)
    p.add_argument("--probe", required=True)
    p.add_argument("--height", type=int, default=32)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--n-intrinsics", type=int, default=None)
    p.add_argument("--n-real", type=int, default=None)
    p.add_argument("--n-probe", type=int, default=48)
    p.add_argument("--dtype", choices=("float16", "uint8", "jpeg"), default="float16")
    p.add_argument("--quality", type=int, default=90, help="JPEG quality with --dtype jpeg")
    p.add_argument("--out", required=True)
    r = sub.add_parser("run")
    r.add_argument("--data", required=True)
    r.add_argument("--name", default="run")
    r.add_argument("--config", default="cpu-small")
    r.add_argument("--set", action="append", default=[])
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--steps", type=int, default=3000)
    r.add_argument("--every", type=int, default=250)
    r.add_argument("--batch", type=int, default=4)
    r.add_argument("--decay", type=float, default=0.5, help="decay_start as a fraction of --steps")
    r.add_argument("--device", default="auto")
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--minutes", type=float, default=None, help="stop (with a last probe row) after this long")
    r.add_argument("--stop-at", type=int, default=None, help="stop (with a last probe row) at this step")
    r.add_argument("--out", default=None)
    r.add_argument("--save", default=None)
    r.add_argument("--half", action="store_true", help="save the weights as float16")
    r.add_argument("--run-dir", default=None, help="a run folder (as iae-train fit's) to checkpoint into at the "
                   "end or at --minutes, and to resume from; needs a protocol pack")
    g = sub.add_parser("grid")
    g.add_argument("--data", required=True)
    g.add_argument("--variants", required=True)
    g.add_argument("--only", nargs="*", default=None)
    g.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    g.add_argument("--steps", type=int, default=3000)
    g.add_argument("--every", type=int, default=250)
    g.add_argument("--batch", type=int, default=4)
    g.add_argument("--decay", type=float, default=0.5, help="decay_start as a fraction of --steps (a variant's `decay` wins)")
    g.add_argument("--device", default="auto")
    g.add_argument("--minutes", type=float, default=None)
    g.add_argument("--stop-at", type=int, default=None)
    g.add_argument("--out", required=True)
    g.add_argument("--save-dir", default=None, help="save every run's final weights (float16) here")
    g.add_argument("--runs-dir", default=None, help="a run folder per run here (VARIANT_sSEED), resumed by a rerun")
    sl = sub.add_parser("slim")
    sl.add_argument("--runs-dir", required=True)
    sl.add_argument("--out", required=True)
    us = sub.add_parser("unslim")
    us.add_argument("--slim", required=True, help="a folder holding slim's run folders (its tars unpacked)")
    us.add_argument("--runs-dir", required=True)
    pc = sub.add_parser("picture")
    pc.add_argument("--data", required=True)
    pc.add_argument("--config", default="cpu-small")
    pc.add_argument("--samples", type=int, default=4)
    pc.add_argument("--scale", type=int, default=3)
    pc.add_argument("--out", required=True)
    pc.add_argument("runs", nargs="+", help="LABEL=WEIGHTS.safetensors[,key=value,...] (the variant's --set values)")
    a = ap.parse_args()
    from train.config import ConfigError
    try:
        {"pack": pack, "run": run, "grid": grid, "slim": slim, "unslim": unslim, "picture": picture}[a.cmd](a)
    except ConfigError as exc:  # a bad --set or size: one line, not a traceback
        sys.exit(f"{a.cmd}: {exc}")


if __name__ == "__main__":
    main()
