"""One rule for every tool that writes a named output file (`--out`, `--json`, `--video`, ...).

An output must not replace an existing file unless the user passes `--force`, and never lands
inside a run folder (marked by `training_options.json`) or a dataset folder (`dataset.json`),
where it could take the place of a checkpoint, a sample or the set's own index. The check runs
before any work, so a refused command costs nothing.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

RUN_MARKER = "training_options.json"
DATASET_MARKER = "dataset.json"


class OutputRefused(ValueError):
    """An output path the tools will not write: it names the option and the reason."""


def protected_folder(path: Path) -> tuple[str, Path] | None:
    """('run' | 'dataset', folder) when `path` is or lies inside a run or dataset folder, else None."""
    path = Path(path).resolve()
    for folder in [path, *path.parents]:
        if (folder / RUN_MARKER).exists():
            return "run", folder
        if (folder / DATASET_MARKER).exists():
            return "dataset", folder
    return None


def refuse_output(out: Path, option: str, force: bool = False) -> Path:
    """`out` if a command may write it; otherwise an OutputRefused naming `option` and the reason."""
    out = Path(out)
    inside = protected_folder(out)
    if inside is not None:
        raise OutputRefused(f"{option} {out}: inside the {inside[0]} folder {inside[1]}; write it elsewhere")
    if out.exists() and not out.is_file():
        raise OutputRefused(f"{option} {out}: exists and is not a file")
    if out.exists() and not force:
        raise OutputRefused(f"{option} {out}: exists; choose a new file or pass --force to replace it")
    folder = out.resolve().parent
    while not folder.exists():
        folder = folder.parent
    try:  # before any work: not "No such file" after all of it. A probe file, since os.access
        fd, probe = tempfile.mkstemp(prefix=".iae_probe_", dir=folder)  # says yes to root anywhere
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputRefused(f"{option} {out}: cannot write in {folder}: {exc.strerror or exc}") from None
    return out


def refuse_output_folder(out: Path, option: str) -> Path:
    """An output folder (grids, previews) must not lie inside a run or dataset folder."""
    out = Path(out)
    inside = protected_folder(out)
    if inside is not None:
        raise OutputRefused(f"{option} {out}: inside the {inside[0]} folder {inside[1]}; write it elsewhere")
    return out
