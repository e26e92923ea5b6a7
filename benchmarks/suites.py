"""What each benchmark suite runs: one ``Run`` per script x task x seed, from ``SUITES``.

Over 400 lines, and meant to be: it is data, not logic. Every committed export's runs keep their command here, spelled
out, so that each still runs what it reports (tests/test_benchmarks.py holds them to it); the logic is ``suite_runs``.

The suites (``SUITES``: each its seeds, how report.py shows it, and one row per variant x task, on
the suite's seeds or its own; ``--seeds`` replaces them):

- ``quick``: the paper's grid on tiny budgets, one seed, in seconds.
- ``paper``: Figure 3 (Hopper: PPO-KL, Q-Prop) and Figures 4-5 (FetchReach: PPO-KL, Q-Prop, IPG
  without and with HER), 5 seeds.
- ``ablations``: Q-Prop's eta and normalisation on Hopper; IPG+HER's nu, control variate,
  off-policy states and HER settings on FetchReach.
- ``eta``: Q-Prop's eta per batch and per sample against PPO-KL, Hopper at 300k steps.
- ``mixing``: does an interpolated gradient (0 < nu < 1) beat both ends? IPG+HER on FetchReach
  at nu 0 to 1, with and without the control variate, small and large on-policy batches; IPG and
  Q-Prop variants on Hopper at 300k (``--only FetchReach`` or ``--only Hopper``: one task).
- ``hopper``: the recipe's IPG at nu 1 and 0.5 in TD3's update regime against PPO-KL at 300k on
  fresh seeds, its variants (narrow noise, the critic's term at scale 1, a sampled target), and
  nu 1 to 1M on a seed of its own.
- ``push``: the paper's IPG+HER (``ipg_her.py``, no recipe) on FetchPush, ``--push-steps`` each.
- ``fetch``: the recipe on Push, PickAndPlace and Slide with each task's defaults when it ran
  (spelled out: its own rows then) and the task's budget, fresh seeds; one critic, mixing at nu
  0.5 and 0.8, and each task's earlier defaults beside it.
- ``goals``: the recipe's defaults when it ran (spelled out), no other flag but the budget, on
  goal tasks none of its settings was chosen on: the Shadow hand (HandReach,
  HandManipulateBlockRotateZ) and PointMaze_Medium; on PointMaze also with ``--gamma 0.995``,
  the setting it lacked (chosen on seeds 11-12), and on HandReach with ``--target-std 0.3``,
  summed and one rule per joint (chosen on seed 11).
- ``one_recipe``: the defaults then (the sigma rule's targets held, spelled out), the task's
  filled in by ``fill_in``, no other flag but the budget, on all six goal tasks at their budgets,
  seeds 401-403, which chose nothing.
- ``one_set``: tuning runs on seeds 11-13 for one set of defaults that earns every goal task,
  each candidate exploration mechanism on the tasks that pull apart; they choose, never report.
- ``every_goal``: the one set of defaults, no flag but the budget, on all six goal tasks,
  seeds 601-603, which chose nothing.

``benchmarks/run.py`` runs a suite (``suite_runs``); ``benchmarks/report.py`` shows it as its
``Report`` says.
"""

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Run:
    name: str  # the algorithm variant: ppo_kl, qprop_ppo, ipg_her, ipg_her_noher, ...
    script: str
    env_id: str
    seed: int
    flags: tuple[str, ...] = field(default=())

    @property
    def folder(self) -> str:
        return f"{self.name}__{self.env_id}__seed{self.seed}"

    def command(self, run_dir: Path, track: bool = False) -> list[str]:
        """The run's command; where an interrupted attempt left a resume point (ipg_her.py's
        ``--resume-freq``), it goes on from the latest one instead of starting again."""
        command = [
            sys.executable,
            str(ROOT / self.script),
            "--env-id",
            self.env_id,
            "--seed",
            str(self.seed),
            "--exp-name",
            self.name,
            "--log-dir",
            str(run_dir),
            *self.flags,
            *(["--track"] if track else []),
        ]
        resume_points = sorted(Path(run_dir).glob("*/resume.pt"), key=lambda p: p.stat().st_mtime)
        return command + (["--resume", str(resume_points[-1].parent)] if resume_points else [])


PPO, QPROP, IPG, RECIPE = "ppo_kl.py", "qprop_ppo.py", "ipg_her.py", "ipg_her_recipe.py"
HOPPER, REACH, PUSH = "Hopper-v5", "FetchReach-v4", "FetchPush-v4"
PICK, SLIDE = "FetchPickAndPlace-v4", "FetchSlide-v4"
CRITIC_ONLY = ("--critic-steps", "--learning-starts", "--diagnostics-every")


def critic_free(flags: tuple[str, ...]) -> tuple[str, ...]:
    """``flags`` without the critic's, which ipg_her.py refuses at nu = 0 (no term uses it)."""
    drop = {i + d for i, f in enumerate(flags) if f in CRITIC_ONLY for d in (0, 1)}
    return tuple(f for i, f in enumerate(flags) if i not in drop)


NUS = ("0.0", "0.2", "0.5", "0.8", "1.0")
K300 = ("--total-timesteps", "300000")
FETCH_EVAL = ("--total-timesteps", "30000", "--eval-freq", "2500", "--eval-episodes", "20")
EVERY = ("--diagnostics-every", "1")  # the mixing study logs ipg/* at every update
# mixing: the on-policy batch, 2 envs x 50 steps or x 500, with the same critic steps and policy
# minibatch steps per environment step (0.5 and 0.1)
BATCHES = {
    "b100": ("--num-steps", "50", *EVERY),
    "b1000": ("--num-steps", "500", "--critic-steps", "500", "--num-minibatches", "10", *EVERY),
}
# mixing on Hopper: ipg_her.py with PPO-KL's batch, learning rate and gamma (at nu = 0 it is PPO-KL,
# but not ppo_kl.py's defaults: KL target 0.01, initial log std 0, input clip 5, no learning-rate
# annealing, 20 evaluation episodes), and a critic trained about once per environment step after a
# real warm-up
HOPPER_IPG = (
    *K300,
    "--num-envs",
    "4",
    "--num-steps",
    "512",
    "--num-minibatches",
    "32",
    "--learning-rate",
    "3e-4",
    "--gamma",
    "0.99",
    "--kl-target",
    "0.01",
    "--norm-reward",
    "--critic-steps",
    "2048",
    "--learning-starts",
    "10000",
    "--eval-freq",
    "20000",
    *EVERY,
)
# Every suite that ran before the one set of defaults (every_goal's) ran the sigma rule's targets held
# and, but for Slide's row, constant learning rates: HELD spells that out (HELD_TARGETS beside --anneal-lr).
HELD_TARGETS = ("--target-std-decay", "1.0")
HELD = (*HELD_TARGETS, "--no-anneal-lr")
# hopper: TD3's update regime, an update every 256 steps, one critic step per environment step,
# 128 policy steps, run in parts; TD3_NARROW: TD3's exploration noise (0.1) with the KL target
# scaled by (0.3 / 0.1)^2, so that the mean's step per update stays what it was at 0.3
TD3 = (
    *K300,
    "--num-envs",
    "1",
    "--num-steps",
    "256",
    "--critic-steps",
    "256",
    "--update-epochs",
    "8",
    "--num-minibatches",
    "16",
    "--learning-rate",
    "3e-4",
    "--gamma",
    "0.99",
    "--tau",
    "0.005",
    "--hidden",
    "256",
    "--twin-critic",
    "--normalization",
    "unbiased",
    "--action-l2",
    "0.0",
    "--target-std",
    "0.3",
    "--q-bar",
    "sample",
    *HELD,
    "--learning-starts",
    "10000",
    "--eval-freq",
    "25600",
    "--eval-episodes",
    "10",
    "--resume-freq",
    "51200",
)
TD3_NARROW = (*[f if f != "0.3" else "0.1" for f in TD3], "--kl-target", "0.9", "--bounds-loss", "1.0")
FETCH_EVERY = ("--eval-freq", "10000", "--eval-episodes", "50", "--resume-freq", "50000")
ONE_CRITIC = ("--no-twin-critic",)  # the recipe's defaults before the twin critic
# The recipe's defaults when the fetch and goals suites ran, before they were read off the task
# from the task, spelled out so that their commands still run what ran: one sigma rule summed
# over the action dimensions at 1 and gamma 0.98 on every goal task; PickAndPlace's and Slide's
# rows of their own (PickAndPlace's grasped starts, 0.5, are what fill_in gives it now).
SUMMED = ("--target-std", "1.0")
PICK_ROW = ("--target-std", "1.0", "1.0", "1.0", "0.3")
SLIDE_ROW = ("--target-std", "0.3", "0.3", "0.3", "1.0", "--action-l2", "0.0", "--bounds-loss", "1.0")  # and --anneal-lr
PICK_ONE_SIGMA = ("--total-timesteps", "500000", *FETCH_EVERY, *SUMMED, *HELD)
SLIDE_CONSTLR = ("--total-timesteps", "1000000", *FETCH_EVERY, *HELD)
# one_set's first candidates: the targets' decay without a floor, and the discount 1 - 1/H unclipped
DECAY03 = ("--target-std-decay", "0.3", "--target-std-decay-steps", "100000", "--target-std-floor", "0.0")
MAZE_GAMMA_THEN = ("--gamma", "0.9983333333333333")  # 1 - 1/600, PointMaze's discount before the clip at 0.995
GOAL_TASKS = (  # every goal task at its budget (one_recipe, every_goal and the tuning seeds' rows of one_set)
    (PUSH, 300_000),
    (PICK, 500_000),
    (SLIDE, 1_000_000),
    ("HandReach-v3", 300_000),
    ("PointMaze_Medium-v3", 300_000),
    ("HandManipulateBlockRotateZ-v1", 1_000_000),
)
PUSH_BUDGET = ("--total-timesteps", "{steps}", "--eval-freq", "25000", "--resume-freq", "50000")
TINY = ("--num-envs", "2", "--num-steps", "128", "--num-minibatches", "4", "--update-epochs", "2", "--eval-episodes", "1")
TINY_IPG = ("--total-timesteps", "300", "--critic-steps", "4", "--eval-freq", "100", "--eval-episodes", "2")


@dataclass(frozen=True)
class Report:
    """How benchmarks/report.py shows a suite: its figures and the tables beyond the common ones."""

    figures: Literal["paper", "mixing", "per task"] = "per task"
    """the paper's Figures 3-5, the mixing study's (success or return against nu), or one figure
    per task with every variant of the suite"""
    per_episode: bool = True
    """a goal task's success figure against episodes (Fetch's 50 steps each), else against steps"""
    median: bool = False
    """curves: the median seed and the band from the lowest to the highest, else the mean and its
    95% bootstrap band"""
    budgets: tuple[int, ...] = (2_500, 5_000, 10_000, 30_000)
    """the success table's columns: evaluation success at these steps"""
    levels: tuple[float, ...] = ()
    """the reach table's success levels, per seed the steps and hours to each (none: no table)"""
    finalists_from: int = 0
    """the finalists table: each variant on seeds from this one on, the fresh ones (0: no table)"""


class Suite(NamedTuple):
    seeds: tuple[int, ...]  # each row's, unless it has its own
    report: Report
    rows: list[tuple]  # (name, script, env_id, flags) or, on seeds of its own, (..., seeds)


# In the push suite "{steps}" and "{k}" stand for --push-steps and the same in thousands.
SUITES: dict[str, Suite] = {
    "paper": Suite(
        (1, 2, 3, 4, 5),
        Report(figures="paper"),
        [
            ("ppo_kl", PPO, HOPPER, ()),
            ("qprop_ppo", QPROP, HOPPER, ()),
            ("ppo_kl", PPO, REACH, FETCH_EVAL),
            ("qprop_ppo", QPROP, REACH, FETCH_EVAL),
            ("ipg", IPG, REACH, ("--no-her",)),
            ("ipg_her", IPG, REACH, ()),
        ],
    ),
    "ablations": Suite(
        (1, 2, 3),
        Report(),
        [
            *[
                (f"qprop_{eta}_{norm}", QPROP, HOPPER, ("--eta-mode", eta, "--normalization", norm))
                for eta in ("conservative", "aggressive", "ones")
                for norm in ("paper", "unbiased")
            ],
            *[(f"ipg_her_nu{nu}", IPG, REACH, ("--nu", nu)) for nu in NUS[:4]],
            ("ipg_her_nu0.2_cv", IPG, REACH, ("--nu", "0.2", "--use-cv")),  # cv needs nu < 1
            ("ipg_her_batch_states", IPG, REACH, ("--off-policy-states", "batch")),
            *[(f"ipg_her_k{k}", IPG, REACH, ("--her-n-sampled-goal", k)) for k in ("1", "8")],
            *[(f"ipg_her_{s}", IPG, REACH, ("--her-goal-selection-strategy", s)) for s in ("final", "episode")],
        ],
    ),
    "eta": Suite(
        (1, 2, 3),
        Report(),
        [
            ("ppo_kl_300k", PPO, HOPPER, K300),
            *[
                (f"qprop_{eta}_300k", QPROP, HOPPER, ("--eta-mode", eta, *K300))
                for eta in ("batch-conservative", "conservative")
            ],
        ],
    ),
    # the screen on seeds 1-5, the finalists also on fresh seeds from 11 on (--seeds)
    "mixing": Suite(
        (1, 2, 3, 4, 5),
        Report(figures="mixing", finalists_from=11),
        [
            *[
                (
                    f"ipg_her_nu{nu}_{batch}" + ("_cv" if cv else ""),
                    IPG,
                    REACH,
                    ("--nu", nu, *(flags if cv or nu != "0.0" else critic_free(flags)), *(("--use-cv",) if cv else ())),
                )
                for batch, flags in BATCHES.items()
                for cv in (False, True)
                for nu in NUS
                if not (cv and nu == "1.0")
            ],  # at nu = 1 the term the cv enters has no weight
            # nu = 1 with Q_bar sampled: sigma learns from the critic, as it does at nu < 1
            ("ipg_her_nu1.0_b100_qsample", IPG, REACH, ("--q-bar", "sample", *EVERY)),
            *[
                (f"ipg_nu{nu}_300k", IPG, HOPPER, ("--nu", nu, *(HOPPER_IPG if nu != "0.0" else critic_free(HOPPER_IPG))))
                for nu in NUS
            ],
            (
                "ipg_nu0.0_1M",
                IPG,
                HOPPER,
                ("--nu", "0.0", *critic_free(("--total-timesteps", "1000000", "--resume-freq", "100000", *HOPPER_IPG[2:]))),
            ),
            # the IPG paper's best variant: nu 0.2, control variate, on-policy states
            ("ipg_nu0.2_cv_batch_300k", IPG, HOPPER, ("--nu", "0.2", "--use-cv", "--off-policy-states", "batch", *HOPPER_IPG)),
            # the off-policy end with DDPG's slow target, then with Q_bar sampled
            ("ipg_nu1.0_tau0.005_300k", IPG, HOPPER, ("--nu", "1.0", "--tau", "0.005", *HOPPER_IPG)),
            (
                "ipg_nu1.0_tau0.005_qsample_300k",
                IPG,
                HOPPER,
                ("--nu", "1.0", "--tau", "0.005", "--q-bar", "sample", *HOPPER_IPG),
            ),
            *[
                (f"qprop_{eta}_300k", QPROP, HOPPER, ("--eta-mode", eta, *K300))
                for eta in ("conservative", "batch-conservative")
            ],
            (
                "qprop_batch-conservative_critic2048_300k",
                QPROP,
                HOPPER,
                ("--critic-steps", "2048", "--learning-starts", "10000", *K300),
            ),
        ],
    ),
    "hopper": Suite(
        (4, 5, 6),
        Report(),
        [  # the regime was screened on seed 1
            ("ppo_kl_300k", PPO, HOPPER, K300),
            *[(f"ipg_td3_nu{nu}_300k", RECIPE, HOPPER, ("--nu", nu, *TD3)) for nu in ("1.0", "0.5")],
            ("ipg_td3_bounds_nu1.0_300k", RECIPE, HOPPER, ("--nu", "1.0", *TD3, "--bounds-loss", "1.0")),
            ("ipg_td3_narrow_nu1.0_300k", RECIPE, HOPPER, ("--nu", "1.0", *TD3_NARROW), (8, 9, 10)),
            # the critic's term at scale 1; the critic's target at a' ~ pi(s') on 14-16 ran with
            # benchmarks/probes/screens/critic_target_and_clip.patch (its rows stay in the export)
            (
                "ipg_td3_paper_nu1.0_300k",
                RECIPE,
                HOPPER,
                ("--nu", "1.0", *[f if f != "unbiased" else "paper" for f in TD3_NARROW]),
                (11, 12, 13),
            ),
            # nu 1 again on fresh trios, and nu 0.5 beside it on the last; PPO-KL on every trio
            ("ipg_td3_nu1.0_300k", RECIPE, HOPPER, ("--nu", "1.0", *TD3), (14, 15, 16)),
            ("ipg_td3_nu1.0_300k", RECIPE, HOPPER, ("--nu", "1.0", *TD3), (17, 18, 19)),
            ("ipg_td3_nu0.5_300k", RECIPE, HOPPER, ("--nu", "0.5", *TD3), (17, 18, 19)),
            *[("ppo_kl_300k", PPO, HOPPER, K300, trio) for trio in ((8, 9, 10), (11, 12, 13), (14, 15, 16), (17, 18, 19))],
            ("ipg_td3_nu1.0_1M", RECIPE, HOPPER, ("--nu", "1.0", "--total-timesteps", "1000000", *TD3[len(K300) :]), (7,)),
        ],
    ),
    # the paper's IPG+HER, FetchReach's defaults, on Push (no recipe)
    "push": Suite(
        (1, 2, 3),
        Report(budgets=(100_000, 200_000, 300_000, 500_000, 1_000_000, 1_500_000), levels=(0.5, 0.9)),
        [
            ("ipg_her_{k}k", IPG, PUSH, PUSH_BUDGET),
            ("ipg_her_{k}k_qsample", IPG, PUSH, (*PUSH_BUDGET, "--q-bar", "sample")),
            ("ipg_her_{k}k_nu0.8", IPG, PUSH, (*PUSH_BUDGET, "--nu", "0.8")),
        ],
    ),
    # every row on seeds of its own, fresh ones unless said; figures in steps, median seed
    "fetch": Suite(
        (),
        Report(
            per_episode=False,
            median=True,
            levels=(0.5, 0.7, 0.9),
            budgets=(100_000, 150_000, 200_000, 300_000, 500_000, 1_000_000),
        ),
        [
            ("ipg_her_300k", RECIPE, PUSH, ("--total-timesteps", "300000", *FETCH_EVERY, *SUMMED, *HELD), (4, 5, 6, 7, 8)),
            (
                "ipg_her_1critic_300k",
                RECIPE,
                PUSH,
                ("--total-timesteps", "300000", *FETCH_EVERY, *SUMMED, *HELD, *ONE_CRITIC),
                (4, 5, 6, 7, 8),
            ),
            ("ipg_her_500k", RECIPE, PICK, ("--total-timesteps", "500000", *FETCH_EVERY, *PICK_ROW, *HELD), (4, 5, 6)),
            (
                "ipg_her_1000k",
                RECIPE,
                SLIDE,
                ("--total-timesteps", "1000000", *FETCH_EVERY, *SLIDE_ROW, *HELD_TARGETS, "--anneal-lr"),
                (7, 8, 9),
            ),
            # PickAndPlace's earlier defaults, one sigma rule for all dimensions: with grasped starts,
            # and before them (on the tuning seeds) with and without the twin critic
            ("ipg_her_grasped_500k", RECIPE, PICK, PICK_ONE_SIGMA, (4, 5, 6)),
            ("ipg_her_nograsp_500k", RECIPE, PICK, (*PICK_ONE_SIGMA, "--grasped-start", "0"), (1, 2, 3)),
            ("ipg_her_nograsp_1critic_500k", RECIPE, PICK, (*PICK_ONE_SIGMA, "--grasped-start", "0", *ONE_CRITIC), (1, 2, 3)),
            # Slide before its annealed learning rates: its own defaults then, and Push's (one sigma
            # rule for all dimensions, the action penalty) on the tuning seeds
            ("ipg_her_constlr_1000k", RECIPE, SLIDE, (*SLIDE_CONSTLR, *SLIDE_ROW), (4, 5, 6)),
            (
                "ipg_her_sigma1_1000k",
                RECIPE,
                SLIDE,
                (*SLIDE_CONSTLR, "--target-std", "1.0", "--action-l2", "1.0", "--bounds-loss", "0.0"),
                (1, 2, 3),
            ),
            # mixing on Push, nu 0.8 and 0.5 at 200k; Push's --normalization paper weighs the terms
            # nu sigma_A : (1 - nu), so eq. 10's nu is "_eq10"
            *[
                (
                    f"ipg_her{kind}_nu{nu}_200k",
                    RECIPE,
                    PUSH,
                    ("--total-timesteps", "200000", "--nu", nu, *FETCH_EVERY, *SUMMED, *HELD, *flags),
                    (4, 5, 6),
                )
                for kind, flags in (("", ()), ("_1critic", ONE_CRITIC), ("_eq10", ("--normalization", "unbiased")))
                for nu in ("0.8", "0.5")
            ],
        ],
    ),
    # the recipe's defaults on goal tasks no run was tuned on; figures in steps (a maze's
    # episode is not 50 steps)
    "goals": Suite(
        (301, 302, 303),
        Report(per_episode=False),
        [
            ("ipg_her_300k", RECIPE, "HandReach-v3", ("--total-timesteps", "300000", *FETCH_EVERY, *SUMMED, *HELD)),
            (
                "ipg_her_300k_std03",
                RECIPE,
                "HandReach-v3",  # chosen on seed 11
                ("--total-timesteps", "300000", "--target-std", "0.3", *FETCH_EVERY, *HELD),
            ),
            (
                "ipg_her_300k_std03x20",
                RECIPE,
                "HandReach-v3",  # one rule per joint, chosen on seed 11
                ("--total-timesteps", "300000", "--target-std", *["0.3"] * 20, *FETCH_EVERY, *HELD),
            ),
            (
                "ipg_her_1000k",
                RECIPE,
                "HandManipulateBlockRotateZ-v1",
                ("--total-timesteps", "1000000", *FETCH_EVERY, *SUMMED, "--gamma", "0.98", *HELD),
            ),
            (
                "ipg_her_300k",
                RECIPE,
                "PointMaze_Medium-v3",
                ("--total-timesteps", "300000", *FETCH_EVERY, *SUMMED, "--gamma", "0.98", *HELD),
            ),
            (
                "ipg_her_300k_gamma0995",
                RECIPE,
                "PointMaze_Medium-v3",  # chosen on seeds 11-12
                ("--total-timesteps", "300000", "--gamma", "0.995", *FETCH_EVERY, *SUMMED, *HELD),
            ),
        ],
    ),
    # the recipe's defaults, the task's filled in by fill_in, no flag but the budget, on every
    # goal task, seeds none of its settings was chosen on; figures in steps (a maze's episode
    # is not 50 steps)
    "one_recipe": Suite(
        (401, 402, 403),
        Report(
            per_episode=False, median=True, levels=(0.5, 0.7, 0.9), budgets=(100_000, 150_000, 300_000, 500_000, 1_000_000)
        ),
        [
            (
                f"ipg_her_{steps // 1000}k",
                RECIPE,
                env_id,
                ("--total-timesteps", str(steps), *FETCH_EVERY, *HELD, *(MAZE_GAMMA_THEN if "Maze" in env_id else ())),
            )
            for env_id, steps in GOAL_TASKS
        ],
    ),
    # tuning runs for one set of defaults that earns every goal task (seeds 11-13 choose; none of these reports):
    # each candidate exploration mechanism on the tasks that pull apart, at screening budgets
    "one_set": Suite(
        (11,),
        Report(
            per_episode=False, median=True, levels=(0.5, 0.7, 0.9), budgets=(100_000, 150_000, 300_000, 500_000, 1_000_000)
        ),
        [
            # the one set of defaults as frozen (no flag but the budget: every_goal's rows), on the tuning seeds
            *[
                (f"defaults_{steps // 1000}k", RECIPE, env_id, ("--total-timesteps", str(steps), *FETCH_EVERY), (11, 12))
                for env_id, steps in GOAL_TASKS
            ],
            # the sigma rule's targets decay geometrically to 0.3 of the rule's over the first 100k steps
            *[
                (
                    f"decay03_{steps // 1000}k",
                    RECIPE,
                    env_id,
                    ("--total-timesteps", str(steps), *FETCH_EVERY, *DECAY03, "--no-anneal-lr", *gamma),
                )
                for env_id, steps, gamma in (
                    (PUSH, 300_000, ()),
                    (SLIDE, 500_000, ()),
                    (PICK, 300_000, ()),
                    ("HandReach-v3", 300_000, ()),
                    ("PointMaze_Medium-v3", 300_000, MAZE_GAMMA_THEN),
                )
            ],
            # the same with both learning rates annealed to zero over the budget (Slide's late noise floor)
            *[
                (
                    f"decay03_annealed_{steps // 1000}k",
                    RECIPE,
                    env_id,
                    ("--total-timesteps", str(steps), *FETCH_EVERY, *DECAY03, "--anneal-lr", *gamma),
                )
                for env_id, steps, gamma in (
                    (SLIDE, 1_000_000, ()),
                    ("HandManipulateBlockRotateZ-v1", 1_000_000, ()),
                    (PUSH, 300_000, ()),
                    (PICK, 300_000, ()),
                    ("HandReach-v3", 300_000, ()),
                    ("PointMaze_Medium-v3", 300_000, MAZE_GAMMA_THEN),
                )
            ],
        ],
    ),
    # the one set of defaults, frozen before any of these runs: no flag but the budget and the evaluation grid, on
    # every goal task, seeds that chose nothing (601-603)
    "every_goal": Suite(
        (601, 602, 603),
        Report(
            per_episode=False, median=True, levels=(0.5, 0.7, 0.9), budgets=(100_000, 150_000, 300_000, 500_000, 1_000_000)
        ),
        [
            (f"ipg_her_{steps // 1000}k", RECIPE, env_id, ("--total-timesteps", str(steps), *FETCH_EVERY))
            for env_id, steps in GOAL_TASKS
        ],
    ),
    "quick": Suite(
        (1,),
        Report(figures="paper"),
        [  # the paper's grid, tiny budgets
            ("ppo_kl", PPO, HOPPER, ("--total-timesteps", "512", *TINY)),
            (
                "qprop_ppo",
                QPROP,
                HOPPER,
                ("--total-timesteps", "512", "--learning-starts", "256", "--critic-steps", "4", *TINY),
            ),
            (
                "ppo_kl",
                PPO,
                REACH,
                (
                    "--total-timesteps",
                    "300",
                    "--num-envs",
                    "2",
                    "--num-steps",
                    "50",
                    "--num-minibatches",
                    "4",
                    "--eval-episodes",
                    "2",
                ),
            ),
            ("ipg", IPG, REACH, ("--no-her", *TINY_IPG)),
            ("ipg_her", IPG, REACH, TINY_IPG),
        ],
    ),
}


def suite_runs(suite: str, seeds: tuple[int, ...] = (), push_steps: int = 1_500_000) -> list[Run]:
    """``SUITES[suite]`` row by row, each row on its seeds (its own, else the suite's), or on
    ``seeds`` when given, of which a row of one seed of its own (a long run) takes the first. A
    run an earlier row gives already is not repeated. ``push_steps``: the push suite's budget."""
    suite_seeds, _, rows = SUITES[suite]
    fill = lambda text: text.format(steps=push_steps, k=push_steps // 1000)
    runs = []
    for name, script, env_id, flags, *own in rows:
        row_seeds = own[0] if own else suite_seeds
        row_seeds = (seeds[:1] if own and len(row_seeds) == 1 else seeds) or row_seeds
        runs += [Run(fill(name), script, env_id, seed, tuple(map(fill, flags))) for seed in row_seeds]
    return list(dict.fromkeys(runs))
