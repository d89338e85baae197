"""A trained R or H as a file other tools run: ONNX (ONNX Runtime, TensorRT, ...) or TorchScript.

Both formats carry the same metadata (ONNX `metadata_props`, TorchScript extra file
`iae_export.json`): which run, step and checkpoint the weights came from, and what the
tensors mean (channel order, encoding, value range), so a user needs nothing from this
project to feed the network correctly. `check_export` refuses a file of another run or a
corrupt one with a one-line error and compares it with PyTorch's output.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from blender_gen.dataset import atomic_target, sha256_file
from blender_gen.outputs import OutputRefused, refuse_output as _refuse_output
from .inference import load_run_checkpoint

FORMATS = ("onnx", "torchscript")
NETS = ("R", "H")
EXTRA_FILE = "iae_export.json"
SCHEMA = "iae-export/1"

INTRINSICS_DOC = ("9 channels in this order: normal XYZ (camera space, unit length, in [-1, 1]); "
                  "albedo RGB; reflection RGB. Albedo and reflection are sRGB-encoded (IEC 61966-2-1) "
                  "linear values clipped to [0, 1], then mapped to [-1, 1] by x * 2 - 1.")
IMAGE_DOC = "3 channels RGB, sRGB-encoded in [0, 1], mapped to [-1, 1] by x * 2 - 1."


MAX_PIXELS = 4096 * 4096


def refuse_output(out: Path, option: str, force: bool) -> Path:
    """The writers' rule (blender_gen.outputs), raised as an ExportError."""
    try:
        return _refuse_output(out, option, force)
    except OutputRefused as exc:
        raise ExportError(str(exc)) from None


class ExportError(ValueError):
    """An export or exported file that cannot be used; the message names the file or option."""


class _Render(nn.Module):
    """R on the full 9-channel stack: the channels an ablation does not use are ignored inside."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, intrinsics: torch.Tensor) -> torch.Tensor:
        return self.model.render(intrinsics)


class _Decompose(nn.Module):
    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.model.decompose(image)


@dataclass(frozen=True)
class Exported:
    path: Path
    metadata: dict


def parse_resolution(text: str) -> tuple[int, int]:
    """'WIDTHxHEIGHT' -> (width, height)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ExportError(f"--resolution {text!r}: expected WIDTHxHEIGHT, e.g. 512x256") from None
    if w < 8 or h < 8:
        raise ExportError(f"--resolution {text!r}: width and height must be at least 8")
    if w * h > MAX_PIXELS:  # the trace runs one example: 100000x100000 would allocate ~360 GB first
        raise ExportError(f"--resolution {text!r}: at most {MAX_PIXELS:,} pixels (e.g. 4096x4096); the batch "
                          "size stays dynamic")
    return w, h


def _divisor(cfg) -> int:
    """Height and width must be multiples of this for the network's down- and up-sampling."""
    m = cfg.model
    if m.kind == "cyclegan":
        return 2 ** cfg.cyclegan.n_down
    if m.kind == "munit":
        return 2 ** cfg.munit.n_down
    return 2 ** max(m.r_downsample + m.r_local_enhancers, m.h_downsample)


def _metadata(run_dir: Path, cfg, step: int, checkpoint: Path, net: str, fmt: str, width: int, height: int,
              half: bool) -> dict:
    if net == "R":  # the Intrinsic Autoencoder's ablations read a subset; the baselines all nine channels
        used = "".join(c for c in "NAF" if c in cfg.model.inputs) if cfg.model.kind in ("iae", "oracle") else "NAF"
        io = {"input": "intrinsics", "input_doc": INTRINSICS_DOC, "output": "image", "output_doc": IMAGE_DOC,
              "input_channels_used": used}
    else:
        io = {"input": "image", "input_doc": IMAGE_DOC, "output": "intrinsics", "output_doc": INTRINSICS_DOC}
    return {"schema": SCHEMA, "net": net, "format": fmt, "model_kind": cfg.model.kind, "config_name": cfg.name,
            "run": str(Path(run_dir).resolve()), "step": step,
            "checkpoint": checkpoint.name, "checkpoint_sha256": sha256_file(checkpoint),
            "width": width, "height": height, "batch": "dynamic", "layout": "NCHW",
            "dtype": "float16" if half else "float32", **io}


def export_network(run_dir: Path, net: str, fmt: str, out: Path, resolution: tuple[int, int] | None = None,
                   half: bool = False, opset: int = 17, force: bool = False) -> Exported:
    """Write R or H of a run's newest checkpoint to `out` (atomically) and return its metadata.
    An existing `out` is refused unless `force`; a path inside a run folder always."""
    refuse_output(out, "--out", force)
    if net not in NETS:
        raise ExportError(f"--net {net!r}: expected one of {', '.join(NETS)}")
    if fmt not in FORMATS:
        raise ExportError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    cfg, model, step, checkpoint = load_run_checkpoint(run_dir)
    if net == "R" and cfg.model.kind == "munit":
        raise ExportError(f"--run {run_dir}: MUNIT's renderer draws a random style code per image; "
                          "export supports R of the Intrinsic Autoencoder, the oracle and CycleGAN")
    width, height = resolution or (cfg.data.width, cfg.data.height)
    d = _divisor(cfg)
    if width % d or height % d:
        raise ExportError(f"--resolution {width}x{height}: width and height must be multiples of {d} "
                          f"for this run's networks")
    wrapper = (_Render(model) if net == "R" else _Decompose(model)).eval()
    dtype = torch.float16 if half else torch.float32
    wrapper = wrapper.to(dtype)
    example = torch.zeros(1, 9 if net == "R" else 3, height, width, dtype=dtype)
    meta = _metadata(run_dir, cfg, step, checkpoint, net, fmt, width, height, half)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_target(out) as tmp, torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer and legacy-exporter notices: the checks below are what count
        if fmt == "torchscript":
            traced = torch.jit.trace(wrapper, example, check_trace=False)
            torch.jit.save(traced, str(tmp), _extra_files={EXTRA_FILE: json.dumps(meta)})
        else:
            _export_onnx(wrapper, example, tmp, meta, opset)
    return Exported(out, meta)


def _export_onnx(wrapper: nn.Module, example: torch.Tensor, path: Path, meta: dict, opset: int) -> None:
    import onnx

    # The TorchScript-based exporter: no onnxscript dependency, and instance norm, reflection
    # padding and transposed convolutions all map to plain ONNX operators.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation and instance-norm notices of the legacy exporter
        torch.onnx.export(wrapper, (example,), str(path), dynamo=False, input_names=[meta["input"]],
                          output_names=[meta["output"]], opset_version=opset,
                          dynamic_axes={meta["input"]: {0: "batch"}, meta["output"]: {0: "batch"}})
    proto = onnx.load(str(path))
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, json.dumps(value)
    proto.producer_name = "intrinsic-autoencoders"
    onnx.save(proto, str(path))


# ------------------------------------------------------------------------------ loading
def read_metadata(path: Path) -> dict:
    """The metadata of an exported file; a one-line error when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"{path}: no such file")
    fmt = "onnx" if path.suffix.lower() == ".onnx" else "torchscript"
    try:
        if fmt == "onnx":
            import onnx

            proto = onnx.load(str(path), load_external_data=False)
            meta = {p.key: json.loads(p.value) for p in proto.metadata_props}
        else:
            extra = {EXTRA_FILE: ""}
            torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
            meta = json.loads(extra[EXTRA_FILE] or "{}")
    except Exception as exc:  # onnx/protobuf and TorchScript raise many kinds on a damaged file
        raise ExportError(f"{path}: not a readable {fmt} file ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else 'damaged'})") from None
    if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
        raise ExportError(f"{path}: a {fmt} file without this project's export metadata (expected schema {SCHEMA})")
    _check_metadata(path, meta)
    return meta


def _check_metadata(path: Path, meta: dict) -> None:
    """Types and ranges of the fields the checks use, before any of them runs (an edited height of
    10^6 would first allocate gigabytes)."""
    def bad(field: str, expected: str) -> ExportError:
        return ExportError(f"{path}: export metadata field {field!r} is {str(meta.get(field))[:40]!r}; expected "
                           f"{expected} (edited or damaged: export it again)")

    if meta.get("net") not in NETS:
        raise bad("net", " or ".join(NETS))
    if meta.get("format") not in FORMATS:
        raise bad("format", " or ".join(FORMATS))
    if meta.get("dtype") not in ("float32", "float16"):
        raise bad("dtype", "float32 or float16")
    for f in ("height", "width", "step"):
        if not isinstance(meta.get(f), int) or isinstance(meta.get(f), bool) or meta[f] < (0 if f == "step" else 8):
            raise bad(f, "an integer" + ("" if f == "step" else " of at least 8"))
    if meta["height"] * meta["width"] > MAX_PIXELS:
        raise bad("height", f"a size of at most {MAX_PIXELS:,} pixels")
    if not isinstance(meta.get("run"), str):
        raise bad("run", "the run folder's path")
    sha = meta.get("checkpoint_sha256")
    if not (isinstance(sha, str) and len(sha) == 64 and all(c in "0123456789abcdef" for c in sha)):
        raise bad("checkpoint_sha256", "64 hex digits")


class ExportedNet:
    """An exported file run by ONNX Runtime (CPU) or TorchScript, on NCHW numpy arrays."""

    def __init__(self, path: Path, threads: int | None = None):
        self.path = Path(path)
        self.meta = read_metadata(self.path)
        if self.meta["format"] == "onnx":
            import onnxruntime as ort

            opts = ort.SessionOptions()
            if threads:
                opts.intra_op_num_threads = threads
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
            self.module = None
        else:
            self.session = None
            self.module = torch.jit.load(str(self.path), map_location="cpu").eval()

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float16 if self.meta["dtype"] == "float16" else np.float32)
        if self.session is not None:
            return self.session.run(None, {self.meta["input"]: x})[0]
        with torch.no_grad():
            return self.module(torch.from_numpy(x)).numpy()


def check_export(path: Path, run_dir: Path, batch: int = 2, seed: int = 0) -> dict:
    """Refuse a file of another run or checkpoint; else compare it with PyTorch on random inputs.

    Returns {"max_abs_diff", "mean_abs_diff", "tolerance", "ok"}; inputs are valid network-space
    tensors (unit normals, colours in [-1, 1]) so the comparison covers the range R and H see.
    """
    meta = read_metadata(path)
    run_dir = Path(run_dir)
    cfg, model, step, checkpoint = load_run_checkpoint(run_dir)
    sha = sha256_file(checkpoint)
    if meta["run"] != str(run_dir.resolve()) or meta["checkpoint_sha256"] != sha:
        raise ExportError(f"{path}: exported from {meta['run']} (step {meta['step']}), not from the newest "
                          f"checkpoint of --run {run_dir} (step {step}); export it again")
    x = example_input(meta["net"], batch, meta["height"], meta["width"], seed)
    with torch.no_grad():
        xt = torch.from_numpy(x)
        ref = (model.render(xt) if meta["net"] == "R" else model.decompose(xt)).numpy()
    try:
        got = ExportedNet(path)(x).astype(np.float32)
    except Exception as exc:  # ONNX Runtime / TorchScript: a file that is not the network its metadata names
        raise ExportError(f"{path}: does not run as its metadata says ({meta['net']}, {meta['width']}x"
                          f"{meta['height']}): {type(exc).__name__}; export it again") from None
    if got.shape != ref.shape:
        raise ExportError(f"{path}: gives {got.shape}, its metadata's {meta['net']} gives {ref.shape}; export it again")
    diff = np.abs(got - ref)
    tol = 2e-2 if meta["dtype"] == "float16" else 1e-4
    return {"max_abs_diff": float(diff.max()), "mean_abs_diff": float(diff.mean()), "tolerance": tol,
            "ok": bool(diff.max() <= tol)}


def example_input(net: str, batch: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """A valid network-space input: unit normals and colours for R, an image for H."""
    rng = np.random.default_rng(seed)
    if net == "H":
        return rng.uniform(-1, 1, (batch, 3, height, width)).astype(np.float32)
    n = rng.normal(size=(batch, 3, height, width))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    colours = rng.uniform(-1, 1, (batch, 6, height, width))
    return np.concatenate([n, colours], axis=1).astype(np.float32)
