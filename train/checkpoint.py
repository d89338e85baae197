"""Checkpoints: weights and optimiser tensors in safetensors, the rest in JSON.

No pickle anywhere, so loading a checkpoint cannot execute code. Tensors and state are
written to temporary names and renamed; `latest.json` (written last) names the newest for
other tools. Resuming does not trust it alone: it takes the newest checkpoint whose files
both read back whole, and says which newer ones it skipped and why.
"""
from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from blender_gen.dataset import atomic_target, atomic_write_json


class CheckpointError(ValueError):
    """A checkpoint is missing or does not fit the model; the message says which key."""


class CheckpointUnreadable(CheckpointError):
    """A checkpoint's files are truncated or corrupt (an older one may still be usable)."""


def _optim_tensors(prefix: str, opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = opt.state_dict()
    tensors = {}
    for pid, state in sd["state"].items():
        for key, value in state.items():
            tensors[f"{prefix}.{pid}.{key}"] = value if torch.is_tensor(value) else torch.tensor(value)
    return tensors, {"param_groups": sd["param_groups"], "state_keys": {str(p): list(s) for p, s in sd["state"].items()}}


def _optim_load(prefix: str, opt: torch.optim.Optimizer, tensors: dict, meta: dict) -> None:
    state = {int(pid): {k: tensors[f"{prefix}.{pid}.{k}"] for k in keys} for pid, keys in meta["state_keys"].items()}
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def save_checkpoint(folder: Path, step: int, model: torch.nn.Module, optimizers: dict, schedulers: dict,
                    extra: dict | None = None, keep: int = 3, ema: torch.nn.Module | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    name = f"step_{step:08d}"
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    if ema is not None:  # the moving average of the weights, beside the raw ones
        tensors.update({f"ema.{k}": v.detach().cpu().contiguous() for k, v in ema.state_dict().items()})
    state: dict = {"step": step, "optimizers": {}, "schedulers": {}, "extra": extra or {}}
    for oname, opt in optimizers.items():
        t, meta = _optim_tensors(f"optim.{oname}", opt)
        tensors.update({k: v.detach().cpu().contiguous() for k, v in t.items()})
        state["optimizers"][oname] = meta
    for sname, sched in schedulers.items():
        state["schedulers"][sname] = sched.state_dict()
    tensors["rng.torch"] = torch.get_rng_state()
    if torch.cuda.is_available():
        tensors["rng.cuda"] = torch.cuda.get_rng_state()
    py_state = random.getstate()
    state["rng"] = {"python": [py_state[0], list(py_state[1]), py_state[2]],
                    "numpy": _np_state_to_json(np.random.get_state())}
    with atomic_target(folder / f"{name}.safetensors") as tmp:
        save_file(tensors, str(tmp))
    atomic_write_json(folder / f"{name}.json", state)
    atomic_write_json(folder / "latest.json", {"step": step, "name": name})
    ckpts = sorted(folder.glob("step_*.safetensors"))
    for old in ckpts[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
        old.with_suffix(".json").unlink(missing_ok=True)
    return folder / f"{name}.safetensors"


def _np_state_to_json(st) -> list:
    return [st[0], st[1].tolist(), int(st[2]), int(st[3]), float(st[4])]


def checkpoint_files(folder: Path) -> list[Path]:
    """Checkpoints in a folder, newest first."""
    return sorted(Path(folder).glob("step_*.safetensors"), reverse=True)


def latest_checkpoint(folder: Path) -> Path | None:
    """The newest checkpoint file (not yet checked to be readable); None if there is none."""
    files = checkpoint_files(folder)
    return files[0] if files else None


def newest_state(folder: Path) -> tuple[Path, int] | None:
    """The newest checkpoint whose JSON state reads, and its step (the one a resume falls back to
    when newer ones are unreadable); None if there is none."""
    for path in checkpoint_files(folder):
        try:
            return path, int(read_state(path)["step"])
        except CheckpointUnreadable:
            continue
    return None


def read_state(path: Path) -> dict:
    """The JSON state beside a checkpoint's tensors."""
    state_path = Path(path).with_suffix(".json")
    try:
        state = json.loads(state_path.read_text(encoding="utf-8"))
        int(state["step"])
        return state
    except FileNotFoundError:
        raise CheckpointUnreadable(f"{state_path}: missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise CheckpointUnreadable(f"{state_path}: truncated or corrupt ({exc})") from None


def _load_tensors(path: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types
        raise CheckpointUnreadable(f"{path}: not a readable safetensors checkpoint ({exc})") from exc


def load_newest(folder: Path, model: torch.nn.Module, optimizers: dict | None = None,
                schedulers: dict | None = None) -> tuple[dict | None, Path | None, list[str]]:
    """Load the newest readable checkpoint: (state, path, reasons newer ones were skipped).

    An unreadable checkpoint (truncated by a crash or a full disk) is skipped for the one
    before it; one that does not fit the model is an error, since older ones would not fit either.
    """
    skipped = []
    for path in checkpoint_files(folder):
        try:
            return load_checkpoint(path, model, optimizers or {}, schedulers or {}), path, skipped
        except CheckpointUnreadable as exc:
            skipped.append(str(exc))
    return None, None, skipped


def load_weights(path: Path, model: torch.nn.Module, tensors: dict[str, torch.Tensor] | None = None,
                 prefix: str = "model.") -> dict[str, torch.Tensor]:
    """Load model weights (the tensors named `prefix`...); a key or shape mismatch is an error that
    names the key."""
    if tensors is None:
        tensors = _load_tensors(path)
    own = model.state_dict()
    weights = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    missing = sorted(set(own) - set(weights))
    unexpected = sorted(set(weights) - set(own))
    if missing or unexpected:
        raise CheckpointError(f"{path}: checkpoint does not match the model config: missing {missing[:3]}, "
                              f"unexpected {unexpected[:3]}")
    for k, v in weights.items():
        if v.shape != own[k].shape:
            raise CheckpointError(f"{path}: {k} has shape {tuple(v.shape)}, the config's model needs {tuple(own[k].shape)}")
    model.load_state_dict(weights)
    return tensors


def load_ema(path: Path, ema: torch.nn.Module) -> bool:
    """Load the moving-average weights saved beside a checkpoint's ("ema." keys) into `ema`;
    False when the checkpoint has none (written without them), leaving `ema` as it is."""
    tensors = _load_tensors(path)
    if not any(k.startswith("ema.") for k in tensors):
        return False
    load_weights(path, ema, tensors, prefix="ema.")
    return True


def load_checkpoint(path: Path, model: torch.nn.Module, optimizers: dict, schedulers: dict) -> dict:
    state = read_state(path)  # both files are read whole before anything is loaded into the model
    tensors = load_weights(path, model, _load_tensors(path))
    for oname, opt in optimizers.items():
        _optim_load(f"optim.{oname}", opt, tensors, state["optimizers"][oname])
    for sname, sched in schedulers.items():
        sched.load_state_dict(state["schedulers"][sname])
    torch.set_rng_state(tensors["rng.torch"])
    if "rng.cuda" in tensors and torch.cuda.is_available():
        torch.cuda.set_rng_state(tensors["rng.cuda"])
    py = state["rng"]["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    npst = state["rng"]["numpy"]
    np.random.set_state((npst[0], np.array(npst[1], dtype=np.uint32), npst[2], npst[3], npst[4]))
    return state
