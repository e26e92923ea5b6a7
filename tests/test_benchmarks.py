"""benchmarks/: the quick suite end to end, resume, the report against the event files, and a
failing run."""

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import scalars

from benchmarks import fetch_lifts, profile_phases, report, run, slide_strikes, update_speed


def test_quick_suite_runs_resumes_and_reports_what_the_event_files_hold(tmp_path, capsys):
    args = run.Args(suite="quick", out_dir=str(tmp_path / "runs"), workers=2)
    assert run.main(args) == 0
    runs = run.suite_runs("quick")
    for r in runs:
        folder = tmp_path / "runs" / "quick" / r.folder
        assert (folder / "exit_code").read_text().strip() == "0"
        assert (folder / "stdout.log").exists() and (folder / "stderr.log").exists()
    capsys.readouterr()
    assert run.main(args) == 0  # resume: nothing left to do
    assert f"0 to run, {len(runs)} already finished" in capsys.readouterr().out

    results = tmp_path / "results"
    assert (
        report.main(
            report.Args(suite="quick", runs_dir=str(tmp_path / "runs"), results_dir=str(results))
        )
        == 0
    )
    for name in (
        "fig3_hopper.png",
        "fig4_fetchreach.png",
        "fig5_fetchreach_success.png",
        "results.md",
        "curves.json",
    ):
        assert (results / name).stat().st_size > 0, name
    text = (results / "results.md").read_text()
    # the Hopper PPO-KL row's final return: the mean of the event file's last 100 training episodes
    row = next(line for line in text.splitlines() if line.startswith("| Hopper-v5 | PPO-KL |"))
    final = float(re.split(r"\s*\|\s*", row)[4].split("±")[0])
    (event_dir,) = [
        p
        for p in (tmp_path / "runs" / "quick" / "ppo_kl__Hopper-v5__seed1").iterdir()
        if p.is_dir()
    ]
    returns = [v for _, v in scalars(event_dir)["charts/episodic_return"]]
    assert abs(final - np.mean(returns[-100:])) <= 0.5
    # the FetchReach IPG+HER row's final eval success is the last eval/success_rate
    row = next(line for line in text.splitlines() if line.startswith("| FetchReach-v4 | IPG+HER |"))
    (event_dir,) = [
        p
        for p in (tmp_path / "runs" / "quick" / "ipg_her__FetchReach-v4__seed1").iterdir()
        if p.is_dir()
    ]
    assert (
        abs(float(re.split(r"\s*\|\s*", row)[7]) - scalars(event_dir)["eval/success_rate"][-1][1])
        <= 0.005
    )
    # the export alone redraws the same table
    assert report.main(report.Args(suite="quick", results_dir=str(results), from_export=True)) == 0
    assert (results / "results.md").read_text() == text


def test_a_failing_run_is_reported_and_the_others_finish(tmp_path, monkeypatch, capsys):
    good = run.suite_runs("quick")[2]  # FetchReach PPO-KL, a few seconds
    bad = run.Run("broken", "ppo_kl.py", "NoSuchEnv-v0", 1)
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
    runs = [r for r in run.suite_runs("quick") if "FetchReach" in r.folder]
    for r in runs:
        assert (tmp_path / "quick" / r.folder / "exit_code").read_text().strip() == "0"
        assert any(p.is_dir() for p in (tmp_path / "quick" / r.folder).iterdir()), "no event folder"
    assert run.main(args) == 0  # resume works the same way


def test_update_speed_times_the_full_eager_update():
    timing = update_speed.time_updates("eager", update_speed.Args(repeats=1))
    assert timing["minibatch_steps"] == 320  # 10 epochs x 32 minibatches, ppo_kl.py's defaults
    assert 0 < timing["min_s"] <= timing["median_s"]


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


def test_the_fetch_suite_runs_ipg_her_with_no_flag_but_the_budget_and_evaluation_grid():
    """Issue 29's grid: Push 5 seeds x 300k, PickAndPlace 3 x 500k, Slide 3 x 1M, evaluated every
    10,000 steps on 50 episodes, resumable; nothing else of the defaults is changed but nu in
    the mixing runs (0.5 and 0.8 on Push, 3 seeds x 200k), one critic on Push and in the mixing
    runs (``_1critic``: the defaults before the twin critic), eq. 10's nu (``_eq10``:
    ``--normalization unbiased``, as Push's default weighs nu sigma_A), and PickAndPlace with its
    earlier single sigma rule (``--target-std 1.0``): with grasped starts on the fresh seeds
    (``_grasped``), without them on the seeds they were tuned on (``_nograsp``, with and without
    twin), and Slide with Push's defaults on the seeds its own were tuned on (``_sigma1``)."""
    runs = run.suite_runs("fetch")
    budgets = {}
    for r in runs:
        assert r.script == "ipg_her.py"
        critics = "1" if "--no-twin-critic" in r.flags else "2"
        assert (critics == "1") == ("_1critic" in r.name)
        constlr = "--no-anneal-lr" in r.flags  # Slide's earlier defaults, and Push's on Slide
        assert constlr == (
            r.env_id == "FetchSlide-v4" and ("_constlr" in r.name or "_sigma1" in r.name)
        )
        pairs = [f for f in r.flags if f not in ("--no-twin-critic", "--no-anneal-lr")]
        flags = dict(zip(pairs[::2], pairs[1::2], strict=True))
        nu = flags.pop("--nu", "1.0")  # the mixing runs: nu alone differs
        std = flags.pop("--target-std", None)  # Slide's and PickAndPlace's earlier sigma rule
        if std == "1.0" and r.env_id == "FetchSlide-v4":
            assert "_sigma1_" in r.name  # Push's defaults: its sigma rule and action penalty
            assert (flags.pop("--action-l2"), flags.pop("--bounds-loss")) == ("1.0", "0.0")
            critics += "_sigma1"
        elif std == "1.0":
            assert r.env_id == "FetchPickAndPlace-v4" and ("_grasped" in r.name) != (
                "--grasped-start" in flags)  # fmt: skip
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
        assert budgets.pop(("FetchPickAndPlace-v4", "500000", "1.0", f"{critics}_nograsp")) == [
            1, 2, 3]  # fmt: skip
        for nu in ("0.5", "0.8"):
            assert budgets.pop(("FetchPush-v4", "200000", nu, critics)) == [4, 5, 6]
    for nu in ("0.5", "0.8"):
        assert budgets.pop(("FetchPush-v4", "200000", nu, "eq10")) == [4, 5, 6]
    assert budgets == {("FetchSlide-v4", "1000000", "1.0", "2"): [7, 8, 9],
                       ("FetchSlide-v4", "1000000", "1.0", "2_constlr"): [4, 5, 6],
                       ("FetchSlide-v4", "1000000", "1.0", "2_sigma1"): [1, 2, 3],
                       ("FetchPickAndPlace-v4", "500000", "1.0", "2_grasped"): [4, 5, 6],
                       ("FetchPickAndPlace-v4", "500000", "1.0", "2"): [4, 5, 6]}  # fmt: skip


def test_the_hopper_suite_runs_both_ends_on_fresh_seeds_and_nu_1_to_1m_on_a_seed_of_its_own():
    """Issue 29's Hopper grid: PPO-KL and IPG at nu 1 and 0.5 (TD3's regime) on seeds 4-6 at
    300k, nu 1 also with the bounds loss; nu 1 with TD3's noise and the bounds loss, and PPO-KL
    beside it, on seeds 8-10, and the same with the critic's term at scale 1 on 11-13; that with
    the critic's target sampled, and nu 1 again, on 14-16; nu 1 and 0.5 again on 17-19 (PPO-KL
    beside them); nu 1 to 1M on seed 7 alone, with the 300k rows' flags but the budget; ``--seeds``
    moves all of them."""
    seeds = {}
    for r in run.suite_runs("hopper"):
        seeds.setdefault(r.name, []).append(r.seed)
    assert seeds == {"ppo_kl_300k": [4, 5, 6, *range(8, 20)],
                     "ipg_td3_nu1.0_300k": [4, 5, 6, *range(14, 20)],
                     "ipg_td3_nu0.5_300k": [4, 5, 6, 17, 18, 19],
                     "ipg_td3_bounds_nu1.0_300k": [4, 5, 6],
                     "ipg_td3_narrow_nu1.0_300k": [8, 9, 10],
                     "ipg_td3_paper_nu1.0_300k": [11, 12, 13],
                     "ipg_td3_paper_sampled_nu1.0_300k": [14, 15, 16],
                     "ipg_td3_nu1.0_1M": [7]}  # fmt: skip
    flags = {r.name: list(r.flags) for r in run.suite_runs("hopper")}
    short, long = flags["ipg_td3_nu1.0_300k"], flags["ipg_td3_nu1.0_1M"]
    assert flags["ipg_td3_bounds_nu1.0_300k"] == [*short, "--bounds-loss", "1.0"]
    narrow = [*short, "--kl-target", "0.9", "--bounds-loss", "1.0"]
    narrow[narrow.index("--target-std") + 1] = "0.1"
    assert flags["ipg_td3_narrow_nu1.0_300k"] == narrow
    assert flags["ipg_td3_paper_nu1.0_300k"] == [*narrow, "--normalization", "paper"]
    paper = flags["ipg_td3_paper_nu1.0_300k"]
    assert flags["ipg_td3_paper_sampled_nu1.0_300k"] == [*paper, "--critic-target", "sample"]
    for f in (short, long):  # the budget is the only pair that differs
        del f[f.index("--total-timesteps") : f.index("--total-timesteps") + 2]
    assert short == long and "--resume-freq" in long
    moved = run.suite_runs("hopper", seeds=(9, 10))
    assert {r.seed for r in moved} == {9, 10} and len(moved) == len(set(moved))
    assert [r.seed for r in run.suite_runs("hopper", seeds=(9, 10)) if "1M" in r.name] == [9]


def test_the_profile_gives_each_sample_to_its_phase():
    """py-spy's raw lines (``frame;frame;... count``) summed into the phases of the docs' tables:
    the same function (``Agent.dist``, a normaliser's ``__call__``) counts where it is called."""
    stacks = {
        "collect_rollout (common/rollout.py:51);SyncVectorEnv.step (gymnasium/vector/"
        "sync_vector_env.py:338);HopperEnv.step (gymnasium/envs/mujoco/hopper_v5.py:290)": 5,
        "collect_rollout (common/rollout.py:47);Agent.dist (ppo_kl.py:120);Module._call_impl "
        "(torch/nn/modules/module.py:1)": 3,
        "ppo_kl_update (ppo_kl.py:155);Agent.dist (ppo_kl.py:120)": 7,
        "collect_rollout (common/rollout.py:45);RunningMeanStd.update (common/normalizer.py:30)": 2,
        "RewardScaler.__call__ (common/normalizer.py:110)": 1,
        "critic_step (ipg_her.py:214);QNetwork.forward (ipg_her.py:180)": 4,
        "sample_replay (common/her.py:279);HerReplayBuffer.sample (common/her.py:230)": 6,
        "end_iteration (common/run.py:193);finished (common/evaluate.py:195)": 8,
        "Adam.__init__ (torch/optim/adam.py:35)": 9,
        "Run.end_iteration (common/run.py:190);SummaryWriter.add_scalar (tensorboard.py:1)": 2,
        "QNetwork.forward (ipg_her.py:180);Module._call_impl (torch/nn/modules/module.py:1)": 1,
    }
    raw = "\n".join(f"<module> (ipg_her.py:1);{stack} {n}" for stack, n in stacks.items())
    assert profile_phases.phase_samples(raw) == {
        "stepping": 5, "policy inference": 3, "policy update": 7, "normalisation": 2,
        "advantages and reward scaling": 1, "critic steps": 4, "replay sampling": 6,
        "evaluation": 8, "logging and checkpoints": 2, "start-up and the rest": 10,
    }  # fmt: skip


def test_the_profile_of_a_tiny_run_names_its_phases(tmp_path):
    import json
    import subprocess
    import sys

    from conftest import ROOT

    cmd = [sys.executable, "benchmarks/profile_phases.py", "ppo_kl.py", "--", "--total-timesteps",
           "2048", "--num-envs", "2", "--num-steps", "512", "--eval-freq", "0",
           "--eval-episodes", "1", "--log-dir", str(tmp_path)]  # fmt: skip
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    phases = {line["phase"]: line for line in lines}
    assert {"stepping", "policy update", "all samples"} <= set(phases)
    assert abs(sum(line["share"] for line in lines[:-1]) - 1) < 0.01


def test_fetch_lifts_counts_a_held_lift_not_a_knock_in_time_order():
    """A lift counts when the object stays 2 cm up for 10 steps (a knock for 9 does not), and the
    replay buffer's episodes are read in time order (episode-major, the envs within)."""
    start, up = 0.425, 0.425 + 0.021
    lift = np.full(50, start)
    lift[20:30] = up
    knock = lift.copy()
    knock[29] = start
    assert fetch_lifts.held(np.array([lift, knock])).tolist() == [True, False]
    goals = np.full((100, 2, 3), start)  # two episodes for each of two envs
    goals[:50, 1, 2] = lift  # the second env's first episode: the second in time
    assert fetch_lifts.replay_lifts({"achieved_goal": goals}, parts=2) == [0.5, 0.0]
    measured = fetch_lifts.policy_by_goal(lambda obs: np.zeros(4), "FetchPickAndPlace-v4", range(4))
    assert sum(r["episodes"] for r in measured.values()) == 4
    assert all(r["held"] == 0 for r in measured.values() if r["episodes"])  # standing still


def test_slide_strikes_measures_a_slide_along_and_beside_its_line():
    """Half way to a goal 0.4 m ahead and 5 cm to its left; a goal straight along +y overshot; a
    still policy never moves the puck and never succeeds; a scripted strike slides it."""
    start = np.array([1.0, 0.5, 0.42])
    half = slide_strikes.slide_outcome(start, start + [0.4, 0, 0], start + [0.2, 0.05, 0])
    assert np.allclose(half, (0.5, 0.05))
    past = slide_strikes.slide_outcome(start, start + [0, 0.3, 0], start + [-0.02, 0.45, 0])
    assert np.allclose(past, (1.5, 0.02))
    still = slide_strikes.policy_strikes(lambda obs: np.zeros(4), range(3))
    assert still.shape == (3, 9) and still[:, 1].sum() == 0
    assert np.allclose(still[:, 2], 0, atol=1e-3) and np.all(still[:, 4:] < 1e-3)
    struck = [s for s in map(slide_strikes.scripted_strike, range(3)) if s]  # the full push
    assert struck and all(slide > 0.4 and peak > 0.03 for slide, peak, *_ in struck)
    assert all(came_in > 0.015 for _, _, came_in, *_ in struck)
    assert np.allclose([s[3:] for s in struck], (1, 1, 0))  # along the line, main axis, other
    halved = [s for s in (slide_strikes.scripted_strike(seed, push=0.5) for seed in range(3)) if s]
    assert halved and np.allclose([s[3:5] for s in halved], 0.5)  # the other axis: half its own
    assert all(0.1 < other < 0.4 for *_, other in halved)  # these lines lie off the axes


def test_slide_strikes_gain_scales_x_and_y_only_once_the_puck_has_moved():
    start = np.array([1.3, 0.75, 0.41])
    policy = lambda obs: np.array([0.6, -0.3, 0.5, 0.2], np.float32)  # noqa: E731
    act = slide_strikes.with_gain(policy, start, 1.5)
    assert np.array_equal(act({"achieved_goal": start + [0.004, 0, 0]}, 0), policy(None))
    pushed = act({"achieved_goal": start + [0.01, 0, 0]}, 1)
    assert pushed.dtype == np.float32 and np.allclose(pushed, [0.9, -0.45, 0.5, 0.2])
    assert np.allclose(slide_strikes.with_gain(policy, start, 2)({"achieved_goal": start + 1}, 2),
                       [1.0, -0.6, 0.5, 0.2])  # clipped to the bounds  # fmt: skip


def test_slide_strikes_reads_the_critic_at_the_step_that_moves_the_puck():
    """A critic Q = max(a_x, 0) by hand: its slope along the line is the line's x share, and
    pushing 1.2 times harder from a_x = 0.5 gains 0.1; a run's saved twin critic reads back."""
    import ipg_her  # the run's critic

    qf = ipg_her.QNetwork(3, 4, hidden=2, low=-1.0, high=1.0)
    with torch.no_grad():
        for layer in qf.net[::2]:
            layer.weight.zero_(), layer.bias.zero_()
        qf.net[0].weight[0, 3] = qf.net[2].weight[0, 0] = qf.net[4].weight[0, 0] = 1.0  # a_x

    class Pushing:  # the policy's interface: its inputs and its action
        inputs = staticmethod(lambda obs: torch.zeros(1, 3))
        __call__ = staticmethod(lambda obs: np.array([0.5, 0, 0, 0], np.float32))

    rows = slide_strikes.critic_at_contact(qf, Pushing(), range(2))
    along = [slide_strikes.reset(gym.make("FetchSlide-v4"), seed)[3] for seed in range(2)]
    assert np.allclose(rows[:, 1], [line[0] for line in along], atol=1e-6)
    assert np.allclose(rows[:, 2], 0.1, atol=1e-6)
    assert np.allclose(rows[:, 3], [0.5 * line[0] for line in along], atol=1e-6)
    saved = ipg_her.QNetwork(24, 4, hidden=8, low=-1.0, high=1.0, twin=True)  # as a run saves it
    content = {"args": {"hidden": 8, "twin_critic": True}, "qf": saved.state_dict()}
    x, a = torch.randn(5, 24), torch.randn(5, 4)
    assert torch.equal(slide_strikes.critic(content)(x, a, True)[1], saved(x, a, True)[1])


def test_slide_strikes_reads_far_slides_and_falls_from_the_replay_buffer_in_time_order():
    """Two envs, two episodes each: the later episode of env 0 slides 0.6 m, the earlier of env 1
    falls off the table; the rest stand still."""
    start = np.array([1.3, 0.75, 0.41])
    goals = np.tile(start, (100, 2, 1))
    after = goals.copy()
    after[50:, 0] += [0.6, 0, 0]  # env 0's second episode: a far slide
    after[:50, 1, 2] -= 0.4  # env 1's first episode: off the table
    rb = {"achieved_goal": goals, "next_achieved_goal": after}
    assert slide_strikes.replay_slides(rb, since=0) == (0.25, 0.25)
    assert slide_strikes.replay_slides(rb, since=0.5) == (0.5, 0.0)


def test_every_suite_command_passes_its_scripts_checks(monkeypatch):
    """A suite row its script would refuse (a flag that changes nothing, say) fails here, not
    hours into a suite."""
    import functools

    import ipg_her
    import ppo_kl
    import qprop_ppo
    from common import cli

    scripts = {"ppo_kl.py": ppo_kl, "qprop_ppo.py": qprop_ppo, "ipg_her.py": ipg_her}
    monkeypatch.setattr(cli.gym, "make", functools.cache(cli.gym.make))  # spaces only: one each
    refused = []
    for suite in run.Args.__annotations__["suite"].__args__:
        for r in run.suite_runs(suite):
            module = scripts[r.script]
            argv = ["--env-id", r.env_id, "--seed", str(r.seed), *r.flags]
            try:
                kwargs = {"task_defaults": ipg_her.TASK_DEFAULTS, "ignored": cli.ipg_ignored}
                args = cli.parse_args(module.Args, argv, **(kwargs if module is ipg_her else {}))
                params = module.check_args.__code__.co_argcount
                module.check_args(*(args, argv)[:params])
            except SystemExit:
                refused.append(f"{suite}/{r.folder}")
    assert not refused, refused
