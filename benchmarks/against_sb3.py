"""IPG + HER against Stable-Baselines3 DDPG + HER on FetchReach-v4, side by side.

For each seed, one after the other on a quiet machine: ``ipg_her.py`` with the defaults, then
the anchor script ``sb3_fetchreach.py --algo ddpg_her`` (in ``--anchors``, a folder outside this
repository, run with the python of a virtual environment that has Stable-Baselines3), both
evaluated every 500 steps on 20 episodes. Then the raw stepping rate (``env_speed.py``) and the
main job ``python ipg_her.py --env-id FetchReach-v4 --seed 1`` as a user runs it. Writes
``results.json`` and ``table.md`` into ``--out``:

    python benchmarks/against_sb3.py --anchor-python $ANCHOR_PY \\
        --anchors $ANCHORS --seeds 21 22 23 24 25 --out benchmarks/results/against_sb3

Training seconds exclude evaluation for both: ours is ``step / charts/SPS`` (SPS counts training
time only, and evaluation runs in this process with ``--eval-workers 0``), SB3's is its
``wall_s`` minus the evaluation seconds so far.
"""

import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.events import read_run  # noqa: E402

THRESHOLD = 0.9


@dataclass
class Args:
    anchor_python: str
    """python of the anchors' virtual environment (has stable-baselines3)"""
    anchors: str
    """folder of the anchor scripts sb3_fetchreach.py and env_speed.py (not in this repository)"""
    seeds: list[int] = field(default_factory=lambda: [21, 22, 23, 24, 25])
    """seeds (not the ones the defaults were tuned on: 1-5)"""
    steps: int = 5000
    """training steps per run"""
    out: str = "benchmarks/results/against_sb3"
    """output folder (its runs/ holds our event files and SB3's summaries)"""
    main_job: bool = True
    """also time the main job against the raw stepping rate"""


def first_step_at(curve: list[tuple[int, float]], seconds: dict[int, float]):
    """(steps, training seconds) of the first evaluation at THRESHOLD or more, else Nones."""
    for step, success in curve:
        if success >= THRESHOLD:
            return step, seconds[step]
    return None, None


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    print("$", " ".join(cmd), flush=True)
    result = subprocess.run(cmd, env=env, capture_output=True, text=True, **kwargs)
    if result.returncode != 0:
        sys.exit(f"error: failed ({result.returncode}):\n{result.stderr[-2000:]}")
    return result


def ours(seed: int, args: Args, runs: Path) -> dict:
    log_dir = runs / f"ipg_her_seed{seed}"
    flags = ["--total-timesteps", str(args.steps), "--eval-freq", "500", "--eval-workers", "0"]
    run([sys.executable, str(ROOT / "ipg_her.py"), "--seed", str(seed), "--log-dir", str(log_dir), *flags], cwd=ROOT)
    (run_dir,) = [p for p in log_dir.iterdir() if p.is_dir()]
    s = read_run(run_dir)
    sps = dict(s["charts/SPS"])
    seconds = {step: step / sps[step] for step, _ in s["eval/success_rate"]}
    steps, secs = first_step_at(s["eval/success_rate"], seconds)
    return {"steps_to_0.9": steps, "train_s_to_0.9": secs, "success": s["eval/success_rate"], "run_dir": str(run_dir)}


def sb3(seed: int, args: Args, runs: Path) -> dict:
    out = runs / f"sb3_ddpg_her_seed{seed}"
    run(
        [
            args.anchor_python,
            os.path.join(args.anchors, "sb3_fetchreach.py"),
            "--algo",
            "ddpg_her",
            "--seed",
            str(seed),
            "--steps",
            str(args.steps),
            "--eval-freq",
            "500",
            "--out",
            str(out),
        ]
    )
    evals = json.loads((out / "summary.json").read_text())["evals"]
    seconds, eval_s = {}, 0.0
    for e in evals:
        eval_s += e["eval_s"]
        seconds[e["step"]] = e["wall_s"] - eval_s
    curve = [(e["step"], e["eval_success"]) for e in evals]
    steps, secs = first_step_at(curve, seconds)
    return {"steps_to_0.9": steps, "train_s_to_0.9": secs, "success": curve}


def main_job(args: Args, runs: Path) -> dict:
    speed = run([args.anchor_python, os.path.join(args.anchors, "env_speed.py")]).stdout
    single = next(json.loads(line) for line in speed.splitlines() if '"single"' in line)
    t0 = time.perf_counter()
    log = run(
        [
            sys.executable,
            str(ROOT / "ipg_her.py"),
            "--env-id",
            "FetchReach-v4",
            "--seed",
            "1",
            "--log-dir",
            str(runs / "main_job"),
        ],
        cwd=ROOT,
    ).stdout
    wall = time.perf_counter() - t0
    evaluations = len(re.findall(r"eval_success=", log))
    steps = 30_000 + evaluations * 20 * 50  # FetchReach episodes are 50 steps
    raw = steps / single["steps_per_s"]
    return {
        "wall_s": wall,
        "env_steps": steps,
        "raw_steps_per_s": single["steps_per_s"],
        "raw_s": raw,
        "ratio": wall / raw,
        "env_speed": speed,
    }


def median(values):
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def table(results: dict) -> str:
    fmt = lambda v, f: "-" if v is None else f.format(v)  # noqa: E731
    lines = [
        "| method | steps to eval success >= 0.9 (per seed) | median | training seconds to 0.9 (per seed) | median |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name in ("ipg_her", "sb3_ddpg_her"):
        rows = results[name]
        steps = [r["steps_to_0.9"] for r in rows]
        secs = [r["train_s_to_0.9"] for r in rows]
        lines.append(
            f"| {name} | {' / '.join(fmt(s, '{:,}') for s in steps)} | "
            f"{fmt(median(steps), '{:,.0f}')} | {' / '.join(fmt(s, '{:.1f}') for s in secs)} | "
            f"{fmt(median(secs), '{:.1f}')} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    args = tyro.cli(Args)
    out = Path(args.out)
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    results = {"seeds": args.seeds, "steps": args.steps, "ipg_her": [], "sb3_ddpg_her": []}
    for seed in args.seeds:  # one after the other, ours then theirs
        results["ipg_her"].append(ours(seed, args, runs))
        results["sb3_ddpg_her"].append(sb3(seed, args, runs))
        print(table(results), flush=True)
    if args.main_job:
        results["main_job"] = main_job(args, runs)
        print(json.dumps({k: v for k, v in results["main_job"].items() if k != "env_speed"}))
    (out / "results.json").write_text(json.dumps(results, indent=1))
    (out / "table.md").write_text(table(results))
    print(table(results))
