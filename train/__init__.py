"""The trainer. `train.load_run(RUN)` gives a trained run as an object (train/api.py); importing the
package itself loads nothing heavy, so `train.config` and the other modules import on their own."""
from __future__ import annotations

from typing import Any

__all__ = ["IntrinsicRun", "load_run"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'train' has no attribute {name!r}")
