"""benchmarks/report.py and its modules (events, stats, tables, figures, peers): the statistics
against values computed by hand, on hand-made event files, and the command's refusals."""

import dataclasses
import errno
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, assert_clean_error, read_only
from torch.utils.tensorboard import SummaryWriter

from benchmarks import events, figures, peers, report, stats, suites, tables

WINDOW = 5


def write_run(runs_dir, name, env_id, seed, returns=(), successes=(), eval_episodes=10, total=0):
    """A finished run as benchmarks/run.py lays it out: training returns one per 100 steps,
    evaluation success rates one per 500 steps, and the hyperparameter table."""
    folder = runs_dir / f"{name}__{env_id}__seed{seed}"
    writer = SummaryWriter(str(folder / f"{env_id}__{name}__{seed}__0"))
    table = f"|param|value|\n|-|-|\n|eval_episodes|{eval_episodes}|"
    table += f"\n|total_timesteps|{total}|" if total else ""
    writer.add_text("hyperparameters", table)
    for i, value in enumerate(returns):
        writer.add_scalar("charts/episodic_return", value, 100 * (i + 1))
    for i, value in enumerate(successes):
        writer.add_scalar("charts/success_rate", value, 500 * (i + 1))
        writer.add_scalar("eval/success_rate", value, 500 * (i + 1))
    writer.add_scalar("charts/SPS", 1000, 100 * max(len(returns), 1))
    writer.close()
    (folder / "exit_code").write_text("0\n")


def report_args(tmp_path, suite: str, **flags) -> report.Args:
    """report.py's arguments, every folder under ``tmp_path``: runs/, results/ and img/ (the
    figures), unless ``flags`` say otherwise."""
    folders = {"runs_dir": "runs", "results_dir": "results", "figures_dir": "img"}
    return report.Args(suite=suite, **{k: str(tmp_path / v) for k, v in folders.items()} | flags)


def test_steps_to_threshold_uses_full_windows_and_counts_unreached_seeds(tmp_path):
    runs = tmp_path / "runs" / "test"
    # seed 1: one huge first episode, which alone (a partial window) would "reach" 2000 at step
    # 100; the first full window, episodes 1-5, has mean (20000 + 400) / 5 = 4080: step 500
    write_run(runs, "algo", "Hopper-v5", 1, [20000] + [100] * 9 + [2500] * 10)
    write_run(runs, "algo", "Hopper-v5", 2, [2100] * 20)  # full window first at episode 5
    write_run(runs, "algo", "Hopper-v5", 3, [500] * 20)  # never
    groups = events.collect(runs, WINDOW)["algo__Hopper-v5"]
    assert groups["1"]["reach"] == 500
    assert groups["2"]["reach"] == 500
    assert np.isnan(groups["3"]["reach"])
    reach = np.array([groups[s]["reach"] for s in "123"])
    assert stats.median_steps(reach) == 500  # median of (500, 500, never)
    assert stats.median_steps(np.array([500.0, np.nan, np.nan])) == np.inf
    assert stats.median_steps(np.array([500.0, 700.0, np.nan, np.nan])) == np.inf
    assert stats.median_steps(np.array([500.0, 700.0, 900.0, np.nan])) == 800


def test_partial_windows_never_count(tmp_path):
    runs = tmp_path / "runs" / "test"
    write_run(runs, "algo", "Hopper-v5", 1, [3000, 3000, 3000, 0, 0, 0, 0, 0])  # 3 big, then 0
    (run,) = events.collect(runs, WINDOW)["algo__Hopper-v5"].values()
    assert np.isnan(run["reach"])  # the only windows of 5 average 1800 and less


def test_table_statistics_equal_hand_computed_values(tmp_path):
    runs = tmp_path / "runs" / "test"
    finals = {1: 1000.0, 2: 2000.0, 3: 3000.0, 4: 10000.0}
    for seed, level in finals.items():
        write_run(runs, "algo", "Hopper-v5", seed, [0.0] * 5 + [level] * WINDOW)
    groups = events.collect(runs, WINDOW)
    row = next(r for r in tables.table(groups, WINDOW).splitlines() if "Hopper-v5" in r)
    cells = [c.strip() for c in row.strip("|").split("|")]
    values = np.array(list(finals.values()))
    assert cells[2] == "4"
    assert cells[3] == f"{values.mean():.0f} ± {values.std(ddof=1):.0f}"  # sample std
    assert cells[4] == f"{np.median(values):.0f}"
    assert cells[5] == f"{(2000 + 3000) / 2:.0f}"  # IQM of 4 values: the middle two
    # the window ending at episode i averages level (i - 5) / 5: 2000 is reached at step 1000
    # (seed 2), 900 (seed 3), 600 (seed 4), never by seed 1: median of (600, 900, 1000, never)
    assert cells[7] == "950 (3/4 seeds)"


def test_a_resumed_run_reads_each_step_once_with_the_resumed_attempts_values(tmp_path):
    """A resumed run (common/run.py) appends a second event file to its folder, opened with
    purge_step: the steps the killed attempt logged from there on are dropped, as TensorBoard does,
    files read in the order they were written, whatever order their names sort in (the same
    second, pid 1000 after pid 999: the second file's name sorts first)."""
    for first, second in (("999", "1000"), ("1000", "999")):
        run_dir = tmp_path / first
        for pid, purge_step, steps, offset in ((first, None, range(1, 11), 0), (second, 6, range(6, 13), 100)):
            writer = SummaryWriter(str(run_dir), purge_step=purge_step)
            for step in steps:
                writer.add_scalar("charts/episodic_return", offset + step, step)
            writer.close()
            (new,) = [p for p in run_dir.iterdir() if ".host." not in p.name]
            new.rename(run_dir / f"events.out.tfevents.1700000000.host.{pid}.0")
        assert events.read_run(run_dir)["charts/episodic_return"] == (
            [[s, s] for s in range(1, 6)] + [[s, 100 + s] for s in range(6, 13)]
        )


def test_bootstrap_band_against_the_exact_bootstrap_distribution():
    """Seeds 0, 3, 6: resampled means are whole numbers; P(mean = 0) = P(mean = 6) = 1/27 > 2.5%,
    so the 95% band of the mean is exactly [0, 6]; identical seeds give a band of zero width."""
    rng = np.random.default_rng(0)
    lo, hi = stats.bootstrap_band(np.array([[0.0], [3.0], [6.0]]), rng)
    assert lo[0] == 0.0 and hi[0] == 6.0
    lo, hi = stats.bootstrap_band(np.full((5, 3), 2.0), rng)
    np.testing.assert_array_equal(lo, 2.0)
    np.testing.assert_array_equal(hi, 2.0)


def test_success_table_columns_and_episode_counts_come_from_the_runs(tmp_path, capsys):
    runs = tmp_path / "runs" / "quick"
    for seed in (1, 2):
        write_run(runs, "ipg_her", "FetchReach-v4", seed, [-50] * 3, [0.0, 0.5, 1.0], 7)
    assert report.main(report_args(tmp_path, "quick")) == 0
    text = (tmp_path / "results" / "results.md").read_text()
    header = next(line for line in text.splitlines() if "eval success @" in line)
    assert re.findall(r"@ ([\d,]+) steps", header) == ["1,500"]  # the runs stop at 1,500 steps
    assert "episodes per evaluation: FetchReach-v4: 7)" in text and "20 episodes" not in text


@pytest.mark.parametrize("content", [None, "# a page without markers\n"])
def test_page_without_file_or_markers_is_one_error_line(tmp_path, content):
    runs = tmp_path / "runs" / "quick"
    write_run(runs, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    page = tmp_path / "results.md"
    if content is not None:
        page.write_text(content)
    cmd = [
        sys.executable,
        "benchmarks/report.py",
        "--suite",
        "quick",
        "--runs-dir",
        str(tmp_path / "runs"),
        "--results-dir",
        str(tmp_path / "out"),
        "--page",
        str(page),
    ]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(page) in errors[0], result.stderr


def test_page_naming_no_file_fails_before_reading_or_writing_anything():
    """The command as typed from the project root, with the defaults (the paper suite): the bad
    --page is reported first, so the committed results and docs figures are left as they are."""
    written = [ROOT / "benchmarks" / "results", ROOT / "docs" / "img"]
    before = {p: p.stat().st_mtime_ns for d in written for p in d.rglob("*")}
    cmd = [sys.executable, "benchmarks/report.py", "--page", "/no/such/file"]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert_clean_error(result, "/no/such/file", "no such file")
    assert {p: p.stat().st_mtime_ns for d in written for p in d.rglob("*")} == before


def test_page_gets_the_block_between_its_markers_and_the_figures_beside_it(tmp_path):
    """--page: the text around the markers stays, the block between them is replaced, and the
    figures (in --figures-dir, here img/quick/ beside the page) are linked relative to it; the
    results folder keeps the export and results.md."""
    runs = tmp_path / "runs" / "quick"
    write_run(runs, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    docs = tmp_path / "docs"
    docs.mkdir()
    page = docs / "results.md"
    start, end = "<!-- results:quick:start -->", "<!-- results:quick:end -->"
    page.write_text(f"# Results\n\nbefore\n{start}\nold block\n{end}\nafter\n")
    args = report_args(tmp_path, "quick", page=str(page), figures_dir=str(docs / "img" / "quick"))
    assert report.main(args) == 0
    text = page.read_text()
    assert text.startswith("# Results\n\nbefore\n" + start) and text.endswith(end + "\nafter\n")
    assert "old block" not in text and "| FetchReach-v4 | IPG+HER | 1 |" in text
    assert "![fig5_fetchreach_success.png](img/quick/fig5_fetchreach_success.png)" in text
    assert (docs / "img" / "quick" / "fig5_fetchreach_success.png").is_file()
    assert not list((tmp_path / "results").glob("*.png"))
    assert (tmp_path / "results" / "results.md").is_file()
    assert (tmp_path / "results" / "curves.json").is_file()


def test_rows_merged_from_an_earlier_export_are_marked(tmp_path):
    """--merge-export keeps rows the runs lack (say, Hopper runs not re-run on new code), marked
    with † and named in the note; rows the runs have come from the runs."""
    old, new = tmp_path / "old_runs" / "paper", tmp_path / "runs" / "paper"
    write_run(old, "algo", "Hopper-v5", 1, [100.0] * 10)
    write_run(old, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 0.0])
    folders = {"runs_dir": str(tmp_path / "old_runs"), "results_dir": str(tmp_path / "old")}
    assert report.main(report_args(tmp_path, "paper", **folders)) == 0
    write_run(new, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [1.0, 1.0])
    args = report_args(tmp_path, "paper", merge_export=str(tmp_path / "old" / "curves.json"), merge_label="commit abc")
    assert report.main(args) == 0
    text = (tmp_path / "results" / "results.md").read_text()
    assert "| Hopper-v5 | algo † | 1 |" in text and "† measured on commit abc" in text
    assert "| FetchReach-v4 | IPG+HER | 1 | 1.00" in text  # the new run, not the merged one


def test_keep_export_adds_new_seeds_to_the_runs_of_an_earlier_machine(tmp_path):
    """--keep-export: seeds whose run folders are gone (a new machine) are read from the suite's
    own curves.json, seed by seed and named in the note; a seed with a run folder is read from
    its events; --replace-export replaces the export with the run folders' runs."""
    import shutil

    runs, results = tmp_path / "runs" / "mixing", tmp_path / "results"
    write_run(runs, "algo", "Hopper-v5", 1, [100.0] * 10)
    write_run(runs, "algo", "Hopper-v5", 2, [300.0] * 10)
    assert report.main(report_args(tmp_path, "mixing")) == 0
    shutil.rmtree(runs)  # the machine is gone, the export stays
    write_run(runs, "algo", "Hopper-v5", 2, [500.0] * 10)  # seed 2 re-run, seed 3 new
    write_run(runs, "algo", "Hopper-v5", 3, [900.0] * 10)
    assert report.main(report_args(tmp_path, "mixing", keep_export=True)) == 0
    text = (results / "results.md").read_text()
    assert "| Hopper-v5 | algo | 3 | 500 ± 400 |" in text  # seeds 1 (100), 2 (500), 3 (900)
    assert "1 of the 3 runs were read from this suite's own earlier export" in text
    assert report.main(report_args(tmp_path, "mixing", replace_export=True)) == 0  # the folders
    assert "| Hopper-v5 | algo | 2 | 700 ± 283 |" in (results / "results.md").read_text()


def test_unfinished_runs_are_left_out_or_marked_with_the_step_they_reached(tmp_path, monkeypatch):
    """A run between two sessions (no exit code, a resume point) is not a result: left out by
    default; with --include-unfinished it is marked ‡ with its last step, a success budget it
    has not reached holds only the seeds that reached it, never its earlier evaluation, and a
    threshold it has not reached yet is not called missed. A failed run is never read."""
    runs = tmp_path / "runs" / "push"
    write_run(runs, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 0.5, 1.0, 1.0])  # to 2,000
    write_run(runs, "ipg_her", "FetchReach-v4", 2, [-50] * 3, [0.0, 0.2])  # stopped at 1,000
    write_run(runs, "ipg_her", "FetchReach-v4", 3, [-50] * 3, [0.0, 0.2])  # failed at 1,000
    for seed, code in ((2, None), (3, "1")):  # both left a resume point
        folder = runs / f"ipg_her__FetchReach-v4__seed{seed}"
        next(f for f in folder.iterdir() if f.is_dir()).joinpath("resume.pt").touch()
        (folder / "exit_code").unlink() if code is None else (folder / "exit_code").write_text(code)

    def results(**flags) -> str:
        assert report.main(report_args(tmp_path, "push", **flags)) == 0
        return (tmp_path / "results" / "results.md").read_text()

    assert "| IPG+HER | 1 |" in results() and "‡" not in results()
    text = results(include_unfinished=True)
    assert "| IPG+HER ‡ | 2 |" in text and "ipg_her seed 2 at 1,000" in text  # not seed 3
    assert "(1/2 seeds; 1 not yet, still running)" in text  # seed 1 reached 0.9, seed 2 not yet
    write_run(runs, "short", "FetchReach-v4", 1, [-50] * 3, [0.0, 0.4], total=1000)
    push = suites.SUITES["push"]
    budgets = dataclasses.replace(push.report, budgets=(500, 1000, 1500))
    monkeypatch.setitem(suites.SUITES, "push", push._replace(report=budgets))
    short = next(
        line for line in results(include_unfinished=True).splitlines() if line.startswith("| FetchReach-v4 | short | 0")
    )
    assert short.split(" | ")[2:] == ["0.00 [0.00, 0.00]", "0.40 [0.40, 0.40]", "- |"]
    row = next(
        line for line in results(include_unfinished=True).splitlines() if line.startswith("| FetchReach-v4 | IPG+HER | 0")
    )
    # at 500 and 1,000 both seeds (0.0 and 0.0; 0.5 and 0.2), at 1,500 seed 1 alone (1.0)
    assert row.split(" | ")[2:] == ["0.00 [0.00, 0.00]", "0.35 [0.20, 0.50]", "1.00 [1.00, 1.00] (1 of 2 seeds) |"]


def test_diagnostics_table_against_hand_computed_medians():
    """Per run: the median over updates (the variance ratio update by update); per variant:
    the median [min, max] over seeds. Runs without diagnostics get no row."""
    run = lambda var, var_cv, eff, corr: {  # noqa: E731
        "ipg/grad_var": [[s, v] for s, v in zip((100, 200, 300), var, strict=True)],
        "ipg/grad_var_cv": [[s, v] for s, v in zip((100, 200, 300), var_cv, strict=True)],
        "ipg/effective_nu": [[100, eff[0]], [200, eff[1]], [300, eff[2]]],
        "ipg/corr_adv_cv": [[100, corr[0]], [200, corr[1]], [300, corr[2]]],
    }
    groups = {
        "ipg_her_nu0.5_b100__FetchReach-v4": {
            # ratios 0.5, 2, 4 (median 2) and 1, 1, 3 (median 1)
            "1": run((2, 1, 1), (1, 2, 4), (0.1, 0.2, 0.6), (0.0, 0.5, 1.0)),
            "2": run((1, 1, 1), (1, 1, 3), (0.3, 0.4, 0.5), (0.2, 0.2, 0.2)),
        },
        "ppo_kl__FetchReach-v4": {"1": {"charts/episodic_return": [[100, -50.0]]}},
    }
    rows = tables.diagnostics_table(groups).splitlines()
    assert len(rows) == 3, "a header, a separator and one row: ppo_kl logged no diagnostics"
    # effective nu: run medians 0.2 and 0.4; ratio: 2 and 1; corr: 0.5 and 0.2
    assert rows[2] == (
        "| FetchReach-v4 | ipg_her_nu0.5_b100 | 2 | 0.30 [0.20, 0.40] | 1.50 [1.00, 2.00] | 0.35 [0.20, 0.50] |"
    )
    assert tables.diagnostics_table({"ppo_kl__Hopper-v5": groups["ppo_kl__FetchReach-v4"]}) == ""


def test_reach_table_gives_steps_and_training_hours_per_seed(tmp_path):
    """Seed 1 first evaluates >= 0.5 at 1,000 steps and >= 0.9 at 1,500; seed 2 (in progress)
    reaches 0.5 at 1,500 and 0.9 not yet; seed 3 (finished) never. Training seconds are the
    step over the SPS logged there: 1,000 / 1,000 SPS = 1 s."""
    runs = tmp_path / "runs" / "push"
    write_run(runs, "ipg_her", "FetchPush-v4", 1, [-50] * 15, [0.0, 0.6, 0.9])
    write_run(runs, "ipg_her", "FetchPush-v4", 2, [-50] * 15, [0.0, 0.2, 0.5])
    write_run(runs, "ipg_her", "FetchPush-v4", 3, [-50] * 15, [0.0, 0.1, 0.1])
    groups = events.collect(runs, WINDOW)
    groups["ipg_her__FetchPush-v4"]["2"]["unfinished_at"] = 1500
    run = groups["ipg_her__FetchPush-v4"]["1"]
    run["charts/SPS"] = [[500, 250], [1000, 1000], [1500, 500]]
    assert stats.first_eval_at(run, 0.5) == (1000, 1.0)
    assert stats.first_eval_at(run, 0.9) == (1500, 3.0)
    assert np.isnan(stats.first_eval_at(run, 0.95)[0])
    row = tables.reach_table(groups, (0.5, 0.9)).splitlines()[2]
    # seed 2 and 3 log SPS 1000 at step 1,500: 1.5 s = 0.0 h
    assert row.split(" | ")[2:] == ["1,000 (0.0) / 1,500 (0.0) / never", "1,500", "1,500 (0.0) / not yet / never", "- |"]


def test_finalists_table_reads_fresh_seeds_only_with_bootstrap_intervals(tmp_path):
    """Seeds 1-2 (the screen) are left out; over fresh seeds 11-13 the mean is exact and the
    95% bootstrap interval of the mean lies within the seeds' range (equal values: a point)."""
    runs = tmp_path / "runs" / "mixing"
    for seed, success in ((1, 0.0), (2, 0.0), (11, 0.4), (12, 0.6), (13, 0.8)):
        write_run(runs, "ipg_her_nu0.8_b100", "FetchReach-v4", seed, [-50] * 15, [0.2] * 5 + [success])
    write_run(runs, "ipg_her_nu1.0_b100", "FetchReach-v4", 11, [-50] * 15, [1.0, 1.0])
    groups = events.collect(runs, WINDOW)
    rows = tables.finalists_table(groups, np.random.default_rng(0), 11).splitlines()
    assert len(rows) == 3, "nu 1.0 has one fresh seed: no interval, no row"
    cells = rows[2].split(" | ")
    assert cells[2] == "3 (11-13)"
    assert cells[3] == "@ 2,500: 0.20 [0.20, 0.20]", "2,500 steps: the same in all"
    mean, lo, hi = map(float, re.findall(r"[0-9.]+", cells[4]))
    assert mean == 0.6 and 0.4 <= lo < mean < hi <= 0.8
    assert tables.finalists_table({}, np.random.default_rng(0), 11) == ""


def test_early_evaluation_is_labelled_with_the_step_it_was_at():
    """Hopper evaluates every 20,480 steps: the last evaluation by 100,000 steps is the one at
    81,920, and the table says so; runs evaluated at different steps give the range."""
    curve = lambda every, values: [[every * (i + 1), v] for i, v in enumerate(values)]  # noqa: E731
    run = lambda every, value: {  # noqa: E731
        "eval/episodic_return": curve(every, [value] * 6),
        "final": value,
    }
    groups = {"ipg_nu0.0_300k__Hopper-v5": {"11": run(20_480, 500.0), "12": run(20_480, 700.0)}}
    row = tables.finalists_table(groups, np.random.default_rng(0), 11).splitlines()[2]
    assert row.split(" | ")[3].startswith("@ 81,920: 600 ["), row
    runs = [run(20_480, 1.0), run(25_000, 1.0)]
    assert stats.steps_at(runs, "eval/episodic_return", 100_000) == "81,920-100,000"
    assert stats.steps_at(runs, "eval/episodic_return", 10_000) == "-"


def test_fetch_suite_report_draws_each_task_with_its_anchor_and_three_reach_levels(tmp_path):
    """The fetch suite: one figure per task in environment steps with the TQC+HER agent's
    points on it, and a reach table at 0.5, 0.7 and 0.9. The figures are drawn into
    --figures-dir only, each once, and results.md links them from where it is."""
    runs = tmp_path / "runs" / "fetch"
    for seed in (4, 5):
        write_run(runs, "ipg_her_300k", "FetchPush-v4", seed, [-50] * 15, [0.0, 0.6, 0.8, 0.95])
    assert report.main(report_args(tmp_path, "fetch")) == 0
    assert (tmp_path / "img" / "fetch_FetchPush-v4.png").stat().st_size > 0
    assert not list((tmp_path / "results").glob("*.png"))
    text = (tmp_path / "results" / "results.md").read_text()
    assert text.endswith("\n![fetch_FetchPush-v4.png](../img/fetch_FetchPush-v4.png)\n")
    assert "first eval >= 0.7" in text and "| 2,000 |" in text  # 0.9 first at 2,000 steps
    assert peers.ANCHORS["FetchPush-v4"] == ((100_000, 0.5), (200_000, 0.9))  # the table


def test_fetch_figures_draw_the_median_seed_and_the_band_from_lowest_to_highest():
    """Issue 29 asks for the median and a band over seeds: with 0.0, 0.2 and 1.0 at the end the
    line ends at 0.2 (the mean would be 0.4) and the band spans 0 to 1."""
    import matplotlib.pyplot as plt

    ends = {1: 0.0, 2: 0.2, 3: 1.0}
    groups = {"ipg_her__FetchPush-v4": {s: {"eval/success_rate": [[0, 0.0], [10, v]]} for s, v in ends.items()}}
    fig, ax = plt.subplots()
    figures.plot(ax, groups, ["ipg_her"], "FetchPush-v4", "eval/success_rate", None, median=True)
    assert ax.lines[0].get_ydata()[-1] == pytest.approx(0.2)
    band = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert band.min() == pytest.approx(0.0) and band.max() == pytest.approx(1.0)
    plt.close(fig)


def test_curves_go_on_dashed_past_the_shortest_seed():
    """An unfinished seed does not cut the figure: the line is solid while every seed has data
    and goes on, dashed and joined to it, over the seeds that ran on (here seed 2 alone)."""
    import matplotlib.pyplot as plt

    runs = {1: [[0, 0.0], [10, 0.2]], 2: [[0, 0.0], [10, 0.4], [20, 0.6]]}
    groups = {"ipg_her__FetchSlide-v4": {s: {"eval/success_rate": p} for s, p in runs.items()}}
    fig, ax = plt.subplots()
    figures.plot(ax, groups, ["ipg_her"], "FetchSlide-v4", "eval/success_rate", None, median=True)
    (solid, dashed) = ax.lines
    x_solid = solid.get_xdata()[np.isfinite(solid.get_ydata())]
    x_dashed, y_dashed = (v[np.isfinite(dashed.get_ydata())] for v in dashed.get_xydata().T)
    assert 9.8 < x_solid.max() <= 10 and x_dashed.min() == x_solid.max()
    assert x_dashed.max() == 20 and y_dashed[-1] == pytest.approx(0.6)
    assert dashed.get_linestyle() == "--" and solid.get_linestyle() == "-"
    plt.close(fig)


def test_iqm_interval_against_the_exact_bootstrap_distribution():
    """Four seeds: a resample's IQM (the mean of its middle two) is the lowest seed when three or
    four of the four draws are that seed, P = 13/256 > 2.5%, so the 95% interval of the IQM is
    exactly [lowest, highest]; the mean's needs all four, P = 1/256, so its interval lies
    strictly inside. Five seeds: the IQM (middle three) is neither the median nor the mean."""
    values = np.array([6.0, 8.0, 10.0, 100.0])
    assert stats.bootstrap_interval(values, stats.iqm, np.random.default_rng(0)) == (9.0, 6, 100)
    _, lo, hi = stats.bootstrap_interval(values, np.mean, np.random.default_rng(0))
    assert 6 < lo and hi < 100
    point, lo, hi = stats.bootstrap_interval([7.0], stats.iqm, np.random.default_rng(0))
    assert point == 7.0 and np.isnan(lo) and np.isnan(hi)  # one seed: no interval
    finals = [0.0, 100.0, 500.0, 600.0, 10000.0]
    groups = {"algo__Hopper-v5": {str(s): {"eval/episodic_return": [[1000, v]]} for s, v in enumerate(finals)}}
    row = tables.task_tables(groups, {}, 0).splitlines()[4]
    median, iqm = row.split(" | ")[2:4]
    assert median.startswith("500 [") and iqm.startswith("400 [")  # (100 + 500 + 600) / 3
    for cell, point in ((median, 500), (iqm, 400)):
        lo, hi = map(float, re.findall(r"[\d.]+", cell.split("[")[1].replace(",", "")))
        assert 0 <= lo < point < hi <= 10000


def test_time_to_threshold_is_each_seeds_step_over_the_sps_it_logged_there():
    """Per level: the median over all seeds of the first evaluation's step, and of each seed's
    own training time to it (its step over the charts/SPS logged at that step, not its final
    rate); a seed that never got there counts as never."""
    groups = {
        "ipg_her__FetchPush-v4": {
            # 0.5 at 2,000 steps, logged at 50 steps/s: 40 s; 0.7 and 0.9 at 3,000 (SPS 100): 30 s
            "1": {
                "eval/success_rate": [[1000, 0.2], [2000, 0.6], [3000, 0.95]],
                "charts/SPS": [[1000, 100], [2000, 50], [3000, 100]],
            },
            # 0.5 at 1,000 steps at 20 steps/s: 50 s; 0.7 at 2,000 (SPS 40): 50 s; 0.9 never
            "2": {
                "eval/success_rate": [[1000, 0.5], [2000, 0.7], [3000, 0.8]],
                "charts/SPS": [[1000, 20], [2000, 40], [3000, 1000]],
            },
            "3": {
                "eval/success_rate": [[1000, 0.1], [2000, 0.1], [3000, 0.1]],  # never
                "charts/SPS": [[1000, 10], [2000, 10], [3000, 10]],
            },
        }
    }
    assert stats.first_eval_at(groups["ipg_her__FetchPush-v4"]["1"], 0.5) == (2000, 40.0)
    lines = tables.task_tables(groups, {}, 0).splitlines()
    assert lines[0] == "**FetchPush-v4** (levels: evaluation success 0.5 / 0.7 / 0.9; no anchor recorded for this task)"
    cells = lines[4].strip(" |").split(" | ")
    # medians of (2,000, 1,000, never) and (40 s, 50 s, never); of (3,000, 2,000, never) and
    # (30 s, 50 s, never); of (3,000, never, never): never
    assert cells[4:12] == ["2,000 (2/3)", "50 s", "3,000 (2/3)", "50 s", "not reached (1/3)", "-", "1,000", "370"]
    hopper = {
        "qprop__Hopper-v5": {
            "1": {"eval/episodic_return": [[100, 900.0], [200, 2500.0]], "charts/SPS": [[100, 10], [200, 10]]}
        }
    }
    lines = tables.task_tables(hopper, {}, 0).splitlines()
    assert "first eval >= 1000:" in lines[2] and "first eval >= 3000:" in lines[2]
    assert lines[4].split(" | ")[4:10] == ["200 (1/1)", "20 s", "200 (1/1)", "20 s", "not reached (0/1)", "-"]
    assert [tables.duration(s) for s in (3.25, 45, 1020, 9000, np.inf)] == ["3.2 s", "45 s", "17 min", "2.5 h", "-"]
    # Hopper's PPO-KL: every 100,352 steps, then once more at the end of its 300k
    assert tables.eval_every([[[100_352, 0], [200_704, 0], [299_008, 0]]] * 2) == "100,352"
    assert tables.eval_every([[[500, 0], [1000, 0]], [[25_600, 0], [51_200, 0]]]) == "500-25,600"


def test_a_level_never_reached_by_half_the_seeds_or_more_is_not_reached():
    """Two seeds of four got there: the median counts the other two as never, so it is never
    (not the median of the two that did); a seed still running is named as such."""
    steps = [1000.0, 2000.0, np.nan, np.nan]
    assert tables.reach_cells(steps, [10.0, 20.0, np.nan, np.nan]) == ("not reached (2/4)", "-")
    assert tables.reach_cells(steps[:3], [10.0, 20.0, np.nan]) == ("2,000 (2/3)", "20 s")
    assert tables.reach_cells([np.nan] * 3, [np.nan] * 3, running=1) == ("not reached (0/3; 1 still running)", "-")
    assert tables.reach_cells([1000.0], None) == ("1,000 (1/1)", "n/a")  # time not recorded
    assert tables.reach_cells([1000.0], [np.nan]) == ("1,000 (1/1)", "n/a")  # no SPS logged


def write_side_by_side(path):
    """An against_sb3.py results.json: two seeds of each, SB3's first at 0.9 at 1,000 and 1,500
    steps."""
    sb3 = [[[0, 0.0], [500, 0.2], [1000, 1.0], [1500, 1.0]], [[0, 0.0], [500, 0.6], [1000, 0.8], [1500, 0.9]]]
    data = {
        "seeds": [21, 22],
        "steps": 1500,
        "sb3_ddpg_her": [
            {"steps_to_0.9": s, "train_s_to_0.9": t, "success": c}
            for s, t, c in zip((1000, 1500), (6.0, 8.0), sb3, strict=True)
        ],
        "ipg_her": [{"steps_to_0.9": 500, "train_s_to_0.9": 1.0, "success": [[500, 1.0]]}] * 2,
    }
    path.write_text(json.dumps(data))
    return sb3


def test_the_anchor_is_drawn_in_and_given_its_row(tmp_path, monkeypatch):
    """FetchReach's anchor (against_sb3.py's SB3 DDPG+HER) is drawn into the paper's success
    figure as the median over its seeds, in episodes, with its band from the lowest to the
    highest seed, and gets a row in the per-task table; the zoo agent's first evaluations are
    stars at their levels."""
    import matplotlib.pyplot as plt

    sb3 = write_side_by_side(tmp_path / "side.json")
    found = peers.load_peers(tmp_path / "side.json")
    (anchor, ours) = found["FetchReach-v4"]
    assert anchor.anchor and not ours.anchor
    assert anchor.first[0.9] == [1000, 1500] and anchor.seconds == {0.9: [6.0, 8.0]}
    fig, ax = plt.subplots()
    figures.draw_anchors(ax, found["FetchReach-v4"], per_episode=True)
    (line,) = ax.lines  # ours side by side is not an anchor: not drawn
    assert line.get_label().startswith("SB3 DDPG+HER, anchor: median of 2 seeds")
    np.testing.assert_allclose(line.get_xdata(), [0, 10, 20, 30])  # 50 steps an episode
    np.testing.assert_allclose(line.get_ydata(), np.median([[v for _, v in c] for c in sb3], 0))
    band = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert band.min() == 0.0 and band.max() == 1.0
    fig, ax = plt.subplots()
    figures.draw_anchors(ax, found["FetchPush-v4"])
    np.testing.assert_array_equal(ax.lines[0].get_xydata(), [[100_000, 0.5], [200_000, 0.9]])
    plt.close("all")

    drawn = []
    monkeypatch.setattr(figures, "draw_anchors", lambda ax, p, **kw: drawn.append((p, kw)))
    runs = tmp_path / "runs" / "quick"
    write_run(runs, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    assert report.main(report_args(tmp_path, "quick", side_by_side=str(tmp_path / "side.json"))) == 0
    assert drawn == [(found["FetchReach-v4"], {"per_episode": True})]  # the success figure
    text = (tmp_path / "results" / "results.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| SB3 DDPG+HER"))
    # finals 1.0 and 0.9; 0.5 first at 1,000 / 500, 0.7 at 1,000 / 1,000, 0.9 at 1,000 / 1,500
    assert row.split(" | ")[1:] == [
        "2 (21-22)",
        "0.95 [0.90, 1.00]",
        "0.95 [0.90, 1.00]",
        "750 (2/2)",
        "n/a",
        "1,000 (2/2)",
        "n/a",
        "1,250 (2/2)",
        "7.0 s",
        "500",
        "n/a |",
    ]
    assert "anchor: SB3 DDPG+HER)" in text and "*SB3 DDPG+HER (anchor)*" in text


def test_the_committed_side_by_side_run_reads_as_it_recorded_itself():
    """load_peers's steps to 0.9, found on the curves, are the ones against_sb3.py recorded."""
    recorded = json.loads(peers.SIDE_BY_SIDE.read_text())
    found = peers.load_peers(peers.SIDE_BY_SIDE)["FetchReach-v4"]
    found = {p.label.split(" ")[0]: p for p in found}
    for key, name in (("sb3_ddpg_her", "SB3"), ("ipg_her", "IPG+HER")):
        assert found[name].first[0.9] == [r["steps_to_0.9"] for r in recorded[key]]
        assert found[name].seconds[0.9] == [r["train_s_to_0.9"] for r in recorded[key]]


def test_an_anchor_run_here_gets_its_row_its_times_and_its_speed(tmp_path, monkeypatch):
    """sb3_fetch.py's runs (a summary.json each) are the task's anchor: its row gives each seed's
    last evaluation, the steps and training seconds (wall time less every evaluation so far) to
    each level, and the mean steps/s; the task's figure draws it in. A seed the suite did not run
    the task on (303) is left out: the anchor is compared on the same seeds."""
    evals = {
        301: [(0, 0.0, 1.0, 1.0), (1000, 0.6, 5.0, 1.0), (2000, 1.0, 9.0, 1.0)],
        302: [(0, 0.0, 2.0, 2.0), (1000, 0.2, 8.0, 2.0), (2000, 0.8, 14.0, 2.0)],
        303: [(0, 0.0, 2.0, 2.0), (1000, 0.0, 8.0, 2.0), (2000, 0.0, 14.0, 2.0)],
    }
    for seed, records in evals.items():
        folder = tmp_path / "anchors" / f"sac_her__HandReach-v3__seed{seed}"
        folder.mkdir(parents=True)
        summary = {
            "algo": "sac_her",
            "env": "HandReach-v3",
            "seed": seed,
            "train_steps_per_s": 100.0 * (seed - 300),
            "evals": [{"step": s, "eval_success": v, "wall_s": w, "eval_s": e} for s, v, w, e in records],
        }
        (folder / "summary.json").write_text(json.dumps(summary))
    seeds = {"HandReach-v3": {301, 302}, "FetchPush-v4": {303}}
    (anchor,) = peers.load_anchor_runs(tmp_path / "anchors", seeds)["HandReach-v3"]
    # seed 301: 0.5 first at 1,000 (5 s less 2 s of evaluation), 0.7 and 0.9 at 2,000 (9 s - 3 s);
    # seed 302: 0.5 and 0.7 at 2,000 (14 s - 6 s), 0.9 never
    assert anchor.first[0.5] == [1000, 2000] and anchor.seconds[0.5] == [3.0, 8.0]
    assert anchor.first[0.7] == [2000, 2000] and anchor.seconds[0.7] == [6.0, 8.0]
    assert anchor.first[0.9][0] == 2000 and anchor.seconds[0.9][0] == 6.0
    assert np.isnan(anchor.first[0.9][1]) and np.isnan(anchor.seconds[0.9][1])

    drawn = []
    monkeypatch.setattr(figures, "draw_anchors", lambda ax, p, **kw: drawn.append((p, kw)))
    for seed in (301, 302):
        write_run(tmp_path / "runs" / "goals", "ipg_her", "HandReach-v3", seed, [-50] * 3, [0, 1])
    assert report.main(report_args(tmp_path, "goals", anchor_runs=str(tmp_path / "anchors"))) == 0
    assert [p.label for p in drawn[0][0]] == ["SB3 SAC+HER (anchor; zoo settings)"]
    assert drawn[0][1] == {"per_episode": False}  # steps: a maze's episode is 600, not 50
    text = (tmp_path / "results" / "results.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| SB3 SAC+HER"))
    # finals 1.0 and 0.8; 0.9: 2,000 and never, so the median is never
    assert row.split(" | ")[1:] == [
        "2 (301-302)",
        "0.90 [0.80, 1.00]",
        "0.90 [0.80, 1.00]",
        "1,500 (2/2)",
        "5.5 s",
        "2,000 (2/2)",
        "7.0 s",
        "not reached (1/2)",
        "-",
        "1,000",
        "150 |",
    ]
    assert "anchor: SB3 SAC+HER)" in text and "(anchor; zoo settings)*" in text


def test_every_goal_task_is_reported_by_its_success():
    """The goals suite's tasks, like Fetch's: evaluation success at 0.5 / 0.7 / 0.9."""
    for env_id in ("FetchPush-v4", "HandReach-v3", "HandManipulateBlockRotateZ-v1", "PointMaze_Medium-v3"):
        assert stats.task_levels(env_id) == stats.GOAL_LEVELS
        assert stats.THRESHOLDS[env_id][0] == "eval/success_rate"
    assert stats.task_levels("Hopper-v5")[0] == "eval/episodic_return"


def test_the_paired_comparison_matches_its_definition():
    """benchmarks/paired.py: differences seed by seed on the seeds both ran, the mean with a
    bootstrap interval inside the differences' range, and the exact two-sided sign-flip test:
    four differences of one sign give p = 2 / 2^4 (all signs kept, or all flipped)."""
    from benchmarks import paired

    export = {
        "a": {str(s): {"final": f} for s, f in ((1, 10.0), (2, 20.0), (3, 30.0), (4, 5.0))},
        "b": {str(s): {"final": f} for s, f in ((1, 12.0), (2, 21.0), (3, 33.0), (4, 9.0), (5, 0.0))},
    }
    r = paired.paired(export, "a", "b")
    assert r["seeds"] == ["1", "2", "3", "4"]
    assert r["difference"].tolist() == [-2.0, -1.0, -3.0, -4.0] and r["mean"] == -2.5
    assert -4.0 <= r["interval"][0] < -2.5 < r["interval"][1] <= -1.0
    assert r["p"] == 2 / 16


def snapshot(folder) -> dict:
    """Every file under ``folder``: its bytes and modification time."""
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.rglob("*") if p.is_file()}


def test_a_report_with_no_runs_refuses_and_leaves_the_export_as_it_is(tmp_path):
    """The issue's command, ``--runs-dir EMPTY`` (a suite folder with no run in it): one error
    line, a non-zero exit, and the export, its results.md and its figures untouched."""
    write_run(tmp_path / "runs" / "paper", "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    assert report.main(report_args(tmp_path, "paper")) == 0
    before = snapshot(tmp_path)
    assert {tmp_path / "results" / f for f in ("curves.json", "results.md")} <= set(before)
    assert tmp_path / "img" / "fig5_fetchreach_success.png" in before
    (tmp_path / "empty" / "paper").mkdir(parents=True)
    cmd = [
        sys.executable,
        "benchmarks/report.py",
        "--suite",
        "paper",
        "--runs-dir",
        str(tmp_path / "empty"),
        "--results-dir",
        str(tmp_path / "results"),
        "--figures-dir",
        str(tmp_path / "img"),
    ]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert_clean_error(result, "no finished run", str(tmp_path / "empty" / "paper"))
    assert snapshot(tmp_path) == before


def test_a_report_with_fewer_runs_than_its_export_refuses_unless_told_to_replace(tmp_path, capsys):
    """Run folders that lack a run of the export (another machine's, a folder removed) would
    lose it: the report refuses and names the way out; --replace-export replaces the export."""
    import shutil

    runs, results = tmp_path / "runs" / "paper", tmp_path / "results"
    for seed in (1, 2):
        write_run(runs, "ipg_her", "FetchReach-v4", seed, [-50] * 3, [0.0, 1.0])
    assert report.main(report_args(tmp_path, "paper")) == 0
    shutil.rmtree(runs / "ipg_her__FetchReach-v4__seed2")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "paper")) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "1 of the 2 runs" in errors[0], errors
    assert "ipg_her__FetchReach-v4 seed 2" in errors[0] and "--replace-export" in errors[0]
    assert snapshot(tmp_path) == before
    assert report.main(report_args(tmp_path, "paper", replace_export=True)) == 0
    export = json.loads((results / "curves.json").read_text())
    assert list(export["ipg_her__FetchReach-v4"]) == ["1"]


@pytest.mark.parametrize("damage", ["length", "event", "cut"])
def test_a_damaged_event_file_is_named_in_a_warning(tmp_path, capsys, damage):
    """A bit flipped in a record's length or in its event fails the record's checksum: the run
    is left out, a warning naming its file; a file cut short mid-record (its writer killed) is
    read up to there, a warning naming it. Never a row of NaN or of part of a run, silently."""
    runs = tmp_path / "runs" / "test"
    for seed in (1, 2):
        write_run(runs, "algo", "Hopper-v5", seed, [100.0 * seed] * 40)
    (event_file,) = (runs / "algo__Hopper-v5__seed2").rglob("events.out.tfevents.*")
    data, starts = bytearray(event_file.read_bytes()), [0]  # a record: length, CRC, event, CRC
    while starts[-1] < len(data):
        starts.append(starts[-1] + 16 + int.from_bytes(data[starts[-1] : starts[-1] + 8], "little"))
    record = starts[len(starts) // 2]  # a record in the middle: a training return's
    if damage == "cut":
        data = data[: record + 14]
    else:
        data[record if damage == "length" else record + 14] ^= 0x04
    event_file.write_bytes(bytes(data))
    capsys.readouterr()
    groups = events.collect(runs, WINDOW)["algo__Hopper-v5"]
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warn")]
    assert len(warnings) == 1 and str(event_file) in warnings[0], warnings
    if damage == "cut":
        assert 0 < len(groups["2"]["charts/episodic_return"]) < 40 and groups["2"]["final"] == 200
    else:
        assert list(groups) == ["1"] and "left out" in warnings[0]


def test_a_suites_report_settings_are_its_entry_in_suites_py_not_branches_on_its_name(tmp_path):
    """report.py and its modules never ask which suite they read: what one shows beyond the
    common tables (its figures, budgets, levels) is the Report beside its runs in suites.py's
    SUITES."""
    modules = ("report", "events", "stats", "tables", "peers", "figures")
    source = "".join((ROOT / "benchmarks" / f"{name}.py").read_text() for name in modules)
    assert not re.findall(r"suite\s*(?:==|!=|not in|in)\s*[(\"']", source)
    reach = {}
    for suite in ("goals", "fetch"):  # the same run: only fetch's Report asks for a reach table
        write_run(tmp_path / "runs" / suite, "ipg_her", "FetchPush-v4", 1, [-50] * 3, [0.0, 0.6])
        args = report_args(tmp_path, suite, results_dir=str(tmp_path / suite))
        assert report.main(args) == 0
        reach[suite] = "steps (training h) per seed" in (tmp_path / suite / "results.md").read_text()
    assert reach == {"goals": False, "fetch": True}
    assert suites.SUITES["goals"].report.levels == () and suites.SUITES["fetch"].report.levels


def test_a_suite_run_py_does_not_know_is_refused_before_anything_is_written(tmp_path):
    """``--suite fetch_fresh`` (an export folder's name, not a suite): its settings would be
    guessed and the committed results.md in that folder rewritten with them."""
    (tmp_path / "fetch_fresh").mkdir()
    (tmp_path / "fetch_fresh" / "curves.json").write_text('{"a__FetchPush-v4": {"1": {}}}')
    before = snapshot(tmp_path)
    folders = ["--results-dir", str(tmp_path / "fetch_fresh"), "--figures-dir", str(tmp_path)]
    cmd = [sys.executable, "benchmarks/report.py", "--suite", "fetch_fresh", "--from-export"]
    result = subprocess.run(cmd + folders, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert_clean_error(result, "--suite fetch_fresh: not a suite", "--results-dir")
    assert snapshot(tmp_path) == before


def test_every_run_folder_left_out_is_named_with_why(tmp_path, capsys):
    """A run whose runner was stopped before it wrote exit_code (kill -9 after the run's end) is
    not known to have finished: it is left out, but not silently; so are a run still running,
    a failed one, a stopped one and one whose exit_code was cut short. Finished runs are read."""
    runs = tmp_path / "runs" / "test"
    codes = {1: "0\n", 2: None, 3: None, 4: "1\n", 5: "130\n", 6: ""}
    for seed, code in codes.items():
        write_run(runs, "algo", "Hopper-v5", seed, [100.0] * 10)
        folder = runs / f"algo__Hopper-v5__seed{seed}"
        (folder / "exit_code").unlink() if code is None else (folder / "exit_code").write_text(code)
    running = runs / "algo__Hopper-v5__seed3"  # a process whose command line names the run
    (runs / "notes.txt").write_text("not a run folder")
    capsys.readouterr()
    sleep = "import time; print(flush=True); time.sleep(60)"
    with subprocess.Popen([sys.executable, "-c", sleep, running.name], stdout=subprocess.PIPE) as sleeper:
        sleeper.stdout.readline()  # started: its command line is its own
        (running / "pid").write_text(f"{sleeper.pid}\n")
        try:
            assert list(events.collect(runs, WINDOW)["algo__Hopper-v5"]) == ["1"]
        finally:
            sleeper.kill()
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warn")]
    why = {
        2: "no exit_code, which benchmarks/run.py writes when a run ends",
        3: f"still running (pid {sleeper.pid})",
        4: "failed (exit code 1",
        5: "stopped by a signal (exit code 130)",
        6: "its exit_code holds ''",
    }
    assert len(warnings) == len(why), warnings
    for (seed, needle), line in zip(why.items(), warnings, strict=True):
        assert line.startswith(f"warning: {runs}/algo__Hopper-v5__seed{seed}: ") and needle in line
        assert line.endswith(("left out", "if it has one")), line


def the_error_line(capsys) -> str:
    """The one ``error:`` line report.main wrote to stderr (it fails if there are more, or none)."""
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, errors
    return errors[0]


@pytest.mark.parametrize("content", ["[]", "3", '{"ppo_kl__Hopper-v5": [1, 2]}', '{"a": {}}'])
@pytest.mark.parametrize("from_export", [False, True])
def test_an_export_of_another_shape_is_one_error_line_and_nothing_is_written(tmp_path, capsys, content, from_export):
    """An export that is JSON but not an object of groups of runs, read to redraw or to be
    replaced: one error line naming it, and nothing written."""
    write_run(tmp_path / "runs" / "quick", "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "curves.json").write_text(content)
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", from_export=from_export)) == 2
    assert "curves.json is not a readable export" in the_error_line(capsys)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "flags, needle",
    [
        ({"merge_export": "no_such.json"}, "no_such.json: no such file"),
        ({"merge_export": "list.json"}, "list.json is not a readable export"),
        ({"window": 0}, "--window 0:"),
        ({"window": -5}, "--window -5:"),
    ],
)
def test_a_bad_merge_export_or_window_is_one_error_line_before_anything_is_written(tmp_path, capsys, flags, needle):
    """--merge-export naming no file or no export, --window 0 or below (Hopper's windowed return
    would be a traceback): one error line naming it, and nothing written."""
    write_run(tmp_path / "runs" / "quick", "ppo_kl", "Hopper-v5", 1, [100.0] * 10)
    (tmp_path / "list.json").write_text("[]")
    flags = {k: str(tmp_path / v) if k == "merge_export" else v for k, v in flags.items()}
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", **flags)) == 2
    assert needle in the_error_line(capsys)
    assert snapshot(tmp_path) == before


def test_an_export_is_redrawn_only_over_the_window_its_runs_were_read_with(tmp_path, capsys):
    """``--from-export --window N``: the export's final returns and steps to threshold were
    computed over the window it was read with, so N only reworded results.md ("the last N
    training episodes") over numbers that are not. Each run keeps its window; another N is one
    error line naming both, and nothing written. An export from before runs kept their window
    was read with the default, 100."""
    write_run(tmp_path / "runs" / "quick", "ppo_kl", "Hopper-v5", 1, [100.0] * 8 + [900.0] * 2)
    assert report.main(report_args(tmp_path, "quick", window=2)) == 0
    export = tmp_path / "results" / "curves.json"
    (run,) = json.loads(export.read_text())["ppo_kl__Hopper-v5"].values()
    assert run["final"] == 900  # the last 2 returns: 900 and 900
    text = (tmp_path / "results" / "results.md").read_text()
    assert "the mean return of the last 2 training episodes" in text
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", from_export=True, window=10)) == 2
    error = the_error_line(capsys)
    assert "--window 10:" in error and "over the last 2 training episodes" in error, error
    assert "pass --window 2" in error, error
    assert snapshot(tmp_path) == before
    assert report.main(report_args(tmp_path, "quick", from_export=True, window=2)) == 0
    assert (tmp_path / "results" / "results.md").read_text() == text

    assert run["window"] == 2  # what the export records
    groups = json.loads(export.read_text())
    del groups["ppo_kl__Hopper-v5"]["1"]["window"]  # an export written before runs kept theirs
    export.write_text(json.dumps(groups))
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", from_export=True, window=2)) == 2
    assert "over the last 100 training episodes" in the_error_line(capsys)


@pytest.mark.parametrize("earlier", ["keep_export", "merge_export"])
def test_runs_kept_or_merged_from_an_export_read_with_another_window_are_refused(tmp_path, capsys, earlier):
    """Runs kept from the suite's export (--keep-export) or merged from an earlier one
    (--merge-export) keep the final return of the window they were read with: beside runs read
    now over another --window, one table would state one window over both. One error line, and
    nothing written."""
    runs = tmp_path / "runs" / "quick"
    write_run(runs, "qprop_ppo", "Hopper-v5", 1, [100.0] * 10)
    assert report.main(report_args(tmp_path, "quick", window=3)) == 0
    (runs / "qprop_ppo__Hopper-v5__seed1" / "exit_code").unlink()  # its event files elsewhere
    write_run(runs, "ppo_kl", "Hopper-v5", 2, [100.0] * 10)
    flags = {"keep_export": True}
    if earlier == "merge_export":
        (tmp_path / "results" / "curves.json").rename(tmp_path / "earlier.json")
        flags = {"merge_export": str(tmp_path / "earlier.json")}
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", window=5, **flags)) == 2
    error = the_error_line(capsys)
    assert "--window 5:" in error and "over the last 3 training episodes" in error, error
    assert snapshot(tmp_path) == before
    assert report.main(report_args(tmp_path, "quick", window=3, **flags)) == 0


def test_a_results_dir_elsewhere_keeps_its_figures_and_never_takes_a_suites(tmp_path, monkeypatch):
    """``--results-dir /elsewhere/paper`` without --figures-dir drew into docs/img/paper, over the
    paper suite's committed figures: the figures now go into the results folder given, linked
    from its results.md. The suite's own results folder, however spelled, keeps docs/img/{suite}."""
    write_run(tmp_path / "runs" / "quick", "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    monkeypatch.chdir(tmp_path)  # report.py's defaults are relative to the project root
    committed = tmp_path / "docs" / "img" / "paper" / "fig5_fetchreach_success.png"
    committed.parent.mkdir(parents=True)
    committed.write_bytes(b"the paper suite's figure")
    elsewhere = tmp_path / "elsewhere" / "paper"
    args = report.Args(suite="quick", runs_dir="runs", results_dir=str(elsewhere))
    assert report.main(args) == 0
    assert committed.read_bytes() == b"the paper suite's figure"
    assert [p.name for p in (tmp_path / "docs" / "img").iterdir()] == ["paper"]
    assert (elsewhere / "fig5_fetchreach_success.png").stat().st_size > 0
    link = "\n![fig5_fetchreach_success.png](fig5_fetchreach_success.png)\n"
    assert link in (elsewhere / "results.md").read_text()
    args = report.Args(suite="quick", runs_dir="runs", results_dir="./benchmarks/results/quick")
    assert report.main(args) == 0
    assert (tmp_path / "docs" / "img" / "quick" / "fig5_fetchreach_success.png").is_file()
    assert not list((tmp_path / "benchmarks" / "results" / "quick").glob("*.png"))


def report_again_with_a_new_seed(tmp_path, **flags) -> dict:
    """A first report of the quick suite (seed 1) under ``tmp_path``, then a second seed's run,
    which a second report would add to every file: a snapshot of the files before it."""
    runs = tmp_path / "runs" / "quick"
    write_run(runs, "ipg_her", "FetchReach-v4", 1, [-50] * 3, [0.0, 1.0])
    assert report.main(report_args(tmp_path, "quick", **flags)) == 0
    write_run(runs, "ipg_her", "FetchReach-v4", 2, [-50] * 3, [0.0, 0.5])
    return snapshot(tmp_path)


@pytest.mark.parametrize("folder", ["results", "img"])
def test_a_folder_it_cannot_write_in_is_one_error_line_and_no_file_changes(tmp_path, folder):
    """A read-only results folder, or figures folder (the export, written first, would already be
    replaced): one error line naming the file, and the export, results.md and the figures as they
    were, no temporary left beside them."""
    before = report_again_with_a_new_seed(tmp_path)
    folders = {"--runs-dir": "runs", "--results-dir": "results", "--figures-dir": "img"}
    cmd = [sys.executable, "benchmarks/report.py", "--suite", "quick"]
    cmd += [f"{flag}={tmp_path / folder}" for flag, folder in folders.items()]
    with read_only(tmp_path / folder):
        result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert_clean_error(result, f"could not write {tmp_path / folder}", "left as they were")
    assert snapshot(tmp_path) == before


def test_a_full_disk_between_the_export_and_results_md_changes_no_file(tmp_path, monkeypatch, capsys):
    """The disk fills up (ENOSPC) when results.md is written, after the export: one error line
    saying so, and the export, results.md, the figures and --page as they were, no temporary
    left."""
    page = tmp_path / "page.md"
    page.write_text("<!-- results:quick:start -->\n<!-- results:quick:end -->\n")
    before = report_again_with_a_new_seed(tmp_path, page=str(page))
    write_text = Path.write_text

    def full_disk(path, *args, **kwargs):
        if "results.md" in path.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write_text(path, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full_disk)
    capsys.readouterr()
    assert report.main(report_args(tmp_path, "quick", page=str(page))) == 2
    error = the_error_line(capsys)
    assert "results.md" in error and error.endswith(
        "(the disk is full); the export, results.md, the figures and --page are left as they were"
    )
    assert snapshot(tmp_path) == before
