"""What the exploration noise costs a run's last policy: its mean against its own Gaussian samples.

    python benchmarks/probes/noise_cost.py RUN_FOLDER [RUN_FOLDER ...] [--episodes 10]

Reads each run folder's ``resume.pt`` (its policy at the last resume point: no ``--save-model``
needed) and plays the same fresh episodes (reset seeds 1000, 1001, ...) with the mean action and
with actions sampled from N(mu, sigma^2), as training does. Prints sigma and both mean returns.
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
from common import checkpoint  # noqa: E402
from common.evaluate import Policy  # noqa: E402

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = list(range(1000, 1000 + args.episodes))
    for run in args.runs:
        saved = checkpoint._read(os.path.join(run, checkpoint.RESUME_FILE))
        normalizer = "InputNormalizer" if "obs_rms" in saved["normalizer"] else "RunningMeanStd"
        policy = Policy({**saved, "last_eval_seeds": [], "normalizer_class": normalizer}, saved["args"]["env_id"])
        mean, _ = policy.evaluate(seeds)
        torch.manual_seed(0)
        sampled, _ = policy.evaluate(seeds, stochastic=True)
        sigma = np.round(policy.log_std.exp().numpy()[0], 2)
        name = os.path.basename(os.path.normpath(run))
        print(f"{name}: sigma {sigma}, mean action {mean.mean():.0f}, sampled {sampled.mean():.0f}")
