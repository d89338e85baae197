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
  grid   variants x seeds as parallel processes (one thread each)
  picture  saved weights of several runs on the first probe images, labelled

  python bench/objective_sweep.py pack --setting s0 --intrinsics I --probe P --out s0.npz
  python bench/objective_sweep.py grid --data s0.npz --variants bench/variants.toml --seeds 0 1 --steps 8000
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


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
    np.savez_compressed(args.out, **packed, PM=enc_mask(probe.masks), setting=args.setting)
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
    out = open(args.out, "w") if args.out else sys.stdout

    def draw(x: torch.Tensor, idx: torch.Tensor, flips: torch.Tensor, stack: bool) -> torch.Tensor:
        b = x[idx.to(dev)].clone()
        for j in torch.nonzero(flips).flatten().tolist():
            b[j] = flip_stack(b[j]) if stack else b[j].flip(-1)
        return b

    t0 = time.time()
    for step in range(1, args.steps + 1):
        ir = torch.randint(0, len(t["XR"]), (args.batch,), generator=gen)
        im = ir if paired else torch.randint(0, len(t["MS"]), (args.batch,), generator=gen)
        f_m, f_i = torch.rand(args.batch, generator=gen) < 0.5, torch.rand(args.batch, generator=gen) < 0.5
        if paired:
            f_m = f_i
        m_s = draw(t["YR"] if paired else t["MS"], im, f_m, True)
        i_r = draw(t["XR"], ir, f_i, False)
        model.train()
        o, g_logs = generator_step(model, opts["G"], g_params, m_s, i_r)
        d_logs = discriminator_step(model, opts["D"], d_params, o) if "D" in opts else {}
        for s in scheds.values():
            s.step()
        if ema is not None:
            update_ema(ema, model, cfg.run.ema_decay, step)
        late = args.minutes is not None and time.time() - t0 > args.minutes * 60
        if step % args.every == 0 or step == args.steps or late:
            row = {"step": step, "t": round(time.time() - t0, 1), "variant": args.name, "seed": args.seed,
                   **{k: round(v, 4) for k, v in evaluate_probe(model, probe).items()},
                   **({k: round(v, 4) for k, v in evaluate_probe(ema, probe, prefix=EMA_PREFIX, references=False).items()}
                      if ema is not None else {}),
                   **{k: round(v, 4) for k, v in {**g_logs, **d_logs}.items()}}
            out.write(json.dumps(row) + "\n")
            out.flush()
        if late:
            break
    if args.save:
        from safetensors.torch import save_file

        dtype = torch.float16 if args.half else None  # half the bytes: enough to render pictures from
        save_file({k: (v.to(dtype) if dtype and v.is_floating_point() else v).contiguous().cpu()
                   for k, v in model.state_dict().items()}, args.save)


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
                   "--out", str(Path(args.out) / f"{name}_s{seed}.jsonl")]
            if args.save_dir:
                cmd += ["--save", str(Path(args.save_dir) / f"{name}_s{seed}.safetensors"), "--half"]
            cmd += [a for s in v["set"] for a in ("--set", s)]
            procs.append((name, seed, subprocess.Popen(cmd, env=env, stderr=open(Path(args.out) / f"{name}_s{seed}.err", "w"))))
    bad = 0
    for name, seed, p in procs:
        bad += p.wait() != 0
    print(f"{len(procs) - bad}/{len(procs)} runs finished in {args.out}")


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
    r.add_argument("--out", default=None)
    r.add_argument("--save", default=None)
    r.add_argument("--half", action="store_true", help="save the weights as float16")
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
    g.add_argument("--out", required=True)
    g.add_argument("--save-dir", default=None, help="save every run's final weights (float16) here")
    pc = sub.add_parser("picture")
    pc.add_argument("--data", required=True)
    pc.add_argument("--config", default="cpu-small")
    pc.add_argument("--samples", type=int, default=4)
    pc.add_argument("--scale", type=int, default=3)
    pc.add_argument("--out", required=True)
    pc.add_argument("runs", nargs="+", help="LABEL=WEIGHTS.safetensors[,key=value,...] (the variant's --set values)")
    a = ap.parse_args()
    {"pack": pack, "run": run, "grid": grid, "picture": picture}[a.cmd](a)


if __name__ == "__main__":
    main()
