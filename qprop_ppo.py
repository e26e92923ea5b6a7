"""Q-Prop (paper eq. 6-9) with a PPO-KL on-policy part (eq. 5) and a DDPG-style critic.

Docs: README.md, section "Q-Prop". Papers: Gu et al. 2017, "Q-Prop: Sample-Efficient Policy
Gradient with an Off-Policy Critic"; Tucker et al. 2018, "The Mirage of Action-Dependent
Baselines" (the normalisation bias); Schulman et al. 2017 (PPO-KL).

Q-Prop subtracts from the Monte Carlo advantage A_hat a control variate built from an off-policy
critic Q_w, and adds back its expectation analytically, so the gradient stays unbiased:

    A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))                           (eq. 9)
    grad J = E[grad log pi(a|s) (A_hat - eta A_bar)]
             + E[eta grad_a Q_w(s, a)|_{a = mu(s)} grad_theta mu(s)]                     (eq. 8)

A_bar has mean zero under pi (it is linear in a - mu), and the second term is the deterministic
policy gradient of eq. 7, which is the gradient of eta * Q_w(s, mu_theta(s)). Inside PPO-KL one
minibatch loss is

    L = -E[r_t(theta) (A_hat_t - eta_t A_bar_t)] - E[eta_t Q_w(s_t, mu_theta(s_t))]
        + beta * KL[pi_old || pi_theta]

eta (``--eta-mode``): the optimal eta is Cov(A_hat, A_bar) / Var(A_bar). ``batch-conservative``
(the default) takes eta = 1 for the whole batch if the batch covariance of A_hat and A_bar is
positive, else 0; ``batch-aggressive`` takes its sign. One eta per batch keeps eq. 8 unbiased up
to the finite-batch estimate of that sign. The paper's own modes decide per sample:
``conservative`` eta_t = 1 where A_hat_t A_bar_t > 0, else 0; ``aggressive``
eta_t = sign(A_hat_t A_bar_t). They are kept because they are what Gu et al. ran, but eta_t then
depends on the sampled action, so E[grad log pi eta_t A_bar_t] is no longer the analytic term:
the per-sample modes are *biased* (tests/test_qprop.py measures it). ``ones``: eta = 1;
``none``: eta = 0, which is exactly PPO-KL (``ppo_kl.py``).

Normalisation (``--normalization``): PPO normalises the learning signal A_hat - eta A_bar by its
std sigma. The original Q-Prop code did that and left the analytic term alone (``paper``), which
multiplies the analytic term's weight by sigma relative to the likelihood-ratio term: the
gradient is then biased (Tucker et al. 2018 showed that this bias, not the control variate, was
what beat TRPO). ``unbiased`` divides the analytic term by the same sigma, so that the update is
a positive multiple of eq. 8's estimator (unbiased with a per-batch or constant eta).

Critic (eq. 6-7): Q_w(s, a) learns off-policy from the replay buffer with the target
r + gamma (1 - terminated) Q_w'(s', mu_theta(s')), using the current policy's mean at s' (no target
policy network), and a soft target update after every critic step (eq. 6). Rewards are stored raw
and scaled at sample time by the same running std that scales GAE's rewards, so critic and GAE
share one scale; the replay stores the action executed (clipped to the bounds). The critic
trains on the new data *before* the policy update, so A_bar, eta and the analytic term use the
updated critic (Q-Prop's Algorithm 1).

The likelihood ratio and A_bar keep the sampled action (A_bar must stay linear in the sampled
action to have mean zero). The rest is ``ppo_kl.py``'s: the KL penalty with its bounded beta, the
separate gradient clipping of policy and V, SAME_STEP autoreset with true final observations,
truncation bootstrapped; goal tasks flattened into one input (no hindsight relabelling here).
"""

import copy
import os
import random
import sys
import time
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import checkpoint, cli, seeding
from common.gae import compute_gae
from common.her import ReplayBuffer
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
    """divide rewards by the running std of the discounted return (GAE and critic alike)"""

    # Q-Prop arguments
    eta_mode: Literal[
        "batch-conservative", "batch-aggressive", "conservative", "aggressive", "ones", "none"
    ] = "batch-conservative"
    """control-variate weight eta: from the batch covariance (unbiased), per sample (the paper's,
    biased), 1, or none (= PPO-KL)"""
    normalization: Literal["paper", "unbiased"] = "unbiased"
    """normalise the learning signal only (paper, biased) or the analytic term with it (unbiased)"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    critic_learning_rate: float = 1e-3
    """the learning rate of the critic Q_w"""
    critic_batch_size: int = 256
    """transitions per critic step"""
    critic_steps: int = 256
    """critic steps per iteration"""
    critic_hidden: int = 100
    """width of the critic's two hidden layers"""
    tau: float = 0.005
    """soft target update rate of eq. 6 (after every critic step)"""
    learning_starts: int = 1000
    """environment steps before the first critic step; the control variate starts with it"""


def check_args(args: Args) -> None:
    """The checks every script shares (``common/cli.py``), then the critic's."""
    cli.check_common(args)
    cli.check_positive(args, "critic_batch_size", "buffer_size", "critic_learning_rate")
    if not 0.0 < args.tau <= 1.0:
        cli.fail(f"--tau must be in (0, 1], got {args.tau}")
    if args.critic_steps < 0 or args.learning_starts < 0:
        cli.fail("--critic-steps and --learning-starts must be non-negative")


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


class QNetwork(nn.Module):
    """Critic Q_w(s, a) of the action the environment executes: ``a`` is clipped to the action
    bounds first, so Q_w is never asked about actions it was not trained on (the targets, the
    control variate and the analytic term all see the policy's action clipped). The action
    joins after the first layer, as in the Q-Prop code."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 100, low=-np.inf, high=np.inf):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, hidden)
        self.fc2 = nn.Linear(hidden + act_dim, hidden)
        self.out = nn.Linear(hidden, 1)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).expand(act_dim))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).expand(act_dim))

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.fc1(x))
        a = torch.clamp(a, self.low, self.high)  # the executed action
        return self.out(torch.relu(self.fc2(torch.cat([h, a], -1)))).squeeze(-1)


# ALGO LOGIC: rollout with the current policy
def collect_rollout(
    envs,
    agent: Agent,
    obs_rms: RunningMeanStd,
    raw_obs: np.ndarray,
    num_steps: int,
    rb: ReplayBuffer,
    update_obs_rms: bool = True,
):
    """Step the vector env ``num_steps`` times with actions sampled from pi_theta; every
    transition also goes raw into the replay buffer ``rb``, with its real next observation.

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
        executed = np.clip(action, low, high)  # the critic learns Q of the action executed
        next_raw_obs, reward, terminated, truncated, infos = envs.step(executed)
        ended = terminated | truncated
        ro["rewards"][t] = torch.as_tensor(reward)
        ro["terminations"][t] = torch.as_tensor(terminated)
        ro["episode_ends"][t] = torch.as_tensor(ended)
        real_next_obs = next_raw_obs.copy()
        # SAME_STEP autoreset: where an episode ended, next_raw_obs[i] is the next one's first
        for i in np.flatnonzero(ended):
            real_next_obs[i] = infos["final_obs"][i]
            ro["final_obs"][t, i] = torch.as_tensor(obs_rms.normalize(infos["final_obs"][i]))
            info = infos["final_info"]
            success = float(info["is_success"][i]) if "is_success" in info else None
            episode_return, length = float(info["episode"]["r"][i]), int(info["episode"]["l"][i])
            episodes.append((t, i, episode_return, length, success))
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
    rb: ReplayBuffer, obs_rms: RunningMeanStd, reward_scale: float, batch_size: int
) -> dict:
    """A replay batch as tensors, inputs normalised and rewards scaled by the current statistics."""
    data = rb.sample(batch_size)
    return {
        "obs": torch.as_tensor(obs_rms.normalize(data["obs"])),
        "next_obs": torch.as_tensor(obs_rms.normalize(data["next_obs"])),
        "actions": torch.as_tensor(data["actions"]),
        "rewards": torch.as_tensor(data["rewards"] * reward_scale),
        "terminations": torch.as_tensor(data["terminations"]),
    }


# ALGO LOGIC: the critic step (eq. 6-7)
def critic_step(
    qf: QNetwork,
    qf_target: QNetwork,
    q_optimizer: optim.Optimizer,
    agent: Agent,
    data: dict,
    gamma: float,
    tau: float,
) -> tuple[float, float]:
    """One step of TD learning on a replay batch ``data``, then the soft target update (eq. 6)."""
    with torch.no_grad():
        next_q = qf_target(data["next_obs"], agent.actor_mean(data["next_obs"]))  # Q_w'(s', mu(s'))
        target = data["rewards"] + gamma * (1.0 - data["terminations"]) * next_q
    q = qf(data["obs"], data["actions"])
    loss = 0.5 * ((q - target) ** 2).mean()
    q_optimizer.zero_grad()
    loss.backward()
    q_optimizer.step()
    with torch.no_grad():
        for p, p_target in zip(qf.parameters(), qf_target.parameters(), strict=True):
            p_target.lerp_(p, tau)  # w' <- tau w + (1 - tau) w'   (eq. 6)
    return loss.item(), q.mean().item()


# ALGO LOGIC: the control variate (eq. 9) and its weight eta
def control_variate(
    qf: QNetwork, agent: Agent, obs: torch.Tensor, actions: torch.Tensor
) -> torch.Tensor:
    """A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))   (eq. 9), no gradient to theta."""
    with torch.no_grad():
        mu = agent.actor_mean(obs)
    mu.requires_grad_(True)
    (grad_q,) = torch.autograd.grad(qf(obs, mu).sum(), mu)
    return (grad_q * (actions - mu)).sum(-1).detach()


def compute_eta(advantages: torch.Tensor, cv: torch.Tensor, mode: str) -> torch.Tensor:
    """eta_t for every sample of the batch.

    Q-Prop's optimal eta is Cov(A_hat, A_bar) / Var(A_bar). ``batch-conservative`` (eta = 1 if
    the batch covariance is positive, else 0) and ``batch-aggressive`` (eta = its sign) fix one
    eta for the whole batch, which keeps eq. 8 unbiased up to the finite-batch estimate of that
    sign. The paper's ``conservative`` (eta_t = 1 where A_hat_t A_bar_t > 0) and ``aggressive``
    (eta_t = sign(A_hat_t A_bar_t)) decide per sample: eta_t then depends on the sampled action,
    E[grad log pi eta_t A_bar_t] is no longer the analytic term, and the gradient is biased.
    """
    if mode.startswith("batch-"):
        cov = batch_covariance(advantages, cv)
        eta = 1.0 if cov > 0 else (-1.0 if mode == "batch-aggressive" else 0.0)
        return torch.full_like(advantages, eta)
    if mode == "conservative":
        return (advantages * cv > 0).float()  # use the control variate only where it correlates
    if mode == "aggressive":
        return torch.sign(advantages * cv)  # flip it where it anti-correlates
    return torch.full_like(advantages, 1.0 if mode == "ones" else 0.0)


def batch_covariance(x: torch.Tensor, y: torch.Tensor) -> float:
    return ((x - x.mean()) * (y - y.mean())).mean().item()


def qprop_surrogate(
    agent: Agent,
    qf: QNetwork,
    pi: Normal,
    obs: torch.Tensor,
    actions: torch.Tensor,
    logprobs_old: torch.Tensor,
    learning_signal: torch.Tensor,
    eta: torch.Tensor,
    analytic_scale: float = 1.0,
) -> torch.Tensor:
    """The Q-Prop objective of eq. 8 as a loss:

        -E[r_t (A_hat - eta A_bar)] - analytic_scale E[eta Q_w(s, mu_theta(s))]

    ``learning_signal`` is the (possibly normalised) A_hat - eta A_bar and ``pi`` is
    ``agent.dist(obs)``. At theta = theta_old the gradient of the first term is
    -E[grad log pi * learning_signal], that of the second the deterministic policy gradient
    (eq. 7).
    """
    ratio = (pi.log_prob(actions).sum(-1) - logprobs_old).exp()  # r_t(theta)
    loss = -(ratio * learning_signal).mean()
    if torch.any(eta != 0):  # the analytic term of eq. 8
        loss = loss - analytic_scale * (eta * qf(obs, agent.actor_mean(obs))).mean()
    return loss


# DIAGNOSTICS: does the control variate reduce variance? (logged as qprop/*; changes nothing)
def gradient_variance(agent: Agent, qf: QNetwork, b: dict, chunks: int = 8) -> dict:
    """Q-Prop's claim, measured on the batch ``b`` at theta = theta_old: the trace of the
    covariance, over ``chunks`` disjoint random chunks, of the chunk's policy-gradient estimate
    without the control variate, grad log pi A_hat, and with it at eta = 1, grad log pi
    (A_hat - A_bar) + grad_theta Q_w(s, mu(s)) (eq. 8: the same expectation); also the
    correlation of A_hat with A_bar and the explained variance 1 - Var(R - V) / Var(R) of V."""
    params = agent.actor_parameters()

    def grad(loss: torch.Tensor, retain_graph: bool = False) -> torch.Tensor:
        grads = torch.autograd.grad(loss, params, retain_graph=retain_graph, allow_unused=True)
        return torch.cat([(torch.zeros_like(p) if g is None else g).flatten()
                          for p, g in zip(params, grads, strict=True)])  # fmt: skip

    adv, cv, obs = b["advantages"], b["cv"], b["obs"]
    lr_grads, cv_grads = [], []
    for rows in torch.randperm(len(adv)).chunk(chunks):
        logp = agent.dist(obs[rows]).log_prob(b["actions"][rows]).sum(-1)
        lr_grads.append(grad(-(logp * adv[rows]).mean(), retain_graph=True))
        analytic = -qf(obs[rows], agent.actor_mean(obs[rows])).mean()
        cv_grads.append(grad(-(logp * (adv[rows] - cv[rows])).mean() + analytic))
    with torch.no_grad():
        values = agent.get_value(obs)
    returns = b["returns"]
    return {
        "grad_var": torch.stack(lr_grads).var(0).sum().item(),
        "grad_var_cv": torch.stack(cv_grads).var(0).sum().item(),
        "corr_adv_cv": torch.corrcoef(torch.stack([adv, cv]))[0, 1].item(),
        "explained_variance": (1 - (returns - values).var() / (returns.var() + 1e-8)).item(),
    }


# ALGO LOGIC: the Q-Prop update: PPO-KL (eq. 5) with the control variate (eq. 8)
def qprop_update(
    agent: Agent,
    optimizer: optim.Optimizer,
    b: dict,
    beta: float,
    args: Args,
    qf: QNetwork | None = None,
) -> tuple[float, dict]:
    """``update_epochs`` passes of minibatch Adam on the Q-Prop loss with the KL penalty, then
    the beta rule.

    ``b`` is ``ppo_kl.ppo_kl_update``'s batch, with ``cv`` (A_bar) and ``eta`` when a critic is
    in use. Without a critic, or with eta = 0 everywhere, this is exactly ``ppo_kl_update``.
    Returns the new beta and the statistics to log.
    """
    batch_size = b["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    use_cv = qf is not None and args.eta_mode != "none"
    eta = b["eta"] if use_cv else torch.zeros_like(b["advantages"])
    # A_hat - eta A_bar, on the raw scale
    learning_signal = b["advantages"] - eta * b["cv"] if use_cv else b["advantages"]
    analytic_scale, signal_std = 1.0, learning_signal.std()
    if args.norm_adv:
        learning_signal = (learning_signal - learning_signal.mean()) / (signal_std + 1e-8)
        if args.normalization == "unbiased":
            analytic_scale = 1.0 / (signal_std.item() + 1e-8)  # the same 1/sigma on both terms
    pi_old = Normal(b["mean"], b["std"])
    epochs_run = 0
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        for start in range(0, batch_size, minibatch_size):
            mb = perm[start : start + minibatch_size]
            pi = agent.dist(b["obs"][mb])
            surrogate = qprop_surrogate(
                agent, qf, pi, obs=b["obs"][mb], actions=b["actions"][mb],
                logprobs_old=b["logprobs"][mb], learning_signal=learning_signal[mb],
                eta=eta[mb], analytic_scale=analytic_scale,
            )  # fmt: skip
            pi_old_mb = Normal(b["mean"][mb], b["std"][mb])
            kl = kl_divergence(pi_old_mb, pi).sum(-1).mean()  # analytic Gaussian KL
            pg_loss = surrogate + beta * kl  # eq. 8 inside eq. 5, negated
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
             "signal_std": signal_std.item()}  # fmt: skip
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

    # ALGO LOGIC: networks, optimisers, normalisers, replay
    agent = Agent(obs_dim, act_dim, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    obs_rms = RunningMeanStd((obs_dim,))
    low, high = envs.single_action_space.low, envs.single_action_space.high
    qf = QNetwork(obs_dim, act_dim, args.critic_hidden, low=low, high=high)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    rb = ReplayBuffer(args.buffer_size, args.num_envs, obs_dim, act_dim, seed=streams.replay_seed)
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
        qf=qf,
        qf_target=qf_target,
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
                envs, agent, obs_rms, raw_obs, args.num_steps, rb, update_obs_rms=args.norm_obs
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

            # ALGO LOGIC: one reward scale for GAE and the critic
            reward_scale = 1.0
            if args.norm_reward:
                ro["rewards"] = scale_rewards(
                    ro["rewards"], ro["episode_ends"], ret_rms, running_return, args.gamma
                )
                reward_scale = float(1.0 / np.sqrt(ret_rms.var + 1e-8))

            # ALGO LOGIC: the critic first (eq. 6-7; Algorithm 1 of Q-Prop), so that A_bar, eta
            # and the analytic term use the trained critic
            learning = (
                global_step >= args.learning_starts
                and args.eta_mode != "none"
                and rb.num_sampleable() > 0
            )
            if learning and args.critic_steps > 0:
                for _ in range(args.critic_steps):
                    data = sample_replay(rb, obs_rms, reward_scale, args.critic_batch_size)
                    critic_loss, q_values = critic_step(
                        qf, qf_target, q_optimizer, agent, data, gamma=args.gamma, tau=args.tau
                    )
                writer.add_scalar("losses/critic_loss", critic_loss, global_step)
                writer.add_scalar("losses/q_values", q_values, global_step)

            # ALGO LOGIC: advantages (eq. 3-4), the control variate (eq. 9) and eta
            last_obs = torch.as_tensor(obs_rms.normalize(raw_obs))
            b = make_batch(agent, ro, last_obs, args.gamma, args.gae_lambda)
            if learning:
                b["cv"] = control_variate(qf, agent, b["obs"], b["actions"])
                b["eta"] = compute_eta(b["advantages"], b["cv"], args.eta_mode)
                writer.add_scalar("qprop/eta", b["eta"].mean().item(), global_step)
                cov = batch_covariance(b["advantages"], b["cv"])
                writer.add_scalar("qprop/cov", cov, global_step)
                for key, value in gradient_variance(agent, qf, b).items():
                    writer.add_scalar(f"qprop/{key}", value, global_step)

            # ALGO LOGIC: the Q-Prop update (eq. 8 inside eq. 5)
            beta, stats = qprop_update(agent, optimizer, b, beta, args, qf if learning else None)
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
            writer.add_scalar("qprop/signal_std", stats["signal_std"], global_step)

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
