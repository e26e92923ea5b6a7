"""What no algorithm is about, so that each script holds only its own.

A script's ``Args`` extends ``RunArgs`` (the run fields, here once) and its loop drives a ``Run``:

    run = Run(args)                                   # run folder, TensorBoard, seeded streams
    ...                                               # environments, networks, optimisers
    run.start(envs, model={...}, training={...})      # what is saved; --resume restores it
    if run.resumed:                                   # the envs mid-episode, step and beta
        raw_obs, global_step = run.resumed_obs, run.global_step
        beta = run.restored("beta", args.beta_init)
    else:
        raw_obs, _ = envs.reset(seed=run.streams.env_seeds)
        global_step, beta = 0, args.beta_init
    with run:                                         # Ctrl-C, kill, NaN: a clean end
        for iteration in run.iterations(num_iterations):
            ...                                       # the rollout
            global_step += args.num_envs * args.num_steps
            run.record_episodes(episodes, global_step)
            ...                                       # the update
            run.end_iteration(stats, beta=beta)       # scalars, evaluation, saving, progress

``model`` holds what ``model.pt`` keeps (``agent`` and its input ``normalizer``, which is all a
policy needs, plus any critic); ``training`` what else ``resume.pt`` needs to go on (optimisers,
replay, reward statistics). Keyword values of ``end_iteration`` (``beta``) are scalars saved in
the resume point, which a resumed run takes back with ``restored``.

Evaluation runs the deterministic policy of a snapshot of ``model`` through
``common.evaluate.Policy``, the same code that ``python -m common.evaluate`` runs on a saved
model, in a background process (``--eval-workers 1``) or in this one (``0``). How a run ends
(signals, exit codes, one-line errors) is ``common/stops.py``'s; its folder's lock
``common/lock.py``'s.
"""

import os
import random
import sys
import threading
import time
from dataclasses import dataclass
from typing import NoReturn

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from common import checkpoint, cli, seeding, tasks, tracking
from common.background import BackgroundEvaluator
from common.envs_state import EnvsState
from common.evaluate import evaluate_snapshot
from common.lock import lock
from common.stops import Stops, disk_error, ending, say


@dataclass
class RunArgs:
    exp_name: str = os.path.basename(sys.argv[0]).removesuffix(".py")
    """the name of this experiment (part of the run folder's name; default: the script's name)"""
    seed: int = 1
    """the run's seed: every random stream of the run derives from it (common/seeding.py)"""
    torch_deterministic: bool = True
    """set torch.backends.cudnn.deterministic (CleanRL's flag; CPU runs are deterministic anyway)"""
    torch_threads: int = 1
    """torch intra-op threads; one is fastest for these small networks"""
    log_dir: str = "runs"
    """parent folder of the run folders"""
    eval_freq: int = 100_000
    """evaluate the deterministic (mean) policy every this many env steps (0: only at the end)"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    eval_workers: int = 1
    """evaluate in a background process while training goes on (0: in this process)"""
    capture_video: bool = False
    """record the evaluation episodes as videos into the run folder (needs moviepy)"""
    save_model: bool = False
    """save model.pt (weights, normaliser, args) into the run folder at the end"""
    save_freq: int = 0
    """with --save-model, also save every this many environment steps (0: only at the end)"""
    resume_freq: int = 0
    """write resume.pt every this many env steps and at the end (0: never), for --resume"""
    resume: str | None = None
    """go on with the run in this folder from its resume.pt (same flags; a larger budget extends)"""
    track: bool = False
    """also send the run to Weights & Biases (pip install wandb; WANDB_MODE=offline: no account)"""
    wandb_project_name: str = tracking.PROJECT
    """the W&B project of a tracked run"""
    wandb_entity: str | None = None
    """the W&B entity (team or user) of a tracked run (None: your default)"""


BAR = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"  # the rate: ours, in the postfix


def writer_for(run_dir: str, **kwargs) -> SummaryWriter:
    """The run's TensorBoard writer, its first lines written now: a folder that cannot take them
    (a full disk) is one error line, and the new event file is removed."""
    before = set(os.listdir(run_dir))
    try:
        writer = SummaryWriter(run_dir, **kwargs)
        writer.flush()
        return writer
    except OSError as e:
        for name in set(os.listdir(run_dir)) - before:
            os.remove(os.path.join(run_dir, name))
        cli.fail(f"cannot write in {run_dir}: {e.strerror}")


def quiet_writer_thread(hook) -> None:
    """TensorBoard's writing thread raises a failed write (a full disk) twice: in its own thread
    and in the next ``add_scalar``. The second ends the run with one line; the first is muted."""
    if not issubclass(hook.exc_type, OSError):
        threading.__excepthook__(hook)


def start_run(args) -> str:
    """A new run folder ``{log_dir}/{env_id}__{exp_name}__{seed}__{unix time}`` (a suffix keeps
    two runs started in the same second apart)."""
    run_name = f"{tasks.task_name(args.env_id)}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.join(args.log_dir, run_name)
    for suffix in range(1, 1000):
        try:
            os.makedirs(run_dir)
            break
        except FileExistsError:
            run_dir = os.path.join(args.log_dir, f"{run_name}-{suffix}")
        except OSError as e:
            cli.fail(f"cannot create the run folder in --log-dir {args.log_dir!r}: {e.strerror}")
    print(f"run folder: {run_dir}", flush=True)
    return run_dir


class Run:
    def __init__(self, args):
        self.args, self.resumed = args, None
        if args.resume:  # TensorBoard drops what the interrupted run logged after its resume point
            try:
                self.resumed = checkpoint.load_resume_state(args.resume, args)
            except checkpoint.CheckpointError as e:
                cli.fail(str(e))
            self.dir, self.lock = args.resume, lock(args.resume)
            self.stops = Stops()  # from the moment the run folder is ours
        else:
            self.stops = Stops()  # from the moment the run folder exists
            self.dir = start_run(args)
            self.lock = lock(self.dir)
        threading.excepthook = quiet_writer_thread  # until __exit__
        batch, steps = args.num_envs * args.num_steps, args.total_timesteps
        if steps % batch:  # training runs in whole batches
            print(
                f"--total-timesteps {steps:,}: {steps // batch * batch:,} steps, whole batches "
                f"of {batch:,} (num_envs * num_steps)",
                flush=True,
            )
        # seeding: one independent stream per use (common/seeding.py)
        self.streams = seeding.streams(args.seed, args.num_envs)
        random.seed(self.streams.global_seed)
        np.random.seed(self.streams.global_seed)
        torch.manual_seed(self.streams.torch_seed)
        self.diagnostics_rng = np.random.default_rng(self.streams.diagnostics_seed)
        self.diagnostics_generator = torch.Generator().manual_seed(self.streams.diagnostics_seed)
        torch.backends.cudnn.deterministic = args.torch_deterministic
        torch.set_num_threads(args.torch_threads)
        self.global_step, self.train_time, self.last_eval, self.last_save = 0, 0.0, 0, 0
        self.eval_seeds, self.eval_returns, self.eval_success = [], np.zeros(0), np.zeros(0)
        self.recent_success, self.latest, self.latest_eval, self.scalars = [], "", "no eval yet", {}
        self.first_iteration, self.last_resume, self.start_time = 1, 0, time.time()
        self.model_step, self.last_line = None, time.time()  # model.pt's step, once written

    def start(self, envs, model: dict, training: dict) -> None:
        """Register what is saved; on ``--resume`` restore it all, the environments too: they go
        on mid-episode from ``resumed_obs``, the raw observation they had reached."""
        self.envs, self.model = envs, model
        streams = dict(
            eval_rng=self.streams.eval_rng,
            diagnostics_rng=self.diagnostics_rng,
            diagnostics_generator=self.diagnostics_generator,
        )
        self.parts = model | training | streams
        self.envs_state = EnvsState(envs)
        if self.resumed:
            r, path = self.resumed, os.path.join(self.dir, checkpoint.RESUME_FILE)
            if missing := [name for name in self.parts if name not in r]:
                cli.fail(f"{path} lacks {', '.join(missing)}: not a resume point of this script")
            try:
                for name, part in self.parts.items():
                    checkpoint.restore(part, r[name])
                if "envs" in r:  # the envs go on mid-episode, as if the run had never stopped
                    self.envs_state.load_state_dict(r["envs"])
                    self.resumed_obs = self.envs_state.observations()
            except (KeyError, ValueError, RuntimeError, TypeError) as e:  # another run's
                cli.fail(f"{path} does not fit this run ({type(e).__name__}: {str(e)[:200]})")
            if "envs" not in r:  # a resume point of earlier code: new episodes
                for part in self.parts.values():
                    if hasattr(part, "end_episodes"):
                        part.end_episodes()
                self.resumed_obs, _ = envs.reset(
                    seed=seeding.resume_env_seeds(self.args.seed, self.args.num_envs, r["global_step"])
                )
            checkpoint.set_rng_states(r["rng"])
            self.scalars = r["scalars"]
            self.global_step, self.train_time = r["global_step"], r["train_time"]
            self.last_eval, self.last_save = r["last_eval"], r["last_save"]
            self.eval_seeds, self.recent_success = r["eval_seeds"], r["recent_success"]
            self.first_iteration, self.last_resume = r["iteration"] + 1, self.global_step
            print(f"resuming run folder: {self.dir} after step {self.global_step:,}", flush=True)
        self.tracker = tracking.start(self.args, self.dir)  # before the writer, which it syncs
        if self.resumed:
            self.writer = writer_for(self.dir, purge_step=self.global_step + 1)
        else:  # the hyperparameters as a text table, as CleanRL does
            self.writer = writer_for(self.dir)
            table = "\n".join(f"|{key}|{value}|" for key, value in vars(self.args).items())
            self.writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
        self.evaluator = BackgroundEvaluator(self.args.eval_workers, lambda line: self.print(line, sys.stderr))
        self.progress = tqdm(
            total=self.args.total_timesteps,
            initial=self.global_step,
            unit=" steps",
            disable=not sys.stdout.isatty(),
            dynamic_ncols=True,
            bar_format=BAR,
        )

    def restored(self, name: str, default):
        """The scalar ``name`` (an ``end_iteration`` keyword) as the resume point saved it
        (``default`` if it saved none: a resume point of code before it)."""
        return self.scalars.get(name, default)

    def iterations(self, num_iterations: int):
        self.num_iterations = num_iterations
        for iteration in range(self.first_iteration, num_iterations + 1):
            self.iteration, self.t0 = iteration, time.time()
            yield iteration

    def record_episodes(self, episodes: list, global_step: int) -> None:
        """Log the finished training episodes ``(t, env, return, length, success)`` of the
        rollout that took the run to ``global_step``."""
        num_envs = self.args.num_envs
        for t, _, episodic_return, length, success in episodes:
            step = self.global_step + (t + 1) * num_envs  # the rollout's t-th step
            self.writer.add_scalar("charts/episodic_return", episodic_return, step)
            self.writer.add_scalar("charts/episodic_length", length, step)
            if success is not None:
                self.recent_success = (self.recent_success + [success])[-100:]
                self.writer.add_scalar("charts/success_rate", np.mean(self.recent_success), step)
        if episodes:  # the live line's training figure: success on goal tasks, else return
            self.latest = (  # the stochastic policy's; evaluations take its mean
                f"train success (stochastic) {np.mean(self.recent_success):.2f}"
                if self.recent_success
                else f"train return (stochastic) {episodes[-1][2]:.1f}"
            )
        self.global_step = global_step

    def log(self, scalars: dict) -> None:
        """TensorBoard scalars at the current global step: ``{tag: value}``."""
        for tag, value in scalars.items():
            self.writer.add_scalar(tag, value, self.global_step)

    def end_iteration(self, stats: dict, **scalars) -> None:
        """After the update: the NaN guard on its ``stats`` (``{tag: value}``, logged), the
        evaluation schedule, saving, the resume point and the live line."""
        if not all(np.isfinite(v) for v in stats.values()):
            raise FloatingPointError(
                f"a loss became NaN or infinite at global step {self.global_step}: "
                + ", ".join(f"{k}={v}" for k, v in stats.items() if not np.isfinite(v))
            )
        self.train_time += time.time() - self.t0
        self.scalars |= scalars
        sps = int(self.global_step / self.train_time)  # steps per second of training time
        self.log(stats | {"charts/SPS": sps})
        args, step, last = self.args, self.global_step, self.iteration == self.num_iterations
        resume_due = args.resume_freq > 0 and (step - self.last_resume >= args.resume_freq or last)
        if last or (args.eval_freq > 0 and step - self.last_eval >= args.eval_freq):
            self.last_eval, self.eval_seeds = step, self.streams.eval_seeds(args.eval_episodes)
            video_dir = self.video_dir(step) if args.capture_video else None
            snapshot = checkpoint.state(self.model)
            self.evaluator.submit(step, evaluate_snapshot, snapshot, args.env_id, self.eval_seeds, video_dir)
        for eval_step, (returns, success) in self.evaluator.finished(wait=last or resume_due):
            self.eval_returns, self.eval_success = returns, success
            self.writer.add_scalar("eval/episodic_return", returns.mean(), eval_step)
            message = f"evaluation of step {eval_step:,} (mean policy): eval_return={returns.mean():.1f}"
            self.latest_eval = f"eval return {returns.mean():.1f} @ {eval_step:,}"
            if len(success):
                self.writer.add_scalar("eval/success_rate", success.mean(), eval_step)
                message += f" eval_success={success.mean():.2f}"
                self.latest_eval = f"eval success {success.mean():.2f} @ {eval_step:,}"
            self.print(f"{message} steps/s={sps}")
            tracking.save_videos(self.tracker, self.dir, self.video_dir(eval_step))
        if args.save_model and args.save_freq and step - self.last_save >= args.save_freq:
            self.last_save = step
            self.save()
        if resume_due:
            checkpoint.save_resume_state(
                self.dir,
                args,
                **self.parts,
                envs=self.envs_state,
                rng=checkpoint.rng_states(),
                scalars=self.scalars,
                iteration=self.iteration,
                global_step=step,
                train_time=self.train_time,
                last_eval=self.last_eval,
                last_save=self.last_save,
                recent_success=self.recent_success,
                eval_seeds=self.eval_seeds,
            )
            self.last_resume = step  # once written
        live = f"{sps:,} steps/s | {self.latest} | {self.latest_eval}"  # training time's rate
        self.progress.update(step - self.progress.n)
        self.progress.set_postfix_str(live, refresh=False)
        if self.progress.disable and time.time() - self.last_line >= 30:  # piped: a line a while
            self.last_line = time.time()
            self.print(f"step {step:,} of {args.total_timesteps:,}: {live}")

    def video_dir(self, step: int) -> str:
        return os.path.join(self.dir, "videos", f"step{step}")

    def save(self) -> str:
        """``model.pt``, unless its weights are not finite: a NaN never replaces a good model."""
        path = os.path.join(self.dir, "model.pt")
        if bad := checkpoint.not_finite(checkpoint.state(self.model)):
            raise FloatingPointError(f"the model holds NaN or infinite values ({bad[0]}, ...)")
        checkpoint.save(path, self.args, self.eval_seeds, **self.model)
        self.model_step = self.global_step
        return path

    def print(self, message: str, file=None) -> None:
        """A line above the live one; a closed pipe (``| tee log`` ended) costs nothing else."""
        say(message, file or sys.stdout, self.progress)

    def __enter__(self):
        # Ctrl-C and kill end the run cleanly from here on, through __exit__; a signal held since
        # the run folder appeared stops it now, as mid-run
        if (held := self.stops.raise_from_now()) is not None:
            self.__exit__(type(held), held, None)
        return self

    def __exit__(self, kind, error, traceback) -> NoReturn:
        """Ctrl-C, kill or a closed terminal: logs kept, exit 130, 143 or 129; a NaN loss, a full
        disk or a folder turned read-only: one error line, exit 1. Either way the model is saved
        (``--save-model``, if finite), everything is closed, and the last line names the
        checkpoints on disk. Further signals stay ignored until the process has exited, so that
        its exit's own clean-up (multiprocessing's temporary folder) runs to its end."""
        self.stops.ignore()  # a second Ctrl-C cannot cut the clean-up short
        self.progress.close()  # the bar stays above the closing lines
        self.progress.disable = True
        code, lines = ending(error, self.global_step, self.dir)  # None: a bug (traceback)
        if self.args.save_model and not isinstance(error, FloatingPointError):
            try:
                lines.append(f"model saved to {self.save()}")
            except (OSError, FloatingPointError) as e:
                if code == 1 and isinstance(error, OSError):  # the same fault: one line
                    lines[-1] += "; model.pt not written either"
                else:
                    lines.append(f"error: model.pt not written: {disk_error(e, self.dir)}")
                code = code or 1
        self.evaluator.close(at_once=error is not None)
        self.envs.close()
        try:
            self.writer.close()
        except OSError as e:  # the event file's last lines, on a full disk
            lines.append(f"error: {disk_error(e, self.dir)}")
        tracking.finish(self.tracker, 1 if code is None else code)
        for line in lines:
            say(line, sys.stderr if line.startswith(("error", "interrupted")) else sys.stdout)
        threading.excepthook = threading.__excepthook__
        self.lock.close()
        if code is None:
            self.stops.restore()
            return False
        seconds = time.time() - self.start_time
        summary = f"{'stopped' if code else 'done'}: {self.global_step:,} steps in {seconds:.0f} s"
        if len(self.eval_returns):
            summary += f"; last evaluation: return {self.eval_returns.mean():.1f}"
        if len(self.eval_success):
            summary += f", success {self.eval_success.mean():.2f}"
        say(summary + self.checkpoints(), sys.stdout)
        sys.exit(code)

    def checkpoints(self) -> str:
        """What is on disk to go on from: the last resume point and the model, with their steps."""
        saved = []
        if self.last_resume:  # what --resume takes back: the last resume point, not this step
            saved.append(f"--resume {self.dir} goes on from step {self.last_resume:,}")
        if self.model_step is not None:
            saved.append(f"model.pt of step {self.model_step:,} in {self.dir}")
        return "; " + "; ".join(saved) if saved else ""
