"""Checkpoints that hold everything needed to evaluate a policy exactly.

A checkpoint is one ``torch.save``'d dict: ``format_version``, the ``script`` that wrote it, its
``args`` (which task, which sizes), the ``state_dict()`` of every part the script passes (the
agent, the observation/goal normaliser, the critic and its target), and the reset seeds of the
last evaluation, so that ``python -m common.evaluate`` can replay it episode for episode.
Writing goes to a temporary file renamed over the old one: a save interrupted half-way leaves the
previous checkpoint intact.
"""

import os

import torch

FORMAT_VERSION = 1
SCRIPTS = ("ppo_kl", "qprop_ppo", "ipg_her")


class CheckpointError(ValueError):
    """A file that is not one of our checkpoints, or of a format this code cannot read."""


def save(path: str, script: str, args, last_eval_seeds: list[int], **parts) -> None:
    state = {"format_version": FORMAT_VERSION, "script": script, "args": dict(vars(args)),
             "last_eval_seeds": list(last_eval_seeds)}  # fmt: skip
    state |= {name: part.state_dict() for name, part in parts.items()}
    tmp = f"{path}.tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)  # atomic on POSIX: readers see the old file or the new one


def load(path: str) -> dict:
    """The checkpoint at ``path`` (a ``model.pt`` or a run folder holding one)."""
    if os.path.isdir(path):
        path = os.path.join(path, "model.pt")
    if not os.path.isfile(path):
        raise CheckpointError(f"no such checkpoint: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise CheckpointError(f"{path} is not a checkpoint of these scripts ({e})") from e
    if not isinstance(state, dict) or state.get("script") not in SCRIPTS:
        raise CheckpointError(
            f"{path} is not a checkpoint of ppo_kl.py, qprop_ppo.py or ipg_her.py"
        )
    if state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {state.get('format_version')!r}; this code reads "
            f"format {FORMAT_VERSION}: evaluate it with the version of the code that wrote it"
        )
    return state
