"""Does a run's policy mean leave the action bounds, and when did its executed actions reach them?

    python benchmarks/probes/mean_bounds.py RUN_FOLDER [RUN_FOLDER ...] [--window 20000]

The critic is fed the executed action, clipped to the bounds, so beyond them it gives mu no
gradient. Reads each run folder's ``resume.pt`` (its last resume point: the policy, the
normaliser and the replay buffer, loaded as data) and prints, per window of environment steps
replayed, two numbers: the share of the last policy's mean components mu_i(s) beyond the bounds on
that window's states, and the mean |a_i| of the actions the run executed then (at most 1, on the
Fetch and hand tasks' [-1, 1]).
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
from common import checkpoint  # noqa: E402
from common.evaluate import Policy  # noqa: E402


def windows(policy, rb: dict, global_step: int, window: int) -> list[tuple[int, float, float]]:
    """(last environment step of the window, share of mu's components beyond the bounds, mean |a|) per
    ``window`` environment steps in the replay buffer ``rb`` (as saved at ``global_step``), oldest first."""
    filled, num_envs = rb["filled"], rb["obs"].shape[1]
    order = (np.arange(filled) + (rb["pos"] if filled == len(rb["obs"]) else 0)) % len(rb["obs"])  # oldest first
    first_step = global_step - filled * num_envs
    rows, per = [], max(1, window // num_envs)
    for start in range(0, filled - per + 1, per):
        rows_ = order[start : start + per]
        raw = {"observation": rb["obs"][rows_].reshape(-1, rb["obs"].shape[-1])}
        if "desired_goal" in rb:
            raw["desired_goal"] = rb["desired_goal"][rows_].reshape(-1, rb["desired_goal"].shape[-1])
        with torch.no_grad():
            mu = policy.actor_mean(policy.normalizer(raw if "desired_goal" in raw else raw["observation"])).numpy()
        beyond = float(((mu < policy.low) | (mu > policy.high)).mean())
        rows.append((first_step + (start + per) * num_envs, beyond, float(np.abs(rb["actions"][rows_]).mean())))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--window", type=int, default=20_000, help="environment steps per printed row")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        saved = checkpoint._read(os.path.join(run, checkpoint.RESUME_FILE))
        normalizer = "InputNormalizer" if "obs_rms" in saved["normalizer"] else "RunningMeanStd"
        policy = Policy({**saved, "last_eval_seeds": [], "normalizer_class": normalizer}, saved["args"]["env_id"])
        print(f"{os.path.basename(os.path.normpath(run))}: the last policy's mu beyond the bounds, executed |a|")
        for step, beyond, executed in windows(policy, saved["rb"], saved["global_step"], args.window):
            print(f"  to {step:>9,}: mu beyond {beyond:.2f}, |a| {executed:.2f}")
