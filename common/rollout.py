"""The rollout the three scripts share: the current policy pi_theta run for T steps in N envs.

Gymnasium 1.x vector environments here reset with ``AutoresetMode.SAME_STEP``: where an episode
ends at step t, the observation returned is already the next episode's first, and the true last
one is in ``infos["final_obs"]``. The rollout keeps it (``final_obs``), so that GAE can bootstrap
a truncated episode from V(s_T) and the replay stores the real transition, never one that
crosses a reset.
"""

import copy

import gymnasium as gym
import numpy as np
import torch

SUCCESS_KEYS = ("is_success", "success")  # Fetch's and the Shadow hand's; the mazes'


def success_of(info: dict):
    """A goal task's success flag in ``info`` (per env in a vector env's), else None."""
    return next((info[key] for key in SUCCESS_KEYS if key in info), None)


def make_vector_env(make_env, num_envs: int) -> gym.vector.SyncVectorEnv:
    """``num_envs`` environments ``make_env()``, stepped in turn, resetting SAME_STEP."""
    envs = gym.vector.SyncVectorEnv([make_env] * num_envs,
                                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)  # fmt: skip
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    return envs


def collect_rollout(envs, agent, norm, raw_obs, num_steps: int, rb=None, update_norm=True):
    """Step ``envs`` ``num_steps`` times with actions sampled from ``agent.dist``; with a replay
    buffer ``rb``, every transition also goes into it raw, with the action executed (clipped to
    the bounds: the critic learns its Q) and its real next observation (a Dict on goal tasks).

    Returns ``(rollout, raw_obs, episodes)``: ``rollout`` holds time-major ``(T, N, ...)`` tensors
    ``obs`` (normalised by ``norm``, as the policy saw them), ``actions``, ``rewards`` (raw),
    ``terminations``, ``episode_ends`` and ``final_obs`` (the normalised true last observation
    where an episode ended at step t, zeros elsewhere); ``raw_obs`` is where the envs stopped;
    ``episodes`` lists the finished training episodes as ``(t, env, return, length, success or
    None)``.
    """
    T, N, act_dim = num_steps, envs.num_envs, envs.single_action_space.shape[0]
    low, high = envs.single_action_space.low, envs.single_action_space.high
    obs_dim = norm(raw_obs).shape[-1]  # the policy's input
    ro = {"obs": torch.zeros((T, N, obs_dim)), "final_obs": torch.zeros((T, N, obs_dim)),
          "actions": torch.zeros((T, N, act_dim)), "rewards": torch.zeros((T, N)),
          "terminations": torch.zeros((T, N)), "episode_ends": torch.zeros((T, N))}  # fmt: skip
    episodes = []
    for t in range(T):
        if update_norm:
            norm.update(raw_obs)
        ro["obs"][t] = norm(raw_obs)
        with torch.no_grad():
            ro["actions"][t] = agent.dist(ro["obs"][t]).sample()
        executed = np.clip(ro["actions"][t].numpy(), low, high)
        next_raw_obs, reward, terminated, truncated, infos = envs.step(executed)
        ended = terminated | truncated
        ro["rewards"][t] = torch.as_tensor(reward)
        ro["terminations"][t] = torch.as_tensor(terminated)
        ro["episode_ends"][t] = torch.as_tensor(ended)
        real_next_obs = copy.deepcopy(next_raw_obs) if ended.any() else next_raw_obs
        for i in np.flatnonzero(ended):  # next_raw_obs[i] is the next episode's first
            final = infos["final_obs"][i]
            if isinstance(real_next_obs, dict):  # a goal task's Dict
                for key in real_next_obs:
                    real_next_obs[key][i] = final[key]
            else:
                real_next_obs[i] = final
            ro["final_obs"][t, i] = norm(final)
            info = infos["final_info"]
            success = None if (flags := success_of(info)) is None else float(flags[i])
            episode_return, length = float(info["episode"]["r"][i]), int(info["episode"]["l"][i])
            episodes.append((t, i, episode_return, length, success))
        if rb is not None:
            rb.add(raw_obs, executed, reward, real_next_obs, terminated, truncated)
        raw_obs = next_raw_obs
    return ro, raw_obs, episodes
