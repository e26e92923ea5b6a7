"""PPO with an adaptive KL penalty (paper eq. 5) and GAE (eq. 3-4), for continuous actions.

Docs: README.md, section "PPO-KL". Papers: Schulman et al. 2017, "Proximal Policy Optimization
Algorithms", sec. 4 (the adaptive KL penalty); Schulman et al. 2016 (GAE).

Each iteration collects ``num_envs * num_steps`` transitions with the Gaussian policy, computes
GAE advantages (eq. 4), then runs ``update_epochs`` passes of minibatch Adam on the penalised
surrogate of eq. 5 (negated, since we minimise):

    L(theta) = -E_t[ r_t(theta) A_t ] + beta * E_t[ KL[pi_old(.|s_t) || pi_theta(.|s_t)] ],
    r_t(theta) = pi_theta(a_t|s_t) / pi_old(a_t|s_t).

beta rule (the PPO paper's, sec. 4): after the epochs, with d the batch-mean analytic KL,
``d < kl_target / 1.5 -> beta /= 2`` and ``d > 1.5 kl_target -> beta *= 2``, then beta is kept in
[1/35, 35] as in DPPO (unbounded, a calm stretch halves it towards 0 and one large step then goes
almost unpenalised). Optionally (``--kl-early-stop``) the epochs stop once d exceeds
``kl_early_stop * kl_target``, as in DPPO. The policy's and V's gradients are clipped separately,
so that V's error cannot shrink the policy's step.

Gymnasium 1.x: the vector environment runs in ``AutoresetMode.SAME_STEP``: on the step an
episode ends the returned observation is already the next episode's first one, and the true
final observation is in ``infos["final_obs"]``. V of that final observation bootstraps a
truncated episode (time limit); a terminated one (the hopper fell) does not bootstrap.
Goal tasks (FetchReach) have a Dict observation, flattened here into one policy input.
"""

import os
import random
import sys
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import checkpoint, cli, seeding
from common.gae import compute_gae
from common.normalizer import RunningMeanStd

cli.register_goal_tasks()
torch.distributions.Distribution.set_default_validate_args(False)  # its checks cost ~10% of a run
SCRIPT = os.path.basename(__file__)[: -len(".py")]
BETA_MIN, BETA_MAX = 1 / 35, 35.0  # DPPO's bounds on beta: a calm stretch cannot switch it off


@dataclass
class Args:
    exp_name: str = SCRIPT
    """the name of this experiment (part of the run folder's name)"""
    seed: int = 1
    """the run's seed: every random stream of the run derives from it (common/seeding.py)"""
    torch_deterministic: bool = True
    """sets `torch.backends.cudnn.deterministic` (CleanRL's flag; it only matters on a GPU: CPU
    runs are deterministic for a given seed either way)"""
    capture_video: bool = False
    """record the evaluation episodes as videos into the run folder (needs moviepy)"""
    save_model: bool = False
    """save a checkpoint (weights, normaliser, args) as model.pt in the run folder at the end"""
    save_freq: int = 0
    """with --save-model, also save every this many environment steps (0: only at the end)"""
    log_dir: str = "runs"
    """parent folder of the run folders"""
    eval_freq: int = 100_000
    """evaluate the deterministic (mean) policy every this many env steps (0: only at the end)"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    torch_threads: int = 1
    """torch intra-op threads; one is fastest for these small networks (measured)"""

    # Algorithm specific arguments
    env_id: str = "Hopper-v5"
    """the id of the gymnasium environment"""
    total_timesteps: int = 1_000_000
    """environment steps to train for, counted over all parallel envs"""
    num_envs: int = 4
    """the number of parallel environments"""
    num_steps: int = 512
    """steps per environment per rollout (batch = num_envs * num_steps)"""
    learning_rate: float = 3e-4
    """the learning rate of Adam"""
    anneal_lr: bool = True
    """anneal the learning rate linearly to zero"""
    gamma: float = 0.99
    """the discount factor gamma"""
    gae_lambda: float = 0.95
    """lam of GAE (eq. 4)"""
    num_minibatches: int = 32
    """the number of minibatches per epoch"""
    update_epochs: int = 10
    """passes over the batch per update"""
    norm_adv: bool = True
    """normalise the advantages of a batch to zero mean and unit std"""
    kl_target: float = 0.02
    """d_targ: the mean KL divergence per update the beta rule aims for"""
    beta_init: float = 1.0
    """initial KL penalty coefficient beta (the PPO paper: insensitive)"""
    kl_early_stop: float | None = None
    """stop an update's epochs once the mean KL exceeds this many times kl_target (None: never)"""
    init_log_std: float = -0.5
    """initial log std of the Gaussian policy"""
    vf_coef: float = 0.5
    """coefficient of the value loss"""
    max_grad_norm: float = 0.5
    """the maximum gradient norm, of the policy and of V each (clipped separately)"""
    norm_obs: bool = True
    """normalise observations by running mean and std (saved with the model)"""
    norm_reward: bool = True
    """divide rewards by the running std of the discounted return (training only)"""


def check_args(args: Args) -> None:
    """The checks every script shares (``common/cli.py``); PPO-KL has no others."""
    cli.check_common(args)


# ENV SETUP
def make_env(env_id: str, video_dir: str | None = None):
    def thunk():
        env = gym.make(env_id, render_mode="rgb_array" if video_dir else None)
        if video_dir:
            env = gym.wrappers.RecordVideo(
                env, video_dir, episode_trigger=lambda e: True, disable_logger=True
            )
        if isinstance(env.observation_space, gym.spaces.Dict):  # goal task: one flat policy input
            env = gym.wrappers.FlattenObservation(env)  # [achieved_goal, desired_goal, observation]
        return gym.wrappers.RecordEpisodeStatistics(env)

    return thunk


# ALGO LOGIC: networks
def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """Gaussian policy pi_theta(a|s) = N(mu_theta(s), diag(exp(log_std))^2), baseline V_phi(s)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 64, init_log_std: float = 0.0):
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, 1), std=1.0),
        )  # fmt: skip
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, act_dim), std=0.01),
        )  # fmt: skip
        # state-independent log std
        self.actor_logstd = nn.Parameter(torch.full((1, act_dim), init_log_std))

    def actor_parameters(self) -> list[nn.Parameter]:
        return [*self.actor_mean.parameters(), self.actor_logstd]

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def dist(self, x: torch.Tensor) -> Normal:
        mean = self.actor_mean(x)
        return Normal(mean, self.actor_logstd.expand_as(mean).exp())


# ALGO LOGIC: rollout with the current policy
def collect_rollout(
    envs,
    agent: Agent,
    obs_rms: RunningMeanStd,
    raw_obs: np.ndarray,
    num_steps: int,
    update_obs_rms: bool = True,
):
    """Step the vector env ``num_steps`` times with actions sampled from pi_theta.

    Returns ``(rollout, raw_obs, episodes)``: ``rollout`` holds time-major ``(T, N, ...)`` tensors
    ``obs`` (normalised, as the policy saw them), ``actions``, ``rewards`` (raw), ``terminations``,
    ``episode_ends`` and ``final_obs`` (normalised true last observation where an episode ended at
    step t, zeros elsewhere); ``raw_obs`` is where the envs stopped; ``episodes`` lists the finished
    training episodes as ``(t, env, return, length, success or None)``.
    """
    T, N = num_steps, envs.num_envs
    obs_dim, act_dim = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]
    low, high = envs.single_action_space.low, envs.single_action_space.high
    ro = {"obs": torch.zeros((T, N, obs_dim)), "final_obs": torch.zeros((T, N, obs_dim)),
          "actions": torch.zeros((T, N, act_dim)), "rewards": torch.zeros((T, N)),
          "terminations": torch.zeros((T, N)), "episode_ends": torch.zeros((T, N))}  # fmt: skip
    episodes = []
    for t in range(T):
        if update_obs_rms:
            obs_rms.update(raw_obs)
        ro["obs"][t] = torch.as_tensor(obs_rms.normalize(raw_obs))
        with torch.no_grad():
            ro["actions"][t] = agent.dist(ro["obs"][t]).sample()
        action = ro["actions"][t].numpy()
        next_raw_obs, reward, terminated, truncated, infos = envs.step(np.clip(action, low, high))
        ended = terminated | truncated
        ro["rewards"][t] = torch.as_tensor(reward)
        ro["terminations"][t] = torch.as_tensor(terminated)
        ro["episode_ends"][t] = torch.as_tensor(ended)
        # SAME_STEP autoreset: where an episode ended, next_raw_obs[i] is the next one's first
        for i in np.flatnonzero(ended):
            ro["final_obs"][t, i] = torch.as_tensor(obs_rms.normalize(infos["final_obs"][i]))
            info = infos["final_info"]
            success = float(info["is_success"][i]) if "is_success" in info else None
            episode_return, length = float(info["episode"]["r"][i]), int(info["episode"]["l"][i])
            episodes.append((t, i, episode_return, length, success))
        raw_obs = next_raw_obs
    return ro, raw_obs, episodes


def scale_rewards(
    rewards: torch.Tensor,
    episode_ends: torch.Tensor,
    ret_rms: RunningMeanStd,
    running_return: np.ndarray,
    gamma: float,
) -> torch.Tensor:
    """Divide rewards by the running std of the discounted return (CleanRL's NormalizeReward).

    ``running_return`` (one per env) carries the discounted return across batches; it is reset
    where an episode ends. The statistics are updated with this batch before scaling.
    """
    returns = np.zeros(rewards.shape)
    for t in range(rewards.shape[0]):
        running_return[:] = running_return * gamma + rewards[t].numpy()
        returns[t] = running_return
        running_return[episode_ends[t].numpy() > 0] = 0.0
    ret_rms.update(returns.reshape(-1))
    return rewards / float(np.sqrt(ret_rms.var + 1e-8))


# ALGO LOGIC: advantages by GAE (eq. 3-4), bootstrapping through truncation
def make_batch(
    agent: Agent, ro: dict, last_obs: torch.Tensor, gamma: float, gae_lambda: float
) -> dict:
    """GAE advantages and the pi_old statistics of a rollout, flattened into one batch.

    V(s_{t+1}) is the next row's value within an episode, V(final_obs) where the episode ended at
    step t (masked by the termination flag inside ``compute_gae``), V(last_obs) for the last row.
    """
    with torch.no_grad():
        values = agent.get_value(ro["obs"])
        next_values = torch.cat([values[1:], agent.get_value(last_obs)[None]])
        next_values = torch.where(
            ro["episode_ends"].bool(), agent.get_value(ro["final_obs"]), next_values
        )
        advantages = compute_gae(
            ro["rewards"], values, next_values, ro["terminations"], ro["episode_ends"],
            gamma=gamma, gae_lambda=gae_lambda,
        )  # fmt: skip
        pi_old = agent.dist(ro["obs"])
        act_dim = ro["actions"].shape[-1]
        return {
            "obs": ro["obs"].flatten(0, 1),
            "actions": ro["actions"].flatten(0, 1),
            "logprobs": pi_old.log_prob(ro["actions"]).sum(-1).flatten(),
            "mean": pi_old.mean.reshape(-1, act_dim),
            "std": pi_old.stddev.reshape(-1, act_dim),
            "advantages": advantages.flatten(),
            "returns": (advantages + values).flatten(),
            "next_values": next_values.flatten(),
        }


# ALGO LOGIC: the PPO-KL update (eq. 5)
def ppo_kl_update(
    agent: Agent, optimizer: optim.Optimizer, b: dict, beta: float, args: Args
) -> tuple[float, dict]:
    """``update_epochs`` passes of minibatch Adam on eq. 5, then the beta rule.

    ``b`` holds the flattened batch: obs, actions, logprobs, mean, std (of pi_old), advantages,
    returns. Returns the new beta and the statistics to log.
    """
    batch_size = b["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    adv = b["advantages"]
    if args.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pi_old = Normal(b["mean"], b["std"])
    actor_params, critic_params = agent.actor_parameters(), list(agent.critic.parameters())
    epochs_run = 0
    for epoch in range(args.update_epochs):
        # shuffle once per epoch: the minibatches are then slices (views), not gathers
        perm = torch.randperm(batch_size)
        keys = ("obs", "actions", "logprobs", "mean", "std", "returns")
        shuffled = {key: b[key][perm] for key in keys} | {"adv": adv[perm]}
        for start in range(0, batch_size, minibatch_size):
            mb = {key: v[start : start + minibatch_size] for key, v in shuffled.items()}
            pi = agent.dist(mb["obs"])
            ratio = (pi.log_prob(mb["actions"]).sum(-1) - mb["logprobs"]).exp()  # r_t(theta)
            pi_old_mb = Normal(mb["mean"], mb["std"])
            kl = kl_divergence(pi_old_mb, pi).sum(-1).mean()  # analytic Gaussian KL
            pg_loss = -(ratio * mb["adv"]).mean() + beta * kl  # eq. 5, negated
            v_loss = 0.5 * ((agent.get_value(mb["obs"]) - mb["returns"]) ** 2).mean()
            loss = pg_loss + args.vf_coef * v_loss
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(actor_params, args.max_grad_norm)  # policy and
            nn.utils.clip_grad_norm_(critic_params, args.max_grad_norm)  # V apart
            optimizer.step()
        epochs_run = epoch + 1
        if args.kl_early_stop is not None:
            with torch.no_grad():
                d = kl_divergence(pi_old, agent.dist(b["obs"])).sum(-1).mean().item()
            if d > args.kl_early_stop * args.kl_target:
                break
    with torch.no_grad():
        pi = agent.dist(b["obs"])
        d = (
            kl_divergence(pi_old, pi).sum(-1).mean().item()
        )  # d: mean KL[pi_old || pi] of the update
        entropy = pi.entropy().sum(-1).mean().item()
    stats = {"policy_loss": pg_loss.item(), "value_loss": v_loss.item(), "approx_kl": d,
             "beta": beta, "epochs": epochs_run, "entropy": entropy}  # fmt: skip
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    beta = min(max(beta, BETA_MIN), BETA_MAX)
    return beta, stats


def evaluate(
    agent: Agent,
    obs_rms: RunningMeanStd,
    env_id: str,
    seeds: list[int],
    video_dir: str | None = None,
    stochastic: bool = False,
):
    """Run the deterministic policy a = mu_theta(s) (``stochastic``: a ~ pi_theta), one episode
    per reset seed in ``seeds``, with frozen normaliser statistics.

    Returns the episodic returns and, on goal tasks, the successes (``is_success`` at the end).
    """
    env = make_env(env_id, video_dir)()
    returns, successes = [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            with torch.no_grad():
                x = torch.as_tensor(obs_rms.normalize(obs)[None])
                action = (agent.dist(x).sample() if stochastic else agent.actor_mean(x)).numpy()[0]
            obs, _, terminated, truncated, info = env.step(
                np.clip(action, env.action_space.low, env.action_space.high)
            )
            done = terminated or truncated
        returns.append(info["episode"]["r"])
        if "is_success" in info:
            successes.append(info["is_success"])
    env.close()
    return np.array(returns, np.float64), np.array(successes, np.float64)


if __name__ == "__main__":
    args = cli.parse_args(Args)
    check_args(args)
    batch_size = args.num_envs * args.num_steps
    num_iterations = args.total_timesteps // batch_size
    run_dir, writer = cli.start_run(args)

    # TRY NOT TO MODIFY: seeding, one independent stream per use (common/seeding.py)
    streams = seeding.streams(args.seed, args.num_envs)
    random.seed(streams.global_seed)
    np.random.seed(streams.global_seed)
    torch.manual_seed(streams.torch_seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.torch_threads)

    # ENV SETUP
    envs = gym.vector.SyncVectorEnv(
        [make_env(args.env_id) for _ in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert isinstance(envs.single_action_space, gym.spaces.Box), "only continuous actions"
    obs_dim = envs.single_observation_space.shape[0]
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(streams.action_space_seed)

    # ALGO LOGIC: networks, optimiser, normalisers
    agent = Agent(obs_dim, act_dim, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    obs_rms = RunningMeanStd((obs_dim,))
    ret_rms, running_return = RunningMeanStd(()), np.zeros(args.num_envs)  # reward scaling
    beta = args.beta_init

    # TRY NOT TO MODIFY: start the game
    global_step, train_time, last_eval, last_save, exit_code = 0, 0.0, 0, 0, 0
    eval_seeds, eval_returns, eval_success = [], np.zeros(0), np.zeros(0)
    model_path = os.path.join(run_dir, "model.pt")
    save = lambda: checkpoint.save(
        model_path,
        script=SCRIPT,
        args=args,
        last_eval_seeds=eval_seeds,
        agent=agent,
        obs_rms=obs_rms,
    )
    progress, latest = cli.Progress(args.total_timesteps), ""
    recent_success = []  # is_success of the last 100 training episodes (goal tasks)
    raw_obs, _ = envs.reset(seed=streams.env_seeds)
    try:
        for iteration in range(1, num_iterations + 1):
            t0 = time.time()
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

            # ALGO LOGIC: rollout
            ro, raw_obs, episodes = collect_rollout(
                envs, agent, obs_rms, raw_obs, args.num_steps, update_obs_rms=args.norm_obs
            )

            # TRY NOT TO MODIFY: record rewards for plotting purposes
            for t, _, episodic_return, length, success in episodes:
                step = global_step + (t + 1) * args.num_envs
                writer.add_scalar("charts/episodic_return", episodic_return, step)
                writer.add_scalar("charts/episodic_length", length, step)
                if success is not None:
                    recent_success = (recent_success + [success])[-100:]
                    writer.add_scalar("charts/success_rate", np.mean(recent_success), step)
            global_step += batch_size

            # ALGO LOGIC: advantages (eq. 3-4) on scaled rewards
            if args.norm_reward:
                ro["rewards"] = scale_rewards(
                    ro["rewards"], ro["episode_ends"], ret_rms, running_return, args.gamma
                )
            last_obs = torch.as_tensor(obs_rms.normalize(raw_obs))
            b = make_batch(agent, ro, last_obs, args.gamma, args.gae_lambda)

            # ALGO LOGIC: the PPO-KL update (eq. 5)
            beta, stats = ppo_kl_update(agent, optimizer, b, beta, args)
            if not all(np.isfinite(v) for v in stats.values()):
                raise FloatingPointError(
                    f"a loss became NaN or infinite at global step {global_step}: {stats}"
                )
            train_time += time.time() - t0

            # TRY NOT TO MODIFY: record losses for plotting purposes
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/policy_entropy", stats["entropy"], global_step)
            writer.add_scalar("charts/SPS", int(global_step / train_time), global_step)
            for key in ("policy_loss", "value_loss", "approx_kl", "beta", "epochs"):
                writer.add_scalar(f"losses/{key}", stats[key], global_step)

            # TRY NOT TO MODIFY: evaluate the deterministic policy
            due = args.eval_freq > 0 and global_step - last_eval >= args.eval_freq
            if iteration == num_iterations or due:
                last_eval, eval_seeds = global_step, streams.eval_seeds(args.eval_episodes)
                video_dir = os.path.join(run_dir, "videos", f"step{global_step}")
                eval_returns, eval_success = evaluate(
                    agent,
                    obs_rms,
                    args.env_id,
                    eval_seeds,
                    video_dir if args.capture_video else None,
                )
                writer.add_scalar("eval/episodic_return", eval_returns.mean(), global_step)
                message = f"step={global_step} eval_return={eval_returns.mean():.1f}"
                if len(eval_success):
                    writer.add_scalar("eval/success_rate", eval_success.mean(), global_step)
                    message += f" eval_success={eval_success.mean():.2f}"
                progress.print(f"{message} SPS={int(global_step / train_time)}")
            if args.save_model and args.save_freq and global_step - last_save >= args.save_freq:
                last_save = global_step
                save()
            if episodes:  # the latest training figure: success on goal tasks, else return
                latest = f"success {np.mean(recent_success):.2f}" if recent_success else ""
                latest = latest or f"return {episodes[-1][2]:.1f}"
            progress.update(global_step, int(global_step / train_time), latest)
    except KeyboardInterrupt as interrupt:
        message = f"interrupted at global step {global_step}; logs are kept in {run_dir}"
        progress.print(message, file=sys.stderr)
        exit_code = cli.exit_code(interrupt)
    except FloatingPointError as e:
        print(f"error: {e}", file=sys.stderr)
        exit_code = 1
    finally:
        if args.save_model:
            save()
            progress.print(f"model saved to {model_path}")
        envs.close()
        writer.close()
    progress.close(global_step, eval_returns, eval_success)
    sys.exit(exit_code)
