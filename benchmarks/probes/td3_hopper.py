"""A peer for IPG's off-policy end: Stable-Baselines3 TD3 on Hopper-v5, its training return.

Where IPG's off-policy end lags PPO-KL at 300k steps, is that our learner, or what a TD3-like
learner does at that budget? TD3 with its author's settings (Fujimoto et al. 2018 and their
repository: 256x256, Adam 3e-4, batch 256, tau 0.005, gamma 0.99, exploration noise 0.1, policy
delay 2, target smoothing 0.2 clipped at 0.5) and our rows' 10,000 steps of uniform actions
first. Needs Stable-Baselines3, so it runs in a virtual environment of its own that has it and
``gymnasium[mujoco]==1.4.0`` (for Hopper's imports):

    OMP_NUM_THREADS=1 $ANCHOR_PY benchmarks/probes/td3_hopper.py --seed 1 \\
        --steps 153600 --out benchmarks/runs/screens/td3

Writes ``DIR/td3_seed{S}.json`` (every training episode's end step and return, the wall time)
and prints the last-100 training return at every 25,600 steps, as ``results.md`` reads ours.
"""

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import TD3
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import NormalActionNoise


class Episodes(BaseCallback):
    """Every finished training episode's (step, return), from RecordEpisodeStatistics."""

    def __init__(self):
        super().__init__()
        self.episodes = []

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self.episodes.append((self.num_timesteps, float(info["episode"]["r"])))
        return True


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--steps", type=int, default=300_000)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/runs/screens/td3"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = gym.wrappers.RecordEpisodeStatistics(gym.make("Hopper-v5"))
    noise = NormalActionNoise(np.zeros(3), 0.1 * np.ones(3))
    model = TD3(
        "MlpPolicy",
        env,
        learning_rate=3e-4,
        buffer_size=1_000_000,
        learning_starts=10_000,
        batch_size=256,
        tau=0.005,
        gamma=0.99,
        action_noise=noise,
        policy_kwargs=dict(net_arch=[256, 256]),
        seed=args.seed,
        device="cpu",
    )
    episodes, start = Episodes(), time.time()
    model.learn(total_timesteps=args.steps, callback=episodes)
    wall = time.time() - start
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"seed": args.seed, "steps": args.steps, "wall_s": wall, "episodes": episodes.episodes}
    (args.out / f"td3_seed{args.seed}.json").write_text(json.dumps(result))
    steps, returns = np.array(episodes.episodes).T
    for at in [*range(25_600, args.steps, 25_600), args.steps]:
        print(f"{at:>7,}: last-100 training return {returns[steps <= at][-100:].mean():,.0f}")
    print(f"{args.steps / wall:.0f} steps/s")
