"""Run an SB3 anchor script on a goal task that names its success flag ``info["success"]`` (the
mazes of gymnasium-robotics), where the anchor script reads Fetch's ``info["is_success"]``: the
flag is copied under Fetch's name, at every step, and nothing else changes. The anchor then
reads the episode's last flag, as ``common/evaluate.py`` does for our runs.

    OMP_NUM_THREADS=1 $ANCHOR_PY benchmarks/anchor_success.py $ANCHORS/sb3_fetch.py \\
        --algo sac_her --env-id PointMaze_Medium-v3 --seed 401 --steps 300000 \\
        --eval-freq 10000 --eval-episodes 50 \\
        --out benchmarks/results/anchors/sac_her__PointMaze_Medium-v3__seed401

Run it with the anchor's Python (SB3 installed); it needs gymnasium only.
"""

import runpy
import sys

import gymnasium as gym


class FetchSuccessKey(gym.Wrapper):
    """The task's ``info["success"]`` also as ``info["is_success"]``, a float as Fetch's."""

    @staticmethod
    def named(info: dict) -> dict:
        if "success" in info and "is_success" not in info:
            info = {**info, "is_success": float(info["success"])}
        return info

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, self.named(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self.named(info)


def make(*args, _make=gym.make, **kwargs):
    """``gym.make`` with the success flag under Fetch's name too."""
    return FetchSuccessKey(_make(*args, **kwargs))


if __name__ == "__main__":
    if len(sys.argv) < 2 or not sys.argv[1].endswith(".py"):
        sys.exit("error: usage: anchor_success.py ANCHOR_SCRIPT.py [its arguments]")
    gym.make = make  # the anchor script calls gym.make by name: it now gets the flag as Fetch's
    sys.argv = sys.argv[1:]
    runpy.run_path(sys.argv[0], run_name="__main__")
