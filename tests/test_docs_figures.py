"""The figures the docs quote are the committed exports' (``benchmarks/results/<suite>/``): every
number of the README's results table, and every row of the headline tables of docs/results.md and
docs/investigations/one_recipe.md, is recomputed here from the export it comes from, by
``benchmarks/report.py``'s own functions (its medians, its bootstrap intervals with their seeds),
and a figure that drifts from it fails, naming its row. Each export's ``results.md`` is checked
against its ``curves.json`` the same way, so that the tables a reader opens there agree too."""

import functools
import json
import re
import statistics
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import report, stats, tables  # noqa: E402
from benchmarks.peers import (  # noqa: E402
    ANCHOR_RUNS,
    SIDE_BY_SIDE,
    load_anchor_runs,
    load_peers,
)
from benchmarks.suites import SUITES as RUNS  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SUITES = sorted(path.parent.name for path in RESULTS.glob("*/curves.json"))


@functools.cache
def curves(suite: str) -> dict:
    """The export's runs; read once (nothing here changes them)."""
    return json.loads((RESULTS / suite / "curves.json").read_text())


@functools.cache
def task_tables(suite: str, seeds: tuple[int, ...] = ()) -> str:
    """report.py's per-task tables of ``suite``, its anchors beside them, as its main() computes
    them; with ``seeds``, from those seeds' runs only."""
    groups = curves(suite)
    if seeds:
        groups = {g: {s: r for s, r in runs.items() if int(s) in seeds} for g, runs in groups.items()}
        groups = {g: runs for g, runs in groups.items() if runs}
    peers = load_peers(SIDE_BY_SIDE)
    ran = defaultdict(set)
    for group, runs in groups.items():
        ran[group.split("__")[1]].update(int(seed) for seed in runs)
    for env_id, anchors in load_anchor_runs(ANCHOR_RUNS, ran).items():
        peers[env_id] += anchors
    return tables.task_tables(groups, peers, report.Args.seed)


def split_row(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split(" | ")]


def export_rows(suite: str, seeds: tuple[int, ...] = ()) -> dict[tuple[str, str], dict]:
    """{(task, row label): {column: cell}} of ``task_tables``; a column header without its
    suffix ("first eval >= 0.5: median steps (seeds there)" is "first eval >= 0.5")."""
    rows, task, header = {}, None, None
    for line in task_tables(suite, seeds).splitlines():
        if line.startswith("**"):
            task, header = line.split("**")[1], None
        elif line.startswith("| algorithm"):
            header = [h.split(":")[0] if h.startswith("first") else h for h in split_row(line)]
        elif line.startswith("| ") and header:
            cells = dict(zip(header, split_row(line), strict=True))
            rows[task, cells["algorithm"]] = cells
    return rows


def export_cell(suite: str, task: str, label: str, column: str, seeds: str = "") -> str:
    """A cell of ``suite``'s row ``label`` on ``task``; with ``seeds`` ("21-25"), that row on
    those seeds, recomputed from them alone where the export pools more."""
    row = export_rows(suite)[task, label]
    if seeds and seeds_of(row) != seeds:
        wanted = {int(s) for part in seeds.split(", ") for s in seed_span(part)}
        row = export_rows(suite, tuple(sorted(wanted)))[task, label]
    assert not seeds or seeds_of(row) == seeds, (suite, task, label, row["seeds"], seeds)
    return row[column]


def seed_span(part: str) -> range:
    first, _, last = part.partition("-")
    return range(int(first), int(last or first) + 1)


def seeds_of(row: dict) -> str:
    """A row's seeds: "3 (401-403)" -> "401-403"; an anchor's "1" -> "1"."""
    match = re.fullmatch(r"\d+ \((.*)\)", row["seeds"])
    return match[1] if match else row["seeds"]


FINAL = "final eval: median [95% CI]"


def final_eval(suite: str, task: str, label: str, seeds: str = "") -> str:
    return export_cell(suite, task, label, FINAL, seeds)


def median(cell: str) -> str:
    """The median of a final-eval cell: "0.68 [0.66, 0.70]" -> "0.68"."""
    return cell.split(" [")[0]


def first_eval(suite: str, task: str, label: str, level: float, seeds: str = "") -> str:
    return export_cell(suite, task, label, f"first eval >= {level:g}", seeds)


def kilo(cell: str) -> str:
    """The README's steps: "170,000 (3/3)" -> "170k"; a level not reached is no figure."""
    assert not cell.startswith("not reached"), cell
    return f"{int(cell.split()[0].replace(',', '')) // 1000}k"


def no_seed(cell: str) -> str:
    """A level no seed reached: "not reached (0/3)" -> "no seed"; any other cell is a wrong claim."""
    assert cell.startswith("not reached (0/"), cell
    return "no seed"


# ---------------------------------------------------------------------------------------------
# each export's results.md against its curves.json


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the std of a one-seed row: nan, as printed
@pytest.mark.parametrize("suite", SUITES)
def test_each_results_md_holds_the_tables_its_curves_json_gives(suite):
    """The per-task tables and the training table of ``results.md`` are what report.py computes
    from the same folder's ``curves.json``: a hand-edited or stale results.md fails."""
    committed = (RESULTS / suite / "results.md").read_text()
    groups = curves(suite)
    computed = task_tables(suite) + "\n" + tables.table(groups, report.Args.window)
    missing = [line for line in computed.splitlines() if line.startswith("|") and line not in committed]
    assert not missing, f"benchmarks/results/{suite}/results.md lacks: {missing[:3]}"


# ---------------------------------------------------------------------------------------------
# the README's results table


def side_by_side() -> tuple[float, float]:
    """The medians of the training seconds to 0.9 in the against_sb3 export: ours, SB3's."""
    data = json.loads(SIDE_BY_SIDE.read_text())
    return tuple(statistics.median(r["train_s_to_0.9"] for r in data[key]) for key in ("ipg_her", "sb3_ddpg_her"))


def every_seed_at(suite: str, group: str, level: float) -> str:
    """The step by which every seed had evaluated at ``level`` or more (stats.first_eval_at)."""
    steps = [stats.first_eval_at(run, level)[0] for run in curves(suite)[group].values()]
    assert np.isfinite(steps).all(), (suite, group, steps)
    return f"{max(steps):,.0f}"


def highest_eval(suite: str, *groups: str) -> str:
    values = [v for g in groups for run in curves(suite)[g].values() for _, v in run["eval/success_rate"]]
    return f"{max(values):.2f}"


def training_return(suite: str, label: str) -> str:
    """The first table's "final (mean ± sample std)" on Hopper, "2220 ± 347" as "2,220 ± 347"."""
    lines = tables.table(curves(suite), report.Args.window).splitlines()
    cells = next(split_row(line) for line in lines if line.startswith(f"| Hopper-v5 | {label} |"))
    mean, std = cells[3].split(" ± ")
    return f"{int(mean):,} ± {int(std):,}"


def readme_rows() -> dict[str, list[str]]:
    """For each row of the README's results table, by its question: the phrases it must hold,
    each built from the export it names, and the words with digits that are no figure (seeds,
    budgets, flags, names)."""
    ours, sb3 = side_by_side()
    reach_side = first_eval("paper", "FetchReach-v4", "IPG+HER side by side (3,000 steps)", 0.9)
    sb3_reach = first_eval("paper", "FetchReach-v4", "SB3 DDPG+HER (anchor; 3,000 steps)", 0.9)
    assert reach_side == sb3_reach  # the row says "as SB3's DDPG+HER"
    push, pick = "FetchPush-v4", "FetchPickAndPlace-v4"
    slide, reach, maze = "FetchSlide-v4", "HandReach-v3", "PointMaze_Medium-v3"
    block, sac = "HandManipulateBlockRotateZ-v1", "SB3 SAC+HER (anchor; zoo settings)"
    slide_flags = "--target-std 0.3 0.3 0.3 1 --action-l2 0 --bounds-loss 1` and annealed rates"
    her, no_her = (every_seed_at("paper", f"{g}__FetchReach-v4", 1.0) for g in ("ipg_her", "ipg"))
    return {
        "Does the main job learn FetchReach, and how fast? (seeds 21-25)": [
            f"success 0.9 after a median {reach_side.split()[0]} steps, as SB3's DDPG+HER",
            f"{sb3 / ours:.1f} times less training time, side by side (medians of {ours:.2f} s against {sb3:.2f} s",
            "21-25",
        ],
        "IPG + HER > Q-Prop > PPO-KL on FetchReach? (seeds 1-5, which chose `ipg_her.py`'s defaults; 30k steps)": [
            f"IPG + HER 1.00 by {her} steps in every seed, IPG without HER by {no_her}",
            "PPO-KL and Q-Prop no evaluation above "
            + highest_eval("paper", "ppo_kl__FetchReach-v4", "qprop_ppo__FetchReach-v4"),
            "1-5",
            "30k",
        ],
        "Q-Prop > PPO-KL on Hopper? (seeds 101-108, 1M steps)": [
            f"final training return {training_return('paper_fresh', 'Q-Prop')} against PPO-KL's "
            f"{training_return('paper_fresh', 'PPO-KL')}, mean ± std over seeds",
            "101-108",
            "1M",
        ],
        "Does an interpolated gradient (0 < nu < 1) beat both ends?": ["0 < nu < 1"],
        "FetchPush, the defaults, 300k (seeds 601-603)": [
            f"last evaluation {final_eval('every_goal', push, 'ipg_her_300k', '601-603')}, 0.9 by a median "
            f"{kilo(first_eval('every_goal', push, 'ipg_her_300k', 0.9))} steps (the target: by "
            f"{TARGETS[push][0] // 1000}k; TQC+HER's published agent: {kilo(first_eval('every_goal', push, TQC, 0.9))})",
            "300k",
            "601-603",
        ],
        "FetchPickAndPlace, the defaults, 500k (seeds 601-603)": [
            f"last evaluation {final_eval('every_goal', pick, 'ipg_her_500k', '601-603')}, 0.9 by a median "
            f"{kilo(first_eval('every_goal', pick, 'ipg_her_500k', 0.9))} steps (the target: by "
            f"{TARGETS[pick][0] // 1000}k, ending ≥ {TARGETS[pick][1]:.2f}; TQC+HER's published agent: "
            f"{kilo(first_eval('every_goal', pick, TQC, 0.9))})",
            "500k",
            "601-603",
        ],
        "FetchSlide, the defaults, 1M (seeds 601-602)": [
            f"last evaluation {final_eval('every_goal', slide, 'ipg_her_1000k', '601-602')} (the target: "
            f"{TARGETS[slide][1]:.2f}); with `{slide_flags} (seeds 7-9) {final_eval('fetch', slide, 'ipg_her_1000k', '7-9')}",
            "1M",
            "601-602",
        ],
        "HandReach, the defaults, 300k (seeds 601-603)": [
            f"last evaluation {final_eval('every_goal', reach, 'ipg_her_300k', '601-603')} (the target: "
            f"{TARGETS[reach][1]:.2f}; SB3 SAC+HER on the same seeds {final_eval('every_goal', reach, sac, '601-603')})",
            "300k",
            "601-603",
        ],
        "PointMaze_Medium, the defaults, 300k (seeds 601-603)": [
            f"last evaluation {final_eval('every_goal', maze, 'ipg_her_300k', '601-603')} (the target: "
            f"{TARGETS[maze][1]:.2f}), 0.9 by a median {kilo(first_eval('every_goal', maze, 'ipg_her_300k', 0.9))}",
            "300k",
            "601-603",
        ],
        "BlockRotateZ, the defaults, 1M (seeds 601-603)": [
            f"last evaluation {final_eval('every_goal', block, 'ipg_her_1000k', '601-603')} (the target: "
            f"{TARGETS[block][1]:.2f}), seed 602 falling to {per_seed('every_goal', f'ipg_her_1000k__{block}').split()[2]} "
            f"after {max(v for _, v in curves('every_goal')[f'ipg_her_1000k__{block}']['602']['eval/success_rate']):.2f}",
            f"the held rule (seeds 401-403) {final_eval('one_recipe', block, 'ipg_her_1000k', '401-403')}",
            "1M",
            "601-603",
        ],
    }


def readme_table() -> list[list[str]]:
    text = (ROOT / "README.md").read_text().split("## Results", 1)[1].split("\n## ", 1)[0]
    return [split_row(line) for line in text.splitlines() if line.startswith("| ")][2:]


def test_every_number_of_the_readmes_results_table_is_its_exports():
    """Each row holds its phrases, every figure in them recomputed from its export; once they and
    the row's seeds, budgets and names are taken out, no digit is left: no figure goes unchecked.
    A row added or reworded must be given its phrases here. Every row is checked, then all that
    drifted are named at once."""
    expected, rows = readme_rows(), dict(readme_table())
    drifted = [f"a row no phrase checks: {q!r}" for q in rows if q not in expected]
    for question, phrases in expected.items():
        if question not in rows:
            drifted.append(f"no row {question!r}")
            continue
        text = re.sub(r"\]\([^)]*\)", "]", f"{question} | {rows[question]}")  # links: no figures
        for phrase in phrases:
            if phrase not in text:
                drifted.append(f"row {question!r}: the export gives {phrase!r}")
            text = text.replace(phrase, "", 1)
        if re.search(r"\d", text.replace("SB3", "")):
            drifted.append(f"row {question!r}: a figure no export checks, in {text!r}")
    assert not drifted, "README's results table:\n" + "\n".join(drifted)


# ---------------------------------------------------------------------------------------------
# the headline rows of the results pages

# (task, seeds, the row's label on the page) -> (suite, the export's row label)
SOURCES = {
    ("Hopper-v5", "101-108", "**PPO-KL, 1M** (held out)"): ("paper_fresh", "PPO-KL"),
    ("Hopper-v5", "101-108", "**Q-Prop, 1M** (held out)"): ("paper_fresh", "Q-Prop"),
    ("Hopper-v5", "1-5", "PPO-KL, 1M"): ("paper", "PPO-KL"),
    ("Hopper-v5", "1-5", "Q-Prop, 1M"): ("paper", "Q-Prop"),
    ("Hopper-v5", "4-6, 14-19", "**IPG at $\\nu = 1$ in TD3's regime, 300k** (held out)"): (
        "hopper",
        "ipg_td3_nu1.0_300k",
    ),
    ("Hopper-v5", "1-2, 4-6, 8-19", "PPO-KL, 300k"): ("hopper", "ppo_kl_300k"),
    ("FetchReach-v4", "21-25", "**IPG+HER** (held out)"): ("mixing", "ipg_her_nu1.0_b100"),
    ("FetchReach-v4", "1-5", "IPG+HER"): ("paper", "IPG+HER"),
    ("FetchReach-v4", "1-5", "IPG without HER"): ("paper", "IPG (no HER)"),
    ("FetchReach-v4", "1-5", "PPO-KL"): ("paper", "PPO-KL"),
    ("FetchReach-v4", "1-5", "Q-Prop"): ("paper", "Q-Prop"),
    ("FetchReach-v4", "21-25", "**IPG+HER, side by side** (held out)"): (
        "paper",
        "IPG+HER side by side (3,000 steps)",
    ),
    ("FetchReach-v4", "21-25", "SB3 DDPG+HER (anchor; the HER paper's settings)"): (
        "paper",
        "SB3 DDPG+HER (anchor; 3,000 steps)",
    ),
    # the recipe's defaults on every goal task (results.md's first goal table, then its task sections)
    ("FetchPush-v4", "601-603", "**the defaults** (held out)"): ("every_goal", "ipg_her_300k"),
    ("HandReach-v3", "601-603", "**the defaults** (held out)"): ("every_goal", "ipg_her_300k"),
    ("HandReach-v3", "601-603", "SB3 SAC+HER (anchor)"): ("every_goal", "SB3 SAC+HER (anchor; zoo settings)"),
    ("PointMaze_Medium-v3", "601-603", "**the defaults** (held out)"): ("every_goal", "ipg_her_300k"),
    ("FetchPickAndPlace-v4", "601-603", "**the defaults** (held out)"): ("every_goal", "ipg_her_500k"),
    ("FetchSlide-v4", "601-602", "**the defaults** (held out)"): ("every_goal", "ipg_her_1000k"),
    ("HandManipulateBlockRotateZ-v1", "601-603", "**the defaults** (held out)"): ("every_goal", "ipg_her_1000k"),
    ("FetchPush-v4", "601-603", "**`ipg_her_recipe.py`, 300k, the defaults** (held out)"): (
        "every_goal",
        "ipg_her_300k",
    ),
    # FetchPush: one_recipe.md's labels
    ("FetchPush-v4", "1-3", "`ipg_her.py`, 1.5M"): ("push", "ipg_her_1500k"),
    ("FetchPush-v4", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_300k",
    ),
    ("FetchPush-v4", "201-205", "`--target-std 1.0` (held out)"): ("fetch_fresh", "ipg_her_300k"),
    ("FetchPickAndPlace-v4", "601-603", "**`ipg_her_recipe.py`, 500k, the defaults** (held out)"): (
        "every_goal",
        "ipg_her_500k",
    ),
    ("FetchPickAndPlace-v4", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_500k",
    ),
    ("FetchPickAndPlace-v4", "201-203", "`--target-std 1.0 1.0 1.0 0.3` (held out)"): (
        "fetch_fresh",
        "ipg_her_500k",
    ),
    ("FetchSlide-v4", "601-602", "**`ipg_her_recipe.py`, 1M, the defaults** (held out)"): ("every_goal", "ipg_her_1000k"),
    ("FetchSlide-v4", "401-403", "`ipg_her_recipe.py`, 1M, the held rule (held out)"): (
        "one_recipe",
        "ipg_her_1000k",
    ),
    ("FetchSlide-v4", "7-9", "**`ipg_her_recipe.py`, 1M, Slide's flags** (held out)"): (
        "fetch",
        "ipg_her_1000k",
    ),
    ("FetchSlide-v4", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_1000k",
    ),
    ("FetchSlide-v4", "7-9", "Slide's flags (held out)"): ("fetch", "ipg_her_1000k"),
    ("HandReach-v3", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_300k",
    ),
    ("HandReach-v3", "301-303", "`--target-std 1.0 --gamma 0.98` (held out)"): (
        "goals",
        "ipg_her_300k",
    ),
    ("HandReach-v3", "301-303", "0.3 for each joint ‡"): ("goals", "ipg_her_300k_std03x20"),
    (
        "HandManipulateBlockRotateZ-v1",
        "401-403",
        "**the held rule, 0.447 for each joint** (held out)",
    ): ("one_recipe", "ipg_her_1000k"),
    ("HandManipulateBlockRotateZ-v1", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_1000k",
    ),
    ("HandManipulateBlockRotateZ-v1", "301-303", "`--target-std 1.0 --gamma 0.98` (held out)"): (
        "goals",
        "ipg_her_1000k",
    ),
    ("PointMaze_Medium-v3", "301-303", "`--target-std 1.0 --gamma 0.995` ‡"): (
        "goals",
        "ipg_her_300k_gamma0995",
    ),
    ("PointMaze_Medium-v3", "401-403", "**the held rule** (held out)"): (
        "one_recipe",
        "ipg_her_300k",
    ),
    ("PointMaze_Medium-v3", "301-303", "`--target-std 1.0 --gamma 0.98` (held out)"): (
        "goals",
        "ipg_her_300k",
    ),
}
TQC = "TQC+HER zoo agent (anchor)"  # the same rows in every Fetch export
for _task, _suite in (
    ("FetchPush-v4", "fetch_fresh"),
    ("FetchPickAndPlace-v4", "fetch_fresh"),
    ("FetchSlide-v4", "fetch"),
):
    SOURCES[_task, "1", "TQC+HER zoo agent (anchor; one seed)"] = (_suite, TQC)
for _task, _seeds, _suite in (
    ("HandReach-v3", "401-403", "one_recipe"),
    ("HandReach-v3", "301-303", "goals"),
    ("PointMaze_Medium-v3", "401-403", "one_recipe"),
):
    SOURCES[_task, _seeds, "SB3 SAC+HER (anchor)"] = (_suite, "SB3 SAC+HER (anchor; zoo settings)")
PAGES = ["docs/results.md", "docs/investigations/one_recipe.md"]


def headline_rows(page: str) -> list[tuple[str, dict]]:
    """(task, {column: cell}) of every table on ``page`` with a column "final eval: median [95%
    CI]"; the task is the row's first column (its budget dropped) or the section's heading."""
    rows, task, header, code = [], None, None, False
    for line in (ROOT / page).read_text().splitlines():
        code ^= line.startswith("```")
        if code:
            continue
        if line.startswith("#"):
            task = line.lstrip("# ").strip()
        if not line.startswith("|"):
            header = None
        elif header is None:
            header = [re.sub(r"(\d),(\d)", r"\1\2", h.replace("≥", ">=")) for h in split_row(line)]
        elif not line.startswith("| ---") and FINAL in header:
            cells = dict(zip(header, split_row(line), strict=True))
            own = cells.get("task (budget)", "").split(" (")[0]
            rows.append((own or task, cells))
    return rows


def row_key(task: str, cells: dict) -> tuple[str, str, str]:
    """A page row's key in SOURCES: (task, seeds, its label)."""
    return task, cells["seeds"], cells.get("settings") or cells.get("algorithm") or cells["algorithm, budget"]


@pytest.mark.parametrize("page", PAGES)
def test_each_headline_row_of_the_results_pages_is_its_exports(page):
    """Every row of the page's headline tables names its export row here (SOURCES: a new row
    must be added), and its seeds, final evaluation and steps to each level are that row's, as
    report.py computes it from the export."""
    rows = headline_rows(page)
    assert len(rows) >= 15, f"{page}: its headline tables were not found"
    for task, cells in rows:
        key = row_key(task, cells)
        assert key in SOURCES, f"{page}: the row {key} names no export in SOURCES"
        suite, name = SOURCES[key]
        for column in [c for c in cells if c == FINAL or c.startswith("first eval")]:
            computed = export_cell(suite, task, name, column, cells["seeds"])
            assert cells[column] == computed, f"{page}, {key}, {column}: the {suite} export gives {computed!r}"


def page_row_keys() -> set[tuple[str, str, str]]:
    return {row_key(task, cells) for page in PAGES for task, cells in headline_rows(page)}


def test_every_source_is_a_row_a_page_shows():
    """A row taken off a page takes its entry in SOURCES with it: none is left that checks nothing."""
    unused = [key for key in SOURCES if key not in page_row_keys()]
    assert not unused, f"SOURCES entries no page shows: {unused}"


# ---------------------------------------------------------------------------------------------
# the goal tasks' targets (each the best this project measured on the task), and the defaults against them

# task: (median steps to 0.9 at most, median last evaluation at least); None: not part of the target
TARGETS = {
    "FetchPush-v4": (170_000, None),
    "FetchPickAndPlace-v4": (200_000, 0.95),
    "FetchSlide-v4": (None, 0.85),
    "HandReach-v3": (None, 0.80),
    "PointMaze_Medium-v3": (None, 0.90),
    "HandManipulateBlockRotateZ-v1": (None, 0.94),
}


def target_cell(task: str, cells: dict) -> str:
    """The target column of the defaults' row: the target, then **met** or what it is short by."""
    steps, final = TARGETS[task]
    wanted, short = [], []
    if steps:
        wanted.append(f"0.9 by a median ≤ {steps // 1000}k")
        reached = cells["first eval >= 0.9"]
        at = None if reached.startswith("not reached") else int(reached.split()[0].replace(",", ""))
        if at is None or at > steps:
            short.append(f"0.9 at a median {at // 1000}k" if at else "0.9 reached by less than half the seeds")
    if final is not None:
        wanted.append(f"≥ {final:.2f}")
        got = float(median(cells[FINAL]))
        if got < final:
            short.append(f"short by {final - got:.2f}")
    return " and ".join(wanted) + ": **" + ("; ".join(short) or "met") + "**"


def verdict(task: str, label: str) -> str:
    """ "met" or "missed": the every_goal export's row against the task's target."""
    return "met" if target_cell(task, export_rows("every_goal")[task, label]).endswith("**met**") else "missed"


def test_the_goal_tables_targets_are_the_exports_verdicts():
    """results.md's table of the defaults on every goal task: each row's target column says the
    issue's target and whether the export's figures meet it (a verdict that drifts fails)."""
    rows = [(task, cells) for task, cells in headline_rows("docs/results.md") if "target" in cells]
    assert rows, "docs/results.md: no table of the defaults against their targets"
    for task, cells in rows:
        assert cells["target"] == target_cell(task, cells), f"{task}: the export gives {target_cell(task, cells)!r}"


# ---------------------------------------------------------------------------------------------
# where the recipe's held rule (the targets held, constant rates) loses: the figures and the flags its page gives

# task: (budget, the export row of the flags that won, its suite and seeds, the flags as written)
WINNERS = {
    "FetchSlide-v4": (
        "1M",
        "ipg_her_1000k",
        "fetch",
        "7-9",
        "--target-std 0.3 0.3 0.3 1 --action-l2 0 --bounds-loss 1 --target-std-decay 1",
    ),
    "FetchPickAndPlace-v4": (
        "500k",
        "ipg_her_500k",
        "fetch_fresh",
        "201-203",
        "--target-std 1.0 1.0 1.0 0.3 --target-std-decay 1 --no-anneal-lr",
    ),
}
SETTINGS_ONLY = {"total_timesteps", "eval_freq", "eval_episodes", "resume_freq", "exp_name"}


@pytest.mark.parametrize("task", WINNERS)
def test_the_flags_the_docs_give_are_the_ones_the_winning_runs_ran(task):
    """The flags written beside a task where the held rule loses set what the fetch suite's row
    (benchmarks/run.py) set: parsed by the recipe's own parser, the same settings."""
    from conftest import parse

    import ipg_her_recipe

    _, name, _, _, flags = WINNERS[task]
    ran = next(row[3] for row in RUNS["fetch"].rows if row[0] == name and row[2] == task)
    settings = [vars(parse(ipg_her_recipe, "--env-id", task, *argv)) for argv in (ran, flags.split())]
    assert {k: v for k, v in settings[0].items() if k not in SETTINGS_ONLY} == {
        k: v for k, v in settings[1].items() if k not in SETTINGS_ONLY
    }, f"{task}: the docs' {flags!r} is not what benchmarks/run.py ran ({' '.join(ran)})"


@pytest.mark.parametrize("task", WINNERS)
def test_the_recipes_page_says_where_its_held_rule_loses(task):
    """ipg_her_recipe.py's page gives, for each task where its held rule loses on held-out seeds, the held rule's last
    evaluation, the flags that won (as they run beside the one set of defaults) and theirs, as the exports give them."""
    budget, name, suite, seeds, flags = WINNERS[task]
    lose = median(final_eval("one_recipe", task, name, "401-403"))
    win = median(final_eval(suite, task, name, seeds))
    text = " ".join((ROOT / "docs" / "ipg_her_recipe.md").read_text().split("## The additions")[0].replace("`", "").split())
    for phrase in (task.split("-")[0], f"{lose} at {budget}", flags, f"reached {win}"):
        assert phrase in text, f"docs/ipg_her_recipe.md: no {phrase!r} where the held rule loses on {task}"


def per_seed(suite: str, group: str, level: float | None = None) -> str:
    """A group's seeds in order, "0.96 / 0.98 / 0.98": each last evaluation, or with ``level``
    the step of its first evaluation at or above it ("150k / 110k / 120k")."""
    runs = [run for _, run in sorted(curves(suite)[group].items(), key=lambda item: int(item[0]))]
    if level is None:
        return " / ".join(f"{run['eval/success_rate'][-1][1]:.2f}" for run in runs)
    return " / ".join(f"{stats.first_eval_at(run, level)[0] / 1000:.0f}k" for run in runs)


def test_the_goal_sections_per_seed_figures_are_the_exports():
    """The prose of results.md's goal-task sections quotes the defaults' seeds one by one, and the
    rows beside them by their medians: each phrase is rebuilt from its export."""
    push, maze, reach = "ipg_her_300k__FetchPush-v4", "ipg_her_300k__PointMaze_Medium-v3", "ipg_her_300k__HandReach-v3"
    pick, sac = "ipg_her_500k__FetchPickAndPlace-v4", "SB3 SAC+HER (anchor; zoo settings)"
    phrases = [
        f"**The recipe reaches 0.9 in every held-out seed** (at {per_seed('every_goal', push, 0.9)})",
        f"the\n  last evaluations are {per_seed('every_goal', push)}",
        "(0.9 by a median "
        f"{kilo(first_eval('one_recipe', 'FetchPush-v4', 'ipg_her_300k', 0.9))} and "
        f"{kilo(first_eval('fetch_fresh', 'FetchPush-v4', 'ipg_her_300k', 0.9))})",
        f"**The defaults reach 0.9 in every held-out seed** (at {per_seed('every_goal', pick, 0.9)}) and hold it: the "
        f"last evaluations are {per_seed('every_goal', pick)}, "
        f"**the target {verdict('FetchPickAndPlace-v4', 'ipg_her_500k')}**",
        f"(a median {median(final_eval('one_recipe', 'FetchPickAndPlace-v4', 'ipg_her_500k', '401-403'))} on seeds "
        f"401-403, {no_seed(first_eval('one_recipe', 'FetchPickAndPlace-v4', 'ipg_her_500k', 0.9))} at 0.9)",
        f"({median(final_eval('fetch_fresh', 'FetchPickAndPlace-v4', 'ipg_her_500k', '201-203'))} on seeds 201-203, "
        f"0.9 by a median {kilo(first_eval('fetch_fresh', 'FetchPickAndPlace-v4', 'ipg_her_500k', 0.9, '201-203'))})",
        f"The defaults end at {per_seed('every_goal', maze)}, each seed having passed 0.9 (at "
        f"{per_seed('every_goal', maze, 0.9)})",
        f"ended at a median {median(final_eval('one_recipe', 'PointMaze_Medium-v3', 'ipg_her_300k', '401-403'))} "
        "on seeds 401-403",
        f"at {median(final_eval('goals', 'PointMaze_Medium-v3', 'ipg_her_300k', '301-303'))} on seeds 301-303",
        f"The defaults end at {per_seed('every_goal', reach)}, the anchor on the same seeds at "
        + " / ".join(median(final_eval("every_goal", "HandReach-v3", sac, str(s))) for s in (601, 602, 603)),
        f"**short of the target, {TARGETS['HandReach-v3'][1]:.2f}, by "
        f"{TARGETS['HandReach-v3'][1] - float(median(final_eval('every_goal', 'HandReach-v3', 'ipg_her_300k'))):.2f}**, "
        f"ahead of the anchor's median, {median(final_eval('every_goal', 'HandReach-v3', sac))}",
        f"ended at a median {median(final_eval('one_recipe', 'HandReach-v3', 'ipg_her_300k', '401-403'))} on seeds "
        f"401-403 (SAC+HER {median(final_eval('one_recipe', 'HandReach-v3', sac, '401-403'))} there)",
        f"$\\gamma$ 0.98 at {median(final_eval('goals', 'HandReach-v3', 'ipg_her_300k', '301-303'))} on seeds 301-303",
    ]
    slide = "ipg_her_1000k__FetchSlide-v4"
    slide_median = float(median(final_eval("every_goal", "FetchSlide-v4", "ipg_her_1000k")))
    phrases += [
        f"**The defaults end at {per_seed('every_goal', slide)}** on seeds 601-602, the two the export holds (0.5 at "
        f"{per_seed('every_goal', slide, 0.5)}, {no_seed(first_eval('every_goal', 'FetchSlide-v4', 'ipg_her_1000k', 0.9))}"
        f" at 0.9): **short of the target, {TARGETS['FetchSlide-v4'][1]:.2f}, by "
        f"{TARGETS['FetchSlide-v4'][1] - slide_median:.2f}**",
    ]
    block_group = "ipg_her_1000k__HandManipulateBlockRotateZ-v1"
    block = curves("every_goal")[block_group]["602"]["eval/success_rate"]
    best = max(block, key=lambda point: point[1])
    zero_from = next(s for s, _ in block if all(v == 0 for t, v in block if t >= s))
    block_median = float(median(final_eval("every_goal", "HandManipulateBlockRotateZ-v1", "ipg_her_1000k")))
    target = TARGETS["HandManipulateBlockRotateZ-v1"][1]
    phrases += [
        f"The defaults end at {per_seed('every_goal', block_group)}: **short of the target, {target:.2f}, by "
        f"{target - block_median:.2f}**. Every seed passed 0.9 (at {per_seed('every_goal', block_group, 0.9)}), but "
        f"seed 602 fell after its best, {best[1]:.2f} at {best[0] // 1000}k: every evaluation from "
        f"{zero_from // 1000}k on read {block[-1][1]:.2f}",
        f"ended at a median {median(final_eval('one_recipe', 'HandManipulateBlockRotateZ-v1', 'ipg_her_1000k'))} on "
        "seeds 401-403",
    ]
    text = " ".join((ROOT / "docs" / "results.md").read_text().split())
    missing = [p for p in phrases if " ".join(p.split()) not in text]
    assert not missing, f"docs/results.md: the exports give {missing}"


def test_the_recipe_pages_rows_of_its_defaults_are_the_exports():
    """The recipe page's results give the defaults per task as the every_goal export has them,
    against each task's target and the anchor on the same seeds."""
    push, maze, reach, pick = "FetchPush-v4", "PointMaze_Medium-v3", "HandReach-v3", "FetchPickAndPlace-v4"
    block, sac = "HandManipulateBlockRotateZ-v1", "SB3 SAC+HER (anchor; zoo settings)"
    slide = "FetchSlide-v4"
    phrases = [
        f"0.9 first reached at a median {kilo(first_eval('every_goal', push, 'ipg_her_300k', 0.9))} steps (the target: "
        f"by {TARGETS[push][0] // 1000}k), last evaluation {final_eval('every_goal', push, 'ipg_her_300k', '601-603')} "
        "on seeds 601-603",
        f"last evaluation {final_eval('every_goal', maze, 'ipg_her_300k', '601-603')} on seeds 601-603, short of the "
        f"target, {TARGETS[maze][1]:.2f}, by "
        f"{TARGETS[maze][1] - float(median(final_eval('every_goal', maze, 'ipg_her_300k'))):.2f}; every seed passed "
        f"0.9 (at a median {kilo(first_eval('every_goal', maze, 'ipg_her_300k', 0.9))})",
        f"ends at {median(final_eval('one_recipe', maze, sac, '401-403'))} on seeds 401-403",
        f"0.9 first reached at a median {kilo(first_eval('every_goal', pick, 'ipg_her_500k', 0.9))} steps (the target: "
        f"by {TARGETS[pick][0] // 1000}k, ending at {TARGETS[pick][1]:.2f} or more), last evaluation "
        f"{final_eval('every_goal', pick, 'ipg_her_500k', '601-603')} on seeds 601-603",
        f"The held rule loses this task: 0.9 reached by {no_seed(first_eval('one_recipe', pick, 'ipg_her_500k', 0.9))} "
        "of 401-403",
        f"last evaluation {final_eval('every_goal', block, 'ipg_her_1000k', '601-603')} on seeds 601-603 (the target: "
        f"{TARGETS[block][1]:.2f}), every seed past 0.9 (at a median "
        f"{kilo(first_eval('every_goal', block, 'ipg_her_1000k', 0.9))})",
        f"The held rule wins this task: {final_eval('one_recipe', block, 'ipg_her_1000k', '401-403')} on seeds 401-403",
        f"last evaluation {final_eval('every_goal', slide, 'ipg_her_1000k', '601-602')} on seeds 601-602 (the target: "
        f"{TARGETS[slide][1]:.2f}), {no_seed(first_eval('every_goal', slide, 'ipg_her_1000k', 0.9))} at 0.9",
        f"with annealed rates ended at {final_eval('fetch', slide, 'ipg_her_1000k', '7-9')} on held-out seeds 7-9. "
        f"The held rule loses this task: {final_eval('one_recipe', slide, 'ipg_her_1000k', '401-403')} on seeds 401-403",
        f"{final_eval('every_goal', reach, 'ipg_her_300k', '601-603')} on seeds 601-603 (the target: "
        f"{TARGETS[reach][1]:.2f}), where SB3's SAC+HER ends at {final_eval('every_goal', reach, sac, '601-603')} on "
        "the same seeds",
    ]
    text = " ".join((ROOT / "docs" / "ipg_her_recipe.md").read_text().split("## Results")[1].split())
    missing = [p for p in phrases if " ".join(p.split()) not in text]
    assert not missing, f"docs/ipg_her_recipe.md: the exports give {missing}"


def mean_bounds(path: str) -> dict[str, list[tuple[int, float, float]]]:
    """benchmarks/probes/mean_bounds.py's output, committed: {seed: [(step, share of mu beyond the bounds, |a|)]}."""
    runs: dict[str, list] = {}
    for line in (ROOT / path).read_text().splitlines():
        if not line.startswith(" "):
            seed = line.split(":")[0].split("__")[2]
        else:
            step, rest = line.split(": mu beyond ")
            beyond, executed = rest.split(", |a| ")
            runs.setdefault(seed, []).append((int(step.split()[-1].replace(",", "")), float(beyond), float(executed)))
    return runs


def test_the_blockrotatez_fall_is_the_probes_committed_output():
    """results.md's account of seed 602's fall quotes the mean_bounds probe's output on seeds 601-603, as committed."""
    runs = mean_bounds("benchmarks/results/probes/mean_bounds_blockrotatez.txt")
    assert sorted(runs) == ["601", "602", "603"]
    executed = {step: a for step, _, a in runs["602"]}
    share = [beyond for _, beyond, _ in runs["602"]]
    others = [beyond for seed in ("601", "603") for _, beyond, _ in runs[seed]]
    phrases = [
        f"their mean $|a|$: {executed[970_000]:.2f} over 965k-970k, {executed[975_000]:.2f} over 970k-975k, "
        f"{executed[1_000_000]:.2f} by 1M",
        f"beyond the bounds on {min(share) * 100:.0f}-{max(share) * 100:.0f}% of its components on every replayed "
        f"state, against {min(others) * 100:.0f}-{max(others) * 100:.0f}% in seeds 601 and 603",
        f"the annealed rates were down to {(1 - 970_000 / 1_000_000) * 100:.0f}% of their start",
    ]
    before = [a for seed in runs for step, _, a in runs[seed] if step <= 970_000]
    evals = dict(curves("every_goal")["ipg_her_1000k__HandManipulateBlockRotateZ-v1"]["602"]["eval/success_rate"])
    best = max(evals.items(), key=lambda point: point[1])
    investigation = [
        f"its best evaluation {best[1]:.2f} at {best[0] // 1000}k, {evals[970_000]:.2f} at 970k, "
        f"{max(v for step, v in evals.items() if step >= 980_000):.2f} from 980k to the end",
        f"on {min(share) * 100:.0f}-{max(share) * 100:.0f}% of its components",
        f"which did not fall, on {min(others) * 100:.0f}-{max(others) * 100:.0f}%",
        f"their mean $|a|$ is {min(before):.2f}-{max(before):.2f} in every stretch of every seed up to 970k, then in "
        f"seed 602 {executed[975_000]:.2f} over 970k-975k, {executed[980_000]:.2f} by 980k and "
        f"{executed[1_000_000]:.2f} by 1M",
    ]
    for page, wanted in (("docs/results.md", phrases), ("docs/investigations/blockrotatez.md", investigation)):
        text = " ".join((ROOT / page).read_text().split())
        missing = [p for p in wanted if " ".join(p.split()) not in text]
        assert not missing, f"{page}: the probe's output gives {missing}"


def test_all_rows_every_goal_table_is_the_exports():
    """all_rows.md's every_goal table is report.py's per-task tables of the export, the time columns left out."""
    expected = []
    parts = task_tables("every_goal").split("**")  # "", task, its tables, task, ...
    for task, block in zip(parts[1::2], parts[2::2], strict=True):
        for line in block.splitlines():
            cells = split_row(line) if line.startswith("| ") else []
            if len(cells) >= 12 and cells[0] != "algorithm" and not cells[0].startswith("---"):
                expected.append(f"| {task}, {' | '.join(cells[i] for i in (0, 1, 2, 3, 4, 6, 8, 10))} |")
    text = (ROOT / "docs" / "investigations" / "all_rows.md").read_text()
    table = text.split("<!-- report.py per-task tables: suite every_goal, every task -->")[1].split("\n\n")[0]
    shown = [line for line in table.splitlines() if line.startswith("| ") and not line.startswith(("| task", "| ---"))]
    assert len(expected) >= 10 and shown == expected, f"all_rows.md's every_goal table: the export gives {expected}"
