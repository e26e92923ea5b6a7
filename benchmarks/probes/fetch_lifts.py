"""Where a FetchPickAndPlace run falls short: goals on the table against goals in the air, and how
often its training episodes held the object up at all (what HER can relabel into a lift).

    python benchmarks/probes/fetch_lifts.py RUN_FOLDER [--episodes 200]

RUN_FOLDER is an ``ipg_her_recipe.py`` run folder with a ``resume.pt`` (``--resume-freq``).
Prints the deterministic policy's success on fresh episodes, split by where the goal is, and the
share of the replay buffer's episodes, in fifths of training, where the object stayed at least
``HELD_CM`` above its start for ``HELD_STEPS`` of its 50 steps (a grasp and a lift, not a knock).
The buffer is read in the order it was written, so for runs of at most ``--buffer-size`` steps
(no wrap).
"""

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the project root
from common import checkpoint, tasks  # noqa: E402
from common.evaluate import Policy  # noqa: E402

HELD_CM, HELD_STEPS, EPISODE = 2.0, 10, 50


def held(heights: np.ndarray) -> np.ndarray:
    """Per episode (rows of object heights over its steps): up by HELD_CM for HELD_STEPS steps."""
    return ((heights - heights[:, :1]) > HELD_CM / 100).sum(1) >= HELD_STEPS


def replay_lifts(rb: dict, parts: int = 5) -> list[float]:
    """The share of held lifts among the replay buffer's episodes, in ``parts`` slices of time."""
    heights = np.asarray(rb["achieved_goal"])[..., 2]  # (steps, envs)
    steps = heights.shape[0] // EPISODE * EPISODE
    episodes = heights[:steps].reshape(-1, EPISODE, heights.shape[1]).transpose(0, 2, 1)
    lifts = held(episodes.reshape(-1, EPISODE))  # time-ordered: episode-major, env-minor
    return [part.mean().item() for part in np.array_split(lifts, parts)]


def policy_by_goal(policy: Policy, env_id: str, seeds: range) -> dict:
    """The deterministic policy's success and held lifts, for goals on the table and in the air."""
    env, rows = gym.make(env_id), []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        heights = [obs["achieved_goal"][2]]
        in_air = obs["desired_goal"][2] - heights[0] > 0.01  # the table's goals sit at its height
        for _ in range(EPISODE):
            obs, _, _, _, info = env.step(policy(obs))
            heights.append(obs["achieved_goal"][2])
        rows.append((in_air, info["is_success"], held(np.array([heights]))[0]))
    env.close()
    r = np.array(rows, float)
    return {
        where: {"episodes": int(m.sum()), "success": r[m, 1].mean(), "held": r[m, 2].mean()}
        for where, m in (("table", r[:, 0] == 0), ("air", r[:, 0] == 1))
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_folder")
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    content = checkpoint.load(str(Path(args.run_folder) / "resume.pt"))
    env_id = content["args"]["env_id"]
    tasks.register_goal_tasks()
    policy = Policy(content, env_id)  # checkpoint.load names a resume.pt's normaliser
    print(f"{env_id}, {content['global_step']:,} steps: the deterministic policy")
    for where, r in policy_by_goal(policy, env_id, range(10**6, 10**6 + args.episodes)).items():
        print(f"  goals {where:5}: {r['episodes']:3} episodes, success {r['success']:.2f}, object held up {r['held']:.2f}")
    fifths = " / ".join(f"{share:.3f}" for share in replay_lifts(content["rb"]))
    print(f"training episodes with the object held up, by fifths of training: {fifths}")
