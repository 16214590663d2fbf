"""Serving figures: in-process policy inference latency, and the policy node's round
trip over DDS against a bare rclpy echo node on the same topics and rate."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ..learners import TrainConfig, train_seeds
from ..serving.checkpoint import save_checkpoint
from ..serving.policy import LoadedPolicy
from ..runs import chapter_loop as chapter
from .harness import BenchSettings, figure, pending, percentile
from .ros_procs import PROBES, bench_node, isolate, ros2_command, ros_missing, run_probe


def trained_checkpoint(s: BenchSettings) -> dict:
    from ..data.collect import collect_transitions

    data = collect_transitions(max(2, s.episodes // 20), 0.3, 0)
    return train_seeds(data, TrainConfig(algo="bc", steps=max(2, s.train_steps // 5), hidden=s.hidden,
                                         batch_size=s.batch_size), [0])[0].checkpoint


def latencies_ms(fn, obs: np.ndarray, calls: int) -> np.ndarray:
    out = np.empty(calls)
    clock = time.perf_counter
    for i in range(calls):
        x = obs[i % len(obs)]
        t0 = clock()
        fn(x)
        out[i] = clock() - t0
    return out * 1e3


def inference_figures(s: BenchSettings, checkpoint: dict, log=print) -> list:
    policy = LoadedPolicy(checkpoint)
    net = chapter.Policy(policy.obs_dim, policy.act_dim, policy.hidden)
    net.net.load_state_dict({k: v.float() for k, v in checkpoint["policy_state"].items()})
    net.eval()

    @torch.no_grad()
    def torch_act(x):
        return net(torch.as_tensor(x).unsqueeze(0))[0].numpy()

    contenders = {"numpy": policy.act, "torch": torch_act}
    try:
        import onnxruntime as ort

        from ..serving.onnx_export import export_onnx
    except Exception:
        ort = None
    if ort is not None:
        with tempfile.TemporaryDirectory() as tmp:
            path = export_onnx(policy, Path(tmp) / "p.onnx")
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        name = sess.get_inputs()[0].name
        contenders["onnxruntime"] = lambda x: sess.run(None, {name: x[None, :]})[0][0]
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((256, policy.obs_dim)).astype(np.float32)
    for fn in contenders.values():  # warm-up
        latencies_ms(fn, obs, 200)
    got = {k: [] for k in contenders}
    rounds = 4
    for _ in range(rounds):  # interleaved quarters
        for k, fn in contenders.items():
            got[k].append(latencies_ms(fn, obs, max(1, s.inference_calls // rounds)))
    p99 = {k: percentile(np.concatenate(v), 99) for k, v in got.items()}
    p50 = {k: percentile(np.concatenate(v), 50) for k, v in got.items()}
    log("  inference p99 ms: " + ", ".join(f"{k} {v:.4f}" for k, v in p99.items()))
    figs = [figure("serve", "inference_p99_ms_numpy_vs_torch", "ms", p99["numpy"], p99["torch"],
                   "torch module forward (chapter policy)", higher_is_better=False,
                   target=lambda o, r, x: o < 0.1, target_text="< 0.1 ms",
                   note=f"LoadedPolicy.act, one observation, hidden {policy.hidden}; p50 {p50['numpy']:.4f} ms",
                   extra={"p50_ms": {k: round(v, 5) for k, v in p50.items()}})]
    if "onnxruntime" in p99:
        figs.append(figure("serve", "inference_p99_ms_numpy_vs_onnxruntime", "ms", p99["numpy"], p99["onnxruntime"],
                           "ONNX Runtime session (1 thread)", higher_is_better=False, target_text="(info)"))
    return figs


# ----------------------------------------------------------------------------- DDS round trip

def _round_trip(n: int, rate_hz: float, log=print) -> dict:
    """Time ``n`` states at ``rate_hz`` answered on /policy/action (in the DDS probe process)."""
    return run_probe(["round-trip", n, rate_hz], timeout=120 + 2 * n / rate_hz)


def dds_figures(s: BenchSettings, checkpoint: dict, log=print) -> list:
    name = f"dds_round_trip_p99_ms_{s.dds_messages}_at_{s.dds_rate_hz:g}hz"
    why = ros_missing()
    if why:
        return [pending("serve", name, "ms", "bare rclpy echo node", why, "within 0.3 ms of echo; 0 lost")]
    isolate()
    with tempfile.TemporaryDirectory(prefix="bench_serve_") as tmp:
        tmp = Path(tmp)
        ckpt = tmp / "policy.pt"
        save_checkpoint(ckpt, checkpoint)
        import sys

        results = {}
        for label, argv in (("echo", [sys.executable, str(PROBES), "echo"]),
                            ("policy", [ros2_command(), "run", "policy", "node", "--checkpoint", str(ckpt)])):
            with bench_node(argv, tmp / f"{label}.log") as proc:
                try:
                    results[label] = _round_trip(s.dds_messages, s.dds_rate_hz, log)
                except Exception as exc:
                    raise RuntimeError(f"{label}: {exc}; node log: {proc.output()[-600:]}") from exc
        log("  DDS round trip: " + "; ".join(f"{k} p50 {v['p50_ms']:.3f} p99 {v['p99_ms']:.3f} ms lost {v['lost']}"
                                             for k, v in results.items()))
    pol, echo = results["policy"], results["echo"]
    return [figure("serve", name, "ms", pol["p99_ms"], echo["p99_ms"], "bare rclpy echo node", higher_is_better=False,
                   target=lambda o, r, x: o - r <= 0.3 and pol["lost"] == 0,
                   target_text="<= echo + 0.3 ms, 0 lost",
                   note=f"policy node lost {pol['lost']} of {pol['sent']}, echo lost {echo['lost']}; "
                        f"p50 {pol['p50_ms']:.3f} vs {echo['p50_ms']:.3f} ms",
                   extra={"policy": pol, "echo": echo})]


def run(s: BenchSettings, log=print) -> list:
    checkpoint = trained_checkpoint(s)
    figs = inference_figures(s, checkpoint, log)
    try:
        figs.extend(dds_figures(s, checkpoint, log))
    except Exception as exc:
        figs.append(pending("serve", "dds_round_trip_p99_ms", "ms", "bare rclpy echo node",
                            f"failed: {type(exc).__name__}: {exc}"[:500], "within 0.3 ms of echo; 0 lost", "skipped"))
    return figs
