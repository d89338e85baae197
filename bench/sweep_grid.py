"""Pictures of objective sweeps: R of several saved sweep runs on the probe's intrinsics.

Columns: the probe's albedo | reflection | R of each run given (`NAME=WEIGHTS.safetensors`,
trained by `objective_sweep.py grid --save-dir`) | the true image. One row per probe sample.

  python bench/sweep_grid.py --data .sweep/protocol_env.npz --samples 0 5 9 14 \\
      --run "default=runs/full_s0.safetensors,model.renderer=net" \\
      --run "+ chroma=runs/full_chroma10_s0.safetensors,model.renderer=net" \\
      --out grid.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the objective_sweep pack the runs trained on")
    ap.add_argument("--run", action="append", required=True,
                    help="LABEL=WEIGHTS.safetensors[,key=value,...] (the run's --set values that shape the model, "
                         "e.g. model.renderer=net for runs of the paper's R)")
    ap.add_argument("--config", default="cpu-small")
    ap.add_argument("--samples", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--scale", type=int, default=3, help="pixel repeat of the (small) probe images")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    import torch
    from safetensors.torch import load_file

    from blender_gen.dataset import save_png
    from bench.objective_sweep import unpack
    from train.config import load_config
    from train.loop import to_display
    from train.model import build_model

    torch.set_num_threads(1)
    z = np.load(a.data)
    maps, images = (torch.from_numpy(unpack(z[k][a.samples])) for k in ("PY", "PX"))
    h, w = maps.shape[2:]
    columns = [maps[:, 3:6], maps[:, 6:9]]
    for spec in a.run:
        label, _, rest = spec.partition("=")
        weights, *sets = rest.split(",")
        if not weights:
            sys.exit(f"--run {spec!r}: expected LABEL=WEIGHTS.safetensors[,key=value,...]")
        model = build_model(load_config(a.config, [f"data.height={h}", f"data.width={w}", *sets]))
        model.load_state_dict({k: v.float() for k, v in load_file(weights).items()})
        model.eval()
        with torch.no_grad():
            columns.append(model.render(maps))
        print(f"column {len(columns)}: {label}")
    columns.append(images)
    rows = [np.concatenate([to_display(c[i]) for c in columns], axis=1) for i in range(len(a.samples))]
    grid = np.concatenate(rows, axis=0).repeat(a.scale, 0).repeat(a.scale, 1)
    save_png(Path(a.out), grid)
    print(f"{a.out}: {len(a.samples)} rows x {len(columns)} columns (albedo, reflection, runs..., truth)")


if __name__ == "__main__":
    main()
