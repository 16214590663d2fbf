"""The chapter's experiment: metrics.json keys, byte-identical reruns, multi-seed summary."""

import dataclasses
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import torch

from offline_rl_core.commands.cli import main
from offline_rl_core.common.seeds import eval_reset_seeds
from offline_rl_core.runs.experiment import METRIC_KEYS, ExperimentConfig, run_experiment


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny(**kw) -> ExperimentConfig:
    # Smaller than --smoke so the fast suite stays fast; same code path.
    return ExperimentConfig.smoke_settings(episodes=4, steps=30, batch_size=16, hidden=16, n_seeds=2, eval_episodes=2, **kw)


def test_eval_reset_seeds_are_the_chapters():
    assert eval_reset_seeds(0, 5, 20) == list(range(500000, 500100))
    assert eval_reset_seeds(2, 2, 4)[:5] == [500002, 500003, 500004, 500005, 500006]


def test_tiny_experiment_is_byte_identical_and_has_the_chapters_keys(tmp_path):
    for run in ("a", "b"):
        run_experiment(tiny(), tmp_path / run, log=lambda line: None)
    a = (tmp_path / "a" / "metrics.json").read_bytes()
    assert a == (tmp_path / "b" / "metrics.json").read_bytes()
    metrics = json.loads(a)
    assert tuple(sorted(metrics)) == METRIC_KEYS
    assert metrics["mode"] == "AWAC" and metrics["n_pooled"] == 4 and metrics["smoke"] is True
    assert metrics["naive"] is False and metrics["offline_mean_abs_q"] > 0
    assert metrics["diff_ci_lo"] <= metrics["diff_ci_hi"]
    for name in ("bc.pt", "offline.pt", "offline_training.png"):
        assert (tmp_path / "a" / name).is_file()


def test_multi_seed_writes_per_seed_metrics_and_summary(tmp_path):
    outcomes = run_experiment(tiny(seeds=[0, 1], algo="naive"), tmp_path, log=lambda line: None)
    assert [o.seed for o in outcomes] == [0, 1]
    for s in (0, 1):
        m = json.loads((tmp_path / f"seed_{s}" / "metrics.json").read_text())
        assert m["seed"] == s and m["mode"] == "naive-maxQ" and m["naive"] is True
        assert (tmp_path / f"seed_{s}" / "offline.pt").is_file()
    summary = (tmp_path / "summary.md").read_text()
    assert "seed 0" in summary and "seed 1" in summary and "pooled" in summary
    assert (tmp_path / "summary.png").stat().st_size > 1000


def test_experiment_cli_rejects_conflicting_flags(tmp_path, capsys):
    assert main(["experiment", "--naive", "--algo", "iql", "--out", str(tmp_path)]) == 2
    assert "--naive" in capsys.readouterr().err


@pytest.mark.slow
def test_smoke_cli_twice_gives_byte_identical_metrics(tmp_path, capsys):
    for run in ("a", "b"):
        assert main(["experiment", "--smoke", "--seed", "0", "--out", str(tmp_path / run)]) == 0
    out = capsys.readouterr().out
    assert "AWAC" in out and "Wilson" in out
    assert (tmp_path / "a" / "metrics.json").read_bytes() == (tmp_path / "b" / "metrics.json").read_bytes()


def test_worker_processes_give_the_same_metrics_as_one_process(tmp_path):
    """Each (learner, seed) run in its own worker process: same numbers as all seeds
    trained together in this process, and progress still reaches the log."""
    lines = []
    together = run_experiment(tiny(seeds=[0, 1], workers=1), tmp_path / "one", log=lambda line: None)
    spread = run_experiment(tiny(seeds=[0, 1], workers=2), tmp_path / "two", log=lines.append)
    assert [o.metrics for o in spread] == [o.metrics for o in together]
    assert any("in 2 worker processes" in line for line in lines)
    assert any("awac s1 step" in line for line in lines)


def test_a_failing_run_stops_the_other_workers_and_reaches_the_caller():
    import multiprocessing

    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.runs.parallel import TrainJob, run_jobs

    data = collect_transitions(2, 0.5, 0)
    long_run = TrainJob("bc s0", [data], TrainConfig(algo="bc", steps=200_000, batch_size=8, hidden=8), [0])
    bad_run = TrainJob("bc s1", [data.select(slice(0, 0))], TrainConfig(algo="bc", steps=10), [1])
    with pytest.raises(ValueError, match="empty dataset"):
        run_jobs([long_run, bad_run], workers=2)
    assert multiprocessing.active_children() == []  # the long run was stopped, not awaited


def test_a_run_takes_the_cores_of_finished_runs_and_trains_the_same_bytes():
    """Once no run waits for a worker, the runs still training take the finished ones'
    cores (the C++ replay spreads their steps): the last long run of an experiment does
    not train on one core while the other idles, and trains exactly what it would alone."""
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train_seeds
    from offline_rl_core.fast import graph_runner
    from offline_rl_core.runs.parallel import TrainJob, run_jobs
    from offline_rl_core.common.machine import available_cores

    if available_cores() < 2 or graph_runner.unavailable_reason() is not None:
        pytest.skip("needs two cores and the C++ step replayer")
    data = collect_transitions(20, 0.5, 0)
    awac = TrainConfig(algo="awac", steps=3000, batch_size=128, hidden=128, log_every=3000)
    short = TrainJob("bc s0", [data], TrainConfig(algo="bc", steps=20, batch_size=16, hidden=16), [0])
    long = TrainJob("awac s0", [data], awac, [0])  # handed out after the short run: starts no earlier
    _, (spread,) = run_jobs([short, long], workers=2)
    assert spread.checkpoint["train_threads"] == 2
    alone = train_seeds(data, dataclasses.replace(awac, threads=1), [0])[0]
    assert alone.checkpoint["train_threads"] == 1
    for name, value in alone.checkpoint["policy_state"].items():
        assert torch.equal(spread.checkpoint["policy_state"][name], value), name


def test_a_killed_worker_fails_the_experiment_at_once_naming_its_job(tmp_path, capsys):
    """A worker killed by the OOM killer (here SIGKILL by pid) fails the experiment with
    one line naming its job and a non-zero exit; the other worker is stopped, not awaited."""
    out = tmp_path / "run"
    codes = []
    experiment = threading.Thread(target=lambda: codes.append(main([
        "experiment", "--smoke", "--episodes", "2", "--steps", "1000000", "--workers", "2", "--out", str(out)])),
        daemon=True)
    experiment.start()
    deadline = time.monotonic() + 300  # a bound, should this ever hang; not a timing assertion
    while not (out / "resume_bc.pt").exists():  # the BC job is training in its worker
        assert experiment.is_alive() and time.monotonic() < deadline, capsys.readouterr()
        time.sleep(0.01)
    (worker,) = [c for c in multiprocessing.active_children() if c.name == "training worker for 'bc s0'"]
    os.kill(worker.pid, signal.SIGKILL)
    experiment.join(timeout=120)
    assert not experiment.is_alive(), "the experiment still waits for its dead worker"
    assert codes == [1]
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("offline-rl: error: training worker for 'bc s0' died (killed by signal 9, SIGKILL")
    assert "--resume" in err[-1] and "Traceback" not in "".join(err)
    assert multiprocessing.active_children() == []  # the AWAC worker was stopped


EXPERIMENT = [sys.executable, "-m", "offline_rl_core", "experiment", "--smoke", "--seed", "0", "--episodes", "8",
              "--steps", "1000"]


def test_a_killed_experiment_resumes_to_the_same_bytes(tmp_path, capsys):
    """SIGKILL mid-training loses at most the last resume point's worth of training:
    --resume continues the jobs and gives the same metrics.json bytes as a run never stopped."""
    killed = tmp_path / "killed"
    proc = subprocess.Popen([*EXPERIMENT, "--out", str(killed), "--resume-every", "0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in proc.stdout:  # the offline learner has trained; BC's first progress line
            if " bc step" in line:
                break
        else:
            pytest.fail("the experiment ended before BC trained")
        assert (killed / "resume_offline.pt").exists() and (killed / "resume_bc.pt").exists()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert not (killed / "metrics.json").exists()  # killed mid-training

    assert main([*EXPERIMENT[3:], "--out", str(killed), "--resume"]) == 0
    assert f"resuming from {killed / 'resume_bc.pt'}" in capsys.readouterr().out
    assert main([*EXPERIMENT[3:], "--out", str(tmp_path / "whole")]) == 0
    assert (killed / "metrics.json").read_bytes() == (tmp_path / "whole" / "metrics.json").read_bytes()
    assert not list(killed.glob("*resume*"))  # spent once the results are written, temp files too


def test_an_experiment_on_another_task_collects_and_evaluates_there(tmp_path):
    from offline_rl_core.commands.experiment import config_from_args, register

    parser = __import__("argparse").ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["experiment", "--task", "pusher7_reach", "--smoke", "--out", str(tmp_path)])
    assert config_from_args(args).task == "pusher7_reach"
    run_experiment(dataclasses.replace(tiny(task="pusher7_reach"), episodes=2, n_seeds=1), tmp_path,
                   log=lambda line: None)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["task"] == "pusher7_reach" and tuple(sorted(set(metrics) - {"task", "task_digest"})) == METRIC_KEYS
    assert metrics["n_pooled"] == 2 and 0 <= metrics["bc_success_rate"] <= 1
    assert torch.load(tmp_path / "bc.pt", weights_only=False)["obs_dim"] == 20
