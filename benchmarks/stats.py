"""The statistics of benchmarks/report.py: what each task is measured by (its threshold, its
levels), a run's final figure and the steps it took to a level, and over seeds the median counting
the seeds that never got there, the interquartile mean and percentile bootstrap intervals."""

import numpy as np

THRESHOLDS = {
    "Hopper-v5": ("charts/episodic_return", 2000.0),
    "FetchReach-v4": ("eval/success_rate", 0.9),
    "FetchPush-v4": ("eval/success_rate", 0.5),
    "FetchPickAndPlace-v4": ("eval/success_rate", 0.9),
    "FetchSlide-v4": ("eval/success_rate", 0.7),
    "HandReach-v3": ("eval/success_rate", 0.9),
    "HandManipulateBlockRotateZ-v1": ("eval/success_rate", 0.9),
    "PointMaze_Medium-v3": ("eval/success_rate", 0.9),
}
TASK_LEVELS = {  # the per-task table's levels: evaluation success, or Hopper's evaluation return
    "Hopper-v5": ("eval/episodic_return", (1000.0, 2000.0, 3000.0)),
}
GOAL_LEVELS = ("eval/success_rate", (0.5, 0.7, 0.9))
GOAL_TASKS = ("Fetch", "Hand", "PointMaze", "AntMaze")  # gymnasium-robotics' goal tasks


def reported_by_success(env_id: str) -> bool:
    """A goal task's figure is its evaluation success; any other task's, its return."""
    return env_id.startswith(GOAL_TASKS)


def task_levels(env_id: str) -> tuple[str, tuple[float, ...]]:
    """The per-task table's figure and levels: evaluation success on goal tasks, else return."""
    if env_id in TASK_LEVELS:
        return TASK_LEVELS[env_id]
    return GOAL_LEVELS if reported_by_success(env_id) else ("eval/episodic_return", ())


def iqm(x: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (robust to one bad seed). rliable's IQM is
    scipy's 25% ``trim_mean``, the same numbers (checked for 3 to 11 seeds); we do not import it
    for four lines, since it would bring arch, scipy, pandas and seaborn into every install."""
    x = np.sort(np.asarray(x, float))
    lo, hi = int(np.floor(0.25 * len(x))), int(np.ceil(0.75 * len(x)))
    return float(x[lo:hi].mean()) if hi > lo else float(x.mean())


def final_performance(run: dict, goal_task: bool, window: int) -> float:
    """Mean of the last ``window`` training episodes' returns; on goal tasks their success rate
    (charts/success_rate is already the share of the last 100 episodes)."""
    if goal_task:
        return run["charts/success_rate"][-1][1] if run.get("charts/success_rate") else float("nan")
    returns = [v for _, v in run.get("charts/episodic_return", [])]
    return float(np.mean(returns[-window:])) if returns else float("nan")


def steps_to_threshold(run: dict, env_id: str, window: int) -> float:
    """The first step where the task's figure reaches its threshold (NaN: never). On the
    training return the figure is the mean of the last ``window`` episodes, counted only once
    ``window`` episodes exist (a mean of the first few episodes is not that figure)."""
    tag, threshold = THRESHOLDS.get(env_id, ("charts/episodic_return", np.inf))
    points = run.get(tag, [])
    if tag == "charts/episodic_return":
        values = np.array([v for _, v in points])
        running = [values[i - window + 1 : i + 1].mean() for i in range(window - 1, len(values))]
        points = [[s, r] for (s, _), r in zip(points[window - 1 :], running, strict=True)]
    return next((s for s, v in points if v >= threshold), float("nan"))


def median_steps(reach) -> float:
    """Median over *all* seeds of the steps to threshold, a seed that never reached it counting
    as infinitely many: inf when half of them or more never did (with exactly half, the median
    averages a finite count and inf)."""
    return float(np.median(np.where(np.isfinite(reach), reach, np.inf)))


def bootstrap_band(curves: np.ndarray, rng: np.random.Generator, n: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """95% bootstrap confidence interval of the mean over seeds, pointwise."""
    seeds = curves.shape[0]
    means = np.stack([np.nanmean(curves[rng.integers(0, seeds, seeds)], 0) for _ in range(n)])
    return np.nanpercentile(means, 2.5, 0), np.nanpercentile(means, 97.5, 0)


def bootstrap_interval(values, statistic, rng, n: int = 2000) -> tuple[float, float, float]:
    """``statistic`` over seeds and its 95% percentile bootstrap interval, the seeds resampled
    with replacement ``n`` times: (value, lo, hi); lo and hi NaN with fewer than two seeds."""
    values = np.asarray(values, float)
    if len(values) < 2:
        return float(statistic(values)), np.nan, np.nan
    resampled = [statistic(values[i]) for i in rng.integers(0, len(values), (n, len(values)))]
    lo, hi = np.percentile(resampled, [2.5, 97.5])
    return float(statistic(values)), float(lo), float(hi)


def first_eval_at(run: dict, level: float, tag: str = "eval/success_rate") -> tuple[float, float]:
    """(step, training seconds) of the first evaluation with ``tag`` >= ``level`` (NaN: none).
    Training seconds are step / ``charts/SPS`` logged at that step (SPS is steps over training
    time, evaluation excluded, carried across a resumed run's sessions)."""
    step = next((s for s, v in run.get(tag, []) if v >= level), np.nan)
    sps = [v for s, v in run.get("charts/SPS", []) if s <= step]
    return step, step / sps[-1] if sps and sps[-1] > 0 else np.nan


def value_at(run: dict, tag: str, budget: float) -> float:
    """The last value of ``tag`` logged at or before ``budget`` steps (NaN: none yet)."""
    return ([v for s, v in run.get(tag, []) if s <= budget] or [np.nan])[-1]


def steps_at(runs: list, tag: str, budget: float) -> str:
    """The step(s) at which ``value_at`` finds its values: "81,920" (Hopper evaluates every
    20,480 steps, so "at 100,000" is the evaluation at 81,920), or a range if runs differ."""
    steps = {([s for s, _ in r.get(tag, []) if s <= budget] or [None])[-1] for r in runs}
    steps = sorted(s for s in steps if s is not None)
    if not steps:
        return "-"
    return f"{steps[0]:,}" if len(steps) == 1 else f"{steps[0]:,}-{steps[-1]:,}"


def median_over_updates(run: dict, tag: str) -> float | None:
    return float(np.median([v for _, v in run[tag]])) if run.get(tag) else None


def variance_ratio(run: dict, prefix: str) -> float | None:
    """Median over updates of grad_var_cv / grad_var (the same update's two measurements)."""
    if not run.get(f"{prefix}/grad_var"):
        return None
    without = dict(map(tuple, run[f"{prefix}/grad_var"]))
    ratios = [v / without[s] for s, v in run[f"{prefix}/grad_var_cv"] if without.get(s, 0) > 0]
    return float(np.median(ratios)) if ratios else None
