"""Run a grid of script x task x seed, each run its own process, locally or on a Ray cluster.

    python benchmarks/run.py --suite paper            # Figures 3-5 of the paper, 5 seeds
    python benchmarks/run.py --suite quick --dry-run  # print the commands only
    python benchmarks/report.py --suite paper         # figures and table from the event files

Every run gets a folder ``{out-dir}/{suite}/{name}__{env_id}__seed{seed}/`` holding the script's
own run folder (TensorBoard events), ``stdout.log``, ``stderr.log``, ``exit_code`` and while it
runs ``pid`` (a later call starts no second copy of a run still running). A run whose
``exit_code`` says 0 is skipped by the next call (resume); a failed one is run again, and one
stopped goes on from its resume point if it has one. The call exits non-zero if any run failed.
Ctrl-C (or SIGTERM) stops the suite: the running scripts save and exit, no other run starts.
"""

import ctypes
import importlib
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    """Run a suite of script x task x seed, one process each; a later call resumes it."""

    suite: Literal["paper", "ablations", "eta", "mixing", "push", "fetch", "hopper", "quick"]
    """which grid: quick (seconds), paper (hours), eta, ablations, mixing, hopper, push, fetch"""
    seeds: tuple[int, ...] = ()
    """override the suite's seeds"""
    only: str = ""
    """run only the runs whose folder name contains this text"""
    workers: int = os.cpu_count() or 1
    """runs at once (each uses one core)"""
    out_dir: str = "benchmarks/runs"
    """parent of the suite folders"""
    backend: Literal["local", "ray"] = "local"
    """local processes, or one Ray task per run (needs Ray; a multi-node cluster: shared files)"""
    ray_address: str | None = None
    """address of an existing Ray cluster (None: start a local Ray instance)"""
    dry_run: bool = False
    """print the commands and exit"""
    push_steps: int = 1_500_000
    """the push suite's budget per run (in its runs' names; resumable every 50,000 steps)"""


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

    def command(self, run_dir: Path) -> list[str]:
        """The run's command; where an interrupted attempt left a resume point (ipg_her.py's
        ``--resume-freq``), it goes on from the latest one instead of starting again."""
        command = [sys.executable, str(ROOT / self.script), "--env-id", self.env_id,
                   "--seed", str(self.seed), "--exp-name", self.name, "--log-dir", str(run_dir),
                   *self.flags]  # fmt: skip
        resume_points = sorted(Path(run_dir).glob("*/resume.pt"), key=lambda p: p.stat().st_mtime)
        return command + (["--resume", str(resume_points[-1].parent)] if resume_points else [])


HOPPER_STEPS, FETCH_STEPS = 1_000_000, 30_000
CRITIC_ONLY = ("--critic-steps", "--learning-starts", "--diagnostics-every")


def critic_free(flags: tuple[str, ...]) -> tuple[str, ...]:
    """``flags`` without the critic's, which ipg_her.py refuses at nu = 0 (no term uses it)."""
    drop = {i + d for i, f in enumerate(flags) if f in CRITIC_ONLY for d in (0, 1)}
    return tuple(f for i, f in enumerate(flags) if i not in drop)


def suite_runs(suite: str, seeds: tuple[int, ...] = (), push_steps: int = 1_500_000) -> list[Run]:
    """The named grids. ``paper``: Figure 3 (Hopper: PPO-KL vs Q-Prop), Figures 4-5 (FetchReach:
    PPO-KL, Q-Prop, IPG without HER, IPG+HER); ``ablations``: Q-Prop's eta and normalisation, IPG's
    nu, control variate and HER settings; ``eta``: Q-Prop's eta modes (and its twin critic) against
    PPO-KL on Hopper at 300k steps; ``mixing``: IPG+HER on FetchReach at nu 0 to 1, with and without
    the control variate, with a small and a large on-policy batch, and IPG and Q-Prop variants on
    Hopper at 300k steps (``--only FetchReach`` or ``--only Hopper`` runs one task); ``hopper``: IPG
    at nu 1 and 0.5 in TD3's update regime against PPO-KL, 300k steps (nu 1 with TD3's noise on
    seeds of its own), and nu 1 to 1M on one seed; ``push``: IPG+HER on FetchPush-v4 with its
    earlier controls; ``fetch``: ``ipg_her.py`` with no flag but the task's, Push 5 fresh seeds x
    300k (and nu 0.5, 0.8 on 3 of them x 200k), PickAndPlace 3 x 500k (and 3 with one sigma rule for
    all dimensions, ``_grasped``, and 3 without grasped starts either, ``_nograsp``), Slide 3 x 1M
    (and with constant learning rates, ``_constlr``, and Push's defaults on seeds it was tuned on,
    ``_sigma1``, both without Slide's annealing),
    and Push and PickAndPlace with one critic (``_1critic``); ``quick``: the paper's shape on tiny
    budgets."""
    fetch = lambda name, script, *flags: (name, script, "FetchReach-v4", flags)  # noqa: E731
    hopper = lambda name, script, *flags: (name, script, "Hopper-v5", flags)  # noqa: E731
    fetch_eval = ("--total-timesteps", str(FETCH_STEPS), "--eval-freq", "2500")
    fetch_eval += ("--eval-episodes", "20")
    if suite == "paper":
        seeds = seeds or (1, 2, 3, 4, 5)
        grid = [
            hopper("ppo_kl", "ppo_kl.py"),
            hopper("qprop_ppo", "qprop_ppo.py"),
            fetch("ppo_kl", "ppo_kl.py", *fetch_eval),
            fetch("qprop_ppo", "qprop_ppo.py", *fetch_eval),
            fetch("ipg", "ipg_her.py", "--no-her"),
            fetch("ipg_her", "ipg_her.py"),
        ]
    elif suite == "ablations":
        seeds = seeds or (1, 2, 3)
        grid = [
            hopper(
                f"qprop_{eta}_{norm}", "qprop_ppo.py", "--eta-mode", eta, "--normalization", norm
            )
            for eta in ("conservative", "aggressive", "ones")
            for norm in ("paper", "unbiased")
        ]
        grid += [
            fetch(f"ipg_her_nu{nu}", "ipg_her.py", "--nu", str(nu)) for nu in (0.0, 0.2, 0.5, 0.8)
        ]
        grid += [
            fetch("ipg_her_nu0.2_cv", "ipg_her.py", "--nu", "0.2", "--use-cv"),  # cv needs nu < 1
            fetch("ipg_her_batch_states", "ipg_her.py", "--off-policy-states", "batch"),
        ]
        grid += [
            fetch(f"ipg_her_k{k}", "ipg_her.py", "--her-n-sampled-goal", str(k)) for k in (1, 8)
        ]
        grid += [
            fetch(f"ipg_her_{s}", "ipg_her.py", "--her-goal-selection-strategy", s)
            for s in ("final", "episode")
        ]
    elif suite == "eta":  # Q-Prop's eta: one per batch (unbiased) vs per sample (the paper's)
        seeds = seeds or (1, 2, 3)
        budget = ("--total-timesteps", "300000")
        grid = [hopper("ppo_kl_300k", "ppo_kl.py", *budget)]
        grid += [
            hopper(f"qprop_{eta}_300k", "qprop_ppo.py", "--eta-mode", eta, *budget)
            for eta in ("batch-conservative", "conservative")
        ]
        # issue 29: the default eta with TD3's twin critic, the stronger critic Q-Prop lacked
        grid.append(hopper("qprop_twin_300k", "qprop_ppo.py", "--twin-critic", *budget))
    elif suite == "mixing":  # does an interpolated gradient (0 < nu < 1) beat both ends?
        seeds = seeds or (1, 2, 3, 4, 5)
        grid = []
        # the on-policy batch: 2 envs x 50 steps or x 500, with the same critic steps and policy
        # minibatch steps per environment step (0.5 and 0.1)
        every = ("--diagnostics-every", "1")  # the study logs ipg/* at every update
        batches = {"b100": ("--num-steps", "50", *every),
                   "b1000": ("--num-steps", "500", "--critic-steps", "500",
                             "--num-minibatches", "10", *every)}  # fmt: skip
        for batch, flags in batches.items():
            for cv in (False, True):
                for nu in (0.0, 0.2, 0.5, 0.8, 1.0):
                    if cv and nu == 1.0:  # the likelihood-ratio term has no weight: nu = 1 again
                        continue
                    name = f"ipg_her_nu{nu}_{batch}" + ("_cv" if cv else "")
                    flags_nu = flags if cv or nu else critic_free(flags)
                    grid.append(fetch(name, "ipg_her.py", "--nu", str(nu), *flags_nu,
                                      *(("--use-cv",) if cv else ())))  # fmt: skip
        # nu = 1 with Q_bar sampled: sigma then learns from the critic, as the likelihood-ratio
        # term lets it at nu < 1 (with Q_bar from the mean, nothing but the KL penalty moves it)
        grid.append(fetch("ipg_her_nu1.0_b100_qsample", "ipg_her.py", "--q-bar", "sample", *every))
        # Hopper, 300k steps: ipg_her with PPO-KL's batch, learning rate and gamma (at nu = 0 it is
        # PPO-KL, but not ppo_kl.py's defaults: KL target 0.01, initial log std 0 not -0.5, input
        # clip 5 not 10, no learning-rate annealing, 20 evaluation episodes not 10), and a
        # critic trained about once per environment step after a real warm-up; the IPG paper's
        # best variant (nu 0.2, control variate, on-policy states); Q-Prop with per-sample and
        # batch eta and with 8x more critic work after a warm-up
        hopper_ipg = ("--total-timesteps", "300000", "--num-envs", "4", "--num-steps", "512",
                      "--num-minibatches", "32", "--learning-rate", "3e-4", "--gamma", "0.99",
                      "--kl-target", "0.01", "--norm-reward", "--critic-steps", "2048",
                      "--learning-starts", "10000", "--eval-freq", "20000", *every)  # fmt: skip
        grid += [hopper(f"ipg_nu{nu}_300k", "ipg_her.py", "--nu", str(nu),
                        *(hopper_ipg if nu else critic_free(hopper_ipg)))
                 for nu in (0.0, 0.2, 0.5, 0.8, 1.0)]  # fmt: skip
        # the winner to 1M steps: nu = 0 (no middle beat it on fresh seeds), run in parts
        to_1m = ("--total-timesteps", "1000000", "--resume-freq", "100000", *hopper_ipg[2:])
        grid.append(hopper("ipg_nu0.0_1M", "ipg_her.py", "--nu", "0.0", *critic_free(to_1m)))
        grid.append(hopper("ipg_nu0.2_cv_batch_300k", "ipg_her.py", "--nu", "0.2", "--use-cv",
                           "--off-policy-states", "batch", *hopper_ipg))  # fmt: skip
        # the off-policy end with DDPG's slow target (tau 0.005, not FetchReach's 0.05): at 2,048
        # critic steps per update a fast target follows the critic, and nu = 1's critic diverged
        grid.append(hopper("ipg_nu1.0_tau0.005_300k", "ipg_her.py", "--nu", "1.0",
                           "--tau", "0.005", *hopper_ipg))  # fmt: skip
        # and there sigma drifted up (entropy 4.3 to 7.0): with Q_bar sampled sigma has a gradient
        grid.append(hopper("ipg_nu1.0_tau0.005_qsample_300k", "ipg_her.py", "--nu", "1.0",
                           "--tau", "0.005", "--q-bar", "sample", *hopper_ipg))  # fmt: skip
        budget = ("--total-timesteps", "300000")
        grid += [hopper(f"qprop_{eta}_300k", "qprop_ppo.py", "--eta-mode", eta, *budget)
                 for eta in ("conservative", "batch-conservative")]  # fmt: skip
        more_critic = ("--critic-steps", "2048", "--learning-starts", "10000")
        grid.append(hopper("qprop_batch-conservative_critic2048_300k", "qprop_ppo.py",
                           *more_critic, *budget))  # fmt: skip
    elif suite == "hopper":  # issue 29: the off-policy end in TD3's update regime, fresh seeds
        seed_1m = seeds[:1] or (7,)  # the 1M figure: one seed none of the others used
        fresh, fresh2, fresh3 = seeds or (8, 9, 10), seeds or (11, 12, 13), seeds or (14, 15, 16)
        fresh4 = seeds or (17, 18, 19)
        seeds = seeds or (4, 5, 6)  # the regime was screened on seed 1 (results.md)
        budget = ("--total-timesteps", "300000")
        # an update every 256 steps, one critic step per environment step, 128 policy steps
        td3 = (*budget, "--num-envs", "1", "--num-steps", "256", "--critic-steps", "256",
               "--update-epochs", "8", "--num-minibatches", "16", "--learning-rate", "3e-4",
               "--gamma", "0.99", "--tau", "0.005", "--hidden", "256", "--twin-critic",
               "--target-std", "0.3", "--q-bar", "sample", "--learning-starts", "10000",
               "--eval-freq", "25600", "--eval-episodes", "10")  # fmt: skip
        td3 += ("--resume-freq", "51200")  # runs in parts
        grid = [hopper("ppo_kl_300k", "ppo_kl.py", *budget)]
        grid += [hopper(f"ipg_td3_nu{nu}_300k", "ipg_her.py", "--nu", str(nu), *td3)
                 for nu in (1.0, 0.5)]  # fmt: skip
        # mu(s) beyond the bounds, where the clipping critic gives no gradient (results.md)
        grid.append(hopper("ipg_td3_bounds_nu1.0_300k", "ipg_her.py", "--nu", "1.0", *td3,
                           "--bounds-loss", "1.0"))  # fmt: skip
        # TD3's exploration noise (0.1) with the KL target scaled by (0.3 / 0.1)^2, so that the
        # mean's step per update stays what it was at 0.3; screened on seed 1 after 4-6 were seen
        narrow = [f if f != "0.3" else "0.1" for f in td3] + ["--kl-target", "0.9"]
        grid.append(("ipg_td3_narrow_nu1.0_300k", "ipg_her.py", "Hopper-v5",
                     ("--nu", "1.0", *narrow, "--bounds-loss", "1.0"), fresh))  # fmt: skip
        # the critic's term at scale 1: "unbiased" divides it by the std of advantages no term
        # uses at nu = 1, which swung 0.7-84 within 40 updates (results.md)
        grid.append(("ipg_td3_paper_nu1.0_300k", "ipg_her.py", "Hopper-v5",
                     ("--nu", "1.0", *narrow, "--bounds-loss", "1.0", "--normalization", "paper"),
                     fresh2))  # fmt: skip
        # and its critic's target at a' ~ pi(s'), screened by branching on seeds 1-2 (results.md)
        grid.append(("ipg_td3_paper_sampled_nu1.0_300k", "ipg_her.py", "Hopper-v5",
                     ("--nu", "1.0", *narrow, "--bounds-loss", "1.0", "--normalization", "paper",
                      "--critic-target", "sample"), fresh3))  # fmt: skip
        # the nu = 1 row again on fresh trios of its own: a second (14-16) and a third (17-19),
        # and nu = 0.5 on the third, where both ends ran side by side (the mixing question)
        grid += [(f"ipg_td3_nu{nu}_300k", "ipg_her.py", "Hopper-v5", ("--nu", str(nu), *td3), trio)
                 for nu, trio in ((1.0, fresh3), (1.0, fresh4), (0.5, fresh4))
                 if trio != seeds]  # fmt: skip
        grid += [("ppo_kl_300k", "ppo_kl.py", "Hopper-v5", budget, trio)
                 for trio in (fresh, fresh2, fresh3, fresh4) if trio != seeds]  # fmt: skip
        to_1m = ("--nu", "1.0", "--total-timesteps", "1000000", *td3[len(budget) :])
        grid += [("ipg_td3_nu1.0_1M", "ipg_her.py", "Hopper-v5", to_1m, seed_1m)]
    elif suite == "push":  # measured with FetchReach's defaults; ipg_her.py now has Push's own
        seeds = seeds or (1, 2, 3)
        budget = ("--total-timesteps", str(push_steps), "--eval-freq", "25000")
        budget += ("--resume-freq", "50000")  # a run goes on after an interruption
        name = f"ipg_her_{push_steps // 1000}k"
        sample = (*budget, "--q-bar", "sample")
        # nu 0.8: the likelihood-ratio term gives sigma a signal, which nu = 1 lacks (its entropy
        # climbs under the KL penalty alone); the best middle nu on FetchReach
        mixed = (*budget, "--nu", "0.8")
        grid = [(name, "ipg_her.py", "FetchPush-v4", budget),
                (f"{name}_qsample", "ipg_her.py", "FetchPush-v4", sample),
                (f"{name}_nu0.8", "ipg_her.py", "FetchPush-v4", mixed)]  # fmt: skip
    elif suite == "fetch":  # evaluated every 10,000 steps on 50 episodes, resumable
        every = ("--eval-freq", "10000", "--eval-episodes", "50", "--resume-freq", "50000")
        tasks = {"FetchPush-v4": (300_000, (4, 5, 6, 7, 8)),  # its settings were tuned on 1-3
                 "FetchPickAndPlace-v4": (500_000, (4, 5, 6)),  # its settings tuned on 1-3
                 "FetchSlide-v4": (1_000_000, (7, 8, 9))}  # tuned on 1, 2, 5, 6  # fmt: skip
        one = ("--no-twin-critic",)  # the defaults before the twin critic (its measured gain)
        grid = [Run(f"ipg_her{critic}_{steps // 1000}k", "ipg_her.py", env_id, seed,
                    ("--total-timesteps", str(steps), *every, *flags))
                for env_id, (steps, task_seeds) in tasks.items()
                for critic, flags in (("", ()), ("_1critic", one))
                if critic == "" or env_id == "FetchPush-v4"
                for seed in seeds or task_seeds]  # fmt: skip
        # PickAndPlace's earlier defaults, one sigma rule for all dimensions: with grasped starts
        # (fresh seeds), and before them (tuning seeds) with and without the twin critic
        summed = ("--total-timesteps", "500000", *every, "--target-std", "1.0")
        nograsp = ("--grasped-start", "0")
        grid += [Run(f"ipg_her_{name}_500k", "ipg_her.py", "FetchPickAndPlace-v4", seed,
                     (*summed, *flags))
                 for name, flags in (("grasped", ()), ("nograsp", nograsp),
                                     ("nograsp_1critic", (*nograsp, *one)))
                 for seed in seeds or ((4, 5, 6) if name == "grasped" else (1, 2, 3))]  # fmt: skip
        # Slide before its annealed learning rates: its defaults then (seeds 4-6, fresh then), and
        # Push's defaults (one sigma rule for all dimensions, the action penalty)
        slide = ("--total-timesteps", "1000000", *every, "--no-anneal-lr")
        grid += [Run("ipg_her_constlr_1000k", "ipg_her.py", "FetchSlide-v4", seed, slide)
                 for seed in seeds or (4, 5, 6)]  # fmt: skip
        grid += [Run("ipg_her_sigma1_1000k", "ipg_her.py", "FetchSlide-v4", seed,
                     (*slide, "--target-std", "1.0", "--action-l2", "1.0", "--bounds-loss", "0.0"))
                 for seed in seeds or (1, 2, 3)]  # fmt: skip
        # mixing asked again with Push's defaults: nu 0.5 and 0.8 against nu = 1 above, 200k; Push's
        # --normalization paper weighs the terms nu sigma_A : (1 - nu), so eq. 10's nu: "_eq10"
        eq10 = ("_eq10", ("--normalization", "unbiased"))
        return grid + [Run(f"ipg_her{kind}_nu{nu}_200k", "ipg_her.py", "FetchPush-v4", seed,
                           ("--total-timesteps", "200000", "--nu", str(nu), *every, *flags))
                       for kind, flags in (("", ()), ("_1critic", one), eq10)
                       for nu in (0.8, 0.5)
                       for seed in seeds or (4, 5, 6)]  # fmt: skip
    else:  # quick
        seeds = seeds or (1,)
        tiny = ("--num-envs", "2", "--num-steps", "128", "--num-minibatches", "4")
        tiny += ("--update-epochs", "2", "--eval-episodes", "1")
        tiny_ipg = ("--total-timesteps", "300", "--critic-steps", "4", "--eval-freq", "100")
        tiny_ipg += ("--eval-episodes", "2")
        grid = [
            hopper("ppo_kl", "ppo_kl.py", "--total-timesteps", "512", *tiny),
            hopper(
                "qprop_ppo",
                "qprop_ppo.py",
                "--total-timesteps",
                "512",
                "--learning-starts",
                "256",
                "--critic-steps",
                "4",
                *tiny,
            ),  # fmt: skip
            fetch(
                "ppo_kl",
                "ppo_kl.py",
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
            ),  # fmt: skip
            fetch("ipg", "ipg_her.py", "--no-her", *tiny_ipg),
            fetch("ipg_her", "ipg_her.py", *tiny_ipg),
        ]
    return [
        Run(name, script, env_id, seed, flags)
        for name, script, env_id, flags, *own_seeds in grid  # a row may name its own seeds
        for seed in (own_seeds[0] if own_seeds else seeds)
    ]


STOPPED, RUNNING, LOCK = [], set(), threading.RLock()  # the signals received, the children
STOP_TIMEOUT = 60.0  # seconds a stopped child has to save and exit before it is killed
LIBC = ctypes.CDLL(None) if sys.platform == "linux" else None


def die_with_runner() -> None:
    """In a child before it starts (Linux): SIGTERM when the runner ends, even by kill -9, so
    that the run stops as on Ctrl-C (saving) rather than going on as an orphan."""
    LIBC.prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


def stop(signum, frame) -> None:
    """Ctrl-C or SIGTERM: no run starts any more, and each running one gets the signal once (its
    own process group keeps the terminal's Ctrl-C from it): its script saves and exits (130 or
    143). A script still running ``STOP_TIMEOUT`` s later, or at a second signal, is killed."""
    with LOCK:
        STOPPED.append(signum)
        for proc in RUNNING:
            proc.send_signal(signum if len(STOPPED) == 1 else signal.SIGKILL)
    if len(STOPPED) == 1:
        timer = threading.Timer(STOP_TIMEOUT, stop, (signal.SIGKILL, None))
        timer.daemon = True  # the runner does not wait for it to end
        timer.start()


def execute(command: list[str], run_dir: str) -> int | None:
    """Run one command with its output kept in ``run_dir``; write and return its exit code (None:
    not started, the suite was stopped). While it runs, its pid is in ``run_dir/pid``."""
    run_dir = Path(run_dir)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with LOCK:  # a stop comes either before (nothing starts) or after (it finds the child)
        if STOPPED:
            return None
        run_dir.mkdir(parents=True, exist_ok=True)
        # appended: an attempt that resumes keeps the output of the one it resumes
        with open(run_dir / "stdout.log", "a") as out, open(run_dir / "stderr.log", "a") as err:
            proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=out, stderr=err,
                                    start_new_session=True,
                                    preexec_fn=die_with_runner if LIBC else None)  # fmt: skip
        RUNNING.add(proc)
        (run_dir / "pid").write_text(f"{proc.pid}\n")
    code = proc.wait()
    with LOCK:
        RUNNING.discard(proc)
    (run_dir / "exit_code").write_text(f"{code}\n")
    (run_dir / "pid").unlink()
    return code


def finished(run_dir: Path) -> bool:
    return (run_dir / "exit_code").exists() and (run_dir / "exit_code").read_text().strip() == "0"


def running(run_dir: Path) -> int | None:
    """The pid of a process still running this run (its runner was killed), or None: the pid
    file names no live process, or (on Linux) one whose command line does not name the run (a
    zombie, or the pid taken by another process since)."""
    try:
        pid = int((run_dir / "pid").read_text())
        os.kill(pid, 0)
        cmdline = Path(f"/proc/{pid}/cmdline")
        return None if cmdline.exists() and run_dir.name not in cmdline.read_text() else pid
    except (OSError, ValueError):
        return None


def fmt(seconds: float) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(seconds))


def main(args: Args) -> int:
    suite_dir = Path(args.out_dir) / args.suite
    runs = suite_runs(args.suite, args.seeds, args.push_steps)
    runs = [r for r in runs if args.only in r.folder]
    todo = [r for r in runs if not finished(suite_dir / r.folder)]
    skipped = len(runs) - len(todo)
    alive = {r: pid for r in todo if (pid := running(suite_dir / r.folder))}
    for r, pid in alive.items():  # a killed runner's run, still stopping: no second copy
        print(f"{r.folder}: still running as pid {pid}; not started again", flush=True)
    todo = [r for r in todo if r not in alive]
    if args.dry_run:
        try:
            for r in todo:
                print(" ".join(r.command(suite_dir / r.folder)))
            print(f"{len(todo)} to run, {skipped} already finished")
            sys.stdout.flush()
        except BrokenPipeError:  # `--dry-run | head`: the reader has what it wanted
            sys.stdout = open(os.devnull, "w")
        return 0
    start, failed, stopped, done = time.time(), [], [], 0
    print(f"suite {args.suite}: {len(todo)} to run, {skipped} already finished, "
          f"{args.workers} workers, backend {args.backend}", flush=True)  # fmt: skip

    def report(run: Run, code: int | None) -> None:
        nonlocal done
        if STOPPED and code != 0:  # stopped by the signal, or never started (None)
            if code is not None:
                stopped.append(run.folder)
            return
        done += 1
        elapsed = time.time() - start
        eta = elapsed / done * (len(todo) - done)
        status = (
            "ok"
            if code == 0
            else f"FAILED (exit {code}; see {suite_dir / run.folder / 'stderr.log'})"
        )
        print(
            f"[{done}/{len(todo)}] {run.folder}: {status}  elapsed {fmt(elapsed)}  ETA {fmt(eta)}",
            flush=True,
        )
        if code != 0:
            failed.append(run.folder)

    if args.backend == "ray":
        try:
            import ray
        except ImportError:
            print("error: --backend ray needs Ray: pip install 'ray[default]'", file=sys.stderr)
            return 2
        # workers import this module from the project folder (the same path on every node)
        ray.init(address=args.ray_address, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}})  # fmt: skip
        sys.path.insert(0, str(ROOT))  # this module by name, as run.py's __main__ won't pickle
        remote = ray.remote(num_cpus=1)(importlib.import_module("benchmarks.run").execute)
        pending = {
            remote.remote(r.command(suite_dir / r.folder), str(suite_dir / r.folder)): r
            for r in todo
        }
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                report(pending.pop(ref), ray.get(ref))
        ray.shutdown()
    else:
        with ThreadPoolExecutor(max_workers=max(args.workers, 1)) as pool:
            futures = {
                pool.submit(execute, r.command(suite_dir / r.folder), str(suite_dir / r.folder)): r
                for r in todo
            }
            for future in as_completed(futures):
                report(futures[future], future.result())
    if STOPPED:
        resumable = sum(any((suite_dir / f).glob("*/resume.pt")) for f in stopped)
        print(f"stopped by {signal.Signals(STOPPED[0]).name}: {done - len(failed)} finished, "
              f"{len(failed)} failed, {len(stopped)} interrupted ({resumable} with a resume "
              f"point), {len(todo) - done - len(stopped)} not started; to resume, run the same "
              f"command again: python {shlex.join(sys.argv)}", flush=True)  # fmt: skip
        return 128 + STOPPED[0]
    print(f"summary: {done - len(failed)} done, {len(failed)} failed, {skipped} skipped, "
          f"{len(alive)} still running, wall time {fmt(time.time() - start)}")  # fmt: skip
    for name in failed:
        print(f"failed: {name}")
    return 1 if failed or alive else 0


def cli() -> int:
    """The command line; Ctrl-C and SIGTERM stop a local suite cleanly (``stop``)."""
    args = tyro.cli(Args)
    if args.backend == "local":
        signal.signal(signal.SIGINT, stop)
        signal.signal(signal.SIGTERM, stop)
    return main(args)


if __name__ == "__main__":
    sys.exit(cli())
