"""The Ray engine on a Ray this module starts (2 CPUs, loopback, no dashboard; stopped at
the end): a run on Ray writes the same metrics.json and weights as the same run done
locally; a fleet decoded by Ray tasks is the same dataset; `experiment --engine ray` gives
the local experiment's metrics."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

# before Ray is imported: a private cluster on loopback that reports nothing home
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
ray = pytest.importorskip("ray", reason="Ray is not installed: the ray extra, pip install -e '.[ray]' "
                                        "(make setup installs it where pip resolves it beside torch 2.13.0)")

from offline_rl_core.data.fleet import expand_bags, read_fleet  # noqa: E402
from offline_rl_core.runs.experiment import ExperimentConfig, run_experiment  # noqa: E402
from offline_rl_core.runs.local_engine import LocalEngine  # noqa: E402
from offline_rl_core.runs.ray_engine import RayEngine, read_fleet_on_ray  # noqa: E402
from offline_rl_core.runs.sweep import load_sweep_spec, run_sweep  # noqa: E402
from offline_rl_core.serving.checkpoint import load_checkpoint  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MIX = REPO / "bags" / "mix.db3"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    try:
        yield ray
    finally:
        ray.shutdown()


def test_a_run_on_ray_writes_the_same_bytes_as_the_same_run_done_locally(cluster, tmp_path):
    spec = load_sweep_spec(_spec(tmp_path))
    local = run_sweep(spec, tmp_path / "local", LocalEngine(workers=1), log=lambda line: None)
    on_ray = run_sweep(spec, tmp_path / "ray", RayEngine(log=lambda line: None), log=lambda line: None)
    assert [r["status"] for r in on_ray.rows] == ["ok", "ok"]
    for run in spec.runs:
        a, b = tmp_path / "local" / run.name, tmp_path / "ray" / run.name
        assert (a / "metrics.json").read_bytes() == (b / "metrics.json").read_bytes()
        assert (a / "run.json").read_bytes() == (b / "run.json").read_bytes()
        pa, pb = load_checkpoint(a / "policy.pt")["policy_state"], load_checkpoint(b / "policy.pt")["policy_state"]
        assert pa.keys() == pb.keys() and all(torch.equal(pa[k], pb[k]) for k in pa)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]  # noqa: E731
    assert strip(local.rows) == strip(on_ray.rows)
    assert json.loads((tmp_path / "ray" / "results.jsonl").read_text().splitlines()[1])["name"] == "awac-s0"


def test_a_fleet_decoded_by_ray_tasks_is_the_fleet_read_here(cluster, tmp_path):
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.data.collect import collect_transitions

    for seed in range(3):
        write_transitions(tmp_path / f"arm{seed}.db3", collect_transitions(2, 0.5, seed))
    paths = expand_bags([tmp_path])
    here, here_summary = read_fleet(paths, workers=1)
    there, there_summary = read_fleet_on_ray(paths, ahead=2)
    assert here_summary == there_summary
    assert all(bool((getattr(here, k) == getattr(there, k)).all()) for k in ("obs", "action", "reward", "episode"))
    assert there.obs.flags.writeable  # copied out of the object store, not a read-only view of it


def test_the_experiment_on_ray_gives_the_local_metrics(cluster, tmp_path):
    tiny = dict(episodes=4, steps=30, batch_size=16, hidden=16, n_seeds=2, eval_episodes=2, seeds=[0, 1])
    run_experiment(ExperimentConfig.smoke_settings(**tiny), tmp_path / "local", log=lambda line: None)
    run_experiment(ExperimentConfig.smoke_settings(engine="ray", **tiny), tmp_path / "ray", log=lambda line: None)
    for s in (0, 1):
        assert (tmp_path / "local" / f"seed_{s}" / "metrics.json").read_bytes() == \
            (tmp_path / "ray" / f"seed_{s}" / "metrics.json").read_bytes()


def test_a_cluster_that_does_not_answer_is_one_line_saying_how_to_start_one(tmp_path):
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    spec = _spec(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core.commands.cli", "sweep", str(spec),
                           "--address", f"127.0.0.1:{port}", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err.count("\n") == 0 and f"127.0.0.1:{port}: no Ray cluster answers there" in err and "ray start --head" in err
    assert not (tmp_path / "out").exists()


def _spec(tmp_path: Path) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(f"bags: {MIX}\nvariants: [{{algo: bc}}, {{algo: awac}}]\nbaseline: bc\n"
                    "train: {steps: 50, hidden: 16, batch_size: 16, deterministic: true}\neval: {episodes: 3}\n")
    return path
