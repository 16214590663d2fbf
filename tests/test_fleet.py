"""Fleets of bags (data/fleet.py): which bags a directory or glob names, the merged dataset
(the same bytes with worker processes as read one bag after another), and the bound on the
bags decoded ahead of the one being copied."""

from __future__ import annotations

import json
from concurrent.futures import Future

import numpy as np
import pytest

from offline_rl_core.commands.cli import main
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import read_transitions, write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.data.fleet import InProcess, expand_bags, iter_fleet, read_fleet
from offline_rl_core.data.transitions import Transitions


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A fleet's day: three single-file bags of different arms and a bag directory, plus
    what a fleet folder also holds (a writer's hidden staging, a note)."""
    root = tmp_path_factory.mktemp("fleet")
    parts = [collect_transitions(2, 0.5, seed) for seed in range(4)]
    write_transitions(root / "arm1.db3", parts[0])
    write_transitions(root / "arm2.mcap", parts[1])
    write_transitions(root / "arm3.db3", parts[2])
    write_transitions(root / "arm4", parts[3])  # a bag directory with metadata.yaml
    (root / ".arm5.db3.partial").mkdir()
    (root / "notes.txt").write_text("day 1\n")
    return root, parts


def one_after_another(paths: list[str]) -> Transitions:
    """The reference: each bag read in this process, episode ids offset per bag."""
    parts, offset = [], 0
    for p in paths:
        data = read_transitions(p)
        data.episode = data.episode - data.episode.min() + offset
        offset = int(data.episode.max()) + 1
        parts.append(data)
    return Transitions.concatenate(parts)


def same(a: Transitions, b: Transitions) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) and getattr(a, k).dtype == getattr(b, k).dtype
               for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "success", "episode",
                         "step", "source"))


def test_a_folder_names_its_bags_in_order(fleet):
    root, _ = fleet
    assert expand_bags([root]) == [str(root / n) for n in ("arm1.db3", "arm2.mcap", "arm3.db3", "arm4")]
    assert expand_bags([str(root / "arm*.db3")]) == [str(root / "arm1.db3"), str(root / "arm3.db3")]
    assert expand_bags([root / "arm4"]) == [str(root / "arm4")]  # a bag directory is one bag


def test_a_bag_folder_that_lost_its_metadata_is_one_bag_not_a_fleet(tmp_path):
    bag = tmp_path / "run7"
    write_transitions(bag, collect_transitions(1, 0.5, 0))
    (bag / "metadata.yaml").unlink()
    assert expand_bags([bag]) == [str(bag)]
    with pytest.raises(UserError, match="no metadata.yaml"):
        read_fleet(expand_bags([bag]))


def test_names_that_give_no_bag_are_refused_naming_them(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="empty: the directory holds no bags"):
        expand_bags([tmp_path / "empty"])
    with pytest.raises(UserError, match=r"nothing\*.db3: the pattern matches no file"):
        expand_bags([str(tmp_path / "nothing*.db3")])


@pytest.mark.parametrize("workers", [1, 2])
def test_the_fleet_is_the_bags_read_one_after_another(fleet, workers):
    root, parts = fleet
    paths = expand_bags([root])
    data, summaries = read_fleet(paths, workers=workers)
    assert same(data, one_after_another(paths))
    assert len(data) == sum(len(p) for p in parts)
    assert [s["path"] for s in summaries] == paths
    assert [s["transitions"] for s in summaries] == [len(p) for p in parts]
    assert len(np.unique(data.episode)) == sum(len(np.unique(p.episode)) for p in parts)


def test_a_bad_bag_in_a_fleet_is_named(fleet, tmp_path):
    root, parts = fleet
    write_transitions(tmp_path / "good.db3", parts[0])
    (tmp_path / "broken.db3").write_text("not a bag\n")
    with pytest.raises(UserError, match="broken.db3"):
        read_fleet(expand_bags([tmp_path]), workers=2)


class CountingExecutor(InProcess):
    """Runs tasks in this process and records how many results were handed out and not
    yet taken by the reader at the worst moment."""

    def __init__(self):
        self.held = self.most_held = 0

    def submit(self, fn, *args) -> Future:
        self.held += 1
        self.most_held = max(self.most_held, self.held)
        future = super().submit(fn, *args)
        result = future.result

        def taken():
            self.held -= 1
            return result()

        future.result = taken
        return future


def test_no_more_bags_are_decoded_ahead_than_allowed(fleet):
    root, _ = fleet
    paths = expand_bags([root]) * 3  # twelve bags
    executor = CountingExecutor()
    got = [len(data) for data, _ in iter_fleet(paths, executor, ahead=2)]
    assert len(got) == 12
    assert executor.most_held == 2


def test_train_takes_a_fleet_folder(fleet, tmp_path, capsys):
    root, parts = fleet
    out = tmp_path / "run"
    assert main(["train", "--bag", str(root), "--algo", "bc", "--steps", "20", "--hidden", "16", "--batch-size", "16",
                 "--eval-episodes", "0", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert [b["path"] for b in metrics["bags"]] == expand_bags([root])
    assert metrics["transitions"] == sum(len(p) for p in parts)
