"""Start a share of PickAndPlace's training episodes with the object already in the gripper.

The HER paper (Andrychowicz et al. 2017, sec. 4.1) made pick-and-place's exploration easier by
starting half of the training episodes from one recorded state in which the box is grasped:
exploration by noise almost never holds a grasp long enough to lift, and HER can only relabel lifts
that happened. Here each training environment records such a state once, at its first reset, by a
scripted grasp (above the object, open, down, close: about 15 simulator steps that no learner
sees and the step budget does not count); later resets restore it with probability ``share``,
keeping the goal the reset drew. Evaluation never uses it: its environments start as the task
defines.
"""

import gymnasium as gym
import numpy as np

STATE = ("qpos", "qvel", "act", "ctrl", "mocap_pos", "mocap_quat")  # MuJoCo's mjData fields


def refusal(env_id: str) -> str | None:
    """Why ``env_id`` cannot start grasped (None if it can): it needs an object and a gripper that
    opens (FetchPickAndPlace; Push and Slide block the gripper)."""
    env = gym.make(env_id).unwrapped
    ok = getattr(env, "has_object", False) and not getattr(env, "block_gripper", True)
    env.close()
    return None if ok else f"--grasped-start needs an object the gripper can hold, not {env_id}"


def scripted_grasp(env, obs: dict) -> dict:
    """Above the object with the gripper open, down to it, then closed; returns the last obs."""
    for phase, steps, close_enough in (("above", 20, 0.01), ("down", 20, 0.005), ("close", 5, 0)):
        for _ in range(steps):
            offset = obs["observation"][6:9] + (0.0, 0.0, 0.03 if phase == "above" else 0.0)
            if np.linalg.norm(offset) < close_enough:  # obs[6:9]: object minus gripper position
                break
            move = np.zeros(3) if phase == "close" else np.clip(offset / 0.05, -1, 1)
            obs = env.step(np.append(move, -1.0 if phase == "close" else 1.0))[0]  # 1: open
    return obs


class GraspedStart(gym.Wrapper):
    """Resets that, with probability ``share``, start from the recorded grasp (goals as drawn)."""

    def __init__(self, env: gym.Env, share: float):
        super().__init__(env)
        self.share, self.state = share, None

    def reset(self, **kwargs):
        import mujoco  # not on import: MuJoCo loads its renderer then (see common/cli.py)

        obs, info = self.env.reset(**kwargs)
        sim = self.env.unwrapped
        if self.state is None:  # record the grasped state once, then start afresh
            scripted_grasp(sim, obs)
            self.state = {name: getattr(sim.data, name).copy() for name in STATE}
            obs, info = self.env.reset()
        if self.np_random.random() < self.share:
            for name, value in self.state.items():
                getattr(sim.data, name)[:] = value
            mujoco.mj_forward(sim.model, sim.data)
            obs = sim._get_obs()  # with the goal the reset drew
        return obs, info
