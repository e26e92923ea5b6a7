"""The figures of benchmarks/report.py: learning curves over seeds (mean and bootstrap band, or
median and range), the anchors drawn in, the paper's Figures 3-5, the mixing study's success
against nu and one figure per task."""

import re
import warnings
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.stats import bootstrap_band, reported_by_success, steps_at, value_at  # noqa: E402
from benchmarks.suites import Report  # noqa: E402
from benchmarks.tables import LABELS  # noqa: E402


def curve_on_grid(points: list, grid: np.ndarray, smooth: int) -> np.ndarray:
    """A run's curve, smoothed by a moving average of ``smooth`` points, interpolated on grid."""
    steps, values = np.array(points, float).T
    if smooth > 1 and len(values) >= smooth:
        values = np.convolve(values, np.ones(smooth) / smooth, mode="valid")
        steps = steps[smooth - 1 :]
    out = np.interp(grid, steps, values)
    out[(grid < steps[0]) | (grid > steps[-1])] = np.nan
    return out


def plot(
    ax,
    groups: dict,
    names: list,
    env_id: str,
    tag: str,
    rng,
    smooth: int = 1,
    per_episode: bool = False,
    median: bool = False,
) -> None:
    warnings.simplefilter("ignore", RuntimeWarning)  # grid points past a seed's last step are NaN on purpose
    for name in names:
        runs = groups.get(f"{name}__{env_id}", {})
        runs = [r[tag] for r in runs.values() if r.get(tag)]
        if not runs:
            continue
        grid = np.linspace(0, max(p[-1][0] for p in runs), 200)
        curves = np.stack([curve_on_grid(p, grid, smooth) for p in runs])
        x = grid / 50 if per_episode else grid  # FetchReach: 50 steps per episode
        centre = np.nanmedian(curves, 0) if median else np.nanmean(curves, 0)
        every_seed = grid <= min(p[-1][0] for p in runs)
        label = f"{LABELS.get(name, name)} ({len(runs)} seeds)"
        (line,) = ax.plot(x, np.where(every_seed, centre, np.nan), label=label)
        if not every_seed.all():  # past the shortest seed: the seeds that ran on, dashed
            past = grid >= grid[every_seed][-1]
            ax.plot(x, np.where(past, centre, np.nan), color=line.get_color(), ls="--")
        if median:  # the band: the lowest and highest seed
            lo, hi = np.nanmin(curves, 0), np.nanmax(curves, 0)
        else:
            lo, hi = bootstrap_band(curves, rng)
        ax.fill_between(x, lo, hi, alpha=0.2)
    ax.set_xlabel("episodes" if per_episode else "environment steps")
    ax.set_ylabel(tag.split("/")[-1].replace("_", " ") + (" (eval)" if tag.startswith("eval") else ""))
    ax.set_title(env_id)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)


def draw_anchors(ax, peers: list, per_episode: bool = False) -> None:
    """The anchors among ``peers`` on a success figure, in black: a recorded curve as the median
    over its seeds with the band from the lowest to the highest seed; first evaluations at a
    level as stars, the levels dotted."""
    scale = 50 if per_episode else 1  # episodes of 50 steps, as plot(per_episode=True)
    for peer in (p for p in peers if p.anchor):
        if peer.curves:
            grid = np.array(sorted({s for c in peer.curves for s, _ in c}), float)
            values = np.stack([curve_on_grid(c, grid, 1) for c in peer.curves])
            label = f"{peer.label.split(' (')[0]}, anchor: median of {len(values)} seeds, min-max"
            ax.plot(grid / scale, np.nanmedian(values, 0), "k-o", markersize=3, linewidth=1.2, label=label)
            ax.fill_between(grid / scale, np.nanmin(values, 0), np.nanmax(values, 0), color="k", alpha=0.1)
        else:
            steps, levels = zip(*[(s[0], level) for level, s in peer.first.items()], strict=True)
            ax.plot(np.array(steps) / scale, levels, "k*", markersize=10, label="TQC+HER zoo agent reached")
            for level in levels:
                ax.axhline(level, color="k", linestyle=":", linewidth=0.8)
        ax.legend(fontsize=8)


def draw_paper_figures(groups: dict, rng, peers: dict | None = None) -> dict:
    """The paper's Figures 3 (Hopper: length and return), 4 (FetchReach: entropy and return) and
    5 (success, with FetchReach's anchor among ``peers``), {file name: figure}; none for a task
    without runs."""
    tasks, figures = {g.split("__")[1] for g in groups}, {}

    def add(fig, name: str) -> None:
        fig.tight_layout()
        figures[name] = fig

    if "Hopper-v5" in tasks:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, tag in zip(axes, ("charts/episodic_length", "charts/episodic_return"), strict=True):
            plot(ax, groups, ["ppo_kl", "qprop_ppo"], "Hopper-v5", tag, rng, smooth=20)
        add(fig, "fig3_hopper.png")
    if "FetchReach-v4" in tasks:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        names = ["ppo_kl", "qprop_ppo", "ipg_her"]
        plot(axes[0], groups, names, "FetchReach-v4", "charts/policy_entropy", rng)
        plot(axes[1], groups, names, "FetchReach-v4", "charts/episodic_return", rng, smooth=10)
        add(fig, "fig4_fetchreach.png")
        fig, ax = plt.subplots(figsize=(6, 4))
        plot(ax, groups, ["ppo_kl", "ipg", "ipg_her"], "FetchReach-v4", "eval/success_rate", rng, per_episode=True)
        draw_anchors(ax, (peers or {}).get("FetchReach-v4", []), per_episode=True)
        add(fig, "fig5_fetchreach_success.png")
    return figures


def mixing_variant(group: str) -> tuple[float, str, str] | None:
    """``ipg_her_nu0.2_b100_cv__FetchReach-v4`` -> (0.2, "b100_cv", "FetchReach-v4"); None for
    a run without nu (Q-Prop)."""
    name, env_id = group.split("__")
    match = re.search(r"nu([0-9.]+)_(.+)", name)
    return (float(match[1]), match[2], env_id) if match else None


def draw_mixing_figures(groups: dict, rng, early: int = 5000) -> dict:
    """Per task: evaluation success against nu, finally and at an ``early`` budget, one line per
    variant (on-policy batch, control variate), mean over seeds with 95% bootstrap intervals;
    and the diagnostics over training: effective nu and the control variate's variance ratio;
    {file name: figure}."""
    figures = {}
    parsed = {g: mixing_variant(g) for g in groups}
    for env_id in sorted({p[2] for p in parsed.values() if p}):
        variants = defaultdict(dict)  # variant -> {nu: [runs]}
        for group, runs in groups.items():
            if parsed[group] and parsed[group][2] == env_id:
                nu, variant, _ = parsed[group]
                variants[variant][nu] = list(runs.values())
        goal = reported_by_success(env_id)
        tag = "eval/success_rate" if goal else "eval/episodic_return"
        first = early if goal else 100_000  # the early budget, in steps
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        evaluated = steps_at([r for g in variants.values() for rs in g.values() for r in rs], tag, first)
        early_title = f"{env_id}: evaluation at {evaluated} (the last by {first:,} steps)"
        for ax, budget, label, title in ((axes[0], np.inf, "final", env_id), (axes[1], first, "early", early_title)):
            for variant in sorted(variants):
                nus = sorted(variants[variant])
                values = [np.array([value_at(r, tag, budget) for r in variants[variant][nu]]) for nu in nus]
                means = [np.nanmean(v) for v in values]
                boot = [[np.nanmean(v[rng.integers(0, len(v), len(v))]) for _ in range(1000)] for v in values]
                lo, hi = np.percentile(boot, 2.5, 1), np.percentile(boot, 97.5, 1)
                seeds = min(len(v) for v in values)
                ax.errorbar(
                    nus,
                    means,
                    yerr=[np.subtract(means, lo), np.subtract(hi, means)],
                    marker="o",
                    capsize=3,
                    label=f"{variant} ({seeds}+ seeds)",
                )
            ax.set_xlabel("nu")
            ax.set_ylabel(f"{tag.split('/')[1].replace('_', ' ')} (eval, {label})")
            ax.set_title(title, fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.tight_layout()
        figures[f"mixing_{env_id}_nu.png"] = fig
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for variant in sorted(variants):
            for nu in sorted(variants[variant]):
                runs = [r for r in variants[variant][nu] if r.get("ipg/effective_nu")]
                if not runs:
                    continue
                steps, eff = np.array(runs[0]["ipg/effective_nu"]).T
                axes[0].plot(steps, eff, label=f"nu {nu} {variant}", lw=1)
                if "cv" not in variant:
                    steps, var = np.array(runs[0]["ipg/grad_var"]).T
                    _, var_cv = np.array(runs[0]["ipg/grad_var_cv"]).T
                    axes[1].semilogy(steps, var_cv / var, label=f"nu {nu} {variant}", lw=1)
        axes[0].set_ylabel("effective nu (seed 1)")
        axes[1].set_ylabel("gradient variance, with CV / without (seed 1)")
        for ax in axes:
            ax.set_xlabel("environment steps")
            ax.set_title(env_id)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=6, ncol=2)
        fig.tight_layout()
        figures[f"mixing_{env_id}_diagnostics.png"] = fig
    return figures


def draw_task_figures(groups: dict, rng, peers: dict, suite: str, settings: Report) -> dict:
    """One figure per task with every variant of the suite: a goal task's evaluation success (in
    episodes or steps, mean or median as ``settings`` say) with its anchors among ``peers``, any
    other task's training return; {file name: figure}."""
    figures = {}
    for env_id in sorted({g.split("__")[1] for g in groups}):
        names = sorted(g.split("__")[0] for g in groups if g.endswith(f"__{env_id}"))
        fig, ax = plt.subplots(figsize=(7, 4))
        if reported_by_success(env_id):
            plot(ax, groups, names, env_id, "eval/success_rate", rng, per_episode=settings.per_episode, median=settings.median)
            draw_anchors(ax, peers.get(env_id, []), per_episode=settings.per_episode)
        else:
            plot(ax, groups, names, env_id, "charts/episodic_return", rng, smooth=20)
        fig.tight_layout()
        figures[f"{suite}_{env_id}.png"] = fig
    return figures
