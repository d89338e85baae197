"""Every writer follows one rule: no output over an existing file without --force, and none
inside a run or dataset folder (blender_gen.outputs)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from blender_gen.outputs import OutputRefused, refuse_output
from eval.cli import main as eval_main
from train.cli import main as train_main


def _run_folder(tmp_path: Path) -> Path:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "training_options.json").write_text("{}")
    ckpt = run / "checkpoints" / "step_00000010.safetensors"
    ckpt.write_bytes(b"weights")
    return run


def _dataset_folder(tmp_path: Path) -> Path:
    data = tmp_path / "data"
    data.mkdir()
    (data / "dataset.json").write_text('{"kind": "pbr"}')
    return data


def test_refuse_output_names_the_option_and_the_reason(tmp_path):
    run, data = _run_folder(tmp_path), _dataset_folder(tmp_path)
    with pytest.raises(OutputRefused, match=r"--json .*inside the run folder"):
        refuse_output(run / "checkpoints" / "step_00000010.safetensors", "--json", force=True)
    with pytest.raises(OutputRefused, match=r"--out .*inside the dataset folder"):
        refuse_output(data / "dataset.json", "--out", force=True)
    mine = tmp_path / "mine.json"
    mine.write_text("{}")
    with pytest.raises(OutputRefused, match="exists; choose a new file or pass --force"):
        refuse_output(mine, "--out")
    assert refuse_output(mine, "--out", force=True) == mine
    assert refuse_output(tmp_path / "new" / "deeper.json", "--out") == tmp_path / "new" / "deeper.json"


def test_diagnose_json_cannot_destroy_a_checkpoint(tmp_path):
    run = _run_folder(tmp_path)
    ckpt = run / "checkpoints" / "step_00000010.safetensors"
    res = CliRunner().invoke(train_main, ["diagnose", "--run", str(run), "--probe", str(tmp_path),
                                          "--json", str(ckpt), "--force"])
    assert res.exit_code != 0 and "inside the run folder" in res.output, res.output
    assert ckpt.read_bytes() == b"weights"


@pytest.mark.parametrize("command", [
    lambda out, data: ["flicker", "--run", str(data), "--path", str(data), "--out", str(out)],
    lambda out, data: ["seeds", str(data), "--out", str(out)],
    lambda out, data: ["merge", str(data), "--out", str(out)],
    lambda out, data: ["fid", "--real", str(data), "--fake", str(data), "--out", str(out)],
    lambda out, data: ["ab-summary", str(data), "--study", str(data / "study.json"), "--out", str(out)],
    lambda out, data: ["decomposition", "--predictions", str(data), "--data", str(data), "--out", str(out)],
])
def test_eval_writers_refuse_an_existing_file_and_a_dataset_folder(tmp_path, command):
    data = _dataset_folder(tmp_path)
    index = data / "dataset.json"
    res = CliRunner().invoke(eval_main, command(index, data) + ["--force"])
    assert res.exit_code != 0 and "inside the dataset folder" in res.output, res.output
    assert json.loads(index.read_text()) == {"kind": "pbr"}
    results = tmp_path / "report" / "results.json"
    results.parent.mkdir()
    results.write_text('{"runs": []}')
    res = CliRunner().invoke(eval_main, command(results, data))
    assert res.exit_code != 0 and "exists; choose a new file or pass --force" in res.output, res.output
    assert results.read_text() == '{"runs": []}'


def test_merge_grids_are_not_drawn_into_a_run_folder(tmp_path):
    run = _run_folder(tmp_path)
    res = CliRunner().invoke(eval_main, ["merge", str(run), "--out", str(tmp_path / "joined.json"),
                                         "--grids", str(run / "grids")])
    assert res.exit_code != 0 and "--grids" in res.output and "inside the run folder" in res.output, res.output
    assert not (tmp_path / "joined.json").exists()
