"""`iae-eval reproduce`'s plan: the time estimate comes from speeds measured on this machine."""
from __future__ import annotations

import os
from dataclasses import replace
import subprocess
import sys
from pathlib import Path

import pytest

from eval.reproduce import BUDGETS, Plan, cars_summary

ROOT = Path(__file__).resolve().parents[1]


def _plan(runs, jobs=2):
    return Plan(BUDGETS["smoke"], Path("unused"), 0, jobs, 1, 0, list(runs))


def test_measured_speeds_cover_every_run_of_the_plan():
    plan = _plan(["full", "no_dec", "oracle"])
    rates = plan.measure_rates(steps=1)
    assert sorted(rates) == ["full", "no_dec", "oracle"]
    assert all(r > 0 for r in rates.values())


def test_the_estimate_packs_runs_into_lanes_as_they_free_up(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    plan = _plan(["full", "no_dec", "oracle"])
    steps = plan.budget.steps
    instant = {n: 1e9 for n in plan.runs}  # training takes no time: data, report and overhead only
    per_min = {"full": steps / 60, "no_dec": steps / 120, "oracle": steps / 60}  # 1, 2 and 1 minutes
    # lane 1: full (1 min) then oracle (1 min); lane 2: no_dec (2 min) -> 2 minutes in all
    assert plan.estimate_minutes(per_min) - plan.estimate_minutes(instant) == pytest.approx(2.0, abs=1e-6)
    one_lane = _plan(["full", "no_dec", "oracle"], jobs=1)
    assert one_lane.estimate_minutes(per_min) - one_lane.estimate_minutes(instant) == pytest.approx(4.0, abs=1e-6)


def test_dry_run_prints_the_measured_speeds():
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs",
                           "no_dec,cyclegan", "--dry-run", "--out", "unused"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    speed = next(line for line in proc.stdout.splitlines() if line.strip().startswith("speed"))
    assert "no_dec" in speed and "cyclegan" in speed and "steps/min" in speed
    assert "expected  about" in proc.stdout


def _checkpoint(out: Path, name: str, step: int) -> None:
    folder = out / "runs" / name / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"step_{step:08d}.safetensors").write_bytes(b"")
    (folder / f"step_{step:08d}.json").write_text(f'{{"step": {step}}}')


def test_a_resumed_plan_counts_only_the_steps_left(tmp_path, monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    plan = Plan(BUDGETS["smoke"], tmp_path, 0, 1, 1, 0, ["full", "no_dec"])
    steps = plan.budget.steps
    _checkpoint(tmp_path, "full", steps // 4)
    _checkpoint(tmp_path, "no_dec", steps)
    (tmp_path / "runs" / "no_dec" / "checkpoints" / f"step_{steps + 1:08d}.safetensors").write_bytes(b"")  # torn
    assert (plan.steps_done("full"), plan.steps_left("full")) == (steps // 4, steps - steps // 4)
    assert (plan.steps_done("no_dec"), plan.steps_left("no_dec")) == (steps, 0)
    assert plan.steps_done("oracle") == 0
    rates = {"full": steps / 60, "no_dec": steps / 60}  # a whole run: one minute each
    fresh = Plan(BUDGETS["smoke"], tmp_path / "fresh", 0, 1, 1, 0, ["full", "no_dec"])
    # fresh: 2 minutes of training; resumed: 3/4 of full's minute, none of no_dec's
    assert fresh.estimate_minutes(rates) - plan.estimate_minutes(rates) == pytest.approx(1.25, abs=1e-6)
    assert sorted(plan.measure_rates(steps=1)) == ["full"]  # a finished run is not timed


def test_parts_sharing_a_data_folder_use_it(tmp_path):
    shared = tmp_path / "shared"
    plan = Plan(BUDGETS["smoke"], tmp_path / "part2", 0, 1, 1, 0, ["full"], data=shared)
    outs = [args[args.index("--out") + 1] for _, args in plan.dataset_commands()]
    assert outs == [str(shared / d) for d in ("intrinsics", "real", "eval", "fid_intrinsics")]
    fit = plan.fit_command("full")
    assert fit[fit.index("--intrinsics") + 1] == str(shared / "intrinsics")
    assert fit[fit.index("--run-dir") + 1] == str(tmp_path / "part2" / "runs" / "full")
    (shared / "eval").mkdir(parents=True)
    (shared / "eval" / "dataset.json").write_text('{"complete": false, "count": 3, "count_requested": 6}')
    assert plan._data_left("eval") == 0.5


def test_a_waiting_lock_holder_blocks_until_the_first_lets_go(tmp_path):
    import threading
    import time

    from blender_gen.dataset import DatasetError, locked_folder

    inside, released, told = threading.Event(), [], []

    def first():
        with locked_folder(tmp_path, "--data"):
            inside.set()
            time.sleep(0.5)
            released.append(time.monotonic())

    t = threading.Thread(target=first)
    t.start()
    inside.wait(5)
    with pytest.raises(DatasetError, match="is being written by pid"):  # without `wait`: fails at once
        with locked_folder(tmp_path, "--data"):
            pass
    with locked_folder(tmp_path, "--data", wait=told.append):  # with it: told who, then waits its turn
        entered = time.monotonic()
    t.join()
    assert released and entered >= released[0]
    assert len(told) == 1 and told[0].startswith(f"pid {os.getpid()} on ")


def test_the_sanity_settings_refuse_a_shared_data_folder(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "sanity-smoke", "--data",
                           str(tmp_path), "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "--data" in proc.stderr and "OUT/data" in proc.stderr


def test_a_part_with_other_counts_refuses_the_shared_data_folder(tmp_path):
    shared = tmp_path / "shared"
    plan = Plan(BUDGETS["smoke"], tmp_path / "part1", 0, 1, 1, 0, ["full"], data=shared)
    plan.check_shared_data()  # nothing there yet
    (shared / "intrinsics").mkdir(parents=True)
    (shared / "intrinsics" / "dataset.json").write_text(f'{{"count": 32, "count_requested": {BUDGETS["smoke"].n_intrinsics}}}')
    plan.check_shared_data()  # made for this plan's counts
    bigger = Plan(replace(BUDGETS["smoke"], n_intrinsics=64), tmp_path / "part2", 0, 1, 1, 0, ["no_A"], data=shared)
    with pytest.raises(ValueError, match=r"intrinsics was made with 32 samples and this plan asks for 64"):
        bigger.check_shared_data()
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--data", str(shared),
                           "--out", str(tmp_path / "part2"), "--intrinsics", "64", "--runs", "no_A", "--dry-run"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1 and "was made with 32 samples" in proc.stderr and "Traceback" not in proc.stderr


def test_resolution_is_width_by_height_everywhere_and_the_swapped_order_is_refused():
    from click.testing import CliRunner

    from eval.cli import main

    swapped = CliRunner().invoke(main, ["reproduce", "--budget", "smoke", "--resolution", "32x64", "--dry-run"])
    assert swapped.exit_code == 2 and "taller than wide; did you mean 64x32?" in swapped.output
    ok = CliRunner().invoke(main, ["reproduce", "--budget", "smoke", "--resolution", "64x32", "--runs", "full",
                                   "--out", "unused_plan", "--dry-run"])
    assert ok.exit_code == 0, ok.output
    assert "steps each at 64x32 (width x height)" in ok.output
    for cli in ("blender_gen.cli", "train.cli", "eval.cli"):
        v = subprocess.run([sys.executable, "-m", cli, "--version"], capture_output=True, text=True, cwd=ROOT)
        assert v.returncode == 0 and "version 0.1.0" in v.stdout


def test_own_cars_and_photos_make_the_plan(tmp_path):
    from .train_helpers import tiny_photos

    photos = tiny_photos(tmp_path / "my_photos", n=12)
    plan = Plan(BUDGETS["smoke"], tmp_path / "out", 0, 1, 1, 0, ["full"], cars=("sedan_a", "suv_b"),
                photos=photos, gallery=3)
    commands = dict(plan.dataset_commands())
    assert len(commands) == 3 and not any("stand-in" in what for what in commands)  # the photos are the real set
    from blender_gen.cli import main as gen_main

    for what, args in commands.items():
        cars = [args[k + 1] for k, a in enumerate(args) if a == "--cars"]
        assert cars == ["sedan_a", "suv_b"], what  # one --cars per token, as iae-gen repeats it
        ctx = gen_main.commands[args[0]].make_context(args[0], list(args[1:]))  # iae-gen parses the command
        assert tuple(ctx.params["cars"]) == ("sedan_a", "suv_b"), what
    framed = replace(plan, coverage=(0.4, 0.65))  # the photos' framing reaches every generated set
    for what, args in framed.dataset_commands():
        ctx = gen_main.commands[args[0]].make_context(args[0], list(args[1:]))
        assert (ctx.params["min_coverage"], ctx.params["max_coverage"]) == (0.4, 0.65), what
    assert plan.split_photos() == (9, 3)
    assert len(list((plan.data_dir / "photos_gallery").iterdir())) == 3
    assert plan.split_photos() == (9, 3)  # idempotent
    fit = plan.fit_command("full")
    assert fit[fit.index("--real") + 1] == str(plan.data_dir / "photos_train")
    oracle = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full,oracle",
                             "--cars", "sedan_a", "--real", str(photos), "--out", str(tmp_path / "o"), "--dry-run"],
                            cwd=ROOT, capture_output=True, text=True)
    assert oracle.returncode == 2 and "photos (--real) have none" in oracle.stderr  # refused before any work
    assert not (tmp_path / "o").exists()
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full",
                           "--cars", "sedan_a", "--real", str(photos), "--out", str(tmp_path / "o"), "--dry-run"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert f"your photos in {photos.resolve()} (3 held out)" in proc.stdout and "cars: sedan_a" in proc.stdout
    bad = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--real",
                          str(tmp_path / "nope"), "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "neither a count nor a folder of photos" in bad.stderr


def test_the_plan_names_the_cars_and_a_file_given_several_times():
    assert cars_summary(("sedan_a",)) == "sedan_a"
    five = ("procedural:train",) + ("/m/sedan.glb",) * 5 + ("/m/van.glb",)
    assert cars_summary(five) == "procedural:train + 2 model files (6 shares of the draw)"
    assert cars_summary(("/m/a.glb", "/m/b.glb+/m/w.glb")) == "2 model files"


def test_an_objective_override_reaches_the_autoencoders_runs_only():
    """`reproduce --set` measures another objective on the same data: the full model and its
    ablations get it; the oracle and the baselines (other config sections) do not."""
    from eval.reproduce import RUNS

    names = [n for n, _, _ in RUNS]
    sets = ("model.renderer=shader", "loss.w_shading_ren=3")
    for budget in ("smoke", "gpu"):
        plan = Plan(BUDGETS[budget], Path("unused"), 0, 1, 1, 0, names, overrides=sets)
        for name in names:
            cmd = plan.fit_command(name)
            has = all(s in cmd for s in sets)
            assert has == (name not in ("oracle", "cyclegan", "munit")), (budget, name)
        plan.check_configs()  # every run's config resolves (the gpu budget's oracle from the paper preset too)


def test_an_override_of_h_s_architecture_also_reaches_the_oracle():
    """The oracle is the ceiling of the same networks: an A/B of H's architecture (here its
    upsampling) trains the oracle's H the same way, in the comparison and the sanity settings,
    while objective values and R's settings stay with the autoencoder's runs."""
    from eval.sanity import SANITY_BUDGETS, SanityPlan
    from train.config import load_config

    sets = ("model.h_upsample=resize", "loss.w_shading_ren=3", "model.r_ngf=12")
    plan = Plan(BUDGETS["smoke"], Path("unused"), 0, 1, 1, 0, ["full", "oracle", "cyclegan"], overrides=sets)
    oracle = load_config(*plan._config_args("oracle"))
    assert oracle.model.kind == "oracle" and oracle.model.h_upsample == "resize"
    assert oracle.loss.w_shading_ren == load_config(BUDGETS["smoke"].preset).loss.w_shading_ren
    assert "model.r_ngf=12" not in plan.fit_command("oracle")
    assert "model.h_upsample=resize" not in plan.fit_command("cyclegan")
    sanity = SanityPlan(SANITY_BUDGETS["sanity-smoke"], "sanity-smoke", Path("unused"), 0, 1, 1, overrides=sets)
    paths = {"intrinsics": Path("i"), "real": Path("r"), "probe": Path("p")}
    oracle_cmd = sanity.fit_command("S0", "oracle", 0, True, paths)
    assert "model.h_upsample=resize" in oracle_cmd and "loss.w_shading_ren=3" not in oracle_cmd
    assert "loss.w_shading_ren=3" in sanity.fit_command("S0", "full_seed0", 0, False, paths)


def test_every_budget_trains_the_default_objective_unless_the_paper_s_is_asked_for():
    """The `gpu` and `paper` budgets take the paper preset's widths; without the objective's values
    they trained the paper's R and Eq. 7 instead of the measured default. `--objective paper` puts the
    paper's objective on any budget's networks; the oracle and baselines are untouched either way."""
    from eval.reproduce import RUNS
    from train.config import Config, load_config

    names = [n for n, _, _ in RUNS]
    default, paper = Config(), load_config("paper")
    for budget in ("cpu", "gpu", "paper"):
        for objective, want in (("default", default), ("paper", paper)):
            plan = Plan(BUDGETS[budget], Path("unused"), 0, 1, 1, 0, names, objective=objective)
            for name in ("full", "no_dec"):
                cfg = load_config(*plan._config_args(name))
                assert cfg.model.renderer == want.model.renderer, (budget, objective, name)
                assert cfg.loss.w_ren == want.loss.w_ren and cfg.loss.w_dec == want.loss.w_dec
                assert cfg.loss.adv_m_on == want.loss.adv_m_on and cfg.loss.w_chroma == want.loss.w_chroma
                # widths stay the budget's preset's
                assert cfg.model.h_ngf == load_config(BUDGETS[budget].preset).model.h_ngf
            assert load_config(*plan._config_args("no_dec")).loss.decomposition_cycle is False
            for name in ("oracle", "cyclegan", "munit"):
                assert not any(s.startswith(("loss.", "model.renderer")) for s in plan.fit_command(name)), name
            plan.check_configs()
    # the cpu budget's default runs get no extra values: their commands are those of runs trained before
    assert Plan(BUDGETS["cpu"], Path("u"), 0, 1, 1, 0, ["full"]).objective_sets() == []


def test_a_started_run_with_another_config_is_refused_before_the_plan_promises_anything(tmp_path, monkeypatch):
    """A rerun with other --set options over finished runs once said "nothing left to train" and
    then had its trainings refused; the plan now refuses first, naming the run folder."""
    import json

    from train.config import ConfigError, load_config

    plan = Plan(BUDGETS["smoke"], tmp_path, 0, 1, 1, 0, ["full"], overrides=("loss.w_dec=3",))
    run = tmp_path / "runs" / "full"
    (run / "checkpoints").mkdir(parents=True)
    config, sets = plan._config_args("full")
    same = load_config(config, sets).to_dict()
    (run / "training_options.json").write_text(json.dumps({"config": same, "intrinsics": "i", "real": "r"}))
    monkeypatch.setattr("train.checkpoint.newest_state", lambda folder: (folder / "step_000010.safetensors", 10))
    plan.check_configs()  # the same options: resumes
    other = load_config(config, [s for s in sets if s != "loss.w_dec=3"]).to_dict()
    (run / "training_options.json").write_text(json.dumps({"config": other, "intrinsics": "i", "real": "r"}))
    with pytest.raises(ConfigError, match=r"runs/full: run 'full' was trained with another config.*'loss'"):
        plan.check_configs()
    monkeypatch.setattr("train.checkpoint.newest_state", lambda folder: None)
    plan.check_configs()  # not started: fit starts it afresh with the new options
