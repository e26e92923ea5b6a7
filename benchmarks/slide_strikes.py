"""Where a FetchSlide run falls short: success by how far the puck must slide, where failed slides
stop (short of the goal, past it, or beside it), how hard the puck was struck, and how hard a
scripted strike at the full action strikes it.

    python benchmarks/slide_strikes.py RUN_FOLDER [--episodes 200]

RUN_FOLDER is an ``ipg_her.py`` run folder with a ``resume.pt`` or ``model.pt``. Speeds are the
environment's own velocities (metres per step of 0.04 s) along the puck's line to its goal.
"""

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from common import checkpoint, cli  # noqa: E402
from common.evaluate import Policy  # noqa: E402

ENV_ID, EPISODE, PUCK_VELP, GRIP_VELP = "FetchSlide-v4", 50, slice(14, 16), slice(20, 22)


def slide_outcome(start: np.ndarray, goal: np.ndarray, end: np.ndarray) -> tuple[float, float]:
    """How far the puck went along the start-to-goal line, as a share of that line's length (1:
    level with the goal), and how far it ended beside the line (metres), on the table's plane."""
    line = (goal - start)[:2]
    along = line / np.linalg.norm(line)
    moved = (end - start)[:2]
    return float(moved @ along / np.linalg.norm(line)), float(moved @ [-along[1], along[0]])


def reset(env, seed: int):
    """A fresh episode: its observation, the puck's start, its goal and the unit line between."""
    obs, _ = env.reset(seed=seed)
    start, goal = obs["achieved_goal"].copy(), obs["desired_goal"].copy()
    return obs, start, goal, (goal - start)[:2] / np.linalg.norm((goal - start)[:2])


def puck_speed(obs: dict, along: np.ndarray) -> float:
    o = obs["observation"]  # the puck's velocity is given relative to the gripper's
    return float((o[PUCK_VELP] + o[GRIP_VELP]) @ along)


def policy_strikes(policy, seeds: range) -> np.ndarray:
    """Per episode: distance to slide, success, ``slide_outcome``'s two numbers, and the puck's
    highest speed along the slide (metres per step: how hard it was struck)."""
    env, rows = gym.make(ENV_ID), []
    for seed in seeds:
        obs, start, goal, along = reset(env, seed)
        peak = 0.0
        for _ in range(EPISODE):
            obs, _, _, _, info = env.step(policy(obs))
            peak = max(peak, puck_speed(obs, along))
        rows.append((np.linalg.norm((goal - start)[:2]), info["is_success"],
                     *slide_outcome(start, goal, obs["achieved_goal"]), peak))  # fmt: skip
    env.close()
    return np.array(rows, float)


def replay_slides(rb: dict, since: float = 0.6) -> tuple[float, float]:
    """Of the replay buffer's training episodes after the first ``since`` of them (in the order
    written; runs of at most ``--buffer-size`` steps): the share that slid the puck at least 0.55
    m (the far third of goals) and stayed on the table, and the share that left the table."""

    def episodes(x):  # (steps, envs, ...) -> (episodes in time order, steps, ...)
        x = np.asarray(x)[: len(x) // EPISODE * EPISODE]
        return x.reshape(-1, EPISODE, *x.shape[1:]).swapaxes(1, 2).reshape(-1, EPISODE, x.shape[-1])

    start, end = episodes(rb["achieved_goal"])[:, 0], episodes(rb["next_achieved_goal"])[:, -1]
    late = slice(int(len(start) * since), None)
    start, end = start[late], end[late]
    on_table = end[:, 2] > start[:, 2] - 0.1
    far = np.linalg.norm((end - start)[:, :2], axis=1) >= 0.55
    return float(np.mean(far & on_table)), float(1 - np.mean(on_table))


def scripted_strike(seed: int, run_up: float = 0.1) -> tuple[float, float] | None:
    """What the arm can do: lift 6 cm, go ``run_up`` + 3 cm behind the puck on its line to the
    goal, come down, then 12 steps of the full action along that line. The puck's top speed and
    how far it slid along the line; None if getting behind it moved the puck (or it fell)."""
    env = gym.make(ENV_ID)
    obs, start, goal, along = reset(env, seed)
    behind = start[:2] - (run_up + 0.03) * along
    steps, peak = 0, 0.0
    up = start[2] + 0.06
    waypoints = ((*obs["observation"][:2], up), (*behind, up), (*behind, start[2] + 0.005))
    for target, budget in zip(waypoints, (10, 15, 8), strict=True):
        for _ in range(budget):  # proportional control to each waypoint
            error = np.array(target) - obs["observation"][:3]
            if np.linalg.norm(error) < 0.005:
                break
            obs = env.step(np.r_[np.clip(error * 30, -1, 1), 0.0])[0]
            steps += 1
    if np.linalg.norm(obs["achieved_goal"] - start) > 0.005:
        return None
    strike = np.r_[along / np.abs(along).max(), 0.0, 0.0]  # the full action along the line
    for step in range(EPISODE - steps):
        obs = env.step(strike if step < 12 else np.zeros(4))[0]
        peak = max(peak, puck_speed(obs, along))
    env.close()
    end = obs["achieved_goal"]
    return None if end[2] < start[2] - 0.1 else (peak, float((end - start)[:2] @ along))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_folder")
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cli.register_goal_tasks()
    content = checkpoint.load(args.run_folder)
    r = policy_strikes(Policy(content, ENV_ID), range(3000, 3000 + args.episodes))
    print(f"{args.run_folder}: success {r[:, 1].mean():.2f} over {len(r)} fresh episodes")
    for part in np.array_split(r[np.argsort(r[:, 0])], 3):
        print(f"  slides of {part[0, 0]:.2f}-{part[-1, 0]:.2f} m: success {part[:, 1].mean():.2f}, "
              f"the puck's top speed {np.median(part[:, 4]):.4f} m/step (median)")  # fmt: skip
    fail = r[r[:, 1] == 0]
    short, past = np.mean(fail[:, 2] < 0.9), np.mean(fail[:, 2] > 1.1)
    beside = np.median(np.abs(fail[:, 3]))
    print(f"  failures ({len(fail)}): stopped short (< 0.9 of the way) {short:.2f}, past the goal "
          f"(> 1.1) {past:.2f}, median distance beside the line {beside:.3f} m")  # fmt: skip
    if "rb" in content:  # a resume.pt: what the exploring policy did in training
        far, fell = replay_slides(content["rb"])
        print(f"  training episodes of the last 40% of the replay buffer: slid at least 0.55 m "
              f"{far:.2f}, left the table {fell:.2f}")  # fmt: skip
    scripted = [s for s in map(scripted_strike, range(3000, 3000 + args.episodes // 10)) if s]
    speed, slide = np.median(scripted, axis=0)
    print(f"  a scripted full strike ({len(scripted)} of {args.episodes // 10} episodes): the "
          f"puck's top speed {speed:.4f} m/step, slides {slide:.2f} m (median), at most "
          f"{np.max(scripted, axis=0)[1]:.2f} m")  # fmt: skip
