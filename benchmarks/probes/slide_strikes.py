"""Where a FetchSlide run falls short: success by how far the puck must slide, where failed slides
stop (short of the goal, past it, or beside it), how hard the puck was struck and pushed, what
the exploring policy slid in training, and what scripted pushes do. ``--gains``: the success of
harder pushes on the same aim; ``--critic``: whether the run's critic asks for one.

    python benchmarks/probes/slide_strikes.py RUN_FOLDER [--episodes 200] [--gains 1.1 1.2] \\
        [--critic]

RUN_FOLDER is an ``ipg_her_recipe.py`` run folder with a ``resume.pt`` (``--critic`` needs one) or a
``model.pt``. Speeds are the environment's own velocities (metres per step of 0.04 s) along the
puck's line to its goal.
"""

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the project root
import ipg_her_recipe  # noqa: E402
from common import checkpoint, tasks  # noqa: E402
from common.evaluate import Policy  # noqa: E402

ENV_ID, EPISODE, PUCK_VELP, GRIP_VELP = "FetchSlide-v4", 50, slice(14, 16), slice(20, 22)
MOVED, PUSH = 0.005, 5  # metres the puck must move to count as struck; steps of a push


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


def follow(env, obs: dict, start, along, act, steps: int):
    """Step ``act(obs, step)`` ``steps`` times. The last observation and info, and how the puck
    was struck: its highest speed along the line, the gripper's speed along it as the step that
    first moved the puck began (how fast it came in), and over the ``PUSH`` steps from that one
    the mean action along the line (1: the full push, ``along / max |along|``), on the line's
    main axis (1: at the bound) and how far the other axis is from the full push's, on average."""
    peak, speed, came_in, pushes = 0.0, 0.0, None, []
    main, full = np.argmax(np.abs(along)), along / np.abs(along).max()
    for step in range(steps):
        action = act(obs, step)
        obs, _, _, _, info = env.step(action)
        peak = max(peak, puck_speed(obs, along))
        if pushes or np.linalg.norm(obs["achieved_goal"] - start) > MOVED:
            came_in = speed if came_in is None else came_in
            a = action[:2]
            pushes.append((a @ along / (full @ along), a[main] / full[main], abs(a[1 - main] - full[1 - main])))
        speed = float(obs["observation"][GRIP_VELP] @ along)
    pushed = np.mean(pushes[:PUSH], axis=0) if pushes else np.zeros(3)
    return obs, info, (peak, came_in or 0.0, *pushed)


def with_gain(policy, start: np.ndarray, gain: float):
    """``follow``'s ``act``: the policy, its x and y action times ``gain`` (clipped to the bounds)
    once the puck has moved from ``start``."""

    def act(obs: dict, _step: int) -> np.ndarray:
        a = policy(obs)  # float32: float64 actions alone change the outcomes (slides are chaotic)
        if gain != 1 and np.linalg.norm(obs["achieved_goal"] - start) > MOVED:
            a = np.clip(a * np.array([gain, gain, 1, 1], a.dtype), -1, 1)
        return a

    return act


def policy_strikes(policy, seeds: range, gain: float = 1.0) -> np.ndarray:
    """Per episode: distance to slide, success, ``slide_outcome``'s two numbers and ``follow``'s
    five (speeds in metres per step); ``gain``: ``with_gain``'s."""
    env, rows = gym.make(ENV_ID), []
    for seed in seeds:
        obs, start, goal, along = reset(env, seed)
        obs, info, struck = follow(env, obs, start, along, with_gain(policy, start, gain), EPISODE)
        rows.append(
            (
                np.linalg.norm((goal - start)[:2]),
                info["is_success"],
                *slide_outcome(start, goal, obs["achieved_goal"]),
                *struck,
            )
        )
    env.close()
    return np.array(rows, float)


def critic(content: dict) -> torch.nn.Module:
    """The run's critic Q_w from its ``resume.pt``, as ``ipg_her_recipe.py`` built it."""
    a, state = content["args"], content["qf"]
    qf = ipg_her_recipe.QNetwork(
        state["net.0.weight"].shape[1] - 4, 4, a["hidden"], -np.ones(4), np.ones(4), a.get("twin_critic", False)
    )
    qf.load_state_dict(state)
    return qf


def critic_at_contact(qf, policy, seeds: range, gain: float = 1.2) -> np.ndarray:
    """Does the critic want a harder push? At the step whose action first moves the puck, per
    episode: distance to slide, Q_1's slope along the line (dQ_1/da . the line), Q_1 of that
    action with x and y times ``gain`` (clipped) minus Q_1 of it, and the action along the line."""
    env, rows, scale = gym.make(ENV_ID), [], torch.tensor([gain, gain, 1, 1])
    for seed in seeds:
        obs, start, goal, along = reset(env, seed)
        for _ in range(EPISODE):
            x, a = policy.inputs(obs).float(), torch.tensor(policy(obs))[None].requires_grad_()
            q = qf(x, a)
            slope = torch.autograd.grad(q.sum(), a)[0][0, :2].numpy() @ along
            with torch.no_grad():
                harder = (qf(x, torch.clamp(a * scale, -1, 1)) - q).item()
            action = a[0].detach().numpy()
            obs = env.step(action)[0]
            if np.linalg.norm(obs["achieved_goal"] - start) > MOVED:
                break
        rows.append((np.linalg.norm((goal - start)[:2]), slope, harder, action[:2] @ along))
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


def scripted_strike(seed: int, push=1.0, hold=12, height=0.005, behind=0.13):
    """What the arm can do: lift 6 cm, go ``behind`` metres behind the puck on its line to the
    goal, come down to ``height`` above its centre, then ``hold`` steps of ``push`` times the full
    action along that line. How far the puck slid along the line and ``follow``'s five; None if
    getting behind it moved the puck (or the puck fell)."""
    env = gym.make(ENV_ID)
    obs, start, goal, along = reset(env, seed)
    back, up, steps = start[:2] - behind * along, start[2] + 0.06, 0
    waypoints = ((*obs["observation"][:2], up), (*back, up), (*back, start[2] + height))
    for target, budget in zip(waypoints, (10, 15, 8), strict=True):
        for _ in range(budget):  # proportional control to each waypoint
            error = np.array(target) - obs["observation"][:3]
            if np.linalg.norm(error) < 0.005:
                break
            obs = env.step(np.r_[np.clip(error * 30, -1, 1), 0.0])[0]
            steps += 1
    if np.linalg.norm(obs["achieved_goal"] - start) > MOVED:
        return None
    strike = np.r_[push * along / np.abs(along).max(), 0.0, 0.0]  # the full action: push = 1
    act = lambda _, step: strike if step < hold else np.zeros(4)  # noqa: E731
    obs, _, struck = follow(env, obs, start, along, act, EPISODE - steps)
    env.close()
    end = obs["achieved_goal"]
    return None if end[2] < start[2] - 0.1 else (float((end - start)[:2] @ along), *struck)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_folder")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--gains", type=float, nargs="*", default=[], help="x, y push gains")
    parser.add_argument("--critic", action="store_true", help="Q_1 at the step that moves the puck")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tasks.register_goal_tasks()
    content = checkpoint.load(args.run_folder)
    policy, episodes = Policy(content, ENV_ID), range(3000, 3000 + args.episodes)  # reset seeds
    r = policy_strikes(policy, episodes)
    print(f"{args.run_folder}: success {r[:, 1].mean():.2f} over {len(r)} fresh episodes")
    for part in np.array_split(r[np.argsort(r[:, 0])], 3):
        peak, came_in, pushed, main, other = np.median(part[:, 4:], axis=0)
        print(
            f"  slides of {part[0, 0]:.2f}-{part[-1, 0]:.2f} m: success {part[:, 1].mean():.2f}; "
            f"medians: the puck's top speed {peak:.4f}, the gripper coming in at {came_in:.4f} "
            f"(m/step), pushing at {pushed:.2f} of the full action ({main:.2f} on its main "
            f"axis, the other axis {other:.2f} from the full push's)"
        )
    for gain in args.gains:
        g = policy_strikes(policy, episodes, gain)
        parts = np.array_split(g[g[:, 0].argsort()], 3)
        thirds = " / ".join(f"{p[:, 1].mean():.2f}" for p in parts)
        short = np.mean(g[g[:, 1] == 0, 2] < 0.9)
        print(
            f"  x, y action times {gain} once the puck moved: success {g[:, 1].mean():.2f}, "
            f"near / middle / far {thirds}; failures stopped short {short:.2f}"
        )
    if args.critic:
        c = critic_at_contact(critic(content), policy, episodes)
        for part in np.array_split(c[c[:, 0].argsort()], 3):
            slope, harder, pushed = np.median(part[:, 1:], axis=0)
            wants = np.mean(part[:, 2] > 0)
            print(
                f"  slides of {part[0, 0]:.2f}-{part[-1, 0]:.2f} m, the step moving the puck: "
                f"dQ_1/da along the line {slope:+.2f}, Q_1(x, y times 1.2) - Q_1 {harder:+.3f} "
                f"(> 0 in {wants:.2f}), action along the line {pushed:.2f}"
            )
    fail = r[r[:, 1] == 0]
    short, past = np.mean(fail[:, 2] < 0.9), np.mean(fail[:, 2] > 1.1)
    beside = np.median(np.abs(fail[:, 3]))
    print(
        f"  failures ({len(fail)}): stopped short (< 0.9 of the way) {short:.2f}, past the goal "
        f"(> 1.1) {past:.2f}, median distance beside the line {beside:.3f} m"
    )
    if "rb" in content:  # a resume.pt: what the exploring policy did in training
        far, fell = replay_slides(content["rb"])
        print(
            f"  training episodes of the last 40% of the replay buffer: slid at least 0.55 m "
            f"{far:.2f}, left the table {fell:.2f}"
        )
    seeds = range(3000, 3000 + args.episodes // 10)
    for name, how in (
        ("the full push, 13 cm behind", {}),
        ("0.95 of it", {"push": 0.95}),
        ("0.9 of it", {"push": 0.9}),
        ("from rest at 5 cm", {"behind": 0.05}),
        ("stopped after 3 steps", {"hold": 3}),
        ("3 cm higher", {"height": 0.035}),
    ):
        struck = [s for s in (scripted_strike(seed, **how) for seed in seeds) if s]
        slide, peak, came_in, *_ = np.median(struck, axis=0)
        print(
            f"  scripted, {name} ({len(struck)} of {len(seeds)} episodes): slides {slide:.2f} m; "
            f"medians: the puck's top speed {peak:.4f}, the gripper coming in at {came_in:.4f}"
        )
    far = np.array_split(np.argsort(r[:, 0]), 3)[-1]  # can the full push reach the far goals?
    reach = np.array([(r[i, 0], s[0]) for i in far if (s := scripted_strike(episodes[i]))])
    print(
        f"  scripted, the full push on the far third's goals ({len(reach)} of {len(far)} "
        f"episodes): slides {np.min(reach[:, 1]):.2f}-{np.max(reach[:, 1]):.2f} m (median "
        f"{np.median(reach[:, 1]):.2f}), to within 5 cm of the goal's distance or beyond in "
        f"{np.mean(reach[:, 1] >= reach[:, 0] - 0.05):.2f}"
    )
