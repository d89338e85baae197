"""The one owner of a run folder's layout (in the manner of stylegan2-ada's run folders):

  training_options.json   the resolved config and data paths: the run is resumed from it
  stats.jsonl             every logged loss, one JSON row per logging step
  events.out.tfevents.*   the same scalars for TensorBoard
  grids/step_XXXXXXXX.png sample grids at fixed inputs
  checkpoints/            safetensors weights + JSON state (train.checkpoint)
  MODEL_CARD.md           what the newest weights are, were trained on and scored (train.model_card)

Training, inference and the report read a run only through this type.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from .config import Config, ConfigError, config_from_dict


class NotARunError(ConfigError):
    """The folder holds no run (no training_options.json)."""


@dataclass(frozen=True)
class RunFolder:
    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def options_path(self) -> Path:
        return self.root / "training_options.json"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def stats_path(self) -> Path:
        return self.root / "stats.jsonl"

    def grid_path(self, step: int) -> Path:
        return self.root / "grids" / f"step_{step:08d}.png"

    def exists(self) -> bool:
        return self.options_path.exists()

    def options(self) -> dict:
        """training_options.json, or a one-line error naming the file."""
        if not self.exists():
            raise NotARunError(f"{self.root}: not a run folder (no training_options.json)")
        try:
            opts = json.loads(self.options_path.read_text(encoding="utf-8"))
            opts["config"], opts["intrinsics"], opts["real"]  # noqa: B018  (all three must be there)
            return opts
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
            raise ConfigError(f"{self.options_path}: truncated or corrupt ({exc}); remove the run folder or restore "
                              "the file") from None

    def config(self) -> Config:
        return config_from_dict(self.options()["config"])

    def stats(self, up_to: int | None = None) -> list[dict]:
        """Rows of stats.jsonl (a torn line from a killed run is skipped), optionally up to a step."""
        if not self.stats_path.exists():
            return []
        rows = []
        for line in self.stats_path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(row, dict) and isinstance(row.get("step"), int) and (up_to is None or row["step"] <= up_to):
                rows.append(row)
        return rows
