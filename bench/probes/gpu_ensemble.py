"""Probe (not part of `make bench`): AWAC steps/s on a GPU with the CUDA graph, one seed
against three seeds trained as one ensemble. Run on a CUDA machine from the repo root:
`python bench/probes/gpu_ensemble.py`. Figures: bench/RESULTS.md, "GPU"."""
import time, torch
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds
data = collect_transitions(200, 0.3, 0)
def rate(seeds, steps=2000):
    last = {}
    train_seeds(data, TrainConfig(algo="awac", steps=steps, log_every=steps, device="cuda"), seeds,
                progress=lambda p: last.update(e=p.elapsed_s))
    return steps / last["e"]
rate([0], 200)
for rep in range(2):
    one = rate([0]); three = rate([0, 1, 2])
    print(f"awac cuda_graph batched: 1 seed {one:.0f} steps/s; 3 seeds {three:.0f} steps/s = {3*three:.0f} member-steps/s ({3*three/one:.2f}x)", flush=True)
