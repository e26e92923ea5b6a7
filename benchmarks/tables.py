"""The Markdown tables of benchmarks/report.py's results.md: the training table, the success table
at budgets, the steps and hours to levels, one table per task with its anchors, the finalists on
fresh seeds and the mixed gradients' diagnostics, with the per-task tables' caption."""

import zlib

import numpy as np

from benchmarks.stats import (
    bootstrap_band,
    bootstrap_interval,
    first_eval_at,
    iqm,
    median_over_updates,
    median_steps,
    reported_by_success,
    steps_at,
    task_levels,
    value_at,
    variance_ratio,
)

LABELS = {"ppo_kl": "PPO-KL", "qprop_ppo": "Q-Prop", "ipg": "IPG (no HER)", "ipg_her": "IPG+HER"}


def table(groups: dict, window: int) -> str:
    rows = [
        "| task | algorithm | seeds | final (mean ± sample std) | final median | final IQM "
        "| final eval | steps to threshold (median) | SPS | wall time (s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for group in sorted(groups, key=lambda g: (g.split("__")[1], g)):
        name, env_id = group.split("__")
        runs = list(groups[group].values())
        goal = any(r.get("charts/success_rate") for r in runs)
        final = np.array([r["final"] for r in runs])
        eval_tag = "eval/success_rate" if goal else "eval/episodic_return"
        final_eval = np.array([r[eval_tag][-1][1] for r in runs if r.get(eval_tag)])
        reach = np.array([r["reach"] for r in runs])
        median, k = median_steps(reach), int(np.isfinite(reach).sum())
        reach_text = f"{median:,.0f}" if np.isfinite(median) else "not reached"
        running = sum(1 for r in runs if "unfinished_at" in r and not np.isfinite(r["reach"]))
        reach_text += f" ({k}/{len(runs)} seeds" + (f"; {running} not yet, still running)" if running else ")")
        sps = np.mean([r["charts/SPS"][-1][1] for r in runs if r.get("charts/SPS")])
        wall = np.mean([r["wall_time"] for r in runs])
        f = ".2f" if goal else ".0f"
        rows.append(
            f"| {env_id} | {LABELS.get(name, name)}{row_marks(runs)} | {len(runs)} "
            f"| {final.mean():{f}} ± {final.std(ddof=1):{f}} | {np.median(final):{f}} "
            f"| {iqm(final):{f}} | {final_eval.mean():{f}} | {reach_text} | {sps:.0f} "
            f"| {wall:.0f} |"
        )
    return "\n".join(rows)


def success_table(groups: dict, budgets=(2500, 5000, 10000, 30000)) -> str:
    """Goal tasks: the evaluation success rate at a few budgets, median and range over seeds;
    only the budgets the runs reached (the last evaluation's step if they reached none). A cell
    leaves out a run whose own budget is smaller, and a run still in progress that has not
    reached the column's budget (either would show an earlier evaluation there); the count of
    seeds is given when not all."""
    last = max(
        (r["eval/success_rate"][-1][0] for g in groups.values() for r in g.values() if r.get("eval/success_rate")), default=0
    )
    checkpoints = [c for c in budgets if c <= last] or ([last] if last else [])
    columns = " | ".join(f"eval success @ {c:,} steps" for c in checkpoints)
    rows = [f"| task | algorithm | {columns} |", "| --- | --- | " + " | ".join("---" for _ in checkpoints) + " |"]
    for group in sorted(groups):
        name, env_id = group.split("__")
        runs = [r for r in groups[group].values() if r.get("eval/success_rate")]
        if not runs:
            continue
        cells = []
        for c in checkpoints:
            values = [
                ([v for s, v in r["eval/success_rate"] if s <= c] or [np.nan])[-1]
                for r in runs  # only budgets within the run's own, and reached if in progress
                if c <= float(r.get("args", {}).get("total_timesteps", np.inf))
                and ("unfinished_at" not in r or r["eval/success_rate"][-1][0] >= c)
            ]
            values = [v for v in values if np.isfinite(v)]
            seeds = f" ({len(values)} of {len(runs)} seeds)" if len(values) < len(runs) else ""
            cells.append(f"{np.median(values):.2f} [{min(values):.2f}, {max(values):.2f}]{seeds}" if values else "-")
        rows.append(f"| {env_id} | {LABELS.get(name, name)} | " + " | ".join(cells) + " |")
    return "\n".join(rows) if len(rows) > 2 else ""


def reach_table(groups: dict, levels: tuple[float, ...]) -> str:
    """Goal tasks: per seed, the steps and training hours to the first evaluation at each level;
    a run in progress that has not reached a level is "not yet", a finished one "never"."""
    head = " | ".join(f"first eval >= {x}: steps (training h) per seed | median steps" for x in levels)
    rows = [f"| task | algorithm | {head} |", "| --- | --- |" + " --- |" * 2 * len(levels)]
    for group in sorted(groups):
        name, env_id = group.split("__")
        runs = [r for _, r in sorted(groups[group].items(), key=lambda kv: int(kv[0])) if r.get("eval/success_rate")]
        if not runs:
            continue
        cells = []
        for level in levels:
            reached = [first_eval_at(r, level) for r in runs]
            per_seed = [
                f"{step:,.0f} ({sec / 3600:.1f})" if np.isfinite(step) else "not yet" if "unfinished_at" in r else "never"
                for (step, sec), r in zip(reached, runs, strict=True)
            ]
            median = median_steps(np.array([step for step, _ in reached]))
            cells += [" / ".join(per_seed), f"{median:,.0f}" if np.isfinite(median) else "-"]
        rows.append(f"| {env_id} | {LABELS.get(name, name)} | " + " | ".join(cells) + " |")
    return "\n".join(rows) if len(rows) > 2 else ""


def seed_ranges(seeds) -> str:
    """[1, 2, 3, 5, 21, 22] -> "1-3, 5, 21-22"."""
    seeds, parts = sorted(int(s) for s in seeds), []
    for s in seeds:
        if parts and s == parts[-1][1] + 1:
            parts[-1][1] = s
        else:
            parts.append([s, s])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in parts)


def row_marks(runs: list) -> str:
    """† for runs merged from an earlier export, ‡ for runs still in progress."""
    mark = " †" if any("measured_on" in r for r in runs) else ""
    return mark + (" ‡" if any("unfinished_at" in r for r in runs) else "")


def with_interval(values, statistic, rng, digits: int) -> str:
    """The value and 95% interval of ``bootstrap_interval``: "value [lo, hi]"; the value alone
    for one seed, "-" for none."""
    if not len(values):
        return "-"
    value, lo, hi = bootstrap_interval(values, statistic, rng)
    text = f"{value:,.{digits}f}"
    return text if np.isnan(lo) else f"{text} [{lo:,.{digits}f}, {hi:,.{digits}f}]"


def mean_and_interval(values: np.ndarray, rng, digits: int) -> str:
    """Mean over seeds and its 95% bootstrap confidence interval: "mean [lo, hi]"."""
    lo, hi = bootstrap_band(np.asarray(values, float)[:, None], rng)
    return f"{np.nanmean(values):,.{digits}f} [{lo[0]:,.{digits}f}, {hi[0]:,.{digits}f}]"


def median_and_range(values: list) -> str:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return f"{np.median(values):.2f} [{min(values):.2f}, {max(values):.2f}]" if values else "-"


def duration(seconds: float) -> str:
    """12.3 s, 45 s, 17 min, 2.5 h; "-" for never."""
    if not np.isfinite(seconds):
        return "-"
    if seconds < 100:
        return f"{seconds:.1f} s" if seconds < 10 else f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 6000 else f"{seconds / 3600:.1f} h"


def reach_cells(steps, seconds, running: int = 0) -> tuple[str, str]:
    """The median over all seeds of the steps, and of the training time, to a level's first
    evaluation, a seed that never got there counting as never (``median_steps``), and how many
    got there (of the others, how many are still running). Time "n/a" when not recorded."""
    steps = np.asarray(steps, float)
    median = median_steps(steps)
    count = f"{int(np.isfinite(steps).sum())}/{len(steps)}"
    count += f"; {running} still running" if running else ""
    text = f"{median:,.0f} ({count})" if np.isfinite(median) else f"not reached ({count})"
    if seconds is None:
        return text, "n/a"
    seconds = np.where(np.isfinite(steps), np.asarray(seconds, float), np.inf)
    return text, "n/a" if np.isnan(seconds).any() else duration(float(np.median(seconds)))


def eval_every(curves: list) -> str:
    """The steps between evaluations, or their range over curves: each curve's most frequent gap
    (the earliest of equally frequent ones), so that a last evaluation off the schedule, at the
    end of the budget, does not count."""
    gaps = set()
    for steps in ([s for s, _ in c] for c in curves if len(c) > 1):
        diffs = [int(d) for d in np.diff(steps)]
        gaps.add(max(diffs, key=lambda d: (diffs.count(d), -diffs.index(d))))
    gaps = sorted(gaps)
    if not gaps:
        return "-"
    return f"{gaps[0]:,}" if len(gaps) == 1 else f"{gaps[0]:,}-{gaps[-1]:,}"


def task_tables(groups: dict, peers: dict, seed: int) -> str:
    """One table per task, a row per algorithm, then the task's peers: the seeds; the median and
    the IQM over seeds of each seed's last evaluation, each with its 95% bootstrap interval
    (resampled from a generator of its own per row, so that no row moves another's); per level,
    the median steps and training time to the first evaluation there; evaluation interval and
    steps per second (as the first table's SPS)."""
    blocks = []
    for env_id in sorted({g.split("__")[1] for g in groups}):
        tag, levels = task_levels(env_id)
        goal, digits = tag == "eval/success_rate", 2 if tag == "eval/success_rate" else 0
        head = "".join(f" first eval >= {x:g}: median steps (seeds there) | median time |" for x in levels)
        rows = [
            f"| algorithm | seeds | final eval: median [95% CI] | final eval: IQM [95% CI] |{head} eval every | steps/s |",
            "|" + " --- |" * (6 + 2 * len(levels)),
        ]
        for group in sorted(g for g in groups if g.endswith(f"__{env_id}")):
            name = group.split("__")[0]
            seeds = sorted(groups[group], key=int)
            runs = [groups[group][s] for s in seeds]
            rng = np.random.default_rng([seed, zlib.crc32(group.encode())])
            finals = [r[tag][-1][1] for r in runs if r.get(tag)]
            of = f" ({len(finals)} seeds)" if len(finals) < len(runs) else ""
            cells = [
                f"{len(runs)} ({seed_ranges(seeds)})",
                with_interval(finals, np.median, rng, digits) + of,
                with_interval(finals, iqm, rng, digits) + of,
            ]
            for level in levels:
                reached = [first_eval_at(r, level, tag) for r in runs]
                running = sum(
                    1 for (step, _), r in zip(reached, runs, strict=True) if "unfinished_at" in r and not np.isfinite(step)
                )
                cells += reach_cells(*zip(*reached, strict=True), running)
            sps = [r["charts/SPS"][-1][1] for r in runs if r.get("charts/SPS")]
            cells += [eval_every([r.get(tag, []) for r in runs]), f"{np.mean(sps):.0f}" if sps else "-"]
            label = LABELS.get(name, name) + row_marks(runs)
            rows.append(f"| {label} | " + " | ".join(cells) + " |")
        for peer in peers.get(env_id, []) if goal else []:
            rng = np.random.default_rng([seed, zlib.crc32(peer.label.encode())])
            finals = [c[-1][1] for c in peer.curves]
            cells = [
                peer.seeds,
                with_interval(finals, np.median, rng, digits) if finals else "n/a",
                with_interval(finals, iqm, rng, digits) if finals else "n/a",
            ]
            for level in levels:
                recorded = level in peer.first
                cells += reach_cells(peer.first[level], peer.seconds.get(level)) if recorded else ("n/a", "n/a")
            cells += [eval_every(peer.curves) if peer.curves else "n/a", f"{np.mean(peer.sps):.0f}" if peer.sps else "n/a"]
            rows.append(f"| {peer.label} | " + " | ".join(cells) + " |")
        what = "evaluation success" if goal else "evaluation return"
        anchors = [p.label.split(" (")[0] for p in peers.get(env_id, []) if p.anchor and goal]
        anchor = f"anchor: {', '.join(anchors)}" if anchors else "no anchor recorded for this task"
        levels_text = f"levels: {what} {' / '.join(f'{x:g}' for x in levels)}; " if levels else ""
        blocks.append(f"**{env_id}** ({levels_text}{anchor})\n\n" + "\n".join(rows))
    return "\n\n".join(blocks)


def task_tables_note(groups: dict, peers: dict) -> str:
    """The per-task tables' caption: how each column was derived, the anchors' sources, and how
    far the suite's wall time is from the training time the time columns are derived from."""
    runs = [r for g in groups.values() for r in g.values() if r.get("charts/SPS")]
    ratios = [
        r["wall_time"] * r["charts/SPS"][-1][1] / r["charts/SPS"][-1][0]
        for r in runs
        if r.get("wall_time") and r["charts/SPS"][-1][1] > 0
    ]
    envs = {g.split("__")[1] for g in groups}
    hopper = any(task_levels(e)[0] == "eval/episodic_return" for e in envs)
    goal = any(task_levels(e)[0] == "eval/success_rate" for e in envs)
    shown = {p.label: p for e in envs if task_levels(e)[0] == "eval/success_rate" for p in peers.get(e, [])}
    what = ["the success rate (goal tasks)"] * goal + ["the mean return (Hopper)"] * hopper
    what = " and ".join(what)
    text = (
        "Per task: *final eval*: each seed's last evaluation of the deterministic policy, "
        f"{what}; over seeds its median and its interquartile mean (IQM: the mean of the middle "
        "half, of all with three seeds or fewer), each with a 95% percentile bootstrap interval "
        "over seeds (2,000 resamples; none with one seed). *first "
        "eval >= x*: the median over all seeds of the step of the first evaluation at or above x, "
        "a seed that never got there counting as never (*not reached* when half of them or more "
        "did not), with how many got there. *median time*: training time, derived, as the export "
        "keeps no clock per step: each seed's step over the `charts/SPS` it logged at that step "
        "(steps per second of training so far, evaluation excluded), then the median over seeds "
        "as for the steps."
    )
    if ratios:
        text += (
            f" Over whole runs, this suite's wall time (first table) is {min(ratios):.2f}-"
            f"{max(ratios):.2f} times the training time so derived."
        )
    if goal:
        text += " Goal-task levels: evaluation success 0.5, 0.7 and 0.9."
    if hopper:
        text += (
            " Hopper levels: evaluation return 1000, 2000 and 3000 (the span of the paper's "
            "Figure 3; the first table's threshold, 2000, is on the mean training return)."
        )
    text += (
        " *eval every*: steps between evaluations, the resolution of the steps columns. "
        "*steps/s*: as *SPS* in the first table."
    )
    if any(label.startswith("SB3 DDPG+HER (anchor") for label in shown):
        text += (
            " *SB3 DDPG+HER (anchor)*: Stable-Baselines3's DDPG+HER with the HER paper's settings, "
            "run one seed after the other with IPG+HER, both evaluated alike, by "
            "`benchmarks/against_sb3.py` (`benchmarks/results/against_sb3/results.json`), so "
            "its *final eval* is at that run's budget; its time is training "
            "seconds (its evaluations' subtracted), recorded to 0.9 only. *IPG+HER side by side*: "
            "ours in that same run, its times recorded to 0.9 only."
        )
    if any("zoo settings" in label for label in shown):
        text += (
            " *SB3 ... (anchor; zoo settings)*: Stable-Baselines3 with HER and rl-baselines3-zoo's "
            "settings, run here on the same seeds and budget and evaluated alike (each run's "
            "summary in `benchmarks/results/anchors/`); its time is "
            "training seconds (its evaluations' subtracted) and its *steps/s* likewise."
        )
    if any("TQC+HER zoo agent" in label for label in shown):
        text += (
            " *TQC+HER zoo agent (anchor)*: the first evaluations of rl-baselines3-zoo's "
            "published TQC+HER agent for the task (v1 environment, one env, one seed) at the "
            "levels recorded (`ANCHORS` in benchmarks/peers.py)."
        )
    return text + " n/a: not recorded.\n\n"


def finalists_table(groups: dict, rng, first_fresh: int) -> str:
    """The finalists on their fresh seeds only (seeds >= ``first_fresh``, none tuned on): per
    variant, the mean and 95% bootstrap interval over those seeds of the last evaluation at or
    before an early budget (labelled with the step it was at) and at the end, and of the final
    training figure. Empty if no variant has two."""
    rows = [
        "| task | algorithm | fresh seeds | eval @ early budget | last eval | final (training) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for group in sorted(groups):
        name, env_id = group.split("__")
        seeds = sorted(int(s) for s in groups[group] if int(s) >= first_fresh)
        runs = [groups[group][str(s)] for s in seeds]
        if len(runs) < 2:
            continue
        goal = reported_by_success(env_id)
        tag, early, digits = ("eval/success_rate", 2_500, 2) if goal else ("eval/episodic_return", 100_000, 0)
        cells = [
            f"{len(runs)} ({seeds[0]}-{seeds[-1]})",
            f"@ {steps_at(runs, tag, early)}: " + mean_and_interval([value_at(r, tag, early) for r in runs], rng, digits),
            mean_and_interval([r[tag][-1][1] for r in runs], rng, digits),
            mean_and_interval([r["final"] for r in runs], rng, digits),
        ]
        rows.append(f"| {env_id} | {LABELS.get(name, name)} | " + " | ".join(cells) + " |")
    return "\n".join(rows) if len(rows) > 2 else ""


def diagnostics_table(groups: dict) -> str:
    """The mixed gradients' diagnostics per variant: effective nu, the gradient-variance ratio
    with / without the control variate, corr(A_hat, A_bar); each the median over a run's
    updates, then the median [min, max] over seeds. Empty if no run logged them."""
    rows = [
        "| task | algorithm | seeds | effective nu | variance ratio, with CV / without | corr(A_hat, A_bar) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for group in sorted(groups):
        name, env_id = group.split("__")
        runs = list(groups[group].values())
        prefix = next((p for p in ("ipg", "qprop") if any(f"{p}/grad_var" in r for r in runs)), "")
        if not prefix:
            continue
        cells = [
            median_and_range([median_over_updates(r, "ipg/effective_nu") for r in runs]),
            median_and_range([variance_ratio(r, prefix) for r in runs]),
            median_and_range([median_over_updates(r, f"{prefix}/corr_adv_cv") for r in runs]),
        ]
        rows.append(f"| {env_id} | {LABELS.get(name, name)} | {len(runs)} | " + " | ".join(cells) + " |")
    return "\n".join(rows) if len(rows) > 2 else ""
