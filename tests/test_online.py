"""The online (HIL-SERL) learner: learning from a live stream on a schedule set by counts,
resuming where it saved, and the in-process stage that the ROS stage is measured against."""

import json

import numpy as np
import pytest
import torch

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.task.corrector import CorrectorParams
from offline_rl_core.learners import TrainConfig, train
from offline_rl_core.learners.online import OnlineLearner, OnlineSettings
from offline_rl_core.runs.online_loop import OnlineRunConfig, run_online
from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY

SMALL = dict(batch_size=32, hidden=32, log_every=10)


@pytest.fixture(scope="module")
def offline():
    return collect_transitions(10, 0.3, 0)


@pytest.fixture(scope="module")
def prior(offline):
    return train(offline, TrainConfig(algo="awac", steps=50, **SMALL), seed=0).checkpoint


def _stream(n, seed=1):
    live = collect_transitions(max(1, n // 100 + 1), 0.0, seed)
    rows = live.select(np.arange(n))
    rows.source[:] = SOURCE_POLICY
    rows.source[::7] = SOURCE_HUMAN
    return rows


def _learner(offline, prior, **settings):
    cfg = TrainConfig(algo="sac", **SMALL)
    return OnlineLearner(offline, cfg, OnlineSettings(**{"publish_every": 10, **settings}), seed=3, prior=prior)


def _feed(learner, rows, start=0, stop=None):
    versions = []
    for i in range(start, len(rows) if stop is None else stop):
        learner.add(rows.select(np.array([i])))
        while learner.updates_owed > 0:
            learner.train()
            if learner.version_due():
                versions.append(learner.cut_version())
    return versions


def _flat(weights):
    return torch.cat([t.flatten() for t in weights["policy_state"].values()])


def test_weights_do_not_depend_on_how_the_stream_is_chunked(offline, prior):
    """Versions are cut by counts: training after every transition or in bursts gives
    the same bytes (so a fast or slow learner serves the same versions)."""
    rows = _stream(40)
    a = _learner(offline, prior, utd=2)
    va = _feed(a, rows)
    b = _learner(offline, prior, utd=2)
    for i in range(len(rows)):  # everything arrives before any training
        b.add(rows.select(np.array([i])))
    vb = []
    while b.updates_owed > 0:
        b.train(max_updates=3)
        if b.version_due():
            vb.append(b.cut_version())
    assert [v["weights_version"] for v in va] == [1, 2, 3, 4] == [v["weights_version"] for v in vb]
    for x, y in zip(va, vb):
        assert torch.equal(_flat(x), _flat(y))
        assert x["trained_through"] == y["trained_through"]


def test_the_prior_initialises_actor_and_critic(offline, prior):
    learner = _learner(offline, prior)
    w = learner.weights()
    assert w["weights_version"] == 0
    for k, v in prior["policy_state"].items():
        assert torch.equal(w["policy_state"][k], v)
    state = learner.learner.learner_state(0)
    assert torch.equal(state["critic1"]["0.weight"], prior["learner_state"]["critic1"]["0.weight"])


def test_a_prior_of_another_width_is_fine_tuned_at_its_width(offline):
    """The learner takes the prior's networks as they are: a prior trained wider than the
    learner's default is fine-tuned at its own width, actor and critic, and its weights
    versions say so."""
    wide = train(offline, TrainConfig(algo="awac", steps=20, **{**SMALL, "hidden": 48}), seed=0).checkpoint
    learner = _learner(offline, wide)
    _feed(learner, _stream(12))
    w = learner.weights()
    assert w["hidden"] == 48 and w["weights_version"] > 0
    assert w["policy_state"]["0.weight"].shape[0] == 48
    assert learner.learner.learner_state(0)["critic1"]["0.weight"].shape[0] == 48


def test_a_resumed_learner_continues_exactly(offline, prior, tmp_path):
    rows = _stream(50)
    whole = _learner(offline, prior)
    _feed(whole, rows)
    first = _learner(offline, prior)
    _feed(first, rows, 0, 23)
    torch.save(first.state(), tmp_path / "state.pt")
    resumed = _learner(offline, prior)
    resumed.restore(torch.load(tmp_path / "state.pt", weights_only=True))
    _feed(resumed, rows, 23)
    assert resumed.updates == whole.updates and resumed.version == whole.version
    assert torch.equal(_flat(resumed.weights()), _flat(whole.weights()))
    assert torch.equal(resumed.weights()["exploration_log_std"], whole.weights()["exploration_log_std"])


def test_in_process_stage_is_reproducible_and_learns_from_corrections(offline, prior):
    cfg = OnlineRunConfig(env_steps=300, seed=0, eval_every=150, eval_episodes=4,
                          corrector=CorrectorParams(patience=4, grace_steps=5, hold_steps=10),
                          settings=OnlineSettings(publish_every=25),
                          train=TrainConfig(algo="sac", **SMALL))
    one = run_online(offline, prior, cfg, log=lambda s: None)
    two = run_online(offline, prior, cfg, log=lambda s: None)
    assert one["counts"] == two["counts"]
    assert [p["success"] for p in one["curve"]] == [p["success"] for p in two["curve"]]
    assert torch.equal(_flat(one["final_weights"]), _flat(two["final_weights"]))
    assert one["counts"]["steps"] == 300 and one["counts"]["human"] > 0  # the corrector took over
    assert [p["env_steps"] for p in one["curve"]] == [0, 150, 300]
    assert one["final_weights"]["weights_version"] == 12


# ---------------------------------------------------------------- the learner node's logic
def _service(tmp_path, bag, prior_path, name, **kw):
    from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig

    settings = kw.pop("settings", OnlineSettings(publish_every=10))
    cfg = LearnerServiceConfig(bags=[str(bag)], out=str(tmp_path / name), prior=str(prior_path), seed=5,
                               settings=settings, train=TrainConfig(algo="sac", **SMALL), **kw)
    return LearnerService(cfg, log=lambda s: None)


@pytest.fixture(scope="module")
def files(tmp_path_factory, offline, prior):
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.serving.checkpoint import save_checkpoint

    d = tmp_path_factory.mktemp("online")
    write_transitions(d / "offline.db3", offline)
    save_checkpoint(d / "prior.pt", prior)
    stream = _stream(40)
    write_transitions(d / "session.db3", stream)
    return d, stream


def _drain(service):
    versions = []
    while service.learner.updates_owed > 0:
        versions += service.work(budget_s=10.0)
    return versions


def test_bad_live_transitions_are_counted_and_never_trained_on(tmp_path, files):
    from offline_rl_core.data.bag.cdr import encode_transition_rows

    d, stream = files
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "bad")
    rows = stream.to_rows()[:3].copy()
    nan, wild, good = rows[0].copy(), rows[1].copy(), rows[2]
    nan[3] = np.nan
    wild[8] = 1e38  # an action far outside [-1, 1]
    payloads = encode_transition_rows(np.stack([nan, wild, good]))
    assert "non-finite obs" in service.receive(payloads[0])
    assert service.receive(payloads[1]) == "action outside [-1, 1]"
    assert service.receive(b"\x00\x01\x00\x00garbage") .startswith("bad layout")
    assert service.receive(payloads[2]) is None
    assert service.learner.n_online == 1
    assert service.rejected.total == 3


def test_a_prior_that_does_not_fit_the_learner_is_one_clear_line(tmp_path, files, prior):
    from offline_rl_core.common.errors import UserError
    from offline_rl_core.serving.checkpoint import save_checkpoint

    d, _ = files
    bad_bias = {**prior, "policy_state": {**prior["policy_state"], "4.bias": torch.zeros(7)}}
    critic = {k: v[:, :3] if k == "0.weight" else v for k, v in prior["learner_state"]["critic1"].items()}
    bad_critic = {**prior, "learner_state": {**prior["learner_state"], "critic1": critic}}
    for name, ckpt, expected in (("bias.pt", bad_bias, "'4.bias' has shape (7,)"),
                                 ("critic.pt", bad_critic, "learner_state does not fit a sac learner")):
        path = save_checkpoint(tmp_path / name, ckpt)
        with pytest.raises(UserError) as refused:
            _service(tmp_path, d / "offline.db3", path, "out")
        assert str(refused.value).startswith(f"{path}: ") and expected in str(refused.value), str(refused.value)
    (tmp_path / "file").write_text("")
    with pytest.raises(UserError, match=r"parameter out: .*/file/out: cannot write: .*/file is a file"):
        _service(tmp_path / "file", d / "offline.db3", d / "prior.pt", "out")  # at start, not at the first save


def test_weights_messages_round_trip_and_snapshots_are_kept(tmp_path, files):
    from offline_rl_core.data.bag.cdr import encode_transition_rows
    from offline_rl_core.serving.signing import Signer
    from offline_rl_core.serving.weights import decode_weights, encode_weights

    d, stream = files
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "w", snapshot_every=20)
    for payload in encode_transition_rows(stream.to_rows()):
        service.receive(payload)
    versions = _drain(service)
    assert [v["weights_version"] for v in versions] == [1, 2, 3, 4]
    signer = Signer.generate()
    back = decode_weights(encode_weights(versions[-1], signer), signer.verifier())
    assert back["weights_version"] == 4 and back["trained_through"] == 40
    assert torch.equal(_flat(back), _flat(versions[-1]))
    assert sorted(p.name for p in (tmp_path / "w" / "snapshots").iterdir()) == [
        "policy_000000.pt", "policy_000020.pt", "policy_000040.pt"]
    assert len((tmp_path / "w" / "progress.jsonl").read_text().splitlines()) == 4


def test_a_killed_learner_resumes_from_its_state_and_the_session_bag(tmp_path, files):
    from offline_rl_core.data.bag.cdr import encode_transition_rows

    d, stream = files
    payloads = encode_transition_rows(stream.to_rows())
    whole = _service(tmp_path, d / "offline.db3", d / "prior.pt", "whole")
    for p in payloads:
        whole.receive(p)
    _drain(whole)
    first = _service(tmp_path, d / "offline.db3", d / "prior.pt", "run")
    for p in payloads[:17]:
        first.receive(p)
    _drain(first)
    first.save()  # its last resume point; then it dies, and transitions 17.. go by unseen
    resumed = _service(tmp_path, d / "offline.db3", d / "prior.pt", "run", resume=True,
                       session_bag=str(d / "session.db3"))
    assert resumed.learner.n_online == 40  # read back from the session's recording
    _drain(resumed)
    assert resumed.learner.version == whole.learner.version == 4
    assert torch.equal(_flat(resumed.learner.weights()), _flat(whole.learner.weights()))


def test_several_actors_feed_one_learner_counted_by_namespace(tmp_path, files):
    """``actors``: each actor's transitions are trained on and counted under its namespace
    (status and progress.jsonl); a namespace that is none, or one named twice, is one line."""
    from offline_rl_core.common.errors import UserError
    from offline_rl_core.data.bag.cdr import encode_transition_rows

    d, stream = files
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "actors", actors=("/arm1", "/arm2"))
    assert [topic for _, topic in service.transition_topics] == ["/arm1/pusher/transition", "/arm2/pusher/transition"]
    payloads = encode_transition_rows(stream.to_rows())
    for i, payload in enumerate(payloads[:30]):
        assert service.receive(payload, "/arm1" if i % 3 else "/arm2") is None
    versions = _drain(service)
    assert service.learner.n_online == 30 and [v["weights_version"] for v in versions] == [1, 2, 3]
    assert service.status()["received_from"] == {"/arm1": 20, "/arm2": 10}
    last = json.loads((tmp_path / "actors" / "progress.jsonl").read_text().splitlines()[-1])
    assert last["received_from"] == {"/arm1": 20, "/arm2": 10} and last["trained_through"] == 30
    service.actor_estops["/arm2"].on_estop(True)  # one arm's own e-stop: only its steps are dropped
    assert service.receive(payloads[30], "/arm2") == "a transition while the e-stop is engaged: not trained on"
    assert service.receive(payloads[31], "/arm1") is None
    assert service.status()["received_from"] == {"/arm1": 21, "/arm2": 10}
    for actors, expected in ((("arm1",), "'arm1' is no namespace"), (("/arm1", "/arm1"), "names an actor twice")):
        with pytest.raises(UserError, match=f"parameter actors: .*{expected}"):
            _service(tmp_path, d / "offline.db3", d / "prior.pt", "bad_actors", actors=actors)
    alone = _service(tmp_path, d / "offline.db3", d / "prior.pt", "alone")
    assert alone.transition_topics == [(None, "pusher/transition")] and "received_from" not in alone.status()


def test_a_paced_actor_waits_for_the_learners_own_weights(offline, prior):
    """Paced, the checkpoint the policy node started from does not count: the session must
    not depend on how soon the learner's first weights message arrives."""
    from offline_rl_core.serving.actor import Actor
    from offline_rl_core.serving.policy import LoadedPolicy

    learner = _learner(offline, prior)
    actor = Actor(LoadedPolicy(prior), explore=True, seed=0, paced_every=10)
    actor.see(1000)
    assert not actor.ready()  # the prior file: no version, no exploration std
    assert actor.offer(LoadedPolicy(learner.weights()))  # the learner's version 0
    assert actor.ready()
    for stamp in range(1001, 1011):
        actor.see(stamp)
    assert actor.states == 10 and not actor.ready()  # state 10 needs version 1
    assert not actor.offer(LoadedPolicy(learner.weights()))  # version 0 again: not newer
    a = actor.act(np.zeros(8, np.float32), stamp=1010)
    assert np.array_equal(actor.act(np.zeros(8, np.float32), stamp=1010), a)  # one draw per state


# ---------------------------------------------------------------- the learner on raw topics
@pytest.fixture(scope="module")
def raw_session(tmp_path_factory):
    """A lockstep session of the sim as a robot logs it (joint states, target, fingertip,
    commands), and its messages in the order a learner takes them."""
    from raw_topic_bags import bag_messages, record_raw_bag

    from offline_rl_core.task.spec import load_task

    bag = tmp_path_factory.mktemp("raw") / "session.db3"
    record_raw_bag(bag, episodes=2, expert_frac=0.5, seed=6, sim_like=True, duplicates=0.05)
    return bag, bag_messages(bag, load_task("pusher_reach"))


def _feed_raw(service, messages):
    for topic, msgtype, payload, recv in messages:
        assert service.receive_message(topic, msgtype, payload, recv) is None
    service.last_poll = -np.inf  # not throttled: the messages came over a while
    service.take_steps(quiet=True)  # all that was published has arrived (not left to the wall clock's quiet rule)


def test_the_learner_on_raw_topics_trains_on_the_rows_of_the_batch_join(tmp_path, files, raw_session):
    """Every step of the arm counts (also an episode's last, which has no transition), so
    the versions stay in step with a paced actor; the rows are the batch join's."""
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.learners.data import MemberData

    d, _ = files
    bag, messages = raw_session
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "raw", from_topics=True)
    _feed_raw(service, messages)
    _drain(service)
    batch, report = transitions_from_topics(bag)
    assert report.steps == 200 and len(batch) == 198
    assert service.learner.n_steps == 199  # the last step waits for a state that never comes
    assert service.learner.n_online == 198
    assert service.learner.version == 19  # every publish_every (10) steps, transitions or not
    expected = MemberData.columns(batch)
    for name in ("obs", "action", "reward", "next_obs", "not_done", "human"):
        got = getattr(service.learner.data, name)[0, service.learner.n_offline:service.learner.n_offline + 198]
        assert np.array_equal(got.numpy(), expected[name]), name
    assert service.status()["join"]["late"] == 0


def test_a_learner_on_raw_topics_resumes_from_the_session_bag(tmp_path, files, raw_session):
    d, _ = files
    bag, messages = raw_session
    whole = _service(tmp_path, d / "offline.db3", d / "prior.pt", "whole", from_topics=True)
    _feed_raw(whole, messages)
    _drain(whole)
    first = _service(tmp_path, d / "offline.db3", d / "prior.pt", "run", from_topics=True)
    _feed_raw(first, messages[:300])
    _drain(first)
    first.save()  # then it dies; the rest of the session goes by unseen
    resumed = _service(tmp_path, d / "offline.db3", d / "prior.pt", "run", from_topics=True, resume=True,
                       session_bag=str(bag))
    # the recording is all of the session there is here (live, the arm's next messages would
    # come): its last steps are final once the join knows nothing more is on the way, not
    # when the wall clock's quiet rule, timed from the bag's reading, says so
    resumed.last_poll = -np.inf
    resumed.take_steps(quiet=True)
    assert 0 < first.learner.n_steps < resumed.learner.n_steps == whole.learner.n_steps == 199
    _drain(resumed)
    assert resumed.learner.version == whole.learner.version == 19
    assert torch.equal(_flat(resumed.learner.weights()), _flat(whole.learner.weights()))


def test_a_full_buffer_evicts_the_oldest_live_rows_and_keeps_the_offline_ones(offline, prior):
    """The online buffer is a ring over ``capacity`` (plus room for a lagging learner): it
    never raises, the offline rows stay, each update samples among the newest ``capacity``
    transitions it may see, and a learner that lags by less than the room gives the same
    weights as one that keeps up."""
    from offline_rl_core.learners.online import LAG_VERSIONS

    rows = _stream(400)
    a = _learner(offline, prior, utd=1, capacity=30)
    offline_obs = a.data.obs[0, :len(offline)].clone()
    va = _feed(a, rows)
    ring = 30 + LAG_VERSIONS * 10
    assert a.n_online == 400 and a.n_evicted == 400 - ring and a.data.sizes == [len(offline) + ring]
    assert torch.equal(a.data.obs[0, :len(offline)], offline_obs)
    held = {a.data.ring_slot(k): k for k in a.held_online()}
    for slot, k in held.items():
        assert torch.equal(a.data.obs[0, slot], torch.from_numpy(rows.obs[k]))
    assert a.n_human == int((rows.source == SOURCE_HUMAN).sum())  # evicted ones counted too
    # update j samples transitions [j + 1 - capacity, j + 1): all still held
    for bound in (a.n_evicted + 30, 300, 400):
        idx = a.sampler.next(bound)[0]
        online = [held[int(s)] for s in idx if int(s) >= len(offline)]
        assert online and all(max(0, bound - 30) <= k < bound for k in online), (bound, online)
    b = _learner(offline, prior, utd=1, capacity=30)
    vb = []
    burst = LAG_VERSIONS * 10 - 10  # arrives before the learner takes any of its updates
    for start in range(0, len(rows), burst):
        for i in range(start, min(start + burst, len(rows))):
            b.add(rows.select(np.array([i])))
        while b.updates_owed > 0:
            b.train(max_updates=7)
            if b.version_due():
                vb.append(b.cut_version())
    assert len(va) == len(vb) == 40
    assert all(torch.equal(_flat(x), _flat(y)) for x, y in zip(va, vb))


@pytest.mark.slow
def test_a_two_hour_realtime_session_runs_on_a_small_buffer(tmp_path, files):
    """50 Hz for two hours (360,000 live transitions) into a learner holding 1,000, with a
    learner far slower than the stream: nothing raises, the newest transitions are held, the
    resume point stays small and resumes. The stream arrives in bursts (the node's own path,
    raw messages into the service, for the last of each burst: decoding 360,000 one by one
    would be most of the test's time)."""
    from offline_rl_core.data.bag.cdr import encode_transition_rows
    from offline_rl_core.data.transitions import LAYOUT_SLICES, Transitions

    d, _ = files
    live = _stream(4000, seed=7).to_rows()
    n = 2 * 3600 * 50
    rows = np.tile(live, (n // len(live), 1))
    rows[:, LAYOUT_SLICES["episode"]] = (np.arange(n) // 100)[:, None]
    rows[:, LAYOUT_SLICES["step"]] = (np.arange(n) % 100)[:, None]
    cfg = dict(settings=OnlineSettings(publish_every=50, capacity=1000))
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "long", **cfg)
    versions = 0
    for start in range(0, n, 5000):
        service.learner.add(Transitions.from_rows(rows[start:start + 4990]))
        for payload in encode_transition_rows(rows[start + 4990:start + 5000]):
            assert service.receive(payload) is None
        versions += len(service.work(budget_s=0.05))
    status = service.status()
    learner = service.learner
    assert status["received"] == n and status["evicted"] == n - learner.data.ring_rows
    newest = learner.data.ring_slot(n - 1)
    assert torch.equal(learner.data.obs[0, newest], torch.from_numpy(rows[n - 1, :8].copy()))
    assert learner.updates > 0 and versions >= 1 and status["weights_version"] == versions
    path = service.save()
    assert path.stat().st_size < 8 << 20  # the ring's rows, not the session's
    again = _service(tmp_path, d / "offline.db3", d / "prior.pt", "long", resume=True, **cfg)
    assert again.learner.n_online == n and again.learner.updates == learner.updates
    assert torch.equal(again.learner.data.obs, learner.data.obs)


def test_while_the_estop_is_engaged_the_learner_trains_on_no_live_transition(tmp_path, files):
    from offline_rl_core.data.bag.cdr import encode_transition_rows

    d, stream = files
    service = _service(tmp_path, d / "offline.db3", d / "prior.pt", "estop")
    payloads = encode_transition_rows(stream.to_rows()[:4])
    assert service.receive(payloads[0]) is None
    service.estop.on_estop(True)
    assert [service.receive(p).reason for p in payloads[1:3]] == ["estop", "estop"]
    assert service.learner.n_online == 1 and service.status()["estop"]["engaged"]
    assert service.status()["rejected"] == {"estop": 2}
    service.estop.on_estop(False)
    assert service.estop.reset()[0]
    assert service.receive(payloads[3]) is None and service.learner.n_online == 2


def test_imitate_expert_keeps_the_actor_near_the_demonstrations(offline, prior):
    """With ``imitate_expert`` the actor's BC term also covers the offline data's expert rows
    (TD3+BC's anchor on demonstrations): after the same updates, on the same stream, the
    actor is nearer the expert's actions than without it, and only the expert rows count."""
    from offline_rl_core.data.transitions import SOURCE_EXPERT
    from offline_rl_core.serving.policy import LoadedPolicy

    rows = _stream(200)
    expert = offline.source == SOURCE_EXPERT
    errors = {}
    for imitate in (False, True):
        learner = _learner(offline, prior, imitate_expert=imitate)
        marked = learner.data.human[0, :len(offline), 0].numpy().astype(bool)
        assert np.array_equal(marked, expert | (offline.source == SOURCE_HUMAN)) if imitate else not marked.any()
        _feed(learner, rows)
        policy = LoadedPolicy(learner.weights())
        errors[imitate] = float(np.mean((policy.act(offline.obs[expert]) - offline.action[expert]) ** 2))
    assert errors[True] < errors[False], errors


def test_critic_warmup_fits_the_critic_alone_before_the_first_update_and_resumes_exactly(offline, prior):
    """``critic_warmup``: before its first update the learner fits the critic alone on the
    offline data (the actor still the prior's), once; a learner saved before that and
    resumed ends with the same weights as one never stopped."""
    rows = _stream(30)
    learner = _learner(offline, prior, critic_warmup=40)
    actor_before = _flat(learner.weights())
    critic_before = [t.clone() for t in learner.learner.critic.online.parameters()]
    learner.add(rows.select(np.array([0])))
    learner._warm_up_critic()
    assert learner.warmup_done == 40 and learner.updates == 0
    assert torch.equal(_flat(learner.weights()), actor_before)  # the actor did not move
    assert any(not torch.equal(a, b) for a, b in zip(critic_before, learner.learner.critic.online.parameters()))
    learner._warm_up_critic()  # once only
    assert learner.warmup_done == 40

    straight = _learner(offline, prior, critic_warmup=40)
    _feed(straight, rows)
    stopped = _learner(offline, prior, critic_warmup=40)
    saved = stopped.state()  # a resume point before the first update
    resumed = _learner(offline, prior, critic_warmup=40)
    resumed.restore(saved)
    _feed(resumed, rows)
    assert torch.equal(_flat(resumed.weights()), _flat(straight.weights()))
    assert resumed.state()["critic_warmup_done"] == 40
    plain = _learner(offline, prior)
    _feed(plain, rows)
    assert not torch.equal(_flat(plain.weights()), _flat(straight.weights()))
    with pytest.raises(ValueError, match="critic_warmup must be >= 0"):
        OnlineSettings(critic_warmup=-1)


def test_normalize_obs_learns_on_z_scored_rows_and_serves_raw_observations(offline, prior, tmp_path):
    """``normalize_obs``: the networks learn on observations z-scored by the offline data's
    statistics (offline and live rows alike), yet every weights version takes raw observations:
    version 0 acts as the prior does, and a resumed learner still ends on the same bytes."""
    from offline_rl_core.serving.policy import LoadedPolicy

    cfg = TrainConfig(algo="sac", normalize_obs=True, **SMALL)
    settings = OnlineSettings(publish_every=10)

    def learner():
        return OnlineLearner(offline, cfg, settings, seed=3, prior=prior)

    rows = _stream(40)
    one = learner()
    held = one.data.obs[0, :len(offline)].numpy()
    assert np.allclose(held.mean(0), 0.0, atol=1e-4) and not np.allclose(offline.obs.mean(0), 0.0, atol=1e-2)
    served, prior_policy = LoadedPolicy(one.weights()), LoadedPolicy(prior)
    assert np.allclose(served.act(offline.obs), prior_policy.act(offline.obs), atol=1e-5)
    _feed(one, rows, 0, 1)
    live = one.data.obs[0, len(offline)].numpy()
    assert np.allclose(live, (rows.obs[0] - one.norm[0]) / one.norm[1], atol=1e-6)
    _feed(one, rows, 1)
    # what is served is what the learner's own (z-scored) actor does
    mean = one.learner.policy(torch.from_numpy((offline.obs - one.norm[0]) / one.norm[1])[None])[0]
    assert np.allclose(LoadedPolicy(one.weights()).act(offline.obs), torch.tanh(mean).detach().numpy(), atol=1e-5)

    first = learner()
    _feed(first, rows, 0, 17)
    torch.save(first.state(), tmp_path / "state.pt")
    resumed = learner()
    resumed.restore(torch.load(tmp_path / "state.pt", weights_only=True))
    _feed(resumed, rows, 17)
    assert torch.equal(_flat(resumed.weights()), _flat(one.weights()))
    plain = _learner(offline, prior)
    _feed(plain, rows)
    assert not torch.equal(_flat(plain.weights()), _flat(one.weights()))
    with pytest.raises(ValueError, match="normalize_obs: no offline transitions"):
        OnlineLearner(offline.select(np.arange(0)), cfg, OnlineSettings(offline_ratio=0.0), seed=3)


def test_a_state_taken_before_its_clock_waits_for_it_and_the_lockstep_steps_stay_whole(tmp_path):
    """On a sim's /clock, the learner stamps each raw message by the tick it was published in
    and, once the stream falls quiet (a lockstep sim waiting for the next weights), flushes
    what waits for a later /clock. A state taken before the /clock published just before it
    must wait for that /clock: stamped by the tick before, the step before it would be handed
    out without its next state, the learner one step short of the sim, and a paced session
    would wait for that step forever."""
    import time

    import velocity_arm as va

    from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig
    from offline_rl_core.task.spec import load_task

    n = 3
    task_file = tmp_path / "arm.yaml"
    task_file.write_text(va.task_yaml(n))
    task = load_task(str(task_file))
    va.record_bag(tmp_path / "offline.db3", task, n, episodes=4, expert_frac=0.5, seed=0)
    service = LearnerService(LearnerServiceConfig(
        bags=[str(tmp_path / "offline.db3")], out=str(tmp_path / "learner"), task=str(task_file), seed=0,
        from_topics=True, sim_time=True, settings=OnlineSettings(publish_every=5),
        train=TrainConfig(algo="sac", **SMALL)), log=lambda s: None)
    msgs, names = va._Messages(), va.joint_names(n)
    rng = np.random.default_rng(0)
    q0, goal = va.sample_reset(n, 11)
    sim0, wall0, tick = va.START_NS, 10**12, va.CONTROL_NS

    def clock(k):
        assert service.receive_clock(wall0 + k * 10**7, sim0 + k * tick) is None

    def state(k):
        q = q0 + 0.01 * k
        raw = msgs.joint_state(sim0 + k * tick, names, q, np.zeros(n))
        assert service.receive_message("/joint_states", "sensor_msgs/msg/JointState", raw, 0,
                                       wall0 + k * 10**7 + 20_000) is None

    def command(k):
        raw = msgs.command(rng.uniform(-1.0, 1.0, n))
        assert service.receive_message("/velocity_controller/commands", "std_msgs/msg/Float64MultiArray", raw, 0,
                                       wall0 + k * 10**7 + 300_000) is None

    def fall_quiet():  # the sim waits for the learner: nothing comes for a while (under quiet_missing)
        service.last_poll = service.last_arrival = service.idle_since = time.monotonic() - 0.2
        service.take_steps()

    service.receive_message("/goal_joints", "sensor_msgs/msg/JointState",
                            msgs.joint_state(sim0, names, goal), 0, wall0 + 10_000)
    for k in range(5):
        clock(k), state(k), command(k)
    state(5)  # before its /clock, published before it: DDS keeps no order between writers
    fall_quiet()
    assert service.publication_clock.clock_behind and service.publication_clock.waiting
    clock(5)
    fall_quiet()
    assert service.learner.n_steps == 5 and service.learner.n_online == 5  # steps 0-4, each with its next state
    assert service.status()["join"]["late"] == 0


def test_lr_decay_brings_the_rates_to_zero_over_the_budget_and_resumes_exactly(offline, prior, tmp_path):
    """``lr_decay_steps``: the optimisers' rates fall along a cosine to about zero at that many
    environment steps (the stage's budget), so the session ends on settled weights; a function
    of the update count alone, so a resumed learner ends on the same bytes."""
    from offline_rl_core.learners.state import optimizers_of

    rows = _stream(40)

    def rates(learner):
        return {float(g["lr"]) for opt in optimizers_of(learner.learner) for g in opt.param_groups}

    one = _learner(offline, prior, lr_decay_steps=40)
    _feed(one, rows, 0, 20)
    assert sorted(rates(one)) == pytest.approx([0.5 * 3e-4], rel=0.05)  # half way: half the rate
    _feed(one, rows, 20)
    assert max(rates(one)) < 1e-6  # the budget's end: about nothing left
    first = _learner(offline, prior, lr_decay_steps=40)
    _feed(first, rows, 0, 17)
    torch.save(first.state(), tmp_path / "state.pt")
    resumed = _learner(offline, prior, lr_decay_steps=40)
    resumed.restore(torch.load(tmp_path / "state.pt", weights_only=True))
    _feed(resumed, rows, 17)
    assert torch.equal(_flat(resumed.weights()), _flat(one.weights())) and rates(resumed) == rates(one)
    constant = _learner(offline, prior)
    _feed(constant, rows)
    assert rates(constant) == {3e-4} and not torch.equal(_flat(constant.weights()), _flat(one.weights()))
    with pytest.raises(ValueError, match="lr_decay_steps must be >= 0"):
        OnlineSettings(lr_decay_steps=-1)


def _feed_labelled(learner, rows, labels):
    for i in range(len(rows)):
        learner.add(rows.select(np.array([i])), labels=labels[i:i + 1])
        while learner.updates_owed > 0:
            learner.train()
            if learner.version_due():
                learner.cut_version()


def test_action_labels_are_imitated_where_the_policy_acted_and_the_critic_keeps_the_action_taken(offline, prior):
    """``add(rows, labels=...)`` (``hil --online --action-labels``): a state the policy acted on
    and a person labelled is imitated toward the label, not toward the policy's action, while the
    row keeps the action the arm took for the critic; an unlabelled row (NaN) stays the policy's
    own, not imitated; the count of labelled rows survives a resume."""
    from offline_rl_core.serving.policy import LoadedPolicy

    rows = _stream(200)
    rows.source[:] = SOURCE_POLICY
    target = np.tile(np.array([[0.8, -0.6]], np.float32), (len(rows), 1))
    labels = target.copy()
    labels[1::2] = np.nan  # every other state unlabelled
    learner = _learner(offline, prior, offline_ratio=0.0)
    first = learner.n_offline
    _feed_labelled(learner, rows, labels)
    held = slice(first, first + len(rows))
    assert torch.equal(learner.data.action[0, held], torch.from_numpy(rows.action))  # the critic's: the arm's
    assert np.array_equal(learner.data.label[0, held][::2].numpy(), target[::2])
    assert np.array_equal(learner.data.label[0, held][1::2].numpy(), rows.action[1::2])
    assert learner.data.human[0, held, 0].numpy().tolist() == [1.0, 0.0] * (len(rows) // 2)
    assert learner.n_labelled == len(rows) // 2 and learner.n_human == 0

    unlabelled = _learner(offline, prior, offline_ratio=0.0)
    _feed(unlabelled, rows)
    gap = {name: float(np.mean((LoadedPolicy(ln.weights()).act(rows.obs) - target) ** 2))
           for name, ln in (("labelled", learner), ("unlabelled", unlabelled))}
    assert gap["labelled"] < 0.5 * gap["unlabelled"], gap

    resumed = _learner(offline, prior, offline_ratio=0.0)
    resumed.restore(learner.state())
    assert resumed.n_labelled == learner.n_labelled
    assert torch.equal(resumed.data.label[0, held], learner.data.label[0, held])


def test_the_stage_with_action_labels_learns_from_the_correctors_labels(offline, prior):
    """In process, ``labels``: every state the corrector leaves to the policy is labelled with
    the corrector's action (counted), takeovers are a person's as before, and the run's config
    says so; without it nothing is labelled."""
    runs = {}
    for labels in (False, True):
        cfg = OnlineRunConfig(env_steps=200, seed=0, eval_every=200, eval_episodes=2, labels=labels,
                              settings=OnlineSettings(publish_every=20), train=TrainConfig(algo="sac", **SMALL))
        runs[labels] = run_online(offline, prior, cfg, log=lambda s: None)
    counts = runs[True]["counts"]
    assert counts["labelled"] == counts["steps"] - counts["human"] > 0
    assert "labelled" not in runs[False]["counts"] and runs[True]["config"]["labels"] is True
    assert counts["human"] > 0  # the takeovers are still a person's
