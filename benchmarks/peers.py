"""The peers of a suite's rows, measured outside it: the anchors to beat (the zoo's TQC+HER
agents' first evaluations, Stable-Baselines3's runs in ``benchmarks/results/anchors/``) and
FetchReach's side-by-side run of benchmarks/against_sb3.py."""

import itertools
import json
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.stats import GOAL_LEVELS, first_eval_at
from benchmarks.tables import seed_ranges

ANCHORS = {  # (steps, level): first evaluations of the zoo's TQC+HER agents (v1, one env, one seed)
    "FetchPush-v4": ((100_000, 0.5), (200_000, 0.9)),
    "FetchPickAndPlace-v4": ((150_000, 0.5), (350_000, 0.9)),
    "FetchSlide-v4": ((300_000, 0.5),),
}
SIDE_BY_SIDE = Path(__file__).parent / "results" / "against_sb3" / "results.json"
ANCHOR_RUNS = Path(__file__).parent / "results" / "anchors"  # the anchor's runs, one folder each
SB3_NAMES = {"sac_her": "SAC+HER", "tqc_her": "TQC+HER", "ddpg_her": "DDPG+HER"}


@dataclass
class Peer:
    """Rows from outside the suite, measured by another script on one task: the anchor we must
    beat, or our own runs evaluated side by side with it. ``curves``: per seed, [[step, eval
    success], ...] (empty: not recorded); ``first``: per level, each seed's step of its first
    evaluation there (a level missing: not recorded); ``seconds``: the same in training seconds;
    ``sps``: each seed's steps per second of training (empty: not recorded)."""

    label: str
    anchor: bool
    seeds: str
    curves: list = field(default_factory=list)
    first: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    sps: list = field(default_factory=list)


def load_peers(side_by_side: Path) -> dict:
    """{env_id: [Peer]}: the TQC+HER zoo agents' first evaluations at the levels ANCHORS holds,
    and, if its results.json is there, FetchReach's side-by-side run of benchmarks/against_sb3.py:
    SB3 DDPG+HER (the anchor) and IPG+HER, evaluated alike."""
    peers = defaultdict(list)
    for env_id, points in ANCHORS.items():
        first = {level: [float(step)] for step, level in points}
        peers[env_id].append(Peer("TQC+HER zoo agent (anchor)", True, "1", first=first))
    if not side_by_side.is_file():
        return peers
    data = json.loads(side_by_side.read_text())
    budget = f"{data['steps']:,} steps" if "steps" in data else "its budget"
    for key, label, anchor in (
        ("sb3_ddpg_her", f"SB3 DDPG+HER (anchor; {budget})", True),
        ("ipg_her", f"IPG+HER side by side ({budget})", False),
    ):
        runs = data.get(key, [])
        if not runs:
            continue
        curves = [[list(p) for p in r["success"]] for r in runs]
        first = {level: [first_eval_at({"eval/success_rate": c}, level)[0] for c in curves] for level in GOAL_LEVELS[1]}
        seconds = {  # recorded per level, as train_s_to_0.9
            float(m[1]): [np.nan if r.get(m[0]) is None else r[m[0]] for r in runs]
            for m in filter(None, (re.fullmatch(r"train_s_to_([0-9.]+)", k) for k in runs[0]))
        }
        seeds = data.get("seeds", [])
        seeds = f"{len(runs)} ({seed_ranges(seeds)})" if len(seeds) == len(runs) else str(len(runs))
        peers["FetchReach-v4"].append(Peer(label, anchor, seeds, curves, first, seconds))
    return peers


def load_anchor_runs(folder: Path, seeds: dict) -> dict:
    """{env_id: [Peer]}: an anchor run here seed by seed (Stable-Baselines3 with HER and
    rl-baselines3-zoo's settings), each run's ``summary.json`` in a folder of its own under
    ``folder``, on the seeds the suite ran the task on (``seeds[env_id]``) only, so the anchor is
    compared on the same seeds or not at all: each seed's evaluations as its curve, its training
    seconds to each level (the wall time at that evaluation less every evaluation's so far) and
    its steps per second of training."""
    found = defaultdict(list)
    for path in sorted(folder.glob("*/summary.json")):
        run = json.loads(path.read_text())
        if run["seed"] in seeds.get(run["env"], ()):
            found[run["algo"], run["env"]].append(run)
    peers = defaultdict(list)
    for (algo, env_id), runs in sorted(found.items()):
        runs.sort(key=lambda r: r["seed"])
        first, seconds = defaultdict(list), defaultdict(list)
        for run, level in itertools.product(runs, GOAL_LEVELS[1]):
            evals, training = run["evals"], np.cumsum([-e["eval_s"] for e in run["evals"]])
            at = next((i for i, e in enumerate(evals) if e["eval_success"] >= level), None)
            first[level].append(np.nan if at is None else evals[at]["step"])
            seconds[level].append(np.nan if at is None else evals[at]["wall_s"] + training[at])
        curves = [[[e["step"], e["eval_success"]] for e in r["evals"]] for r in runs]
        seeds = f"{len(runs)} ({seed_ranges(r['seed'] for r in runs)})"
        label = f"SB3 {SB3_NAMES.get(algo, algo)} (anchor; zoo settings)"
        peers[env_id].append(
            Peer(label, True, seeds, curves, dict(first), dict(seconds), [r["train_steps_per_s"] for r in runs])
        )
    return peers
