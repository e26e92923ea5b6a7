"""Interpolated Policy Gradient (paper eq. 10) on PPO-KL, with Hindsight Experience Replay (Fig. 2).

Docs: README.md, section "IPG + HER". Papers: Gu et al. 2017, "Interpolated Policy Gradient";
Andrychowicz et al. 2017, "Hindsight Experience Replay"; Schulman et al. 2017 (PPO-KL).

IPG mixes an on-policy likelihood-ratio gradient with an off-policy one through a critic Q_w:

    grad J = (1 - nu) E_{rho^pi, pi}[grad log pi(a|s) A_hat(s, a)]
             + nu E_{s ~ beta}[grad Q_bar_w(s)]                                          (eq. 10)

with Q_bar_w(s) = E_{a ~ pi}[Q_w(s, a)], estimated by Q_w(s, mu_theta(s)) (``--q-bar mean``, the
default: the deterministic policy gradient of eq. 7) or by one reparameterised sample
Q_w(s, mu_theta(s) + sigma_theta eps) (``--q-bar sample``, which also gives sigma a gradient).
The choice matters at nu near 1, where the likelihood-ratio term, the other signal for sigma,
has no weight: with the mean, sigma follows only the KL penalty, whose gradient in log sigma,
1 - (sigma_old^2 + delta^2) / sigma^2, widens sigma whenever the mean moves by delta, so sigma
only grows (FetchReach's entropy rises from 5.7 to about 7 over 30,000 steps; FetchPush's to 13
over 300,000, sigma about 6 on actions bounded to [-1, 1], so that the behaviour policy acts
almost at random). With the sample it falls, but the noisy gradient slows learning (FetchReach:
2,000 steps to 0.9 instead of 1,500 in 5 of 5 seeds, measured). Evaluation uses the mean.
nu = 0 is PPO-KL, nu = 1 is DDPG with a stochastic exploring policy. Here the on-policy part
is PPO-KL's surrogate (eq. 5), so one minibatch loss is

    L = (1 - nu) * -E[r_t(theta) A_t] + nu * -E_{s ~ beta}[Q_w(s, mu_theta(s))]
        + beta_KL * KL[pi_old || pi_theta]

(the KL coefficient is called ``beta`` in the code, as in ``ppo_kl.py``; the state distribution
beta of the paper is ``--off-policy-states``: ``replay``, uniform over the replay buffer, as the
IPG paper found best, or ``batch``, the on-policy states). With ``--use-cv`` the learning signal
becomes A_hat - A_bar, A_bar the Taylor control variate of Q-Prop (eq. 9), and the off-policy
term's weight becomes 1 (IPG's b = 1).

Normalisation (``--normalization``): PPO normalises the likelihood-ratio signal to unit std
sigma, while Q_w stays in return units; left so (``paper``, what the reference code did), the
weight ratio of the two terms is nu sigma / (1 - nu), not nu / (1 - nu), and nu's meaning drifts
with the reward scale. ``unbiased`` (the default) divides the off-policy term by the same sigma,
so that the whole update is a positive multiple of eq. 10 and nu is eq. 10's nu whatever the
reward scale (tests/test_ipg.py checks that scaling rewards and critic by c leaves the update
unchanged). The KL penalty, its bounded beta and the separate gradient clipping of policy and V
are ``ppo_kl.py``'s.

Critic (eq. 6-7): Q_w(s, a) learns off-policy from the replay buffer with the target
r + gamma (1 - terminated) Q_w'(s', mu_theta(s')), using the current policy's mean at s' (no target
policy network), and a soft target update after every critic step (eq. 6). Rewards are stored raw
and scaled at sample time by the same running std that scales GAE's rewards, so critic and GAE
share one scale; the replay stores the action executed (clipped to the bounds). The critic
trains on the new data *before* the policy update, so A_bar and the off-policy term use the
updated critic. On goal tasks the targets are clipped to
[-1/(1-gamma), 0], the returns a 0/-1 reward allows (OpenAI baselines' HER recipe), so that the
critic cannot drift above the best possible return.

HER (Figure 2) enters only through the off-policy parts: the critic learns from relabelled
transitions, and the off-policy term is evaluated at relabelled (state, goal) pairs. The
likelihood-ratio term keeps the real goals: a relabelled on-policy sample is not a sample of the
policy conditioned on the new goal, so using it would need importance weights (Rauber et al.
2019, "Hindsight Policy Gradients"); the off-policy terms need no such correction.

Inputs are normalised by running statistics, observation and goal separately. The replay buffer
stores raw observations and normalises them at sample time with the current statistics, so
stored data never goes stale when the statistics drift; the on-policy batch is normalised once,
when collected, since the policy must be updated on the inputs it acted on.
"""

import copy
import functools
import os
import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import checkpoint, cli, seeding
from common.evaluate import BackgroundEvaluator
from common.gae import compute_gae
from common.her import HerReplayBuffer, ReplayBuffer
from common.normalizer import InputNormalizer, RunningMeanStd

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
    resume_freq: int = 0
    """write resume.pt into the run folder every this many env steps and at the end (0: never):
    everything the run needs to go on after an interruption (see --resume)"""
    resume: str | None = None
    """go on with the run in this run folder from its resume.pt: give the command that started
    it (a larger --total-timesteps extends it). The environments restart with fresh episodes, so
    the run goes on as a valid run, not as the same numbers an uninterrupted one gives"""
    log_dir: str = "runs"
    """parent folder of the run folders"""
    eval_freq: int = 2500
    """evaluate the deterministic (mean) policy every this many env steps (0: only at the end)"""
    eval_episodes: int = 20
    """episodes per evaluation"""
    eval_workers: int = 1
    """evaluate in a background process, so that training goes on meanwhile (0: in this one)"""
    torch_threads: int = 1
    """torch intra-op threads; one is fastest for these small networks (measured)"""
    diagnostics_every: int = 10
    """log the gradient diagnostics ipg/* (norms, effective nu, variances) every this many
    updates (1: every update; 0: never). They draw from a stream of their own: on or off, the
    training is the same"""

    # Algorithm specific arguments
    env_id: str = "FetchReach-v4"
    """the id of the gymnasium environment"""
    total_timesteps: int = 30_000
    """environment steps to train for, counted over all parallel envs"""
    num_envs: int = 2
    """the number of parallel environments"""
    num_steps: int = 50
    """steps per environment per rollout (batch = num_envs * num_steps)"""
    learning_rate: float = 1e-3
    """the learning rate of Adam"""
    anneal_lr: bool = False
    """anneal the learning rate linearly to zero"""
    gamma: float = 0.98
    """the discount factor gamma"""
    gae_lambda: float = 0.95
    """lam of GAE (eq. 4)"""
    num_minibatches: int = 1
    """the number of minibatches per epoch"""
    update_epochs: int = 10
    """passes over the batch per update"""
    norm_adv: bool = True
    """normalise the advantages of a batch to zero mean and unit std"""
    kl_target: float = 0.1
    """d_targ: the mean KL divergence per update the beta rule aims for (0.01, PPO's, held the
    off-policy end back: FetchReach needed 3,000 steps instead of 1,500, measured)"""
    beta_init: float = 1.0
    """initial KL penalty coefficient beta (the PPO paper: insensitive)"""
    kl_early_stop: float | None = None
    """stop an update's epochs once the mean KL exceeds this many times kl_target (None: never)"""
    init_log_std: float = 0.0
    """initial log std of the Gaussian policy"""
    vf_coef: float = 0.5
    """coefficient of the value loss"""
    max_grad_norm: float = 0.5
    """the maximum gradient norm, of the policy and of V each (clipped separately)"""
    hidden: int = 64
    """width of the two hidden layers of every network (128 learned no faster, at twice the cost)"""
    norm_reward: bool = False
    """divide rewards by the running std of the discounted return (GAE and critic alike)"""

    # IPG arguments
    nu: float = 1.0
    """nu of eq. 10: weight of the off-policy term (0: PPO-KL, 1: DDPG-like, stochastic policy)"""
    use_cv: bool = False
    """control variate: learning signal A_hat - A_bar (eq. 9) and off-policy weight 1"""
    off_policy_states: Literal["replay", "batch"] = "replay"
    """the off-policy term's states: uniform from the replay buffer, or the on-policy batch"""
    normalization: Literal["paper", "unbiased"] = "unbiased"
    """normalise the learning signal only (paper, biased) or the off-policy term too (unbiased)"""
    q_bar: Literal["mean", "sample"] = "mean"
    """Q_bar_w(s) as Q_w(s, mu(s)) (mean) or Q_w(s, mu(s) + sigma eps), a reparameterised sample"""
    clip_q_target: bool = True
    """goal tasks with Fetch's 0/-1 reward: clip critic targets to [-1/(1-gamma), 0]"""
    off_policy_batch_size: int = 256
    """replay states per policy minibatch for the off-policy term"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    critic_learning_rate: float = 1e-3
    """the learning rate of the critic Q_w"""
    critic_batch_size: int = 256
    """transitions per critic step"""
    critic_steps: int = 50
    """critic steps per iteration (20 needed 2,000-2,500 steps to 0.9 on FetchReach, 50 1,500)"""
    tau: float = 0.05
    """soft target update rate of eq. 6 (after every critic step)"""
    learning_starts: int = 100
    """environment steps before the critic and the off-policy term start"""

    # HER arguments (goal tasks only)
    her: bool = True
    """relabel replayed transitions with hindsight goals (goal tasks; ignored on others)"""
    her_n_sampled_goal: int = 4
    """k: relabelled transitions per real one (relabelled share 1 - 1/(k+1))"""
    her_goal_selection_strategy: Literal["future", "final", "episode"] = "future"
    """where relabelled goals come from: later in the episode, its end, or anywhere in it"""


def check_args(args: Args, argv: list[str]) -> None:
    """The checks every script shares (``common/cli.py``), then IPG's and HER's."""
    goal_task = cli.check_common(args)
    cli.check_positive(args, "critic_batch_size", "buffer_size", "off_policy_batch_size")
    cli.check_positive(args, "critic_learning_rate")
    if not 0.0 <= args.nu <= 1.0:
        cli.fail(f"--nu must be in [0, 1], got {args.nu}")
    if not 0.0 < args.tau <= 1.0:
        cli.fail(f"--tau must be in (0, 1], got {args.tau}")
    names = ("critic_steps", "learning_starts", "her_n_sampled_goal", "eval_workers", "resume_freq")
    for name in names:
        if getattr(args, name) < 0:
            cli.fail(f"--{name.replace('_', '-')} must be non-negative, got {getattr(args, name)}")
    her_flags = ("--her", "--her-n-sampled-goal", "--her-goal-selection-strategy")
    given = [a.split("=")[0] for a in argv if a.split("=")[0] in her_flags]
    if given and not goal_task:
        cli.fail(f"{given[0]} needs a goal task (Dict observation with desired_goal); "
                 f"{args.env_id} has none")  # fmt: skip


# ENV SETUP
def make_env(env_id: str, video_dir: str | None = None):
    def thunk():
        env = gym.make(env_id, render_mode="rgb_array" if video_dir else None)
        if video_dir:
            env = gym.wrappers.RecordVideo(
                env, video_dir, episode_trigger=lambda e: True, disable_logger=True
            )
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


class QNetwork(nn.Module):
    """Critic Q_w(s, a) of the action the environment executes: ``a`` is clipped to the action
    bounds first, so Q_w is never asked about actions it was not trained on (the targets, the
    off-policy term and the control variate all see the policy's action clipped)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 128, low=-np.inf, high=np.inf):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(),
            nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 1),
        )  # fmt: skip
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).expand(act_dim))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).expand(act_dim))

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        a = torch.clamp(a, self.low, self.high)  # the executed action
        return self.net(torch.cat([x, a], -1)).squeeze(-1)


# ALGO LOGIC: rollout with the current policy
def collect_rollout(
    envs,
    agent: Agent,
    norm: InputNormalizer,
    raw_obs,
    num_steps: int,
    rb: ReplayBuffer,
):
    """Step the vector env ``num_steps`` times with actions sampled from pi_theta; every
    transition also goes raw into the replay buffer ``rb``, with its real next observation.

    Returns ``(rollout, raw_obs, episodes)``: ``rollout`` holds time-major ``(T, N, ...)`` tensors
    ``obs`` (normalised, as the policy saw them), ``actions``, ``rewards`` (raw), ``terminations``,
    ``episode_ends`` and ``final_obs`` (normalised true last observation where an episode ended at
    step t, zeros elsewhere); ``raw_obs`` is where the envs stopped; ``episodes`` lists the finished
    training episodes as ``(t, env, return, length, success or None)``.
    """
    T, N, act_dim = num_steps, envs.num_envs, envs.single_action_space.shape[0]
    low, high = envs.single_action_space.low, envs.single_action_space.high
    input_dim = norm.raw(raw_obs).shape[-1]
    ro = {"obs": torch.zeros((T, N, input_dim)), "final_obs": torch.zeros((T, N, input_dim)),
          "actions": torch.zeros((T, N, act_dim)), "rewards": torch.zeros((T, N)),
          "terminations": torch.zeros((T, N)), "episode_ends": torch.zeros((T, N))}  # fmt: skip
    episodes = []
    for t in range(T):
        norm.update(raw_obs)
        ro["obs"][t] = norm.raw(raw_obs)
        with torch.no_grad():
            ro["actions"][t] = agent.dist(ro["obs"][t]).sample()
        action = ro["actions"][t].numpy()
        executed = np.clip(action, low, high)  # the critic learns Q of the action executed
        next_raw_obs, reward, terminated, truncated, infos = envs.step(executed)
        ended = terminated | truncated
        ro["rewards"][t] = torch.as_tensor(reward)
        ro["terminations"][t] = torch.as_tensor(terminated)
        ro["episode_ends"][t] = torch.as_tensor(ended)
        # SAME_STEP autoreset: where an episode ended, next_raw_obs[i] is the next one's first
        real_next_obs = next_raw_obs
        if ended.any():  # copy only then: most steps end no episode
            real_next_obs = copy.deepcopy(next_raw_obs)
        for i in np.flatnonzero(ended):
            if norm.goal_task:
                for key in real_next_obs:
                    real_next_obs[key][i] = infos["final_obs"][i][key]
            else:
                real_next_obs[i] = infos["final_obs"][i]
            ro["final_obs"][t, i] = norm.raw(infos["final_obs"][i])
            info = infos["final_info"]
            success = float(info["is_success"][i]) if "is_success" in info else None
            episode_return, length = float(info["episode"]["r"][i]), int(info["episode"]["l"][i])
            episodes.append((t, i, episode_return, length, success))
        if norm.goal_task:
            rb.add(
                obs=raw_obs["observation"], actions=executed, rewards=reward,
                next_obs=real_next_obs["observation"], terminations=terminated,
                truncations=truncated, achieved_goal=raw_obs["achieved_goal"],
                next_achieved_goal=real_next_obs["achieved_goal"],
                desired_goal=raw_obs["desired_goal"],
            )  # fmt: skip
        else:
            rb.add(
                obs=raw_obs, actions=executed, rewards=reward, next_obs=real_next_obs,
                terminations=terminated, truncations=truncated,
            )  # fmt: skip
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


def sample_replay(
    rb: ReplayBuffer,
    norm: InputNormalizer,
    reward_scale: float,
    batch_size: int,
    count: int = 1,
    rng: np.random.Generator | None = None,
) -> list[dict]:
    """``count`` (hindsight-relabelled) replay batches as dicts of tensors, inputs normalised and
    rewards scaled by the current statistics.

    The batches come from one draw of ``count * batch_size`` transitions, split: the same
    distribution as ``count`` draws (nothing changes the buffer or the statistics in between),
    at a fraction of the per-call cost. ``rng``: draw from this generator, not the buffer's.
    """
    data = rb.sample(batch_size * count, rng)
    goal = data["desired_goal"] if norm.goal_task else None
    tensors = {
        "obs": norm(data["obs"], goal),
        "next_obs": norm(data["next_obs"], goal),
        "actions": torch.as_tensor(data["actions"]),
        "rewards": torch.as_tensor(data["rewards"] * reward_scale),
        "terminations": torch.as_tensor(data["terminations"]),
    }
    chunks = {key: t.split(batch_size) for key, t in tensors.items()}
    return [{key: chunks[key][i] for key in chunks} for i in range(count)]


def replay_state_batches(rb: ReplayBuffer, norm: InputNormalizer, batch_size: int, count: int):
    """The off-policy term's states s ~ beta: ``count`` replay batches, drawn at the first
    ``next`` (a generator: an update that never asks draws nothing)."""
    for batch in sample_replay(rb, norm, 1.0, batch_size, count):
        yield batch["obs"]


# ALGO LOGIC: the critic step (eq. 6-7)
def critic_step(
    qf: QNetwork,
    qf_target: QNetwork,
    q_optimizer: optim.Optimizer,
    agent: Agent,
    data: dict,
    gamma: float,
    tau: float,
    target_range: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """One step of TD learning on a replay batch ``data``, then the soft target update (eq. 6).

    ``target_range`` clips the targets to the returns the rewards allow (OpenAI baselines' HER
    recipe): a critic that cannot overestimate keeps the off-policy term honest.
    """
    with torch.no_grad():
        next_q = qf_target(data["next_obs"], agent.actor_mean(data["next_obs"]))  # Q_w'(s', mu(s'))
        target = data["rewards"] + gamma * (1.0 - data["terminations"]) * next_q
        if target_range is not None:
            target = target.clamp(*target_range)
    q = qf(data["obs"], data["actions"])
    loss = 0.5 * ((q - target) ** 2).mean()
    q_optimizer.zero_grad()
    loss.backward()
    q_optimizer.step()
    with torch.no_grad():
        for p, p_target in zip(qf.parameters(), qf_target.parameters(), strict=True):
            p_target.lerp_(p, tau)  # w' <- tau w + (1 - tau) w'   (eq. 6)
    return loss.item(), q.mean().item()


def sparse_return_range(compute_reward, goal_dim: int, gamma: float) -> tuple | None:
    """[-1/(1-gamma), 0], the returns Fetch's reward allows (0 where the goal is reached, -1
    elsewhere), if ``compute_reward`` is that reward; None for any other (PointMaze's is 0/+1)."""
    goal = np.zeros((2, goal_dim))
    far = goal + np.array([[0.0], [1e3]])
    rewards = np.asarray(compute_reward(far, goal), np.float64)
    return (-1.0 / (1.0 - gamma), 0.0) if rewards.tolist() == [0.0, -1.0] else None


# ALGO LOGIC: the control variate (eq. 9)
def control_variate(
    qf: QNetwork, agent: Agent, obs: torch.Tensor, actions: torch.Tensor
) -> torch.Tensor:
    """A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))   (eq. 9), no gradient to theta."""
    with torch.no_grad():
        mu = agent.actor_mean(obs)
    mu.requires_grad_(True)
    (grad_q,) = torch.autograd.grad(qf(obs, mu).sum(), mu)
    return (grad_q * (actions - mu)).sum(-1).detach()


# ALGO LOGIC: the IPG update (eq. 10) on the PPO-KL surrogate (eq. 5)
def ipg_update(
    agent: Agent,
    optimizer: optim.Optimizer,
    b: dict,
    beta: float,
    args: Args,
    qf: QNetwork | None = None,
    replay_states: Callable[[], torch.Tensor] | None = None,
) -> tuple[float, dict]:
    """``update_epochs`` passes of minibatch Adam on the interpolated loss with the KL penalty,
    then the beta rule.

    ``b`` is ``ppo_kl.ppo_kl_update``'s batch, with ``cv`` (A_bar) when ``args.use_cv``. The
    off-policy term's states s ~ beta are the minibatch's own (``--off-policy-states batch``) or
    a fresh draw ``replay_states()`` from the replay buffer for each minibatch. With nu = 0 and
    no control variate this is exactly ``ppo_kl_update``. Returns the new beta and the statistics
    to log.
    """
    batch_size = b["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    # A_hat (A_hat - A_bar with the control variate), on the raw scale
    learning_signal = b["advantages"] - b["cv"] if args.use_cv else b["advantages"]
    off_scale, signal_std = 1.0, learning_signal.std()
    if args.norm_adv:
        learning_signal = (learning_signal - learning_signal.mean()) / (signal_std + 1e-8)
        if args.normalization == "unbiased":
            off_scale = 1.0 / (signal_std.item() + 1e-8)  # the same 1/sigma on both terms
    off_weight = 1.0 if args.use_cv else args.nu  # b = 1 with the control variate
    use_off_policy = qf is not None and off_weight > 0
    pi_old = Normal(b["mean"], b["std"])
    on_term, off_term = torch.zeros(()), torch.zeros(())
    epochs_run = 0
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        for start in range(0, batch_size, minibatch_size):
            mb = perm[start : start + minibatch_size]
            pi = agent.dist(b["obs"][mb])
            pi_old_mb = Normal(b["mean"][mb], b["std"][mb])
            kl = kl_divergence(pi_old_mb, pi).sum(-1).mean()  # analytic Gaussian KL
            pg_loss = beta * kl
            if args.nu < 1:  # the likelihood-ratio part, eq. 5's (weight 0 at nu = 1: skipped)
                logratio = pi.log_prob(b["actions"][mb]).sum(-1) - b["logprobs"][mb]
                on_term = -(logratio.exp() * learning_signal[mb]).mean()  # r_t(theta) A
                pg_loss = pg_loss + (1.0 - args.nu) * on_term
            if use_off_policy:
                on_policy = args.off_policy_states == "batch"
                s_off = b["obs"][mb] if on_policy else replay_states()
                a_off = agent.actor_mean(s_off)
                if args.q_bar == "sample":  # a = mu + sigma eps: the gradient reaches sigma too
                    a_off = a_off + agent.actor_logstd.exp() * torch.randn_like(a_off)
                off_term = -qf(s_off, a_off).mean()  # -Q_bar_w(s), s ~ beta (eq. 10)
                pg_loss = pg_loss + off_weight * off_scale * off_term
            v_loss = 0.5 * ((agent.get_value(b["obs"][mb]) - b["returns"][mb]) ** 2).mean()
            loss = pg_loss + args.vf_coef * v_loss
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.actor_parameters(), args.max_grad_norm)  # policy and
            nn.utils.clip_grad_norm_(agent.critic.parameters(), args.max_grad_norm)  # V apart
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
             "beta": beta, "epochs": epochs_run, "entropy": entropy,
             "on_policy_term": on_term.item(), "off_policy_term": off_term.item(),
             "signal_std": signal_std.item()}  # fmt: skip
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    beta = min(max(beta, BETA_MIN), BETA_MAX)
    return beta, stats


# DIAGNOSTICS: what the mixture does (logged as ipg/*; none of it changes the update)
def gradient_diagnostics(
    agent: Agent,
    qf: QNetwork,
    b: dict,
    args: Args,
    off_states: torch.Tensor,
    chunks: int = 4,
    generator: torch.Generator | None = None,
) -> dict:
    """Measured on the batch ``b`` before the update, at theta = theta_old:

    * ``on_grad_norm``, ``off_grad_norm``: norms of the two weighted terms of the update's
      policy gradient, (1 - nu) g_on and b g_off, normalised as the update normalises them, and
      ``effective_nu`` = |off| / (|on| + |off|), the share the off-policy term really has;
    * ``grad_var``, ``grad_var_cv``: the trace of the covariance, over ``chunks`` disjoint random
      chunks of the batch, of the chunk's policy-gradient estimate without the control variate,
      grad log pi A_hat, and with it, grad log pi (A_hat - A_bar) + grad_theta Q_w(s, mu(s))
      (eq. 8 with eta = 1: the same expectation), on the raw advantage scale. Their ratio is
      Q-Prop's claim: below 1 if the control variate reduces variance;
    * ``corr_adv_cv``: the correlation of A_hat with A_bar (eq. 9) over the batch;
    * ``explained_variance``: 1 - Var(R - V) / Var(R) of the baseline V on the batch.

    Its random draws (chunks, Q_bar's sample) come from ``generator``, so that measuring does not
    move the training's random stream.
    """
    params = agent.actor_parameters()

    def grad(loss: torch.Tensor) -> torch.Tensor:
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        return torch.cat([(torch.zeros_like(p) if g is None else g).flatten()
                          for p, g in zip(params, grads, strict=True)])  # fmt: skip

    adv = b["advantages"]
    cv = b["cv"] if "cv" in b else control_variate(qf, agent, b["obs"], b["actions"])
    logp = lambda rows: agent.dist(b["obs"][rows]).log_prob(b["actions"][rows]).sum(-1)  # noqa: E731
    everything = torch.arange(len(adv))
    signal = adv - cv if args.use_cv else adv
    sigma = signal.std() + 1e-8 if args.norm_adv else torch.ones(())
    if args.norm_adv:
        signal = (signal - signal.mean()) / sigma
    g_on = grad(-(logp(everything) * signal).mean())
    a_off = agent.actor_mean(off_states)
    if args.q_bar == "sample":
        a_off = a_off + agent.actor_logstd.exp() * torch.randn(a_off.shape, generator=generator)
    off_scale = 1.0 / sigma if args.normalization == "unbiased" else 1.0  # as the update
    g_off = grad(-qf(off_states, a_off).mean() * off_scale)
    on = (1.0 - args.nu) * g_on.norm().item()
    off = (1.0 if args.use_cv else args.nu) * g_off.norm().item()
    lr_grads, cv_grads = [], []
    for rows in torch.randperm(len(adv), generator=generator).chunk(chunks):
        lr_grads.append(grad(-(logp(rows) * adv[rows]).mean()))
        analytic = -qf(b["obs"][rows], agent.actor_mean(b["obs"][rows])).mean()
        cv_grads.append(grad(-(logp(rows) * (adv[rows] - cv[rows])).mean() + analytic))
    with torch.no_grad():
        values = agent.get_value(b["obs"])
    returns = b["returns"]
    return {
        "on_grad_norm": on,
        "off_grad_norm": off,
        "effective_nu": off / (on + off + 1e-12),
        "grad_var": torch.stack(lr_grads).var(0).sum().item(),
        "grad_var_cv": torch.stack(cv_grads).var(0).sum().item(),
        "corr_adv_cv": torch.corrcoef(torch.stack([adv, cv]))[0, 1].item(),
        "explained_variance": (1 - (returns - values).var() / (returns.var() + 1e-8)).item(),
    }


def evaluate(
    agent: Agent,
    norm: InputNormalizer,
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
                x = norm.raw(obs)[None]
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
    check_args(args, sys.argv[1:])
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    minibatch_steps = args.update_epochs * len(range(0, batch_size, minibatch_size))  # per update
    num_iterations = args.total_timesteps // batch_size
    resumed = None  # the saved state of a run to go on with (--resume)
    if args.resume:
        try:
            resumed = checkpoint.load_resume_state(args.resume, args)
        except checkpoint.CheckpointError as e:
            cli.fail(str(e))
        run_dir, writer = cli.resume_run(args.resume, resumed["global_step"])
    else:
        run_dir, writer = cli.start_run(args)

    # TRY NOT TO MODIFY: seeding, one independent stream per use (common/seeding.py)
    streams = seeding.streams(args.seed, args.num_envs)
    random.seed(streams.global_seed)
    np.random.seed(streams.global_seed)
    torch.manual_seed(streams.torch_seed)
    diagnostics_rng = np.random.default_rng(streams.diagnostics_seed)  # their own stream
    diagnostics_generator = torch.Generator().manual_seed(streams.diagnostics_seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.torch_threads)

    # ENV SETUP
    envs = gym.vector.SyncVectorEnv(
        [make_env(args.env_id) for _ in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert isinstance(envs.single_action_space, gym.spaces.Box), "only continuous actions"
    space = envs.single_observation_space
    goal_task = isinstance(space, gym.spaces.Dict)
    obs_dim = space["observation"].shape[0] if goal_task else space.shape[0]
    goal_dim = space["desired_goal"].shape[0] if goal_task else 0
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(streams.action_space_seed)

    # ALGO LOGIC: networks, optimisers, normalisers, replay
    norm = InputNormalizer(obs_dim, goal_dim)
    agent = Agent(obs_dim + goal_dim, act_dim, hidden=args.hidden, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    low, high = envs.single_action_space.low, envs.single_action_space.high
    qf = QNetwork(obs_dim + goal_dim, act_dim, hidden=args.hidden, low=low, high=high)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    q_range = None  # the returns the reward allows, for clipping the critic's targets
    if goal_task:  # hindsight relabelling needs the task's reward function
        reward_env = gym.make(args.env_id)  # gymnasium 1.x wrappers do not forward attributes
        compute_reward = lambda ag, g: reward_env.unwrapped.compute_reward(ag, g, None)
        if args.clip_q_target:
            q_range = sparse_return_range(compute_reward, goal_dim, args.gamma)
        rb = HerReplayBuffer(
            args.buffer_size, args.num_envs, obs_dim, act_dim, goal_dim,
            compute_reward=compute_reward,
            n_sampled_goal=args.her_n_sampled_goal if args.her else 0,
            goal_selection_strategy=args.her_goal_selection_strategy, seed=streams.replay_seed,
        )  # fmt: skip
    else:
        rb = ReplayBuffer(
            args.buffer_size, args.num_envs, obs_dim, act_dim, seed=streams.replay_seed
        )
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
        normalizer=norm,
        qf=qf,
        qf_target=qf_target,
    )
    evaluator = BackgroundEvaluator(args.eval_workers)
    progress, latest = cli.Progress(args.total_timesteps), ""
    recent_success = []  # is_success of the last 100 training episodes (goal tasks)
    # everything --resume-freq saves, besides the counters and the global random states
    parts = dict(agent=agent, optimizer=optimizer, qf=qf, qf_target=qf_target,
                 q_optimizer=q_optimizer, norm=norm, ret_rms=ret_rms, rb=rb,
                 eval_rng=streams.eval_rng, diagnostics_rng=diagnostics_rng,
                 diagnostics_generator=diagnostics_generator)  # fmt: skip
    first_iteration, last_resume, reset_seeds = 1, 0, streams.env_seeds
    if resumed:
        for name, part in parts.items():
            checkpoint.restore(part, resumed[name])
        checkpoint.set_rng_states(resumed["rng"])
        beta, iteration, global_step = resumed["beta"], resumed["iteration"], resumed["global_step"]
        train_time, last_eval = resumed["train_time"], resumed["last_eval"]
        last_save, eval_seeds = resumed["last_save"], resumed["eval_seeds"]
        recent_success = resumed["recent_success"]
        first_iteration, last_resume = iteration + 1, global_step
        rb.end_episodes()  # the envs restart with new episodes: the unfinished ones end here
        reset_seeds = seeding.resume_env_seeds(args.seed, args.num_envs, global_step)
    raw_obs, _ = envs.reset(seed=reset_seeds)
    try:
        for iteration in range(first_iteration, num_iterations + 1):
            t0 = time.time()
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

            # ALGO LOGIC: rollout
            ro, raw_obs, episodes = collect_rollout(envs, agent, norm, raw_obs, args.num_steps, rb)

            # TRY NOT TO MODIFY: record rewards for plotting purposes
            for t, _, episodic_return, length, success in episodes:
                step = global_step + (t + 1) * args.num_envs
                writer.add_scalar("charts/episodic_return", episodic_return, step)
                writer.add_scalar("charts/episodic_length", length, step)
                if success is not None:
                    recent_success = (recent_success + [success])[-100:]
                    writer.add_scalar("charts/success_rate", np.mean(recent_success), step)
            global_step += batch_size

            # ALGO LOGIC: one reward scale for GAE and the critic
            reward_scale = 1.0
            if args.norm_reward:
                ro["rewards"] = scale_rewards(
                    ro["rewards"], ro["episode_ends"], ret_rms, running_return, args.gamma
                )
                reward_scale = float(1.0 / np.sqrt(ret_rms.var + 1e-8))

            # ALGO LOGIC: the critic first (eq. 6-7), so that A_bar and the off-policy term see
            # the new data
            learning = global_step >= args.learning_starts and rb.num_sampleable() > 0
            if learning and args.critic_steps > 0:
                batches = sample_replay(
                    rb, norm, reward_scale, args.critic_batch_size, count=args.critic_steps
                )
                for data in batches:
                    critic_loss, q_values = critic_step(
                        qf, qf_target, q_optimizer, agent, data,
                        gamma=args.gamma, tau=args.tau,
                        target_range=None if q_range is None else (q_range[0] * reward_scale, 0.0),
                    )  # fmt: skip
                writer.add_scalar("losses/critic_loss", critic_loss, global_step)
                writer.add_scalar("losses/q_values", q_values, global_step)

            # ALGO LOGIC: advantages (eq. 3-4) and the control variate (eq. 9)
            b = make_batch(agent, ro, norm.raw(raw_obs), args.gamma, args.gae_lambda)
            if args.use_cv:
                b["cv"] = control_variate(qf, agent, b["obs"], b["actions"])

            # DIAGNOSTICS: gradient norms and variances before the update (ipg/*)
            diagnostics = {}
            every = args.diagnostics_every
            if every > 0 and (iteration - 1) % every == 0 and learning:
                off_states = b["obs"]
                if args.off_policy_states == "replay":
                    off_states = sample_replay(
                        rb, norm, 1.0, args.off_policy_batch_size, rng=diagnostics_rng
                    )[0]["obs"]
                diagnostics = gradient_diagnostics(
                    agent, qf, b, args, off_states, generator=diagnostics_generator
                )

            # ALGO LOGIC: the IPG update (eq. 10 on eq. 5)
            states = replay_state_batches(rb, norm, args.off_policy_batch_size, minibatch_steps)
            replay_states = functools.partial(next, states)
            beta, stats = ipg_update(
                agent, optimizer, b, beta, args, qf=qf if learning else None,
                replay_states=replay_states,
            )  # fmt: skip
            if not all(np.isfinite(v) for v in stats.values()):
                raise FloatingPointError(
                    f"a loss became NaN or infinite at global step {global_step}: {stats}"
                )
            train_time += time.time() - t0

            # TRY NOT TO MODIFY: record losses for plotting purposes
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/policy_entropy", stats["entropy"], global_step)
            writer.add_scalar("charts/SPS", int(global_step / train_time), global_step)
            for key in ("policy_loss", "value_loss", "approx_kl", "beta"):
                writer.add_scalar(f"losses/{key}", stats[key], global_step)
            writer.add_scalar("ipg/nu", args.nu, global_step)
            writer.add_scalar("ipg/on_policy_term", stats["on_policy_term"], global_step)
            writer.add_scalar("ipg/off_policy_term", stats["off_policy_term"], global_step)
            writer.add_scalar("ipg/signal_std", stats["signal_std"], global_step)
            if args.use_cv:
                writer.add_scalar("ipg/cv_mean", b["cv"].mean().item(), global_step)
            for key, value in diagnostics.items():
                writer.add_scalar(f"ipg/{key}", value, global_step)

            # TRY NOT TO MODIFY: evaluate the deterministic policy (a snapshot of it, in the
            # background with --eval-workers 1: training goes on meanwhile)
            due = args.eval_freq > 0 and global_step - last_eval >= args.eval_freq
            resume_due = args.resume_freq > 0 and (
                global_step - last_resume >= args.resume_freq or iteration == num_iterations
            )
            if iteration == num_iterations or due:
                last_eval, eval_seeds = global_step, streams.eval_seeds(args.eval_episodes)
                video_dir = os.path.join(run_dir, "videos", f"step{global_step}")
                evaluator.submit(
                    global_step, evaluate, agent, norm, args.env_id, eval_seeds,
                    video_dir if args.capture_video else None,
                )  # fmt: skip
            for step, (eval_returns, eval_success) in evaluator.finished(
                wait=iteration == num_iterations or resume_due  # resume.pt: no evaluation lost
            ):
                writer.add_scalar("eval/episodic_return", eval_returns.mean(), step)
                message = f"step={step} eval_return={eval_returns.mean():.1f}"
                if len(eval_success):
                    writer.add_scalar("eval/success_rate", eval_success.mean(), step)
                    message += f" eval_success={eval_success.mean():.2f}"
                progress.print(f"{message} SPS={int(global_step / train_time)}")
            if args.save_model and args.save_freq and global_step - last_save >= args.save_freq:
                last_save = global_step
                save()
            if resume_due:
                last_resume = global_step
                checkpoint.save_resume_state(
                    run_dir, args, **parts, rng=checkpoint.rng_states(), beta=beta,
                    iteration=iteration, global_step=global_step, train_time=train_time,
                    last_eval=last_eval, last_save=last_save, recent_success=recent_success,
                    eval_seeds=eval_seeds,
                )  # fmt: skip
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
        evaluator.close()
        envs.close()
        writer.close()
    progress.close(global_step, eval_returns, eval_success)
    sys.exit(exit_code)
