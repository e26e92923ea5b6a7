"""Where a run's time goes: a script under the py-spy sampling profiler, its samples summed into
phases (stepping, policy inference, normalisation, replay, critic steps, policy update, ...).

    python benchmarks/probes/profile_phases.py ppo_kl.py -- --env-id Hopper-v5 \
        --total-timesteps 40960 --eval-freq 0 --eval-episodes 1
    python benchmarks/probes/profile_phases.py ipg_her.py -- --env-id FetchReach-v4 --seed 1

runs the script under ``py-spy record`` (200 samples a second, read from outside the process, so
the run keeps its speed), then gives every sample to the first phase of ``PHASES`` whose rule its
call stack matches. It prints one JSON line per phase, seconds and share of the samples, then the
run's wall time: the tables of docs/benchmarks.md. py-spy samples the main process only and
leaves out time it spends waiting (ipg_her.py's evaluation runs in a process of its own); stacks
it could not read whole (about 3%) fall into "start-up and the rest".
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import tyro

ROOT = os.path.abspath(os.path.join(__file__, "../../.."))  # the project root
# (phase, names of which one must be on the stack, the files it must be in, a name that must be
# outside it): a sample goes to the first phase whose rule its stack matches
PHASES = (
    ("evaluation", ("evaluate", "finished", "evaluate_policy"), ("common/evaluate.py", "common/background.py"), None),
    ("stepping", ("SyncVectorEnv.step",), None, None),
    ("replay writes", ("add",), ("common/replay.py", "common/her.py"), None),
    ("replay sampling", ("sample_replay",), None, None),
    ("critic steps", ("critic_step",), None, None),
    ("diagnostics", ("interpolation_report", "qprop_report", "variance_report"), None, None),
    ("policy update", ("ppo_kl_update", "qprop_update", "ipg_update"), None, None),
    ("advantages and reward scaling", ("make_batch", "control_variate", "RewardScaler.__call__"), None, None),
    ("normalisation", ("update", "normalize", "__call__", "inputs"), ("common/normalizer.py",), None),
    ("policy inference", ("dist", "_call_impl", "sample"), None, "rollout"),
    ("rollout bookkeeping", ("rollout",), None, None),
    ("logging and checkpoints", ("end_iteration", "record_episodes", "Run.log"), None, None),
)
RATE = 200  # samples per second


@dataclass
class Args:
    script: tyro.conf.Positional[str]
    """ppo_kl.py, qprop_ppo.py or ipg_her.py; its own flags follow a --"""


def phase_of(stack: list[tuple[str, str]]) -> str:
    """The phase of a sample whose call stack (outermost first) is ``stack`` of (function, file);
    py-spy names methods ``Class.function``, which a rule may name either way."""
    names = [({f, f.rpartition(".")[2]}, file) for f, file in stack]
    for phase, functions, paths, within in PHASES:
        inside = [i for i, (name, _) in enumerate(names) if within is None or within in name]
        for name, file in names[inside[0] :] if inside else ():
            if set(functions) & name and (paths is None or any(p in file for p in paths)):
                return phase
    return "start-up and the rest"  # imports, building envs and networks, the final flush


def parse_frame(frame: str) -> tuple[str, str]:
    """py-spy's ``function (file:line)`` as (function, file)."""
    function, _, where = frame.partition(" (")
    return function, where.rpartition(":")[0].replace(os.sep, "/")


def phase_samples(raw: str) -> dict:
    """Samples per phase from py-spy's raw output: one ``frame;frame;... count`` line per stack."""
    totals = {}
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if not count.isdigit():  # a frame's name broken over lines (a docstring-built one)
            continue
        phase = phase_of([parse_frame(frame) for frame in stack.split(";")])
        totals[phase] = totals.get(phase, 0) + int(count)
    return totals


if __name__ == "__main__":
    ours, script_args = sys.argv[1:], []
    if "--" in ours:
        ours, script_args = ours[: ours.index("--")], ours[ours.index("--") + 1 :]
    args = tyro.cli(Args, args=ours)
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "samples.txt")
        start = time.perf_counter()
        py_spy = os.path.join(os.path.dirname(sys.executable), "py-spy")  # this venv's, or PATH's
        py_spy = py_spy if os.path.exists(py_spy) else "py-spy"
        subprocess.run(
            [
                py_spy,
                "record",
                "--rate",
                str(RATE),
                "--nonblocking",
                "--format",
                "raw",
                "--output",
                out,
                "--",
                sys.executable,
                os.path.join(ROOT, args.script),
                *script_args,
            ],
            cwd=ROOT,
            check=True,
            stdout=sys.stderr,
        )
        wall = time.perf_counter() - start
        with open(out) as f:
            totals = phase_samples(f.read())
    total = sum(totals.values())
    for phase, samples in sorted(totals.items(), key=lambda item: -item[1]):
        print(json.dumps({"phase": phase, "seconds": round(samples / RATE, 2), "share": round(samples / total, 3)}))
    print(
        json.dumps(
            {
                "phase": "all samples",
                "seconds": round(total / RATE, 2),
                "wall_s": round(wall, 2),
                "script": args.script,
                "args": " ".join(script_args),
            }
        )
    )
