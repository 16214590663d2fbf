"""Curves where researchers read them: the event files TensorBoard's own reader opens (and
W&B's offline run file), with the tags and last values of metrics.json / summary.json, the
run's settings as hyper-parameters, and metrics.json byte for byte what it was without them."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from offline_rl_core.commands.cli import main
from offline_rl_core.data.bag import write_transitions
from offline_rl_core.data.collect import collect_transitions

TINY = ["--steps", "40", "--log-every", "20", "--batch-size", "16", "--hidden", "16", "--eval-episodes", "3"]


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "tiny.db3"
    write_transitions(path, collect_transitions(4, 0.5, 0))
    return path


def events(run_dir: Path):
    """TensorBoard's own reader on a run directory."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    return acc


def last(acc, tag: str):
    return acc.Scalars(tag)[-1]


def hparams_of(acc) -> dict:
    """The hyper-parameters a run logged, as TensorBoard's HParams tab reads them."""
    from tensorboard.plugins.hparams import plugin_data_pb2

    content = acc.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    info = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info
    return {k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind")) for k, v in info.hparams.items()}


def event_files(run_dir: Path) -> list[Path]:
    return sorted(run_dir.glob("events.out.tfevents.*"))


def test_train_logs_losses_eval_and_settings_that_tensorboard_reads_back(bag, tmp_path, capsys):
    tb, plain = tmp_path / "tb", tmp_path / "plain"
    assert main(["train", "--bag", str(bag), "--algo", "awac", *TINY, "--out", str(tb)]) == 0
    assert main(["train", "--bag", str(bag), "--algo", "awac", *TINY, "--out", str(plain), "--logger", "none"]) == 0
    assert (tb / "metrics.json").read_bytes() == (plain / "metrics.json").read_bytes()  # the logger adds files only
    assert len(event_files(tb)) == 1 and not event_files(plain)

    metrics = json.loads((tb / "metrics.json").read_text())
    acc = events(tb)
    tags = set(acc.Tags()["scalars"])
    assert {"train/critic_loss", "train/policy_loss", "train/steps_per_s"} <= tags
    for name, value in metrics["final_losses"].items():  # the loop's last report is metrics.json's final loss
        point = last(acc, f"train/{name}")
        assert point.step == metrics["steps"] == 40
        assert point.value == pytest.approx(value, rel=1e-5, abs=1e-6)
    assert [p.step for p in acc.Scalars("train/policy_loss")] == [20, 40]
    for key in ("success_rate", "wilson_ci_lo", "wilson_ci_hi", "mean_final_dist", "mean_return"):
        point = last(acc, f"eval/{key}")
        assert point.step == 40 and point.value == pytest.approx(metrics["eval"][key], rel=1e-5, abs=1e-6)
    assert last(acc, "train/steps_per_s").value > 0
    hp = hparams_of(acc)
    assert hp["algorithm"] == "awac" and hp["seed"] == 0 and hp["config/batch_size"] == 16
    assert hp["config/correction_ratio"] == "None"  # unset settings are named, not dropped

    # a new run in the same directory replaces the curves of the last one
    assert main(["train", "--bag", str(bag), "--algo", "bc", *TINY, "--out", str(tb)]) == 0
    assert len(event_files(tb)) == 1
    assert "train/critic_loss" not in events(tb).Tags()["scalars"]


def test_eval_logs_beside_its_json_at_the_checkpoints_step_and_keeps_the_training_curves(bag, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--bag", str(bag), "--algo", "bc", *TINY, "--out", str(run)]) == 0
    assert main(["eval", "--checkpoint", str(run), "--episodes", "2", "--json", str(run / "eval.json")]) == 0
    result = json.loads((run / "eval.json").read_text())
    acc = events(run)
    assert "train/policy_loss" in acc.Tags()["scalars"]  # the training run's event file is still there
    points = acc.Scalars("eval/success_rate")
    assert points[-1].step == 40 and points[-1].value == pytest.approx(result["success_rate"], abs=1e-6)
    assert last(acc, "eval/wilson_ci_hi").value == pytest.approx(result["wilson_ci_hi"], rel=1e-5)


def test_eval_of_the_scripted_expert_logs_at_step_zero(tmp_path, capsys):
    out = tmp_path / "expert" / "eval.json"
    assert main(["eval", "--expert", "--episodes", "2", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    acc = events(out.parent)
    (point,) = acc.Scalars("eval/success_rate")
    assert point.step == 0 and point.value == pytest.approx(result["success_rate"])
    assert hparams_of(acc)["algorithm"] == "expert"


def test_a_logger_that_cannot_be_made_is_one_line_before_training(bag, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "wandb", None)  # as where wandb is not installed
    out = tmp_path / "run"
    assert main(["train", "--bag", str(bag), "--algo", "bc", *TINY, "--out", str(out), "--logger", "wandb"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("offline-rl: error: --logger wandb: the wandb package is not installed; "
                   "pip install 'offline_rl_core[wandb]' (or: pip install wandb)")
    assert not out.exists()  # refused before anything was written


def wandb_records(run_file: Path):
    """The records of a W&B run file (``run-*.wandb``): its LevelDB-style log of protobuf records."""
    from wandb.proto import wandb_internal_pb2

    data, block, pos, pending = run_file.read_bytes(), 32768, 7, b""  # 7: the ":W&B" header
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        length, kind = int.from_bytes(data[pos + 4:pos + 6], "little"), data[pos + 6]
        payload, pos = data[pos + 7:pos + 7 + length], pos + 7 + length
        if kind in (1, 2):  # FULL, FIRST
            pending = payload
        elif kind in (3, 4):  # MIDDLE, LAST
            pending += payload
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            yield record


def test_wandb_offline_gets_the_same_curves(bag, tmp_path, capsys, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    out = tmp_path / "run"
    assert main(["train", "--bag", str(bag), "--algo", "bc", *TINY, "--out", str(out), "--logger", "wandb"]) == 0
    assert not event_files(out)
    (run_file,) = out.glob("wandb/offline-run-*/run-*.wandb")
    history, summary, config = {}, {}, {}
    for record in wandb_records(run_file):
        kind = record.WhichOneof("record_type")
        if kind == "history":
            step = record.history.step.num
            for item in record.history.item:
                key = item.key or "/".join(item.nested_key)
                history.setdefault(key, []).append((step, json.loads(item.value_json)))
        elif kind == "summary":
            summary.update({item.key or "/".join(item.nested_key): json.loads(item.value_json)
                            for item in record.summary.update})
        elif kind == "config":
            config.update({item.key: json.loads(item.value_json) for item in record.config.update})
    metrics = json.loads((out / "metrics.json").read_text())
    assert history["train/policy_loss"][-1] == (40, pytest.approx(metrics["final_losses"]["policy_loss"], rel=1e-6))
    assert summary["eval/success_rate"] == pytest.approx(metrics["eval"]["success_rate"])
    assert config["algorithm"] == "bc" and config["config/batch_size"] == 16


def test_experiment_logs_each_arm_of_each_seed_in_its_directory(tmp_path):
    from offline_rl_core.runs.experiment import ExperimentConfig, run_experiment

    cfg = ExperimentConfig.smoke_settings(seeds=[0, 1], episodes=4, steps=30, batch_size=16, hidden=16, n_seeds=2,
                                          eval_episodes=2, workers=1)
    run_experiment(cfg, tmp_path, log=lambda line: None)
    final = {}
    for s in (0, 1):
        d = tmp_path / f"seed_{s}"
        metrics = json.loads((d / "metrics.json").read_text())
        acc = events(d)
        tags = set(acc.Tags()["scalars"])
        assert {"bc/train/policy_loss", "offline/train/critic_loss", "offline/train/policy_loss"} <= tags
        for key in ("bc_success_rate", "offline_success_rate", "diff_ci_lo", "diff_ci_hi", "offline_mean_final_dist"):
            assert last(acc, f"eval/{key}").value == pytest.approx(metrics[key], rel=1e-5, abs=1e-6)
        assert 0.0 <= last(acc, "eval/bc_wilson_ci_lo").value <= last(acc, "eval/bc_wilson_ci_hi").value <= 1.0
        assert hparams_of(acc)["seed"] == s
        final[s] = last(acc, "offline/train/critic_loss").value
    # both seeds trained as one ensemble, each logged its own run's losses, not their mean
    assert final[0] != final[1]


def test_the_online_stage_logs_its_curve_and_each_weights_version(tmp_path):
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.learners.online import OnlineSettings
    from offline_rl_core.runs.loggers import open_logger
    from offline_rl_core.runs.online_loop import OnlineRunConfig, run_online
    from offline_rl_core.task.corrector import CorrectorParams

    offline = collect_transitions(6, 0.5, 0)
    cfg = OnlineRunConfig(env_steps=200, seed=0, eval_every=100, eval_episodes=3,
                          corrector=CorrectorParams(patience=4, grace_steps=5, hold_steps=10),
                          settings=OnlineSettings(publish_every=25),
                          train=TrainConfig(algo="sac", batch_size=16, hidden=16))
    with open_logger("tensorboard", tmp_path, name="online") as curves:
        summary = run_online(offline, None, cfg, log=lambda s: None, logger=curves)
    acc = events(tmp_path)
    point = summary["curve"][-1]
    assert [p.step for p in acc.Scalars("eval/success_rate")] == [0, 100, 200]
    assert last(acc, "eval/success_rate").value == pytest.approx(point["success"])
    assert last(acc, "eval/wilson_ci_lo").value == pytest.approx(point["ci"][0], abs=1e-6)
    assert last(acc, "online/intervention_rate").value == pytest.approx(point["intervention_rate"], abs=1e-6)
    versions = acc.Scalars("online/weights_version")
    assert [v.step for v in versions] == list(range(25, 201, 25)) and versions[-1].value == 8
    assert last(acc, "train/critic_loss").value == pytest.approx(point["critic_loss"], rel=1e-4)
    assert {"online/weights_age_steps", "online/env_steps_per_s", "train/steps_per_s"} <= set(acc.Tags()["scalars"])


def test_the_learner_service_logs_what_progress_jsonl_holds(tmp_path):
    from offline_rl_core.data.bag.cdr import encode_transition_rows
    from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.learners.online import OnlineSettings
    from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig

    write_transitions(tmp_path / "offline.db3", collect_transitions(4, 0.5, 0))
    live = collect_transitions(1, 0.0, 1).select(np.arange(30))
    live.source[:] = SOURCE_POLICY
    live.source[::5] = SOURCE_HUMAN
    service = LearnerService(LearnerServiceConfig(
        bags=[str(tmp_path / "offline.db3")], out=str(tmp_path / "learner"), settings=OnlineSettings(publish_every=10),
        train=TrainConfig(algo="sac", batch_size=16, hidden=16)), log=lambda s: None)
    for payload in encode_transition_rows(live.to_rows()):
        service.receive(payload)
    while service.learner.updates_owed > 0:
        service.work(budget_s=10.0)
    service.close()
    lines = [json.loads(line) for line in (tmp_path / "learner" / "progress.jsonl").read_text().splitlines()]
    acc = events(tmp_path / "learner")
    assert [p.step for p in acc.Scalars("online/weights_version")] == [line["trained_through"] for line in lines]
    assert last(acc, "online/updates").value == lines[-1]["updates"]
    assert last(acc, "online/human_transitions").value == lines[-1]["human"] == 6
    assert last(acc, "train/critic_loss").value == pytest.approx(lines[-1]["critic_loss"], abs=1e-6)  # rounded there
    assert hparams_of(acc)["online/publish_every"] == 10


def test_hil_online_in_process_logs_its_curve_beside_summary_json(bag, tmp_path, capsys):
    out = tmp_path / "online"
    assert main(["hil", "--online", "--in-process", "--no-prior", "--bag", str(bag), "--env-steps", "200",
                 "--publish-every", "25", "--eval-every", "100", "--eval-episodes", "2", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    acc = events(out)
    assert [(p.step, p.value) for p in acc.Scalars("eval/success_rate")] == \
        [(p["env_steps"], pytest.approx(p["success"])) for p in summary["curve"]]
    assert last(acc, "online/weights_version").value == 8
    hp = hparams_of(acc)
    assert hp["env_steps"] == 200 and hp["prior_from"] == "none"
    assert "logger" not in summary["config"]  # summary.json is what it was
