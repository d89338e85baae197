"""How fast each training of a `reproduce` plan runs on this machine.

A few real optimisation steps (generator and discriminator) of each run's own model and config on
random batches of the run's size, in as many processes at once as the plan has lanes, each with
the plan's threads: trainings side by side slow each other down, and CPUs differ by more than 2x
(a 2-core EPYC without AVX-512 trains the `cpu` budget's full model 2.4x slower than the machine
its fixed rate was timed on), so a time estimate from a fixed rate can be hours off.
Data loading, probes and checkpoints are not in the figure: they add a few percent.

Run as a module by `eval.reproduce.Plan.measure_rates`: argv[1] is a JSON list of
[name, preset, [--set ...]]; prints one JSON object {name: steps per second}.
"""
from __future__ import annotations

import json
import sys
import time


def time_steps(preset: str, sets: list[str], steps: int = 2, warmup: int = 1, *, channels_last: bool = False,
               compile: bool = False, bf16: bool = False) -> tuple[float, float]:
    """(steps per second, warm-up seconds) of one training of `preset` with `sets`.

    The keyword variants (memory layout, torch.compile, bf16 autocast) are what
    bench/bench_cpu_speed.py compares; `reproduce` times the trainings as they will run.
    """
    from contextlib import nullcontext

    import torch

    from train.config import load_config
    from train.loop import build_optimisation, discriminator_step, generator_step
    from train.model import build_model

    cfg = load_config(preset, sets)
    torch.manual_seed(0)
    model = build_model(cfg)
    model.train()
    g, d, opts, _ = build_optimisation(cfg, model)
    b, h, w = cfg.data.batch_size, cfg.data.height, cfg.data.width
    m_s, i_r = torch.rand(b, 9, h, w) * 2 - 1, torch.rand(b, 3, h, w) * 2 - 1
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
        m_s, i_r = (x.contiguous(memory_format=torch.channels_last) for x in (m_s, i_r))
    if compile:
        model.forward_all = torch.compile(model.forward_all)
    autocast = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if bf16 else nullcontext

    def one() -> None:
        out, _ = generator_step(model, opts["G"], g, m_s, i_r, autocast)
        if d:
            discriminator_step(model, opts["D"], d, out, autocast)

    t = time.perf_counter()
    for _ in range(warmup):  # first-call allocations, oneDNN kernel selection, compilation
        one()
    warm = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(steps):
        one()
    return steps / (time.perf_counter() - t), warm


def step_rate(preset: str, sets: list[str], steps: int = 2) -> float:
    """Steps per second of one training of `preset` with `sets`, after one warm-up step."""
    return time_steps(preset, sets, steps)[0]


def main() -> None:
    jobs = json.loads(sys.argv[1])
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    print(json.dumps({name: step_rate(preset, sets, steps) for name, preset, sets in jobs}))


if __name__ == "__main__":
    main()
