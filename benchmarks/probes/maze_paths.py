"""Where does a maze run fall short: goals a straight line away, or goals behind walls?

    python benchmarks/probes/maze_paths.py RUN_FOLDER [RUN_FOLDER ...] [--episodes 200]

Reads each run folder's ``resume.pt`` (its policy at the last resume point) and plays fresh
episodes (reset seeds 1000, 1001, ...) with the mean action, as evaluation does. For each episode
it takes the maze cells of the start and of the goal and counts the cells of the shortest path
between them through the open cells (breadth-first, four neighbours). Prints, per path length,
how many episodes, the share that ended at the goal (the evaluation's success), and the share
that touched the goal at any step (a maze episode runs on after it is reached).
"""

import argparse
import collections
import os
import sys

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
from common import checkpoint  # noqa: E402
from common.evaluate import Policy  # noqa: E402


def path_length(maze_map, start: tuple[int, int], goal: tuple[int, int]) -> int:
    """Moves between open cells (0 in ``maze_map``) on the shortest path from start to goal."""
    seen, queue = {start: 0}, collections.deque([start])
    while queue:
        cell = queue.popleft()
        if cell == goal:
            return seen[cell]
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            r, c = cell[0] + dr, cell[1] + dc
            if maze_map[r][c] != 1 and (r, c) not in seen:
                seen[(r, c)] = seen[cell] + 1
                queue.append((r, c))
    raise ValueError(f"no path from {start} to {goal}")


def by_length(lengths, ended, touched) -> dict[int, tuple[int, float, float]]:
    """Per path length: episodes, the share that ended at the goal, the share that touched it."""
    lengths, ended, touched = map(np.asarray, (lengths, ended, touched))
    return {int(n): (int((lengths == n).sum()), ended[lengths == n].mean(),
                     touched[lengths == n].mean()) for n in np.unique(lengths)}  # fmt: skip


def play(policy: Policy, seeds: list[int]):
    env = gym.make(policy.env_id)
    maze = env.unwrapped.maze
    lengths, ended, touched = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        cells = [tuple(maze.cell_xy_to_rowcol(obs[k])) for k in ("achieved_goal", "desired_goal")]
        lengths.append(path_length(maze.maze_map, *cells))
        done, reached = False, False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            done, reached = terminated or truncated, reached or bool(info["success"])
        ended.append(float(info["success"]))
        touched.append(float(reached))
    env.close()
    return lengths, ended, touched


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = list(range(1000, 1000 + args.episodes))
    for run in args.runs:
        saved = checkpoint._read(os.path.join(run, checkpoint.RESUME_FILE))
        policy = Policy({**saved, "last_eval_seeds": [], "normalizer_class": "InputNormalizer"},
                        saved["args"]["env_id"])  # fmt: skip
        lengths, ended, touched = play(policy, seeds)
        print(f"{os.path.basename(os.path.normpath(run))}: ended at the goal {np.mean(ended):.2f}, "
              f"touched it {np.mean(touched):.2f}")  # fmt: skip
        print("  cells on the path | episodes | ended at the goal | touched the goal")
        for n, (count, end, touch) in by_length(lengths, ended, touched).items():
            print(f"  {n:17d} | {count:8d} | {end:17.2f} | {touch:.2f}")
