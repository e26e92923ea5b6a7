"""Model and resume files: tensors and plain values only, read without running any code.

``model.pt`` is one ``torch.save``'d dict: ``format_version``, the run's ``args`` (a dict), the
reset seeds of its last evaluation (so that ``python -m common.evaluate`` can replay it), and the
``state_dict()`` of every part of the model (``agent``, its input ``normalizer`` and any critic),
the kinds of each network's layers (``agent_layers``: ``{"actor_mean": ["Linear", "Tanh", ...]}``)
and ``normalizer_class`` naming the normaliser: all a policy needs to be rebuilt as the script
built it, without the script's code. ``resume.pt`` adds what a run needs to go on (optimisers,
replay, random states, counters), read by ``--resume``; ``python -m common.evaluate`` reads its
policy too.

Loading a pickle can run any code it names (a shared ``model.pt`` could). Both files are read
with ``torch.load(weights_only=True)``, which builds tensors and plain Python values only and
refuses anything else; numpy arrays are stored as tensors (``{"ndarray": tensor}``) for that.
Writing goes to a temporary file renamed over the old one: an interrupted save leaves the
previous file intact.
"""

import contextlib
import dataclasses
import io
import os
import pickle
import random
import sys
import zipfile

import numpy as np
import torch

from common.cli import flag

FORMAT_VERSION = 3  # 3: the networks' layer kinds beside their weights
SCRIPT = os.path.basename(sys.argv[0])  # the script running, e.g. ipg_her.py
RESUME_FILE = "resume.pt"
# may differ on --resume: how long, how often saved, evaluation workers, the run's label
RESUMABLE_ARGS = (
    "resume",
    "resume_freq",
    "total_timesteps",
    "eval_workers",
    "exp_name",
    "track",
    "wandb_project_name",
    "wandb_entity",
)
# what every resume.pt holds besides the script's parts (common/run.py writes and reads them)
RESUME_FIELDS = (
    "script",
    "args",
    "rng",
    "scalars",
    "iteration",
    "global_step",
    "train_time",
    "last_eval",
    "last_save",
    "recent_success",
    "eval_seeds",
)


class CheckpointError(ValueError):
    """A file that is not one of our checkpoints, or of a format this code cannot read."""


def plain(value):
    """``value`` with numpy arrays and scalars turned into what ``weights_only`` loads."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(plain(v) for v in value)
    if isinstance(value, np.ndarray):
        return {"ndarray": torch.from_numpy(np.ascontiguousarray(value))}
    return value.item() if isinstance(value, np.generic) else value


def unplain(value):
    """The inverse of ``plain``."""
    if isinstance(value, dict):
        if value.keys() == {"ndarray"}:
            return value["ndarray"].numpy()
        return {k: unplain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(unplain(v) for v in value)
    return value


def layers(module: torch.nn.Module) -> dict[str, list[str]]:
    """The kinds of the layers of each ``nn.Sequential`` in ``module`` (``["Linear", "Tanh",
    ...]``): with its weights, what rebuilds the network without the script's code."""
    children = module.named_children()
    return {
        name: [type(layer).__name__ for layer in child] for name, child in children if isinstance(child, torch.nn.Sequential)
    }


def with_layers(content: dict, parts: dict) -> dict:
    """``content`` and, for each network among ``parts``, its ``layers`` as ``NAME_layers``."""
    return content | {f"{name}_layers": layers(part) for name, part in parts.items() if isinstance(part, torch.nn.Module)}


def state(model: dict) -> dict:
    """The model's parts as state dicts, their networks' layer kinds, the normaliser's class."""
    parts = {name: part.state_dict() for name, part in model.items()}
    return with_layers(parts, model) | {"normalizer_class": type(model["normalizer"]).__name__}


BOUNDS = ("low", "high")  # a critic's copy of the action bounds: a Box's may be infinite


def not_finite(value, name: str = "") -> list[str]:
    """The names of the tensors and arrays in ``value`` (nested dicts) holding NaN or infinity
    (only NaN in ``BOUNDS``)."""
    if isinstance(value, dict):
        return [bad for key, v in value.items() for bad in not_finite(v, f"{name}.{key}".strip("."))]
    if torch.is_tensor(value) and value.is_floating_point() and name.split(".")[-1] in BOUNDS:
        return [name] if value.isnan().any() else []
    if torch.is_tensor(value) and value.is_floating_point():
        return [] if torch.isfinite(value).all() else [name]
    if isinstance(value, np.ndarray | float) and np.issubdtype(np.asarray(value).dtype, np.floating):
        return [] if np.isfinite(value).all() else [name]
    return []


def save(path: str, args, last_eval_seeds: list[int], **model) -> None:
    _write(
        {"format_version": FORMAT_VERSION, "args": dict(vars(args)), "last_eval_seeds": list(last_eval_seeds), **state(model)},
        path,
    )


def _write(content: dict, path: str) -> None:
    """Serialise in memory, write a temporary file, rename it over ``path``. A failed write (a
    full disk) removes the temporary file, keeps the old ``path`` and raises ``OSError`` with
    the file's name."""
    buffer, tmp = io.BytesIO(), f"{path}.tmp"
    torch.save(plain(content), buffer)  # in memory: a full disk then fails as an OSError
    try:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())
    except BaseException as e:  # a full disk, Ctrl-C: no temporary file left behind
        with contextlib.suppress(OSError):
            os.remove(tmp)
        if isinstance(e, OSError):
            raise OSError(e.errno, e.strerror, path) from e
        raise
    os.replace(tmp, path)  # atomic on POSIX: readers see the old file or the new one


def rng_states() -> dict:
    """The global generators: python's ``random``, numpy's legacy one, torch's."""
    return {"random": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def set_rng_states(states: dict) -> None:
    random.setstate(states["random"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])


def save_resume_state(run_dir: str, args, **content) -> None:
    """Write ``run_dir/resume.pt``: ``args`` and ``content``, where anything with a
    ``state_dict`` is stored as it and a generator as its state."""

    def saved(value):
        if hasattr(value, "state_dict"):
            return value.state_dict()
        if isinstance(value, torch.Generator):
            return value.get_state()
        return value.bit_generator.state if isinstance(value, np.random.Generator) else value

    content = with_layers({key: saved(value) for key, value in content.items()}, content)
    _write(
        {"format_version": FORMAT_VERSION, "script": SCRIPT, "args": dict(vars(args)), **content},
        os.path.join(run_dir, RESUME_FILE),
    )


def load_resume_state(run_dir: str, args) -> dict:
    """What ``save_resume_state`` wrote in ``run_dir``, after checking that ``args`` are the
    run's own (only ``RESUMABLE_ARGS`` may differ). ``CheckpointError`` says why not."""
    if not os.path.isdir(run_dir):
        raise CheckpointError(f"--resume {run_dir}: no such run folder")
    path = os.path.join(run_dir, RESUME_FILE)
    if not os.path.isfile(path):
        raise CheckpointError(
            f"no {RESUME_FILE} in {run_dir} (the run must be started with --resume-freq for it to be written)"
        )
    content = _read(path)
    if missing := [key for key in RESUME_FIELDS if key not in content]:
        what = "a model.pt, not a resume point" if "script" not in content else "an incomplete file"
        raise CheckpointError(f"{path} lacks {', '.join(missing)}: {what}")
    # a flag added to the code since the run started: the run had its default
    saved = {f.name: f.default for f in dataclasses.fields(args)} | content["args"]
    if content["script"] != SCRIPT:
        raise CheckpointError(f"{run_dir} is a run of {content['script']}; resume it with that")
    differ = [
        f"{flag(k)} {saved.get(k)!r} (now {v!r})"
        for k, v in vars(args).items()
        if k not in RESUMABLE_ARGS and saved.get(k) != v
    ]
    if getattr(args, "anneal_lr", False) and args.total_timesteps != saved["total_timesteps"]:
        differ.append("--total-timesteps with --anneal-lr (the schedule would jump)")
    if differ:
        raise CheckpointError(
            f"{run_dir} was run with other arguments: {', '.join(differ)}; resume it with the command that started it"
        )
    return content


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
    """The policy in ``path``: a ``model.pt``, a ``resume.pt`` (the policy at its resume point,
    with the seeds of the evaluation it had run last), or a run folder (its model.pt if any)."""
    if os.path.isdir(path):
        names = [os.path.join(path, name) for name in ("model.pt", RESUME_FILE)]
        if not (found := [name for name in names if os.path.isfile(name)]):
            raise CheckpointError(
                f"no model.pt or {RESUME_FILE} in {path}: a run writes them only with --save-model or --resume-freq"
            )
        path = found[0]
    if not os.path.isfile(path):
        raise CheckpointError(f"no such file: {path}")
    content = _read(path)
    if "agent" not in content or "normalizer" not in content:
        raise CheckpointError(f"{path} holds no policy: it is not a model.pt or a resume.pt")
    if bad := not_finite({"agent": content["agent"], "normalizer": content["normalizer"]}):
        raise CheckpointError(
            f"{path} holds NaN or infinite values ({', '.join(bad[:3])}): "
            "a run stopped by a NaN loss; use an earlier checkpoint"
        )
    if "script" in content:  # a resume.pt: what a model.pt names, read from what it holds
        goals = "obs_rms" in content["normalizer"]
        content |= {
            "normalizer_class": "InputNormalizer" if goals else "RunningMeanStd",
            "last_eval_seeds": content.get("eval_seeds"),
        }
    fields = {"args": dict, "last_eval_seeds": list, "normalizer_class": str}  # save()'s, state()'s
    if bad := [name for name, kind in fields.items() if not isinstance(content.get(name), kind)]:
        raise CheckpointError(
            f"{path} lacks a readable {', '.join(bad)}: it is not a whole model.pt or resume.pt of these scripts"
        )
    return content


def corrupt(path: str) -> str:
    size = os.path.getsize(path)
    return f"{path} is truncated or corrupt ({size:,} bytes), or not a checkpoint of these scripts"


def _read(path: str) -> dict:
    """A file ``_write`` wrote, in this code's format, or a ``CheckpointError`` saying why not."""
    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if not zipfile.is_zipfile(path):  # not torch.save's zip: cut short, or something else
            raise CheckpointError(corrupt(path)) from e
        raise CheckpointError(  # a pickle naming code to run: never loaded
            f"{path} was refused: it holds more than tensors and plain values (format 1's "
            "pickled arrays are refused too: retrain, or load them with the code that wrote them)"
        ) from e
    except Exception as e:  # cut short by a full disk or a copy, or not a torch file at all
        raise CheckpointError(corrupt(path)) from e
    if not isinstance(content, dict) or content.get("format_version") != FORMAT_VERSION:
        version = content.get("format_version") if isinstance(content, dict) else None
        raise CheckpointError(f"{path} has checkpoint format {version!r}; this code reads format {FORMAT_VERSION}")
    return unplain(content)
