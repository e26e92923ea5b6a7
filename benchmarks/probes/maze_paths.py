"""Where does a maze run fall short: goals a straight line away, or goals behind walls?

    python benchmarks/probes/maze_paths.py RUN_FOLDER [RUN_FOLDER ...] [--episodes 200]

Loads each run folder's policy (its model.pt or resume.pt, ``common.evaluate.load_policy``)
and plays fresh episodes (reset seeds 1000, 1001, ...) with the mean action, as evaluation does.
For each episode it takes the maze cells of the start and of the goal and counts the cells of the
shortest path between them through the open cells (breadth-first, four neighbours). Prints, per
path length, how many episodes, the share that ended at the goal (the evaluation's success), the
share that touched the goal at any step (a maze episode runs on after it is reached), and the
median step of the first touch among those (what the discount makes of the goal: gamma ** steps).
"""

import argparse
import collections
import os
import sys

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
from common.evaluate import Policy, load_policy  # noqa: E402


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


def by_length(lengths, ended, first) -> dict[int, tuple[int, float, float, float]]:
    """Per path length: episodes, the share that ended at the goal, the share that touched it,
    the median step of the first touch (``first``: that step, or -1 for never; nan if none)."""
    lengths, ended, first = map(np.asarray, (lengths, ended, first))
    table = {}
    for n in np.unique(lengths):
        f = first[lengths == n]
        steps = np.median(f[f >= 0]) if (f >= 0).any() else np.nan
        table[int(n)] = (len(f), ended[lengths == n].mean(), (f >= 0).mean(), steps)
    return table


def play(policy: Policy, seeds: list[int]):
    env = gym.make(policy.env_id)
    maze = env.unwrapped.maze
    lengths, ended, first = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        cells = [tuple(maze.cell_xy_to_rowcol(obs[k])) for k in ("achieved_goal", "desired_goal")]
        lengths.append(path_length(maze.maze_map, *cells))
        done, step, reached = False, 0, -1
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            done, step = terminated or truncated, step + 1
            reached = step if reached < 0 and info["success"] else reached
        ended.append(float(info["success"]))
        first.append(reached)
    env.close()
    return lengths, ended, first


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = list(range(1000, 1000 + args.episodes))
    for run in args.runs:
        policy = load_policy(run)  # its model.pt or, without --save-model, its resume.pt
        lengths, ended, first = play(policy, seeds)
        print(
            f"{os.path.basename(os.path.normpath(run))}: gamma {policy.args['gamma']}, ended "
            f"at the goal {np.mean(ended):.2f}, touched it {np.mean(np.array(first) >= 0):.2f}"
        )
        print("  cells on the path | episodes | ended at the goal | touched it | first touch")
        for n, (count, end, touch, steps) in by_length(lengths, ended, first).items():
            print(f"  {n:17d} | {count:8d} | {end:17.2f} | {touch:10.2f} | {steps:.0f}")
