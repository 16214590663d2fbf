"""`offline-rl eval` and `offline-rl export-onnx` from the command line."""

import json

import numpy as np
import pytest
import torch

from offline_rl_core.commands.cli import main
from offline_rl_core.serving.policy import policy_sequential
from offline_rl_core.serving.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, save_checkpoint
from offline_rl_core.serving.policy import load_policy


def make_checkpoint(path, hidden=32, obs_dim=8, act_dim=2, task=None):
    torch.manual_seed(0)
    net = policy_sequential(obs_dim, hidden, act_dim)
    ckpt = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "algorithm": "bc",
            "obs_dim": obs_dim, "act_dim": act_dim, "hidden": hidden, "policy_state": net.state_dict()}
    if task is not None:
        ckpt["task"] = {**task.layout(), "spec": task.describe()}
    return save_checkpoint(path, ckpt)


def one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("offline-rl: error: "), err
    return err[0]


def test_eval_missing_checkpoint_exits_2_with_one_line(tmp_path, capsys):
    assert main(["eval", "--checkpoint", str(tmp_path / "nope.pt"), "--episodes", "2"]) == 2
    assert "nope.pt" in one_error_line(capsys)


def test_eval_broken_checkpoint_and_wrong_dims(tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    assert main(["eval", "--checkpoint", str(bad)]) == 2
    assert "bad.pt" in one_error_line(capsys)
    wrong = make_checkpoint(tmp_path / "wrong.pt", obs_dim=5)
    assert main(["eval", "--checkpoint", str(wrong)]) == 2
    assert "obs_dim" in one_error_line(capsys)


def test_eval_writes_json_and_sequential_agrees(tmp_path, capsys):
    ckpt = make_checkpoint(tmp_path / "p.pt")
    out_b, out_s = tmp_path / "b.json", tmp_path / "s.json"
    assert main(["eval", "--checkpoint", str(ckpt), "--episodes", "6", "--seed", "3", "--json", str(out_b)]) == 0
    text = capsys.readouterr().out
    assert "success" in text and "Wilson" in text and "mean final dist" in text
    assert main(["eval", "--checkpoint", str(ckpt), "--episodes", "6", "--seed", "3", "--json", str(out_s), "--sequential"]) == 0
    b, s = json.loads(out_b.read_text()), json.loads(out_s.read_text())
    for key in ("success_rate", "successes", "episodes", "wilson_ci_lo", "wilson_ci_hi", "seed", "checkpoint", "mean_final_dist"):
        assert key in b
    assert b["episodes"] == 6 and b["seed"] == 3 and b["successes"] == s["successes"]
    assert b["mean_final_dist"] == pytest.approx(s["mean_final_dist"], abs=2e-6)


def test_export_onnx_matches_numpy_policy(tmp_path, capsys):
    ort = pytest.importorskip("onnxruntime")
    ckpt = make_checkpoint(tmp_path / "p.pt", hidden=64)
    out = tmp_path / "policy.onnx"
    assert main(["export-onnx", "--checkpoint", str(ckpt), "--out", str(out)]) == 0
    assert "verified" in capsys.readouterr().out
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["obs"] and [o.name for o in session.get_outputs()] == ["action"]
    obs = np.random.default_rng(1).standard_normal((17, 8)).astype(np.float32)
    (got,) = session.run(["action"], {"obs": obs})
    np.testing.assert_allclose(got, load_policy(ckpt).act(obs), atol=1e-5)


def test_export_onnx_missing_checkpoint(tmp_path, capsys):
    assert main(["export-onnx", "--checkpoint", str(tmp_path / "x.pt"), "--out", str(tmp_path / "x.onnx")]) == 2
    one_error_line(capsys)


def test_eval_on_another_task_the_expert_and_a_checkpoint_of_its_size(tmp_path, capsys):
    out = tmp_path / "expert.json"
    assert main(["eval", "--task", "pusher7_reach", "--expert", "--episodes", "2", "--json", str(out)]) == 0
    assert "the task's scripted expert" in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["task"] == "pusher7_reach" and result["successes"] == 2 and result["wilson_ci_lo"] > 0
    assert result["mean_final_dist"] < 0.05 and result["algorithm"] == "expert"
    # a pusher-reach checkpoint is refused on it, naming both sizes; one of its own sizes rolls out
    assert main(["eval", "--task", "pusher7_reach", "--checkpoint", str(make_checkpoint(tmp_path / "p.pt")),
                 "--episodes", "1"]) == 2
    assert "obs_dim=8, act_dim=2); the task here is pusher7_reach (digest" in one_error_line(capsys)
    from offline_rl_core.task.spec import load_task

    ckpt = make_checkpoint(tmp_path / "p7.pt", obs_dim=20, act_dim=7, task=load_task("pusher7_reach"))
    assert main(["eval", "--task", "pusher7_reach", "--checkpoint", str(ckpt), "--episodes", "1", "--json",
                 str(out)]) == 0
    assert json.loads(out.read_text())["episodes"] == 1
