"""A training run survives being killed: ``--resume`` finishes it with the same bytes as a
run that was never stopped."""

import os
import signal
import subprocess
import sys
import time

import pytest

ARGS = ["--bag", "bags/mix.db3", "--algo", "awac", "--steps", "1500", "--seed", "3", "--hidden", "64",
        "--batch-size", "64", "--eval-episodes", "5", "--log-every", "50"]


def _train(out, *extra):
    return subprocess.run([sys.executable, "-m", "offline_rl_core", "train", *ARGS, "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_killed_run_resumes_to_identical_results(tmp_path):
    whole = tmp_path / "whole"
    assert _train(whole).returncode == 0
    assert not (whole / "resume.pt").exists()  # a finished run leaves no resume point

    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "offline_rl_core", "train", *ARGS, "--out", str(killed),
                             "--resume-every", "0.2"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        progress = ""
        while "step    400/" not in progress:  # well into training, with resume points written
            line = proc.stderr.readline()
            assert line, "training ended before it could be killed"
            progress += line
        assert (killed / "resume.pt").exists()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert not (killed / "policy.pt").exists()

    done = _train(killed, "--resume")
    assert done.returncode == 0, done.stderr
    assert "resuming from" in done.stderr
    assert (killed / "metrics.json").read_bytes() == (whole / "metrics.json").read_bytes()
    import torch

    a = torch.load(killed / "policy.pt", weights_only=True)
    b = torch.load(whole / "policy.pt", weights_only=True)
    for key in b["policy_state"]:
        assert torch.equal(a["policy_state"][key], b["policy_state"][key])
    for key in b["learner_state"]["critic1"]:
        assert torch.equal(a["learner_state"]["critic1"][key], b["learner_state"]["critic1"][key])


def test_a_resume_point_of_another_run_is_refused(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "offline_rl_core", "train", *ARGS, "--out", str(out),
                             "--resume-every", "0.05"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while not (out / "resume.pt").exists():
            assert proc.poll() is None, "training ended before writing a resume point"
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    other = _train(out, "--seed", "4", "--resume")  # the last --seed wins
    assert other.returncode == 2
    assert "resume.pt: that resume point is of another run" in other.stderr
    assert "Traceback" not in other.stderr


def test_a_resume_point_write_killed_half_way_leaves_no_temp_file_behind_the_next_run(tmp_path):
    """A kill during a resume point's write leaves its partial temp file (as big as the
    resume point); the next run, resumed or not, removes it and keeps the other files."""
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train_seeds
    from offline_rl_core.learners.resume import ResumePoints

    path = tmp_path / "resume.pt"
    half_write = ("import os, signal, sys\nfrom offline_rl_core.common.atomic import atomic_path\n"
                  "with atomic_path(sys.argv[1]) as tmp:\n    tmp.write_bytes(b'half a resume point')\n"
                  "    os.kill(os.getpid(), signal.SIGKILL)\n")
    data = collect_transitions(2, 0.5, 0)
    (tmp_path / "metrics.json").write_text("{}")
    for resume in (False, True):
        killed = subprocess.run([sys.executable, "-c", half_write, str(path)])
        assert killed.returncode == -signal.SIGKILL
        assert len(list(tmp_path.glob(".resume.pt.*.tmp"))) == 1
        train_seeds(data, TrainConfig(algo="bc", steps=3, batch_size=8, hidden=8), [0],
                    resume=ResumePoints(path, resume=resume))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json", "resume.pt"]  # this run's own
