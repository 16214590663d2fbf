"""Probe (not part of `make bench`): AWAC steps/s on a GPU with the CUDA graph, one seed
against three seeds trained as one ensemble. Run on a CUDA machine from the repo root:
`python bench/probes/gpu_ensemble.py --json bench/gpu_ensemble.json` (then
`python bench/results_page.py` puts it on bench/RESULTS.md)."""
import argparse

from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--json", help="write the rounds, the command and the machine here")
args = ap.parse_args()
facts = run_facts()
data = collect_transitions(200, 0.3, 0)


def rate(seeds, steps=2000):
    last = {}
    train_seeds(data, TrainConfig(algo="awac", steps=steps, log_every=steps, device="cuda"), seeds,
                progress=lambda p: last.update(e=p.elapsed_s))
    return steps / last["e"]


rate([0], 200)  # warm-up: the graph's recording
rounds = []
for rep in range(2):
    one = rate([0])
    three = rate([0, 1, 2])
    rounds.append({"one_seed_steps_per_s": round(one, 1), "three_seeds_member_steps_per_s": round(3 * three, 1)})
    print(f"awac cuda_graph batched: 1 seed {one:.0f} steps/s; 3 seeds {three:.0f} steps/s = {3*three:.0f} "
          f"member-steps/s ({3*three/one:.2f}x)", flush=True)
if args.json:
    write_json_atomic(args.json, {"rounds": rounds, **facts})
