"""How much of the learning could hide behind FetchReach's stepping? A probe only.

    OMP_NUM_THREADS=1 python benchmarks/probes/overlap_probe.py

Times 3,000 environment steps (two FetchReach-v4 envs, random actions) and 1,500 critic-sized
Adam steps (batch 256, 17 inputs, two 64-wide layers): each alone, then (a) the stepping in a
thread while the main thread learns, (b) one critic step between each ``step_async`` and
``step_wait`` of an ``AsyncVectorEnv`` (a process per env), (c) the same interleaving in one
process. The main job's steps and critic steps come in this ratio (100 to 50 per iteration).
"""

import threading
import time

import gymnasium as gym
import gymnasium_robotics
import numpy as np
import torch
import torch.nn as nn

STEPS = 3000
torch.set_num_threads(1)
gym.register_envs(gymnasium_robotics)
q = nn.Sequential(nn.Linear(17, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, 1))
optimizer = torch.optim.Adam(q.parameters(), lr=1e-3)
x, y = torch.randn(256, 17), torch.randn(256, 1)
rng = np.random.default_rng(0)


def critic_step():
    loss = ((q(x) - y) ** 2).mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()


def seconds(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def make_envs(vector_env):
    envs = vector_env([lambda: gym.make("FetchReach-v4")] * 2, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    envs.reset(seed=0)
    return envs


def actions():
    return rng.uniform(-1, 1, (2, 4)).astype(np.float32)


if __name__ == "__main__":
    sync, processes = make_envs(gym.vector.SyncVectorEnv), make_envs(gym.vector.AsyncVectorEnv)
    stepping = lambda: [sync.step(actions()) for _ in range(STEPS // 2)]  # noqa: E731
    learning = lambda: [critic_step() for _ in range(STEPS // 2)]  # noqa: E731

    def in_a_thread():
        thread = threading.Thread(target=stepping)
        thread.start()
        learning()
        thread.join()

    def interleaved(envs):
        for _ in range(STEPS // 2):
            envs.step_async(actions())
            critic_step()
            envs.step_wait()

    def one_process():
        for _ in range(STEPS // 2):
            sync.step(actions())
            critic_step()

    stepping(), learning()  # warm-up
    for _ in range(2):
        a, b = seconds(stepping), seconds(learning)
        print(
            f"stepping {a:.2f} s, learning {b:.2f} s: serial {a + b:.2f} s, "
            f"ideal {max(a, b):.2f} s; (a) thread {seconds(in_a_thread):.2f} s, (b) processes"
            f" {seconds(lambda: interleaved(processes)):.2f} s, (c) interleaved in one process"
            f" {seconds(one_process):.2f} s"
        )
    processes.close()
