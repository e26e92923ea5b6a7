"""Figures and a results table from the TensorBoard event files of a benchmark suite (nothing else).

    python benchmarks/report.py --suite paper                      # read benchmarks/runs/paper
    python benchmarks/report.py --suite paper --from-export        # redraw from the export

Writes into ``--results-dir`` (default ``benchmarks/results/{suite}``) ``curves.json`` (a compact
export of every run's curves, enough to redraw everything) and ``results.md`` (the tables and how
they were measured: among them one per task with the median and IQM of the final evaluation, the
steps and training time to three levels, and the anchor, the peer to beat, where one is recorded:
``ANCHORS`` in ``benchmarks/peers.py``, ``benchmarks/results/against_sb3/results.json``, and the
anchor's own runs in ``benchmarks/results/anchors/``), and PNG figures, the anchor drawn in, into
``--figures-dir`` (default ``docs/img/{suite}`` for the suite's own results folder, as the docs
site serves only ``docs/``, and the ``--results-dir`` folder itself for any other), linked from
``results.md``. The files change together or not at all (each written beside itself, then renamed
over it). What a suite's report shows beyond the common tables (its figures, budgets, levels) is
its ``Report`` in ``benchmarks/suites.py``'s ``SUITES``. Run folders that lack a run of the export
they would replace are refused (``--keep-export``, ``--replace-export``); a run folder left out of
the report (failed, stopped, still running, no exit code) is named in a warning saying why.

This file is the command line; the work is in ``events.py`` (the event files and exports read),
``stats.py`` (the statistics), ``tables.py``, ``figures.py`` and ``peers.py`` (the anchors).
"""

import contextlib
import errno
import json
import os
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.events import collect, read_export  # noqa: E402
from benchmarks.figures import (  # noqa: E402
    draw_mixing_figures,
    draw_paper_figures,
    draw_task_figures,
)
from benchmarks.peers import ANCHOR_RUNS, SIDE_BY_SIDE, load_anchor_runs, load_peers  # noqa: E402
from benchmarks.suites import SUITES  # noqa: E402  each suite's settings, beside its runs
from benchmarks.tables import (  # noqa: E402
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
    """final performance: mean over this many last training episodes (an export keeps the window
    its runs were read with: --from-export, --keep-export and --merge-export need the same)"""
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
        return refuse(
            f"--suite {args.suite}: not a suite of benchmarks/run.py ({known}); --results-dir names another export folder"
        )
    if args.window < 1:
        return refuse(
            f"--window {args.window}: the final return is the mean of the last --window training episodes; give 1 or more"
        )
    # a bad --page is caught before anything is read or written
    page = Path(args.page)
    start, end = f"<!-- results:{args.suite}:start -->", f"<!-- results:{args.suite}:end -->"
    if args.page and not page.is_file():
        return refuse(
            f"--page {page}: no such file; name an existing Markdown page holding the "
            f"markers {start} and {end}, or leave out --page"
        )
    if args.page and not page.read_text().count(start) == page.read_text().count(end) == 1:
        return refuse(f"--page {page} needs the markers {start} and {end}, once each, around the place to write; add them")
    merged = Path(args.merge_export)
    if args.merge_export and not merged.is_file():
        return refuse(f"--merge-export {merged}: no such file; name an earlier curves.json, or leave out --merge-export")
    try:
        to_merge = read_export(merged) if args.merge_export else {}
    except (OSError, ValueError) as error:
        return refuse(f"--merge-export {merged} is not a readable export ({error}); name an earlier curves.json")
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
            return refuse(
                f"{export} is not a readable export ({error}); restore it (git "
                "checkout) or, reading the runs, pass --replace-export"
            )
        old = {}
    if args.from_export:
        if not old:
            return refuse(f"no runs in {export}; run report.py without --from-export on the event files first")
        groups = old
    else:
        runs_dir = Path(args.runs_dir) / args.suite
        if not runs_dir.is_dir():
            return refuse(f"no runs in {runs_dir}; run benchmarks/run.py --suite {args.suite} first")
        groups = collect(runs_dir, args.window, args.include_unfinished)
        if not groups:
            return refuse(f"no finished run in {runs_dir}, nothing to report; {results} is left as it is")
        if args.keep_export:  # seed by seed
            for group, runs in old.items():
                for seed, run in runs.items():
                    if seed not in groups.get(group, {}) and "measured_on" not in run:
                        groups[group][seed] = run | {"kept": True}
        for group, runs in to_merge.items():  # rows the runs lack, kept visibly apart
            if group not in groups:
                groups[group] = {seed: run | {"measured_on": args.merge_label} for seed, run in runs.items()}
        lost = [f"{g} seed {s}" for g, runs in old.items() for s in runs if s not in groups.get(g, {})]
        if lost and not args.replace_export:  # a committed result is never lost by accident
            n = sum(map(len, old.values()))
            return refuse(
                f"{len(lost)} of the {n} runs in {export} are not in {runs_dir} "
                f"({lost[0]}, ...), so the export is left as it is: --keep-export "
                "keeps them, --replace-export drops them"
            )
    # results.md states one window: every run's final return and steps to threshold, computed
    # when it was read from its event files, must be over --window's
    windows = {run["window"] for runs in groups.values() for run in runs.values()}
    if other := sorted(windows - {args.window}):
        held = export if args.from_export else f"{export} (--keep-export) or --merge-export"
        instead = "read the event files without --from-export" if args.from_export else "leave those runs out"
        return refuse(
            f"--window {args.window}: the runs from {held} hold their final return and steps to "
            f"threshold over the last {' or '.join(map(str, other))} training episodes, which an "
            f"export's downsampled curves cannot give again over {args.window}; pass --window "
            f"{other[0]}, or {instead}"
        )
    settings = SUITES[args.suite].report
    rng = np.random.default_rng(args.seed)
    peers = load_peers(Path(args.side_by_side) if args.side_by_side else SIDE_BY_SIDE)
    suite_seeds = defaultdict(set)  # the seeds this suite ran each task on
    for group, runs in groups.items():
        suite_seeds[group.split("__")[1]].update(int(seed) for seed in runs)
    for env_id, anchors in load_anchor_runs(Path(args.anchor_runs or ANCHOR_RUNS), suite_seeds).items():
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
    earlier = sorted({r["measured_on"] for g in groups.values() for r in g.values() if "measured_on" in r})
    merged_note = f"† measured on {', '.join(earlier)}, not re-run on this code.\n\n" if earlier else ""
    kept = sum("kept" in r for g in groups.values() for r in g.values())
    if kept:
        merged_note += (
            f"{kept} of the {sum(map(len, groups.values()))} runs were read from this suite's "
            "own earlier export (`curves.json`: their event files were on an earlier machine), "
            "the others from their event files.\n\n"
        )
    unfinished = [
        f"{g.split('__')[0]} seed {seed} at {r['unfinished_at']:,}"
        for g, runs in sorted(groups.items())
        for seed, r in sorted(runs.items())
        if "unfinished_at" in r
    ]
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
    finalists = finalists_table(groups, rng, settings.finalists_from) if settings.finalists_from else ""
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
