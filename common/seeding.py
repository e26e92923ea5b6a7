"""Every random stream of a run, derived from its one ``--seed``.

``env.reset(seed=s)`` on a vector env seeds env i with s + i, so seed 1's second env would replay
seed 2's first; evaluation seeded with ``seed + 10_000 + k`` would share 19 of 20 episodes with
the neighbouring seed's run. Instead, ``numpy.random.SeedSequence(seed)`` spawns one independent
child per stream: the training envs' first resets, the evaluation episodes (fresh ones at every
evaluation), torch, the replay sampler, the action space, the diagnostics (which must not move
the training's streams) and python/numpy's global generators. Two runs with different seeds
then share no stream, and no evaluation episode starts from a training reset seed (all are
32-bit draws from independent streams; a collision has probability about 2^-32 per pair).
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class Streams:
    env_seeds: list[int]  # the first reset of each training env
    eval_rng: np.random.Generator  # draws each evaluation's episode seeds
    torch_seed: int
    replay_seed: int
    action_space_seed: int
    global_seed: int  # python's ``random`` and numpy's legacy global generator
    diagnostics_seed: int  # measurements that must not move the training's streams

    def eval_seeds(self, episodes: int) -> list[int]:
        """Seeds of the next evaluation's episodes: new ones at every call."""
        return [int(s) for s in self.eval_rng.integers(0, 2**32, size=episodes)]


def streams(seed: int, num_envs: int) -> Streams:
    # spawn keys 0-6: a stream added at the end leaves the earlier ones as they were
    env, evaluation, torch_, replay, space, glob, diag = np.random.SeedSequence(seed).spawn(7)
    first = lambda ss: int(ss.generate_state(1)[0])
    return Streams(
        env_seeds=[int(s) for s in env.generate_state(num_envs)],
        eval_rng=np.random.default_rng(evaluation),
        torch_seed=first(torch_),
        replay_seed=first(replay),
        action_space_seed=first(space),
        global_seed=first(glob),
        diagnostics_seed=first(diag),
    )


def resume_env_seeds(seed: int, num_envs: int, step: int) -> list[int]:
    """Reset seeds for the training envs of a run resumed at ``step`` from a resume point of
    earlier code, which holds no environment state (common/run.py): a stream of its own (spawn key
    7, then the step), apart from the seven above and from every other resume point."""
    sequence = np.random.SeedSequence(seed, spawn_key=(7, step))
    return [int(s) for s in sequence.generate_state(num_envs)]
