"""Two algorithms run on the same seeds, compared seed by seed from a report.py export.

    python benchmarks/paired.py benchmarks/results/paper_fresh/curves.json \\
        qprop_ppo__Hopper-v5 ppo_kl__Hopper-v5

Per seed, each one's final figure (report.py's ``final``: the mean of the last 100 training
returns, or the training success rate on goal tasks) and the difference A - B; then the mean
difference with its 95% percentile bootstrap interval (seeds resampled in pairs, 2,000 times,
generator seeded 0) and the two-sided exact sign-flip permutation test of a zero mean difference.
"""

import itertools
import json
import sys

import numpy as np


def paired(export: dict, a: str, b: str, resamples: int = 2000, seed: int = 0) -> dict:
    """The seeds both groups ran, their figures and differences, the mean difference with its
    bootstrap interval, and the permutation test's p-value."""
    seeds = sorted(set(export[a]) & set(export[b]), key=int)
    fa, fb = (np.array([export[g][s]["final"] for s in seeds]) for g in (a, b))
    d = fa - fb
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), (resamples, len(d)))].mean(1)
    flips = np.array(list(itertools.product((1, -1), repeat=len(d))))  # every sign assignment
    p = np.mean(np.abs((flips * d).mean(1)) >= abs(d.mean()) - 1e-9)
    return {
        "seeds": seeds,
        "a": fa,
        "b": fb,
        "difference": d,
        "mean": d.mean(),
        "interval": np.percentile(means, [2.5, 97.5]),
        "p": p,
    }


if __name__ == "__main__":
    path, a, b = sys.argv[1:4]
    r = paired(json.loads(open(path).read()), a, b)
    print(f"| seed | {a} | {b} | difference |\n| --- | --- | --- | --- |")
    for row in zip(r["seeds"], r["a"], r["b"], r["difference"], strict=True):
        print(f"| {row[0]} | {row[1]:,.0f} | {row[2]:,.0f} | {row[3]:+,.0f} |")
    lo, hi = r["interval"]
    print(
        f"\nmean difference {r['mean']:+,.0f}, 95% paired bootstrap interval [{lo:+,.0f}, "
        f"{hi:+,.0f}] over {len(r['seeds'])} seeds; A ahead on {np.sum(r['difference'] > 0)}; "
        f"exact sign-flip permutation test p = {r['p']:.3f} (two-sided)"
    )
