"""Does the sigma rule cycle, and do a run's evaluation falls come at the entropy's troughs?

    python benchmarks/probes/sigma_cycle.py RUN_FOLDER [RUN_FOLDER ...] [--bin 10000] [--start 0]
    python benchmarks/probes/sigma_cycle.py --export CURVES_JSON --name RUN_NAME [...]

Reads each run folder's event files (``benchmarks/report.py``'s ``read_run``, resumed attempts
included), or each seed of one run name in an export (``report.py``'s ``curves.json``: the
evaluation, entropy and training success only, the entropy thinned to 300 points), and prints,
per bin of ``--bin`` environment steps, the mean of: the evaluation's success, the policy's
entropy, the sigma rule's alpha, the KL penalty's beta, the KL per update, the critic's Q on
replay batches and the training success; then the binned entropy's range per 100,000 steps. A
trough is a bin whose entropy is the lowest within two bins either side and below the run's
median; the last line sets the evaluations of the troughs' bins and of the bins just after them
against all the others.
"""

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.abspath(os.path.join(__file__, "../../..")))  # the project root
from benchmarks.events import read_run  # noqa: E402

COLUMNS = {
    "eval": "eval/success_rate",
    "entropy": "charts/policy_entropy",
    "alpha": "ipg/alpha",
    "beta": "losses/beta",
    "KL": "losses/approx_kl",
    "Q": "losses/q_values",
    "train": "charts/success_rate",
}


def binned(points, width: int, start: int = 0) -> dict[int, float]:
    """{bin's last step: mean value} over the bins (end - width, end] from ``start`` on."""
    sums = {}
    for step, value in points:
        if step > start:
            end = start + width * int(np.ceil((step - start) / width))
            sums.setdefault(end, []).append(value)
    return {end: float(np.mean(values)) for end, values in sorted(sums.items())}


def troughs(entropy: dict[int, float]) -> list[int]:
    """The bins whose entropy is the lowest within two bins either side and below the median."""
    ends, h = list(entropy), np.array(list(entropy.values()))
    return [ends[i] for i in range(len(h)) if h[i] < np.median(h) and h[i] == h[max(i - 2, 0) : i + 3].min()]


def ranges(entropy: dict[int, float], width: int = 100_000) -> dict[int, tuple[float, float]]:
    """{last step of each ``width`` steps: (lowest, highest) binned entropy in them}."""
    out = {}
    for end, h in entropy.items():
        span = width * int(np.ceil(end / width))
        lo, hi = out.get(span, (h, h))
        out[span] = (min(lo, h), max(hi, h))
    return out


def at_troughs(evals: dict[int, float], low: list[int], width: int) -> tuple[list, list]:
    """The evaluations of the troughs' bins and of the bins just after them; all the others."""
    near = set(low) | {end + width for end in low}
    return [e for end, e in evals.items() if end in near], [e for end, e in evals.items() if end not in near]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", help="run folders")
    parser.add_argument("--export", help="an export's curves.json instead of run folders")
    parser.add_argument("--name", help="with --export: the run name (e.g. ipg_her_1000k__Task-v1)")
    parser.add_argument("--bin", type=int, default=10_000, help="environment steps per bin")
    parser.add_argument("--start", type=int, default=0, help="leave out the steps before this")
    args = parser.parse_args()
    if bool(args.runs) == bool(args.export) or bool(args.export) != bool(args.name):
        parser.error("give run folders, or --export with --name")
    if args.export:
        runs = {
            f"{args.name} seed {seed}": scalars
            for seed, scalars in json.loads(Path(args.export).read_text())[args.name].items()
        }
    else:
        runs = {
            os.path.basename(os.path.normpath(run)): read_run(
                max(Path(run).glob("**/events.out.tfevents.*")).parent, tags=tuple(COLUMNS.values())
            )
            for run in args.runs
        }
    for label, scalars in runs.items():
        table = {name: binned(scalars.get(tag, []), args.bin, args.start) for name, tag in COLUMNS.items()}
        print(f"{label}\n  step  " + "  ".join(f"{name:>7}" for name in COLUMNS))
        for end in table["entropy"]:
            row = (f"{table[name][end]:7.3g}" if end in table[name] else "      -" for name in COLUMNS)
            print(f"  {end // 1000:4d}k " + "  ".join(row))
        spans = ranges(table["entropy"]).items()
        print("  entropy per 100k: " + ", ".join(f"{end // 1000}k {lo:.0f} to {hi:.0f}" for end, (lo, hi) in spans))
        low = troughs(table["entropy"])
        near, rest = at_troughs(table["eval"], low, args.bin)
        print(f"  troughs at {', '.join(f'{end // 1000}k' for end in low)}")
        print(
            f"  evaluation: mean {np.mean(near):.2f} in the {len(near)} bins at or just after a "
            f"trough, {np.mean(rest):.2f} in the {len(rest)} others"
        )
