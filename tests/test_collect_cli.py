"""`offline-rl collect` and `offline-rl bag-info` from the command line."""

from __future__ import annotations

import numpy as np

from offline_rl_core.commands import cli
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.data.collect import collect_transitions


def _collect(out, *extra) -> int:
    return cli.main(["collect", "--episodes", "4", "--expert-frac", "0.5", "--seed", "2", "--out", str(out), *extra])


def test_collect_is_bit_reproducible(tmp_path, capsys):
    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    second.mkdir()
    assert _collect(first / "d.db3") == 0
    out = capsys.readouterr()
    assert "400 transitions, 4 episodes" in out.out and "expert: 2 episodes" in out.out
    assert "collect: 4/4 episodes" in out.err
    assert _collect(second / "d.db3") == 0
    assert (first / "d.db3").read_bytes() == (second / "d.db3").read_bytes()
    expected = collect_transitions(4, 0.5, 2).to_rows()
    assert np.array_equal(read_transitions(first / "d.db3").to_rows(), expected)
    # Overwriting replaces the bag in place, byte for byte the same.
    assert _collect(first / "d.db3") == 0
    assert (first / "d.db3").read_bytes() == (second / "d.db3").read_bytes()
    assert sorted(p.name for p in first.iterdir()) == ["d.db3"]


def test_collect_mcap_directory_and_bag_info(tmp_path, capsys):
    out = tmp_path / "mixdir"
    assert _collect(out, "--storage", "mcap") == 0
    assert (out / "mixdir.mcap").is_file() and (out / "metadata.yaml").is_file()
    capsys.readouterr()
    assert cli.main(["bag-info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Storage id:        mcap" in text
    assert "Topic: /pusher/transition | Type: std_msgs/msg/Float32MultiArray | Count: 400" in text
    assert "random:" in text and "expert:" in text


def test_collect_refuses_missing_parent(tmp_path, capsys):
    target = tmp_path / "nowhere" / "x.db3"
    assert _collect(target) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(target) in err and "does not exist" in err
    assert not (tmp_path / "nowhere").exists()


def test_collect_another_task_records_it_in_the_bag(tmp_path, capsys):
    from offline_rl_core.data.task_record import recorded_task
    from offline_rl_core.task.spec import load_task

    out = tmp_path / "p7.db3"
    assert cli.main(["collect", "--task", "pusher7_reach", "--episodes", "2", "--expert-frac", "0.5", "--seed", "1",
                     "--out", str(out)]) == 0
    assert "200 transitions, 2 episodes" in capsys.readouterr().out
    assert recorded_task(out).digest == load_task("pusher7_reach").digest  # a bag that needs no --task
    data = read_transitions(out)
    assert (data.obs.shape[1], data.action.shape[1]) == (20, 7)
    assert data.success[data.episode == 0][-1] and list(np.unique(data.source)) == [0, 1]  # the expert reached
    assert cli.main(["bag-info", str(out)]) == 0
    assert "expert:      1 episodes" in capsys.readouterr().out


def test_collect_a_task_no_sim_hosts_is_one_line(tmp_path, capsys):
    from offline_rl_core.task.spec import load_task

    task = tmp_path / "nosim.yaml"
    task.write_text(load_task("pusher7_reach").path.read_text().split("\nsim:")[0])
    assert cli.main(["collect", "--task", str(task), "--episodes", "1", "--out", str(tmp_path / "x.db3")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "has no sim section" in err and not (tmp_path / "x.db3").exists()
