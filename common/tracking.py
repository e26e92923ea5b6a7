"""``--track``: a run in Weights & Biases as CleanRL sends one: ``wandb.init`` before the
TensorBoard writer starts (``sync_tensorboard``: every scalar follows), the run's arguments as its
config, the script's code saved, and the evaluation videos uploaded as they are made.

wandb is optional (``pip install wandb==0.31.0``) and imported only under ``--track``. Without an
account or a network, ``WANDB_MODE=offline`` writes the run's record into ``{log_dir}/wandb``,
for ``wandb sync`` later. A failure of W&B itself (not logged in, no network) is one line, and
the run goes on with TensorBoard alone. A resumed run goes on in its W&B run: the run's id is
read off its folder's name, which a resume keeps.
"""

import contextlib
import hashlib
import os

INSTALL = "pip install wandb==0.31.0"
PROJECT = "mixed-policy-gradients"  # --wandb-project-name's default (CleanRL's: cleanRL)


def refusal(args) -> str | None:
    """Why the ``--track`` flags cannot serve, or None: checked before any run folder exists."""
    if not args.track and (args.wandb_entity is not None or args.wandb_project_name != PROJECT):
        return "--wandb-project-name and --wandb-entity would be ignored without --track"
    if args.track:
        try:
            import wandb  # noqa: F401  (a broken install fails here too, not mid-run)
        except ImportError as e:
            return f"--track needs wandb, which does not import ({e}): {INSTALL}"
    return None


def run_id(run_dir: str) -> str:
    """The W&B id of the run in ``run_dir``: the same for a resumed run, whose folder is its own."""
    return hashlib.sha256(os.path.basename(os.path.normpath(run_dir)).encode()).hexdigest()[:16]


def start(args, run_dir: str):
    """``wandb.init`` for the run in ``run_dir`` (the ``wandb`` module, or None: not tracked, or
    W&B failed, which prints why)."""
    if not args.track:
        return None
    import wandb

    try:
        offline = wandb.setup().settings.mode in ("offline", "dryrun", "disabled")
        if not offline and not wandb.login(prompt=False, verify=False):  # never a prompt
            raise RuntimeError("not logged in: wandb login, or WANDB_API_KEY")
        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=os.path.basename(os.path.normpath(run_dir)),
            id=run_id(run_dir),
            resume="allow",
            dir=args.log_dir,
            save_code=True,
        )
    except Exception as e:  # not logged in, no network, a server refusing: TensorBoard goes on
        with contextlib.suppress(Exception):
            wandb.tensorboard.unpatch()  # the writer as without --track
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        alone = "the run goes on with TensorBoard alone (WANDB_MODE=offline needs no account)"
        print(f"warning: --track: W&B did not start ({first}); {alone}", flush=True)
        return None
    return wandb


def save_videos(tracker, run_dir: str, video_dir: str) -> None:
    """Upload the videos an evaluation recorded into ``video_dir``."""
    if tracker is not None and os.path.isdir(video_dir):
        tracker.save(os.path.join(video_dir, "*.mp4"), base_path=run_dir, policy="now")


def finish(tracker, exit_code: int) -> None:
    """End the W&B run (after the writer's last lines), with the run's exit code."""
    if tracker is not None:
        try:
            tracker.finish(exit_code=exit_code)
        except Exception as e:  # the run's own results are on disk already
            print(f"warning: --track: W&B did not finish ({type(e).__name__})", flush=True)
