"""benchmarks/: the quick suite end to end, resume, the report against the event files, and a
failing run."""

import re

import gymnasium as gym
import numpy as np
import pytest
from conftest import scalars

from benchmarks import report, run, suites
from common import cli


def test_quick_suite_runs_resumes_and_reports_what_the_event_files_hold(tmp_path, capsys):
    args = run.Args(suite="quick", out_dir=str(tmp_path / "runs"), workers=2)
    assert run.main(args) == 0
    runs = suites.suite_runs("quick")
    for r in runs:
        folder = tmp_path / "runs" / "quick" / r.folder
        assert (folder / "exit_code").read_text().strip() == "0"
        assert (folder / "stdout.log").exists() and (folder / "stderr.log").exists()
    capsys.readouterr()
    assert run.main(args) == 0  # resume: nothing left to do
    assert f"0 to run, {len(runs)} already finished" in capsys.readouterr().out

    results, figures = tmp_path / "results", tmp_path / "img"
    folders = dict(results_dir=str(results), figures_dir=str(figures))
    assert report.main(report.Args(suite="quick", runs_dir=str(tmp_path / "runs"), **folders)) == 0
    for name in ("results.md", "curves.json"):
        assert (results / name).stat().st_size > 0, name
    for name in ("fig3_hopper.png", "fig4_fetchreach.png", "fig5_fetchreach_success.png"):
        assert (figures / name).stat().st_size > 0, name
    text = (results / "results.md").read_text()
    # the Hopper PPO-KL row's final return: the mean of the event file's last 100 training episodes
    row = next(line for line in text.splitlines() if line.startswith("| Hopper-v5 | PPO-KL |"))
    final = float(re.split(r"\s*\|\s*", row)[4].split("±")[0])
    (event_dir,) = [p for p in (tmp_path / "runs" / "quick" / "ppo_kl__Hopper-v5__seed1").iterdir() if p.is_dir()]
    returns = [v for _, v in scalars(event_dir)["charts/episodic_return"]]
    assert abs(final - np.mean(returns[-100:])) <= 0.5
    # the FetchReach IPG+HER row's final eval success is the last eval/success_rate
    row = next(line for line in text.splitlines() if line.startswith("| FetchReach-v4 | IPG+HER |"))
    (event_dir,) = [p for p in (tmp_path / "runs" / "quick" / "ipg_her__FetchReach-v4__seed1").iterdir() if p.is_dir()]
    assert abs(float(re.split(r"\s*\|\s*", row)[7]) - scalars(event_dir)["eval/success_rate"][-1][1]) <= 0.005
    # the export alone redraws the same table
    assert report.main(report.Args(suite="quick", from_export=True, **folders)) == 0
    assert (results / "results.md").read_text() == text


def test_a_failing_run_is_reported_and_the_others_finish(tmp_path, monkeypatch, capsys):
    good = suites.suite_runs("quick")[2]  # FetchReach PPO-KL, a few seconds
    bad = suites.Run("broken", "ppo_kl.py", "NoSuchEnv-v0", 1)
    monkeypatch.setattr(run, "suite_runs", lambda *args: [bad, good])
    assert run.main(run.Args(suite="quick", out_dir=str(tmp_path), workers=2)) == 1
    out = capsys.readouterr().out
    assert "1 done, 1 failed" in out and "failed: broken__NoSuchEnv-v0__seed1" in out
    assert "NoSuchEnv-v0" in (tmp_path / "quick" / bad.folder / "stderr.log").read_text()
    assert (tmp_path / "quick" / good.folder / "exit_code").read_text().strip() == "0"


def test_quick_suite_on_a_local_ray_instance(tmp_path):
    pytest.importorskip("ray")
    args = run.Args(suite="quick", out_dir=str(tmp_path), backend="ray", only="FetchReach")
    assert run.main(args) == 0
    runs = [r for r in suites.suite_runs("quick") if "FetchReach" in r.folder]
    for r in runs:
        assert (tmp_path / "quick" / r.folder / "exit_code").read_text().strip() == "0"
        assert any(p.is_dir() for p in (tmp_path / "quick" / r.folder).iterdir()), "no event folder"
    assert run.main(args) == 0  # resume works the same way


def test_a_dry_run_piped_into_head_ends_quietly():
    """``run.py --dry-run | head``: a reader that closes the pipe early gets no traceback."""
    import subprocess
    import sys

    from conftest import ROOT

    cmd = [sys.executable, "benchmarks/run.py", "--suite", "paper", "--dry-run"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # gone before the first line is written, as head is after its lines
    stderr = proc.communicate(timeout=60)[1].decode()
    assert proc.returncode == 0 and "Error" not in stderr, stderr


def without(flags: tuple[str, ...], *parts: tuple[str, ...]) -> tuple[str, ...]:
    """``flags`` with each of ``parts`` (a run of consecutive flags and values) taken out once."""
    for part in parts:
        at = next((i for i in range(len(flags)) if flags[i : i + len(part)] == part), None)
        flags = flags if at is None else flags[:at] + flags[at + len(part) :]
    return flags


def test_the_goals_suite_runs_the_recipes_defaults_then_with_no_flag_but_the_budget():
    """Goal tasks no setting was chosen on, three fresh seeds each, no flag that could tune: the
    budget, evaluation every 10,000 steps on 50 episodes, resume points, and the defaults the
    recipe had when they ran, spelled out (the summed sigma rule at 1, gamma 0.98: see
    test_the_fetch_and_goals_suites_still_run_what_ran). The exceptions are named, each beside its
    task's defaults: PointMaze with the discount it lacked, HandReach with a narrower sigma
    target (summed and one rule per joint)."""
    runs = suites.suite_runs("goals")
    flag = re.compile(r"(--\S+) ([^-\s]\S*(?: [^-\s]\S*)*)")  # a flag and its values
    then = (suites.SUMMED, ("--gamma", "0.98"), suites.HELD)
    budgets = {
        (r.name, r.env_id, r.seed): dict(flag.findall(" ".join(without(r.flags, *then))))
        for r in runs
        if r.script == "ipg_her_recipe.py"
    }
    assert len(budgets) == len(runs) == 18
    assert {seed for *_, seed in budgets} == {301, 302, 303}
    steps = {"HandReach-v3": "300000", "HandManipulateBlockRotateZ-v1": "1000000", "PointMaze_Medium-v3": "300000"}
    named = {
        ("ipg_her_300k_gamma0995", "PointMaze_Medium-v3"): {"--gamma": "0.995"},
        ("ipg_her_300k_std03", "HandReach-v3"): {"--target-std": "0.3"},
        ("ipg_her_300k_std03x20", "HandReach-v3"): {"--target-std": " ".join(["0.3"] * 20)},
    }
    for (name, env_id, _), flags in budgets.items():
        extra = named.get((name, env_id), {})
        assert extra or name in ("ipg_her_300k", "ipg_her_1000k")
        assert flags == {
            "--total-timesteps": steps[env_id],
            "--eval-freq": "10000",
            "--eval-episodes": "50",
            "--resume-freq": "50000",
            **extra,
        }


@pytest.mark.parametrize("suite", ["one_recipe", "every_goal"])
def test_the_one_recipe_and_every_goal_suites_run_every_goal_task_with_no_flag_but_the_budget(suite):
    """The defaults, the task's filled in by fill_in, on seeds that chose nothing (401-403, 601-603): each goal task at
    its budget, evaluated every 10,000 steps on 50 episodes, resumable, no other flag; one_recipe's with the defaults it
    ran with spelled out (the targets held, constant rates, PointMaze's discount 1 - 1/600 before the clip)."""
    runs = suites.suite_runs(suite)
    seeds = {"one_recipe": (401, 402, 403), "every_goal": (601, 602, 603)}[suite]
    budgets = {
        "FetchPush-v4": 300_000,
        "FetchPickAndPlace-v4": 500_000,
        "FetchSlide-v4": 10**6,
        "HandReach-v3": 300_000,
        "PointMaze_Medium-v3": 300_000,
        "HandManipulateBlockRotateZ-v1": 10**6,
    }
    assert sorted((r.env_id, r.seed) for r in runs) == sorted((env_id, seed) for env_id in budgets for seed in seeds)
    for r in runs:
        assert r.script == "ipg_her_recipe.py" and r.name == f"ipg_her_{budgets[r.env_id] // 1000}k"
        then = () if suite == "every_goal" else (*suites.HELD, *("--gamma", str(1 - 1 / 600)) * r.env_id.startswith("Point"))
        assert r.flags == ("--total-timesteps", str(budgets[r.env_id]), *suites.FETCH_EVERY, *then)


def test_the_tuning_suite_runs_the_frozen_defaults_on_seeds_11_and_12_as_every_goal_runs_them_on_601_603():
    """one_set's ``defaults_`` rows are every_goal's commands, on the tuning seeds: what chose is what reports."""
    tuning = sorted((r.env_id, r.flags, r.seed) for r in suites.suite_runs("one_set") if r.name.startswith("defaults_"))
    reporting = sorted((r.env_id, r.flags) for r in suites.suite_runs("every_goal") if r.seed == 601)
    assert sorted({(env_id, flags) for env_id, flags, _ in tuning}) == reporting
    assert sorted(seed for *_, seed in tuning) == [11] * 6 + [12] * 6


def test_the_fetch_and_goals_suites_still_run_what_ran():
    """Their exports were run when the recipe's defaults were RECIPE's summed sigma rule at 1,
    gamma 0.98 and rows for PickAndPlace and Slide: every run of theirs, parsed as the script
    parses it now, gets the arguments those defaults gave it, so the commands on the results
    page still run what they report."""
    import ipg_her_recipe as recipe

    args_then = dict(gamma=0.98, grasped_start=0.0, target_std_decay=1.0, anneal_lr=False)  # the Args defaults then
    recipe_then = dict(hidden=256, target_std=1.0, normalization="paper", action_l2=1.0, twin_critic=True)
    rows_then = {
        "FetchPickAndPlace-v4": recipe_then | dict(grasped_start=0.5, target_std=(1.0, 1.0, 1.0, 0.3)),
        "FetchSlide-v4": recipe_then | dict(target_std=(0.3, 0.3, 0.3, 1.0), action_l2=0.0, bounds_loss=1.0, anneal_lr=True),
    }
    runs = suites.suite_runs("fetch") + suites.suite_runs("goals")
    assert len(runs) == 67
    for r in runs:
        argv = ["--env-id", r.env_id, *r.flags]
        now = cli.parse_args(recipe.Args, argv)
        recipe.fill_in(now)  # as the script's main does
        then = cli.parse_args(recipe.Args, argv)
        given = cli.given(argv)
        for name, value in (args_then | rows_then.get(r.env_id, recipe_then)).items():
            if name not in given:
                setattr(then, name, value)
        assert vars(now) == vars(then), (r.name, r.env_id)


def test_the_recipes_runs_in_every_suite_still_run_what_ran():
    """Before its defaults were its Args' fields, the recipe's Args had ipg_her.py's (64 wide, unbiased, no action
    penalty, one critic, gamma 0.98, no sigma rule, no grasped starts), and a goal task took its task defaults on top,
    which fill_in and the fields give now. Every recipe run on a task without goals (Hopper), parsed as the script
    parses it now, gets what those Args gave it."""
    import ipg_her_recipe as recipe

    then_defaults = dict(
        hidden=64, normalization="unbiased", action_l2=0.0, twin_critic=False, gamma=0.98, target_std=None, grasped_start=0.0
    ) | dict(target_std_decay=1.0, anneal_lr=False)
    runs = [r for suite in suites.SUITES for r in suites.suite_runs(suite) if r.script == "ipg_her_recipe.py"]
    hopper = [r for r in runs if r.env_id.startswith("Hopper")]
    assert len(hopper) >= 10
    for r in hopper:
        argv = ["--env-id", r.env_id, *r.flags]
        now = cli.parse_args(recipe.Args, argv)
        recipe.fill_in(now)
        then = cli.parse_args(recipe.Args, argv)
        given = cli.given(argv)
        for name, value in then_defaults.items():
            if name not in given:
                setattr(then, name, value)
        assert vars(now) == vars(then), (r.name, r.env_id)


def test_the_fetch_suite_runs_the_recipe_with_no_flag_but_the_budget_and_evaluation_grid():
    """The fetch grid, all of it ``ipg_her_recipe.py``: Push 5 seeds x 300k, PickAndPlace 3 x
    500k, Slide 3 x 1M, evaluated every 10,000 steps on 50 episodes, resumable, with each task's
    defaults when it ran spelled out; nothing else of those defaults is changed but nu in the
    mixing runs (0.5 and 0.8 on Push, 3 seeds x 200k), one critic on Push and in the mixing runs
    (``_1critic``: the defaults before the twin critic), eq. 10's nu (``_eq10``:
    ``--normalization unbiased``, as Push's default weighs nu sigma_A), and PickAndPlace with its
    earlier single sigma rule (``--target-std 1.0``): with grasped starts on the fresh seeds
    (``_grasped``), without them on the seeds they were tuned on (``_nograsp``, with and without
    twin), and Slide with Push's defaults on the seeds its own were tuned on (``_sigma1``)."""
    runs = suites.suite_runs("fetch")
    budgets = {}
    for r in runs:
        assert r.script == "ipg_her_recipe.py"
        then = {
            "FetchPush-v4": (suites.SUMMED, suites.HELD),
            "FetchPickAndPlace-v4": (suites.PICK_ROW, suites.HELD),
            "FetchSlide-v4": (suites.SLIDE_ROW, suites.HELD_TARGETS, ("--anneal-lr",)),
        }[r.env_id]
        held = without(r.flags, suites.HELD)
        r_flags = held if "_grasped" in r.name or "_nograsp" in r.name else without(r.flags, *then)
        critics = "1" if "--no-twin-critic" in r_flags else "2"
        assert (critics == "1") == ("_1critic" in r.name)
        constlr = "--no-anneal-lr" in r_flags  # Slide's earlier defaults, and Push's on Slide
        assert constlr == (r.env_id == "FetchSlide-v4" and ("_constlr" in r.name or "_sigma1" in r.name))
        pairs = [f for f in r_flags if f not in ("--no-twin-critic", "--no-anneal-lr")]
        flags = dict(zip(pairs[::2], pairs[1::2], strict=True))
        nu = flags.pop("--nu", "1.0")  # the mixing runs: nu alone differs
        std = flags.pop("--target-std", None)  # Slide's and PickAndPlace's earlier sigma rule
        if std == "1.0" and r.env_id == "FetchSlide-v4":
            assert "_sigma1_" in r.name  # Push's defaults: its sigma rule and action penalty
            assert (flags.pop("--action-l2"), flags.pop("--bounds-loss")) == ("1.0", "0.0")
            critics += "_sigma1"
        elif std == "1.0":
            assert r.env_id == "FetchPickAndPlace-v4" and ("_grasped" in r.name) != ("--grasped-start" in flags)
            critics += "_grasped" if "_grasped" in r.name else ""
        if flags.pop("--grasped-start", None) == "0":
            assert "_nograsp" in r.name and r.env_id == "FetchPickAndPlace-v4"
            critics += "_nograsp"
        if flags.pop("--normalization", None) == "unbiased":
            assert "_eq10_" in r.name and nu != "1.0"
            critics = "eq10"
        assert set(flags) == {
            "--total-timesteps",
            "--eval-freq",
            "--eval-episodes",
            "--resume-freq",
        }
        assert (flags["--eval-freq"], flags["--eval-episodes"]) == ("10000", "50")
        critics += "_constlr" if "_constlr" in r.name else ""
        budgets.setdefault((r.env_id, flags["--total-timesteps"], nu, critics), []).append(r.seed)
    for critics in ("1", "2"):
        assert budgets.pop(("FetchPush-v4", "300000", "1.0", critics)) == [4, 5, 6, 7, 8]
        assert budgets.pop(("FetchPickAndPlace-v4", "500000", "1.0", f"{critics}_nograsp")) == [1, 2, 3]
        for nu in ("0.5", "0.8"):
            assert budgets.pop(("FetchPush-v4", "200000", nu, critics)) == [4, 5, 6]
    for nu in ("0.5", "0.8"):
        assert budgets.pop(("FetchPush-v4", "200000", nu, "eq10")) == [4, 5, 6]
    assert budgets == {
        ("FetchSlide-v4", "1000000", "1.0", "2"): [7, 8, 9],
        ("FetchSlide-v4", "1000000", "1.0", "2_constlr"): [4, 5, 6],
        ("FetchSlide-v4", "1000000", "1.0", "2_sigma1"): [1, 2, 3],
        ("FetchPickAndPlace-v4", "500000", "1.0", "2_grasped"): [4, 5, 6],
        ("FetchPickAndPlace-v4", "500000", "1.0", "2"): [4, 5, 6],
    }


def test_the_hopper_suite_runs_both_ends_on_fresh_seeds_and_nu_1_to_1m_on_a_seed_of_its_own():
    """The Hopper grid: PPO-KL and IPG at nu 1 and 0.5 (the recipe in TD3's regime) on seeds 4-6 at
    300k, nu 1 also with the bounds loss; nu 1 with TD3's noise and the bounds loss, and PPO-KL
    beside it, on seeds 8-10, and the same with the critic's term at scale 1 on 11-13; nu 1
    again on 14-16 (the critic's target sampled ran there with a patch); 17-19: nu 1 and 0.5 (PPO-KL
    beside them); nu 1 to 1M on seed 7 alone, with the 300k rows' flags but the budget; ``--seeds``
    moves all of them."""
    seeds = {}
    for r in suites.suite_runs("hopper"):
        seeds.setdefault(r.name, []).append(r.seed)
    assert seeds == {
        "ppo_kl_300k": [4, 5, 6, *range(8, 20)],
        "ipg_td3_nu1.0_300k": [4, 5, 6, *range(14, 20)],
        "ipg_td3_nu0.5_300k": [4, 5, 6, 17, 18, 19],
        "ipg_td3_bounds_nu1.0_300k": [4, 5, 6],
        "ipg_td3_narrow_nu1.0_300k": [8, 9, 10],
        "ipg_td3_paper_nu1.0_300k": [11, 12, 13],
        "ipg_td3_nu1.0_1M": [7],
    }
    flags = {r.name: list(r.flags) for r in suites.suite_runs("hopper")}
    short, long = flags["ipg_td3_nu1.0_300k"], flags["ipg_td3_nu1.0_1M"]
    assert flags["ipg_td3_bounds_nu1.0_300k"] == [*short, "--bounds-loss", "1.0"]
    narrow = [*short, "--kl-target", "0.9", "--bounds-loss", "1.0"]
    narrow[narrow.index("--target-std") + 1] = "0.1"
    assert flags["ipg_td3_narrow_nu1.0_300k"] == narrow
    narrow[narrow.index("--normalization") + 1] = "paper"
    assert flags["ipg_td3_paper_nu1.0_300k"] == narrow
    for f in (short, long):  # the budget is the only pair that differs
        del f[f.index("--total-timesteps") : f.index("--total-timesteps") + 2]
    assert short == long and "--resume-freq" in long
    moved = suites.suite_runs("hopper", seeds=(9, 10))
    assert {r.seed for r in moved} == {9, 10} and len(moved) == len(set(moved))
    assert [r.seed for r in suites.suite_runs("hopper", seeds=(9, 10)) if "1M" in r.name] == [9]


def test_every_suite_command_passes_its_scripts_checks(monkeypatch):
    """A suite row its script would refuse (a flag that changes nothing, say) fails here, not
    hours into a suite; every suite of the command line has its table."""
    import functools

    import ipg_her
    import ipg_her_recipe
    import ppo_kl
    import qprop_ppo
    from common import cli, tasks

    scripts = {"ppo_kl.py": ppo_kl, "qprop_ppo.py": qprop_ppo, "ipg_her.py": ipg_her, "ipg_her_recipe.py": ipg_her_recipe}
    monkeypatch.setattr(tasks.gym, "make", functools.cache(tasks.gym.make))  # spaces only: one each
    names = run.Args.__annotations__["suite"].__args__
    assert sorted(names) == sorted(suites.SUITES)
    refused = []
    for suite in names:
        for r in suites.suite_runs(suite):
            module = scripts[r.script]
            argv = ["--env-id", r.env_id, "--seed", str(r.seed), *r.flags]
            try:
                args = cli.parse_args(module.Args, argv)
                params = module.check_args.__code__.co_argcount
                module.check_args(*(args, argv)[:params])
            except SystemExit:
                refused.append(f"{suite}/{r.folder}")
    assert not refused, refused


def test_every_committed_export_redraws_its_results_md_and_its_figures(tmp_path):
    """Each results folder's curves.json, through report.py --from-export with the suite its
    results.md names, gives that results.md byte for byte, its figures linked from it under
    docs/img/{folder} (committed there once, none beside the export)."""
    import shutil

    from conftest import ROOT

    for export in sorted((ROOT / "benchmarks" / "results").glob("*/curves.json")):
        name, committed = export.parent.name, (export.parent / "results.md").read_text()
        (suite,) = set(re.findall(r"benchmarks/run\.py --suite (\w+)", committed))
        results, figures = (
            tmp_path / "benchmarks" / "results" / name,
            tmp_path / "docs" / "img" / name,
        )
        results.mkdir(parents=True)
        shutil.copy(export, results)
        args = report.Args(suite=suite, results_dir=str(results), figures_dir=str(figures), from_export=True)
        assert report.main(args) == 0, name
        assert (results / "results.md").read_text() == committed, name
        drawn = sorted(p.name for p in figures.iterdir())
        assert drawn == sorted(p.name for p in (ROOT / "docs" / "img" / name).glob("*.png")), name
        links = re.findall(r"^!\[(.+)\]\(\.\./\.\./\.\./docs/img/(.+)/\1\)$", committed, re.M)
        assert sorted(links) == [(f, name) for f in drawn], name
        assert not list(export.parent.glob("*.png")), name


def test_benchmarks_and_tests_name_no_path_outside_the_repository():
    """A clone runs on its own: no code, probe or test reads a folder beside the repository (the
    anchors' scripts are passed as arguments where needed) or a machine's absolute path."""
    from conftest import ROOT

    files = [*(ROOT / "benchmarks").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]
    outside = re.compile(r"\.\./shared|/work/|ROOT\.parent\b")
    found = [
        f"{f.relative_to(ROOT)}:{i}"
        for f in files
        for i, line in enumerate(f.read_text().splitlines(), 1)
        if outside.search(line) and "re.compile" not in line
    ]
    assert not found, found


class FlagEnv(gym.Env):
    """A goal task's success flag under the mazes' name, True on every other step."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, key: str = "success"):
        self.key, self.t = key, 0

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return np.zeros(1, np.float32), {self.key: False}

    def step(self, action):
        self.t += 1
        return np.zeros(1, np.float32), 0.0, False, self.t >= 4, {self.key: self.t % 2 == 1}


def test_an_anchor_on_a_maze_reads_the_mazes_success_flag_at_every_step(tmp_path):
    """benchmarks/anchor_success.py: the anchor script reads ``info["is_success"]``; on a maze it
    is the maze's ``info["success"]`` at every step, a Fetch task's own flag is left alone, and
    the anchor script run through it gets the wrapped ``gym.make``."""
    import subprocess
    import sys

    from conftest import ROOT

    from benchmarks import anchor_success

    env = anchor_success.FetchSuccessKey(FlagEnv())
    flags = [env.reset()[1]] + [env.step(np.zeros(1))[4] for _ in range(4)]
    assert [info["is_success"] for info in flags] == [0.0, 1.0, 0.0, 1.0, 0.0]
    assert [info["success"] for info in flags] == [False, True, False, True, False]
    fetch = anchor_success.FetchSuccessKey(FlagEnv(key="is_success"))
    assert [fetch.reset()[1]] + [fetch.step(np.zeros(1))[4] for _ in range(2)] == [
        {"is_success": False},
        {"is_success": True},
        {"is_success": False},
    ]

    script = tmp_path / "anchor.py"
    script.write_text("import sys, gymnasium as gym\nprint(type(gym.make('CartPole-v1')).__name__, sys.argv[1:])\n")
    cmd = [sys.executable, "benchmarks/anchor_success.py", str(script), "--seed", "1"]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "FetchSuccessKey ['--seed', '1']"
