"""Training step rates of the recipe (``ipg_her_recipe.py``, its defaults) and SB3 TQC+HER (the
settings of rl-baselines3-zoo's published agents) on Fetch tasks, measured in one session.

A full TQC+HER run is out of reach here (3x512 networks, two critics of 25 quantiles, one
gradient step of batch 512 per environment step), so its steps to a level come from the zoo's
published curves (``ANCHORS`` in benchmarks/peers.py) and its wall-clock from the rate measured
here. First the anchor (``sb3_fetch.py --algo tqc_her --trained-agent``, in ``--anchors``, a folder
outside this repository, run with the python of a virtual environment that has sb3-contrib) on
every task at once, one process a task; then ours alike: the same load, one process a core on a
two-core machine with nothing else running. Each trains ``--steps`` steps and is evaluated once,
at its end, on one episode; the rates exclude evaluation (ours: ``charts/SPS``; theirs:
``train_steps_per_s``). Writes ``results.json`` and ``table.md`` into ``--out``, which must not
hold them yet:

    python benchmarks/step_rates.py --anchor-python $ANCHOR_PY --anchors $ANCHORS \\
        --tasks FetchPush-v4 FetchPickAndPlace-v4 --steps 20000 --out benchmarks/results/step_rates
"""

import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.events import read_run  # noqa: E402


@dataclass
class Args:
    anchor_python: str
    """python of the anchors' virtual environment (has sb3-contrib)"""
    anchors: str
    """folder of the anchor script sb3_fetch.py (not in this repository)"""
    tasks: list[str] = field(default_factory=lambda: ["FetchPush-v4", "FetchPickAndPlace-v4"])
    """the tasks, run at once: one process a task, for each side in turn"""
    steps: int = 20_000
    """training steps per run"""
    seed: int = 1
    """the seed of every run"""
    out: str = "benchmarks/results/step_rates"
    """output folder (its runs/ holds our event files and the anchor's summaries)"""


def run_all(commands: dict[str, list[str]], logs: Path) -> None:
    """Start every command at once, wait for all; one that fails ends the others, one error line."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = {}
    try:
        for name, command in commands.items():
            print("$", " ".join(command), flush=True)
            with open(logs / f"{name}.log", "w") as log:
                procs[name] = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        for name, proc in procs.items():
            if proc.wait() != 0:
                sys.exit(f"error: {name} failed (exit {proc.returncode}); its output: {logs / f'{name}.log'}")
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.terminate()
                proc.wait()


def table(results: dict) -> str:
    lines = ["| task | ours: steps/s | TQC+HER: steps/s | ours / TQC+HER |", "| --- | --- | --- | --- |"]
    for task, r in results["tasks"].items():
        lines.append(f"| {task} | {r['ours']:.1f} | {r['tqc_her']:.1f} | {r['ours'] / r['tqc_her']:.1f} |")
    return "\n".join(lines) + f"\n\n{results['steps']:,} training steps each, seed {results['seed']}.\n"


if __name__ == "__main__":
    args = tyro.cli(Args)
    out = Path(args.out)
    if any((out / name).exists() for name in ("results.json", "table.md")):
        sys.exit(f"error: {out} holds results already; give another --out")
    if not (script := Path(args.anchors) / "sb3_fetch.py").is_file():
        sys.exit(f"error: no sb3_fetch.py in --anchors {args.anchors}")
    if args.steps < 1:
        sys.exit(f"error: --steps must be positive, got {args.steps}")
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    seed, steps = str(args.seed), str(args.steps)
    evaluate_once = ["--eval-freq", steps, "--eval-episodes", "1"]
    theirs = {
        f"tqc_her__{task}": [args.anchor_python, str(script), "--algo", "tqc_her", "--trained-agent", "--env-id", task]
        + ["--seed", seed, "--steps", steps, *evaluate_once, "--out", str(runs / f"tqc_her__{task}")]
        for task in args.tasks
    }
    ours = {
        f"ours__{task}": [sys.executable, str(ROOT / "ipg_her_recipe.py"), "--env-id", task, "--seed", seed]
        + ["--total-timesteps", steps, *evaluate_once, "--eval-workers", "0", "--log-dir", str(runs / f"ours__{task}")]
        for task in args.tasks
    }
    run_all(theirs, runs)
    run_all(ours, runs)
    results = {"steps": args.steps, "seed": args.seed, "tasks": {}}
    for task in args.tasks:
        summary = json.loads((runs / f"tqc_her__{task}" / "summary.json").read_text())
        (run_dir,) = [p for p in (runs / f"ours__{task}").iterdir() if p.is_dir()]
        sps = read_run(run_dir)["charts/SPS"][-1][1]
        results["tasks"][task] = {
            "ours": sps,
            "tqc_her": summary["train_steps_per_s"],
            "tqc_hyperparams": summary["hyperparams"],
        }
    texts = {"results.json": json.dumps(results, indent=1), "table.md": table(results)}
    for name, text in texts.items():  # both, or neither
        (out / f".{name}.tmp").write_text(text)
    for name in texts:
        os.replace(out / f".{name}.tmp", out / name)
    print(texts["table.md"])
