"""The command-line shell every script shares, so that the scripts hold only their algorithms.

Nothing here is about reinforcement learning: parsing an ``Args`` dataclass with tyro, and
refusing bad input with one ``error:`` line before any training starts (and before any run
folder exists). A check either returns or exits through ``fail``; it never changes ``args``.
"""

import contextlib
import dataclasses
import io
import math
import os
import re
import signal
import sys
from typing import NoReturn, TypeVar

INTERRUPTED = "interrupted; nothing was written"


def interrupted(kind, error, traceback) -> None:
    """``sys.excepthook``: Ctrl-C before a run is under way (imports, checks, loading a resume
    point) or an evaluation ends in one line instead of a traceback (the exit code stays Ctrl-C's,
    130); anything else as usual."""
    if issubclass(kind, KeyboardInterrupt):
        print(INTERRUPTED, file=sys.stderr)
    else:
        sys.__excepthook__(kind, error, traceback)


def interrupted_while_loading(signum, frame) -> NoReturn:
    """SIGINT while a script's libraries load ends it at once, in one line with Ctrl-C's exit
    code: raised there as a KeyboardInterrupt, it could surface from a compiled module's start-up
    as an ImportError (mujoco's), or be swallowed by a library that tries an import and goes on.
    Nothing has been written yet. ``parse_args`` hands Ctrl-C back to Python."""
    os.write(2, f"{INTERRUPTED}\n".encode())
    os._exit(130)


sys.excepthook = interrupted  # before the slow imports below
MAIN = getattr(sys.modules.get("__main__"), "__file__", None)  # the script run (none in a shell)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if MAIN and os.path.abspath(MAIN).startswith(ROOT + os.sep) and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, interrupted_while_loading)  # a script of ours, Ctrl-C not ignored

import numpy as np  # noqa: E402
import tyro  # noqa: E402

from common import tasks, tracking  # noqa: E402

A = TypeVar("A")


def fail(message: str) -> NoReturn:
    """Bad input: one clear line, no traceback, non-zero exit."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_args(args_class: type[A], argv: list[str] | None = None, prog: str | None = None) -> A:
    """``tyro.cli``, with a parse error reduced to one line (tyro draws a box)."""
    if signal.getsignal(signal.SIGINT) is interrupted_while_loading:  # the libraries are loaded
        signal.signal(signal.SIGINT, signal.default_int_handler)
    captured, argv = io.StringIO(), sys.argv[1:] if argv is None else argv
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(args_class, args=argv, prog=prog)
    except SystemExit as e:
        if e.code:
            fail(parse_error(captured.getvalue()))
        raise


def spelled(values: dict) -> str:
    """``{field: value}`` as one would type it: ``--a-b 1.0 1.0, --flag`` (a tuple's values one by one)."""
    typed = {k: " ".join(map(str, np.atleast_1d(v))) for k, v in values.items()}
    return ", ".join(flag(k) if v is True else f"{flag(k)} {typed[k]}" for k, v in values.items())


EXPECTS = {
    "INT": "an integer",
    "FLOAT": "a number",
    "{None}|FLOAT": "a number or None",
    "{None}|FLOAT|{[FLOAT [FLOAT ...]]}": "None, a number or several",
}  # tyro's metavars


def parse_error(box: str) -> str:
    """tyro's error box as one line: what the flag expects and what it got."""
    text = " ".join(re.sub(r"[│╭╮╰╯─]|-{3,}", " ", box).split())
    if m := re.search(r"Error parsing (--[\w-]+): (.*?) Argument helptext: --[\w-]+ (.*)", text):
        union = re.search(r"instantiated from \[(.*?)\]", m[2])  # a union's: every value
        quoted = re.findall(r"'(.*?)'", union[1] if union else m[2])
        value = " ".join(quoted if union else quoted[-1:])
        metavar = next((k for k in EXPECTS if m[3].startswith(f"{k} ")), m[3].split()[0])
        return f"{m[1]} expects {EXPECTS.get(metavar, metavar)}, got {value!r}"
    if m := re.search(
        r"invalid choice '(.*?)' for argument '(--[\w-]+)'\. Expected one of "
        r"\((.*?)\)",
        text,
    ):
        choices = ", ".join(re.findall(r"'(.*?)'", m[3]))
        return f"{m[2]} expects one of ({choices}), got {m[1]!r}"
    if m := re.search(r"Missing value for argument '(--[\w-]+)'", text):
        return f"{m[1]} expects a value"
    if "Unrecognized options:" in text:  # tyro's headings and each guess's help: one line
        rest = text.split("Unrecognized options:", 1)[1]
        options = re.split(r" (?:Perhaps|Arguments similar|For full)", rest, maxsplit=1)[0]
        guesses = re.findall(r"(?:meant|similar to --[\w-]+): (--[\w-]+)", rest)
        guess = f"; did you mean {' or '.join(guesses)}?" if guesses else ""
        return f"unrecognized option {options.strip()}{guess} (--help lists them)"
    return re.sub(r" For full helptext.*", "", text)


def given(argv: list[str]) -> dict[str, str]:
    """The fields ``argv`` sets, whatever the spelling (``--a-b``, ``--a_b``, ``--a-b=1``,
    ``--no-a``, ``--no_a``): ``{field: flag as typed}``."""
    return {re.sub(r"^no_", "", a.split("=")[0][2:].replace("-", "_")): a.split("=")[0] for a in argv if a.startswith("--")}


def flag(name: str) -> str:
    """The command-line spelling of an ``Args`` field: ``num_envs`` -> ``--num-envs``."""
    return "--" + name.replace("_", "-")


def check_positive(args, *names: str) -> None:
    for name in names:
        if getattr(args, name) <= 0:
            fail(f"{flag(name)} must be positive, got {getattr(args, name)}")


def check_non_negative(args, *names: str) -> None:
    for name in names:
        if getattr(args, name) < 0:
            fail(f"{flag(name)} must be non-negative, got {getattr(args, name)}")


def check_range(args, name: str, low: float, high: float, open_low: bool = False) -> None:
    """``args.name`` in [low, high], or (low, high] with ``open_low``."""
    value = getattr(args, name)
    if not (low < value if open_low else low <= value) or value > high:
        fail(f"{flag(name)} must be in {'(' if open_low else '['}{low:g}, {high:g}], got {value}")


def check_finite(args) -> None:
    """Every float flag, and every float in a tuple flag, is a finite number (nan, inf: no)."""
    for field in dataclasses.fields(args):
        value = getattr(args, field.name)
        values = value if isinstance(value, tuple) else (value,)
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            fail(f"{flag(field.name)} must be a finite number, got {' '.join(map(str, values))}")


def check_run(args) -> bool:
    """The checks of what every run has (``RunArgs``, the task and the budget): finite numbers, a
    task that exists and that these scripts can drive, a budget of at least one batch, and
    ``--capture-video``'s prerequisites. Returns whether the task is a goal task."""
    check_finite(args)
    check_exp_name(args.exp_name)
    refuse(tracking.refusal(args))
    check_positive(args, "num_envs")
    goal_task = check_task(args.env_id, args.num_envs)
    check_positive(args, "total_timesteps", "num_steps", "torch_threads", "eval_episodes")
    if args.save_freq and not args.save_model:
        fail(
            f"--save-freq {args.save_freq} would be ignored (it saves model.pt, which only "
            "--save-model writes): add --save-model or leave it out"
        )
    for name in ("seed", "save_freq", "eval_freq", "eval_workers", "resume_freq"):
        if getattr(args, name) < 0:
            off = " (0 turns it off)" if name.endswith("freq") else ""
            fail(f"{flag(name)} must be non-negative{off}, got {getattr(args, name)}")
    batch_size = args.num_envs * args.num_steps
    if args.total_timesteps < batch_size:
        fail(f"--total-timesteps {args.total_timesteps} is less than one batch (num_envs * num_steps = {batch_size})")
    if args.capture_video:
        check_video(args.env_id)
    return goal_task


def check_minibatches(batch_size: int, num_minibatches: int) -> None:
    if batch_size % num_minibatches:
        fail(
            f"batch {batch_size} (num_envs * num_steps) does not split into {num_minibatches} "
            "minibatches; change --num-minibatches"
        )


def check_ppo_kl(args) -> None:
    """The flags of PPO-KL (eq. 4-5) that every script has: its update, its beta rule and GAE."""
    check_positive(args, "num_minibatches", "update_epochs", "learning_rate", "kl_target")
    check_positive(args, "vf_coef", "max_grad_norm")  # <= 0: V unlearnt, reversed or frozen
    check_non_negative(args, "beta_init")
    if args.kl_early_stop is not None:
        check_positive(args, "kl_early_stop")
    if args.gamma is not None:  # None: a script fills it in from the task
        check_range(args, "gamma", 0.0, 1.0, open_low=True)
    check_range(args, "gae_lambda", 0.0, 1.0)
    check_minibatches(args.num_envs * args.num_steps, args.num_minibatches)


def check_exp_name(name: str) -> None:
    """The middle of a run folder's name ``{env_id}__{exp_name}__{seed}__{time}``: a path in it
    would put the folder outside --log-dir, under a name report.py cannot read."""
    if not name or "/" in name or "\0" in name:
        fail(f"--exp-name {name!r} must be a plain name, without '/'")


def refuse(why: str | None) -> None:
    """Fail with ``why``, the reason a module gives for refusing the input (None: no refusal)."""
    if why:
        fail(why)


def ignored(*rules: tuple[bool, str, str]) -> dict[str, str]:
    """``{flag: why}`` from the rules ``(when, "--flag --other-flag", why)`` that hold: the flags a
    run would ignore (a later rule's why wins)."""
    return {flag: why for when, flags, why in rules if when for flag in flags.split()}


def refuse_ignored(argv: list[str], ignored: dict[str, str]) -> None:
    """A flag given on the command line that would change nothing fails: ``{flag: why}``; any
    spelling of it (``--a_b``, ``--no-a``, ``--a=1``) too."""
    for name, typed in given(argv).items():
        if flag(name) in ignored:
            fail(f"{typed} would be ignored ({ignored[flag(name)]}): leave it out")


def check_task(env_id: str, num_envs: int = 1) -> bool:
    """``tasks.task_refusal``'s checks, failing with its line. Returns whether it is a goal
    task."""
    refuse(tasks.task_refusal(env_id, num_envs))
    return tasks.goal_task(env_id)


def check_memory(nbytes: float, what: str) -> None:
    """Fail if ``what`` (a flag and its value) would need more than the available memory: an
    allocation the machine cannot serve, refused before the run rather than a traceback in it."""
    if nbytes > (free := tasks.available_memory()):
        fail(
            f"{what} needs about {nbytes / 2**30:,.1f} GiB of memory, and "
            f"{free / 2**30:.1f} GiB are available; make it smaller"
        )


def check_video(env_id: str) -> None:
    refuse(tasks.video_refusal(env_id))
