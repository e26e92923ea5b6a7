"""Seconds per PPO-KL update, as ``ppo_kl.py`` runs it and compiled with ``torch.compile``.

One update is ``update_epochs`` x ``num_minibatches`` Adam steps (320 with the defaults) on a
Hopper-sized batch (11 observations, 3 actions, 2,048 samples) of random data: the cost does not
depend on the values. This is the measurement behind PPO-KL's speed paragraph in
docs/benchmarks.md: whether a compiled training step would buy the throughput that the eager one
lacks.

    python benchmarks/probes/update_speed.py --modes eager compile
"""

import json
import os
import sys
import time
from dataclasses import dataclass
from typing import Literal

import torch
import tyro

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
import ppo_kl  # noqa: E402


@dataclass
class Args:
    modes: tuple[Literal["eager", "compile"], ...] = ("eager", "compile")
    """eager: ppo_kl.ppo_kl_update as is; compile: torch.compile(ppo_kl.ppo_kl_update)"""
    repeats: int = 8
    """timed updates per mode, after one untimed first call (which compiles)"""
    obs_dim: int = 11
    act_dim: int = 3


def time_updates(mode: str, args: Args) -> dict:
    torch.manual_seed(0)
    ppo_args = ppo_kl.Args()
    agent = ppo_kl.Agent(args.obs_dim, args.act_dim, init_log_std=ppo_args.init_log_std)
    optimizer = torch.optim.Adam(agent.parameters(), lr=ppo_args.learning_rate, eps=1e-5, fused=True)
    n = ppo_args.num_envs * ppo_args.num_steps
    b = {
        "obs": torch.randn(n, args.obs_dim),
        "actions": 0.6 * torch.randn(n, args.act_dim),
        "advantages": torch.randn(n),
        "returns": torch.randn(n),
    }
    with torch.no_grad():
        pi = agent.dist(b["obs"])
        b |= {"logprobs": pi.log_prob(b["actions"]).sum(-1), "mean": pi.mean, "std": pi.stddev}
    update = ppo_kl.ppo_kl_update if mode == "eager" else torch.compile(ppo_kl.ppo_kl_update)
    seconds = []
    for _ in range(args.repeats + 1):
        start = time.perf_counter()
        update(agent, optimizer, b, 1.0, ppo_args)
        seconds.append(time.perf_counter() - start)
    first, rest = seconds[0], sorted(seconds[1:])
    return {
        "mode": mode,
        "first_s": round(first, 3),
        "min_s": round(rest[0], 4),
        "median_s": round(rest[len(rest) // 2], 4),
        "minibatch_steps": ppo_args.update_epochs * ppo_args.num_minibatches,
    }


if __name__ == "__main__":
    args = tyro.cli(Args)
    torch.set_num_threads(1)
    for mode in args.modes:
        print(json.dumps(time_updates(mode, args)), flush=True)
