"""Checkpoints that hold everything needed to evaluate a policy exactly.

A checkpoint is one ``torch.save``'d dict: ``format_version``, the ``script`` that wrote it, its
``args`` (which task, which sizes), the ``state_dict()`` of every part the script passes (the
agent, the observation/goal normaliser, the critic and its target), and the reset seeds of the
last evaluation, so that ``python -m common.evaluate`` can replay it episode for episode.
Writing goes to a temporary file renamed over the old one: a save interrupted half-way leaves the
previous checkpoint intact.

A run started with ``--resume-freq`` also writes ``resume.pt`` into its run folder: everything it
needs to go on (optimisers, replay buffer, random states, counters), read by ``--resume``.
"""

import dataclasses
import os
import random

import numpy as np
import torch

FORMAT_VERSION = 1
SCRIPTS = ("ppo_kl", "qprop_ppo", "ipg_her")


class CheckpointError(ValueError):
    """A file that is not one of our checkpoints, or of a format this code cannot read."""


def save(path: str, script: str, args, last_eval_seeds: list[int], **parts) -> None:
    state = {"format_version": FORMAT_VERSION, "script": script, "args": dict(vars(args)),
             "last_eval_seeds": list(last_eval_seeds)}  # fmt: skip
    state |= {name: part.state_dict() for name, part in parts.items()}
    _write(state, path)


def _write(state: dict, path: str) -> None:
    tmp = f"{path}.tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)  # atomic on POSIX: readers see the old file or the new one


# Resuming: everything a run needs to go on, not only to evaluate
RESUME_FILE = "resume.pt"
RESUMABLE_ARGS = ("resume", "resume_freq", "total_timesteps", "eval_workers")  # may change


def rng_states() -> dict:
    """The global generators: python's ``random``, numpy's legacy one, torch's."""
    return {"random": random.getstate(), "numpy": np.random.get_state(),
            "torch": torch.get_rng_state()}  # fmt: skip


def set_rng_states(states: dict) -> None:
    random.setstate(states["random"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])


def save_resume_state(run_dir: str, args, **state) -> None:
    """Write ``run_dir/resume.pt``: ``args`` and ``state``, where anything with a ``state_dict``
    (networks, optimisers, normalisers, the replay buffer) is stored as its state dict and a
    numpy ``Generator`` as its bit generator's state."""

    def saved(value):
        if hasattr(value, "state_dict"):
            return value.state_dict()
        if isinstance(value, torch.Generator):
            return value.get_state()
        return value.bit_generator.state if isinstance(value, np.random.Generator) else value

    state = {key: saved(value) for key, value in state.items()}
    _write({"format_version": FORMAT_VERSION, "args": dict(vars(args)), **state},
           os.path.join(run_dir, RESUME_FILE))  # fmt: skip


def load_resume_state(run_dir: str, args) -> dict:
    """The state ``save_resume_state`` wrote in ``run_dir``, after checking that ``args`` are
    the run's own (only ``RESUMABLE_ARGS`` may differ: a longer budget extends a run). Raises
    ``CheckpointError`` with the reason otherwise."""
    path = os.path.join(run_dir, RESUME_FILE)
    if not os.path.isfile(path):
        raise CheckpointError(f"no {RESUME_FILE} in {run_dir} (the run must be started with "
                              "--resume-freq for it to be written)")  # fmt: skip
    state = _read(path)
    # a flag added to the code since the run started: the run had its default
    saved = {f.name: f.default for f in dataclasses.fields(args)} | state["args"]
    differ = [f"--{k.replace('_', '-')} {saved.get(k)!r} (now {v!r})"
              for k, v in vars(args).items()
              if k not in RESUMABLE_ARGS and saved.get(k) != v]  # fmt: skip
    if getattr(args, "anneal_lr", False) and args.total_timesteps != saved["total_timesteps"]:
        differ.append("--total-timesteps with --anneal-lr (the schedule would jump)")
    if differ:
        raise CheckpointError(f"{run_dir} was run with other arguments: {', '.join(differ)}; "
                              "resume it with the command that started it")  # fmt: skip
    return state


def restore(target, saved) -> None:
    """Put a saved state back into ``target``: a ``load_state_dict``, a numpy or torch
    generator."""
    if isinstance(target, torch.Generator):
        target.set_state(saved)
    elif isinstance(target, np.random.Generator):
        target.bit_generator.state = saved
    else:
        target.load_state_dict(saved)


def load(path: str) -> dict:
    """The checkpoint at ``path`` (a ``model.pt`` or a run folder holding one)."""
    if os.path.isdir(path):
        path = os.path.join(path, "model.pt")
    if not os.path.isfile(path):
        raise CheckpointError(f"no such checkpoint: {path}")
    state = _read(path)
    if state.get("script") not in SCRIPTS:
        raise CheckpointError(
            f"{path} is not a checkpoint of ppo_kl.py, qprop_ppo.py or ipg_her.py"
        )
    return state


def _read(path: str) -> dict:
    """A file ``_write`` wrote, in this code's format, or a ``CheckpointError`` saying why not."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise CheckpointError(f"{path} is not a checkpoint of these scripts ({e})") from e
    if not isinstance(state, dict):
        raise CheckpointError(f"{path} is not a checkpoint of these scripts")
    if state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {state.get('format_version')!r}; this code reads "
            f"format {FORMAT_VERSION}: use it with the version of the code that wrote it"
        )
    return state
