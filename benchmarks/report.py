"""Figures and a results table from the TensorBoard event files of a benchmark suite (nothing else).

    python benchmarks/report.py --suite paper                      # read benchmarks/runs/paper
    python benchmarks/report.py --suite paper --from-export        # redraw from the export

Writes into ``--results-dir`` (default ``benchmarks/results/{suite}``) ``curves.json`` (a compact
export of every run's curves, enough to redraw everything) and ``results.md`` (the tables and how
they were measured: among them one per task with the median and IQM of the final evaluation, the
steps and training time to three levels, and the anchor, the peer to beat, where one is recorded:
``ANCHORS`` below, ``benchmarks/results/against_sb3/results.json``, and the anchor's own runs in
``benchmarks/results/anchors/``), and PNG figures, the anchor drawn in, into ``--figures-dir``
(default ``docs/img/{suite}`` for the suite's own results folder, as the docs site serves only
``docs/``, and the ``--results-dir`` folder itself for any other), linked from ``results.md``. The
files change together or not at all (each written beside itself, then renamed over it). What a
suite's report shows beyond the common tables (its figures, budgets, levels) is its ``Report`` in
``benchmarks/run.py``'s ``SUITES``. Run folders that lack a run of the export they would replace
are refused (``--keep-export``, ``--replace-export``); a run folder left out of the report (failed,
stopped, still running, no exit code) is named in a warning saying why.
"""

import contextlib
import errno
import json
import os
import re
import sys
import warnings
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import tyro  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.events import (  # noqa: E402
    collect,
    read_export,
    read_run,  # noqa: F401  against_sb3.py, probes/sigma_cycle.py, tests/test_ipg.py import it here
)
from benchmarks.peers import ANCHOR_RUNS, SIDE_BY_SIDE, load_anchor_runs, load_peers  # noqa: E402
from benchmarks.stats import (  # noqa: E402
    bootstrap_band,
    reported_by_success,
    steps_at,
    value_at,
)
from benchmarks.suites import SUITES, Report  # noqa: E402  each suite's settings, beside its runs
from benchmarks.tables import (  # noqa: E402
    LABELS,
    diagnostics_table,
    finalists_table,
    reach_table,
    success_table,
    table,
    task_tables,
    task_tables_note,
)


@dataclass
class Args:
    suite: str = "paper"
    """the suite folder to read"""
    runs_dir: str = "benchmarks/runs"
    """parent of the suite folders written by run.py"""
    results_dir: str = ""
    """where to write the export and results.md (default benchmarks/results/{suite})"""
    figures_dir: str = ""
    """where to draw the figures, linked from results.md (default: docs/img/{suite} for the suite's
    own results folder, as the docs site serves only docs/; the --results-dir folder itself for
    any other)"""
    from_export: bool = False
    """redraw from the results folder's curves.json instead of the event files"""
    window: int = 100
    """final performance: mean over this many last training episodes"""
    seed: int = 0
    """seed of the bootstrap confidence intervals"""
    merge_export: str = ""
    """add the groups of this earlier curves.json that the runs lack, marked as earlier code's"""
    merge_label: str = "earlier code"
    """what the merged groups were measured on (shown in the table's note)"""
    page: str = ""
    """also write the tables and links to the figures into this page, between its suite markers"""
    keep_export: bool = False
    """also keep the runs in the suite's curves.json that the run folders lack (other machines')"""
    replace_export: bool = False
    """replace the suite's curves.json even where it holds runs the run folders lack (without
    it, or --keep-export, the report refuses and leaves the export as it is)"""
    include_unfinished: bool = False
    """also read runs not finished yet (a long run between sessions), marked with their step"""
    side_by_side: str = ""
    """against_sb3.py's results.json, FetchReach's anchor (default: the committed one)"""
    anchor_runs: str = ""
    """folder of the anchor's runs, a summary.json each (default: benchmarks/results/anchors)"""


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
    warnings.simplefilter(
        "ignore", RuntimeWarning
    )  # grid points past a seed's last step are NaN on purpose
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
    ax.set_ylabel(
        tag.split("/")[-1].replace("_", " ") + (" (eval)" if tag.startswith("eval") else "")
    )
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
            ax.plot(grid / scale, np.nanmedian(values, 0), "k-o", markersize=3, linewidth=1.2,
                    label=label)  # fmt: skip
            ax.fill_between(
                grid / scale, np.nanmin(values, 0), np.nanmax(values, 0), color="k", alpha=0.1
            )
        else:
            steps, levels = zip(*[(s[0], level) for level, s in peer.first.items()], strict=True)
            ax.plot(np.array(steps) / scale, levels, "k*", markersize=10,
                    label="TQC+HER zoo agent reached")  # fmt: skip
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
        plot(ax, groups, ["ppo_kl", "ipg", "ipg_her"], "FetchReach-v4", "eval/success_rate", rng,
             per_episode=True)  # fmt: skip
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
        evaluated = steps_at([r for g in variants.values() for rs in g.values() for r in rs],
                             tag, first)  # fmt: skip
        early_title = f"{env_id}: evaluation at {evaluated} (the last by {first:,} steps)"
        for ax, budget, label, title in ((axes[0], np.inf, "final", env_id),
                                         (axes[1], first, "early", early_title)):  # fmt: skip
            for variant in sorted(variants):
                nus = sorted(variants[variant])
                values = [np.array([value_at(r, tag, budget) for r in variants[variant][nu]])
                          for nu in nus]  # fmt: skip
                means = [np.nanmean(v) for v in values]
                boot = [[np.nanmean(v[rng.integers(0, len(v), len(v))]) for _ in range(1000)]
                        for v in values]  # fmt: skip
                lo, hi = np.percentile(boot, 2.5, 1), np.percentile(boot, 97.5, 1)
                seeds = min(len(v) for v in values)
                ax.errorbar(nus, means, yerr=[np.subtract(means, lo), np.subtract(hi, means)],
                            marker="o", capsize=3, label=f"{variant} ({seeds}+ seeds)")  # fmt: skip
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
            plot(ax, groups, names, env_id, "eval/success_rate", rng,
                 per_episode=settings.per_episode, median=settings.median)  # fmt: skip
            draw_anchors(ax, peers.get(env_id, []), per_episode=settings.per_episode)
        else:
            plot(ax, groups, names, env_id, "charts/episodic_return", rng, smooth=20)
        fig.tight_layout()
        figures[f"{suite}_{env_id}.png"] = fig
    return figures


def refuse(message: str) -> int:
    """Bad input or a result at risk: one line on stderr, exit code 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def write_together(files: dict) -> None:
    """Write each file of ``files`` ({path: text, or a figure to save as PNG}) to a temporary
    beside it, then rename each over its file (a rename within a folder is atomic), so that the
    files change together or not at all: an OSError while writing (a read-only folder, a full
    disk) removes the temporaries and leaves every file as it was; it is raised naming the file."""
    temporaries = {}
    try:
        for path, content in files.items():
            if path.is_dir():  # found now, not when half the files are renamed
                raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR))
            temporaries[path] = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            if isinstance(content, str):
                temporaries[path].write_text(content)
            else:
                content.savefig(temporaries[path], dpi=100, format="png")
    except OSError as error:
        for temporary in temporaries.values():
            with contextlib.suppress(OSError):
                temporary.unlink(missing_ok=True)
        raise OSError(error.errno, error.strerror or str(error), str(path)) from error
    for path, temporary in temporaries.items():
        os.replace(temporary, path)


def main(args: Args) -> int:
    if args.suite not in SUITES:  # its settings would be guessed and its results.md rewritten
        known = ", ".join(SUITES)
        return refuse(f"--suite {args.suite}: not a suite of benchmarks/run.py ({known}); "
                      "--results-dir names another export folder")  # fmt: skip
    if args.window < 1:
        return refuse(
            f"--window {args.window}: the final return is the mean of the last --window training "
            "episodes; give 1 or more"
        )
    # a bad --page is caught before anything is read or written
    page = Path(args.page)
    start, end = f"<!-- results:{args.suite}:start -->", f"<!-- results:{args.suite}:end -->"
    if args.page and not page.is_file():
        return refuse(f"--page {page}: no such file; name an existing Markdown page holding the "
                      f"markers {start} and {end}, or leave out --page")  # fmt: skip
    if args.page and not page.read_text().count(start) == page.read_text().count(end) == 1:
        return refuse(f"--page {page} needs the markers {start} and {end}, once each, around "
                      "the place to write; add them")  # fmt: skip
    merged = Path(args.merge_export)
    if args.merge_export and not merged.is_file():
        return refuse(
            f"--merge-export {merged}: no such file; name an earlier curves.json, or leave out "
            "--merge-export"
        )
    try:
        to_merge = read_export(merged) if args.merge_export else {}
    except (OSError, ValueError) as error:
        return refuse(
            f"--merge-export {merged} is not a readable export ({error}); name an earlier "
            "curves.json"
        )
    own = Path(f"benchmarks/results/{args.suite}")
    results = Path(args.results_dir or own)
    # the suite's own results have their figures in the docs; any other results folder keeps its
    # figures inside it, so that it never replaces the committed figures of a suite
    default_figures = f"docs/img/{args.suite}" if results.resolve() == own.resolve() else results
    figures_dir = Path(args.figures_dir or default_figures)
    export = results / "curves.json"
    try:
        old = read_export(export) if export.is_file() else {}
    except ValueError as error:  # a damaged export: restored or replaced, never merged
        if args.from_export or not args.replace_export:
            return refuse(f"{export} is not a readable export ({error}); restore it (git "
                          "checkout) or, reading the runs, pass --replace-export")  # fmt: skip
        old = {}
    if args.from_export:
        if not old:
            return refuse(f"no runs in {export}; run report.py without --from-export on the "
                          "event files first")  # fmt: skip
        groups = old
    else:
        runs_dir = Path(args.runs_dir) / args.suite
        if not runs_dir.is_dir():
            return refuse(f"no runs in {runs_dir}; run benchmarks/run.py --suite {args.suite} "
                          "first")  # fmt: skip
        groups = collect(runs_dir, args.window, args.include_unfinished)
        if not groups:
            return refuse(f"no finished run in {runs_dir}, nothing to report; {results} is left "
                          "as it is")  # fmt: skip
        if args.keep_export:  # seed by seed
            for group, runs in old.items():
                for seed, run in runs.items():
                    if seed not in groups.get(group, {}) and "measured_on" not in run:
                        groups[group][seed] = run | {"kept": True}
        for group, runs in to_merge.items():  # rows the runs lack, kept visibly apart
            if group not in groups:
                groups[group] = {seed: run | {"measured_on": args.merge_label}
                                 for seed, run in runs.items()}  # fmt: skip
        lost = [
            f"{g} seed {s}" for g, runs in old.items() for s in runs if s not in groups.get(g, {})
        ]
        if lost and not args.replace_export:  # a committed result is never lost by accident
            n = sum(map(len, old.values()))
            return refuse(f"{len(lost)} of the {n} runs in {export} are not in {runs_dir} "
                          f"({lost[0]}, ...), so the export is left as it is: --keep-export "
                          "keeps them, --replace-export drops them")  # fmt: skip
    settings = SUITES[args.suite].report
    rng = np.random.default_rng(args.seed)
    peers = load_peers(Path(args.side_by_side) if args.side_by_side else SIDE_BY_SIDE)
    suite_seeds = defaultdict(set)  # the seeds this suite ran each task on
    for group, runs in groups.items():
        suite_seeds[group.split("__")[1]].update(int(seed) for seed in runs)
    for env_id, anchors in load_anchor_runs(
        Path(args.anchor_runs or ANCHOR_RUNS), suite_seeds
    ).items():
        peers[env_id] += anchors

    if settings.figures == "paper":
        figures = draw_paper_figures(groups, rng, peers)
    elif settings.figures == "mixing":
        figures = draw_mixing_figures(groups, rng)
    else:
        figures = draw_task_figures(groups, rng, peers, args.suite, settings)

    episodes = {}  # evaluation episodes per task, from the runs' own hyperparameters
    for group, runs in groups.items():
        for run in runs.values():
            if "eval_episodes" in run.get("args", {}):
                episodes.setdefault(group.split("__")[1], set()).add(run["args"]["eval_episodes"])
    per_task = "; ".join(f"{e}: {' or '.join(sorted(n))}" for e, n in sorted(episodes.items()))
    eval_note = f" (episodes per evaluation: {per_task})" if per_task else ""
    curves = "mean over seeds with a 95% bootstrap confidence band"
    if settings.median:
        curves = "median over seeds, the band from the lowest to the highest seed"
    earlier = sorted({r["measured_on"] for g in groups.values() for r in g.values()
                      if "measured_on" in r})  # fmt: skip
    merged_note = (
        f"† measured on {', '.join(earlier)}, not re-run on this code.\n\n" if earlier else ""
    )
    kept = sum("kept" in r for g in groups.values() for r in g.values())
    if kept:
        merged_note += (
            f"{kept} of the {sum(map(len, groups.values()))} runs were read from this suite's "
            "own earlier export (`curves.json`: their event files were on an earlier machine), "
            "the others from their event files.\n\n"
        )
    unfinished = [f"{g.split('__')[0]} seed {seed} at {r['unfinished_at']:,}"
                  for g, runs in sorted(groups.items()) for seed, r in sorted(runs.items())
                  if "unfinished_at" in r]  # fmt: skip
    finished = "finished (‡: or were stopped mid-way)" if unfinished else "finished"
    if unfinished:
        merged_note += (
            "‡ includes runs still in progress (resumable, stopped at a session's end), read "
            f"at the last step each logged: {'; '.join(unfinished)}. Their *final* columns are "
            "the figures at that step, not at the budget.\n\n"
        )
    per_task = task_tables(groups, peers, args.seed)
    per_task_block = f"{per_task}\n\n{task_tables_note(groups, peers)}" if per_task else ""
    success = success_table(groups, settings.budgets)
    success_block = per_task_block + (f"{success}\n\n" if success else "")
    reach = reach_table(groups, settings.levels) if settings.levels else ""
    if reach:
        success_block += (
            f"{reach}\n\nSeeds in order of their number; *training h*: hours of training to "
            "that evaluation, evaluation excluded, from the run's `charts/SPS` (so on the load "
            "of its sessions: several runs shared two cores); median over all seeds, a seed "
            "that has not reached the level counting as never.\n\n"
        )
    finalists = (
        finalists_table(groups, rng, settings.finalists_from) if settings.finalists_from else ""
    )
    if finalists:
        success_block += (
            f"{finalists}\n\nThe finalists on fresh seeds only (seeds {settings.finalists_from} "
            "and up; the screen's seeds are pooled in the rows above): mean over seeds [95% "
            "bootstrap interval of the mean]. Early budget: the last evaluation at or before "
            "2,500 steps on FetchReach, 100,000 on Hopper, labelled with the step it was at "
            "(Hopper evaluates every 20,480 steps); *final (training)*: as *final* above.\n\n"
        )
    diagnostics = diagnostics_table(groups)
    diagnostics_block = ""
    if diagnostics:
        diagnostics_block = (
            f"{diagnostics}\n\nDiagnostics (`ipg/*`, `qprop/*`): each the median over a run's "
            "updates, then the median [min, max] over seeds. *effective nu*: the off-policy "
            "term's share of the update's gradient norm; *variance ratio*: the trace of the "
            "policy gradient's covariance over random chunks of the batch, with the control "
            "variate (eta = 1) over without it (below 1: it reduces variance).\n\n"
        )
    text = f"""{table(groups, args.window)}

{merged_note}{success_block}{diagnostics_block}How this was measured: every row is the runs of
`benchmarks/run.py --suite {args.suite}` that {finished}, read from their TensorBoard event files
by `benchmarks/report.py`. *final*: the mean return of the last {args.window} training episodes
(stochastic policy); on FetchReach the success rate of the last 100 training episodes. Mean ±
sample std, median and interquartile mean (IQM) over seeds. *final eval*: the last evaluation of
the deterministic policy{eval_note}. *steps to threshold*: first step where the mean of the last
{args.window} training returns (once there are {args.window}) reaches 2000 (Hopper), or where an
evaluation reaches 0.9 success (FetchReach, PickAndPlace; 0.5 on Push, 0.7 on Slide); median
over all seeds, a seed that never reached it counting as never. *SPS*: environment steps per
second of training, evaluation excluded; *wall time*: first to last logged event (a resumed
run: summed over its sessions, with the work an interruption threw away).
Curves: {curves} (dashed past the shortest seed: the seeds that ran on), Hopper smoothed
over 20 logged episodes, FetchReach returns over 10. The success table gives, for goal tasks,
the median [min, max] over seeds of the last evaluation at or before each budget.
"""
    links = lambda where: "\n".join(  # noqa: E731
        f"![{f}]({os.path.relpath(figures_dir / f, where)})" for f in figures
    )
    files = {} if args.from_export else {export: json.dumps(groups, separators=(",", ":"))}
    files |= {figures_dir / name: fig for name, fig in figures.items()}
    files[results / "results.md"] = f"{text}\n{links(results)}\n"
    if args.page:
        before, rest = page.read_text().split(start)
        images = links(page.parent)
        note = "<!-- written by benchmarks/report.py: do not edit by hand -->"
        files[page] = before + f"{start}\n{note}\n{text}\n{images}\n{end}" + rest.split(end)[1]
    try:
        results.mkdir(parents=True, exist_ok=True)
        figures_dir.mkdir(parents=True, exist_ok=True)
        write_together(files)
    except OSError as error:
        full = " (the disk is full)" if error.errno in (errno.ENOSPC, errno.EDQUOT) else ""
        return refuse(
            f"could not write {error.filename}: {error.strerror}{full}; the export, results.md, "
            "the figures and --page are left as they were"
        )
    finally:
        plt.close("all")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
