"""Interpolated Policy Gradient (paper eq. 10) on PPO-KL, with Hindsight Experience Replay (Fig. 2).

Docs: docs/ipg_her.md. Papers: Gu et al. 2017, "Interpolated Policy Gradient"; Andrychowicz et
al. 2017, "Hindsight Experience Replay"; Schulman et al. 2017 (PPO-KL).

IPG mixes the on-policy likelihood-ratio gradient with an off-policy one through a critic Q_w:

    grad J = (1 - nu) E_{rho, pi}[grad log pi(a|s) A_hat(s, a)] + nu E_{s ~ beta}[grad Q_bar_w(s)]

(eq. 10), Q_bar_w(s) = E_{a ~ pi}[Q_w(s, a)] taken as Q_w(s, mu(s)) or one reparameterised sample.
nu = 0 is PPO-KL, nu = 1 DDPG with a stochastic exploring policy. One minibatch loss is
(1 - nu) (-E[r_t A_t]) + nu (-E_{s ~ beta}[Q_bar_w(s)]) + beta_KL KL[pi_old || pi]; the KL
coefficient is ``beta`` as in ppo_kl.py, the paper's state distribution beta is
``--off-policy-states``. HER enters only through the off-policy parts: the critic and the
off-policy term see relabelled goals; the likelihood-ratio term keeps the real ones.
"""

import copy
import functools
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import cli
from common.gae import compute_gae
from common.her import HerReplayBuffer, ReplayBuffer
from common.normalizer import InputNormalizer, RewardScaler
from common.rollout import collect_rollout
from common.run import Run, RunArgs

cli.register_goal_tasks()
torch.distributions.Distribution.set_default_validate_args(False)  # its checks cost ~10% of a run
BETA_MIN, BETA_MAX = 1 / 35, 35.0  # DPPO's bounds on beta: a calm stretch cannot switch it off


@dataclass
class Args(RunArgs):
    """IPG with HER: an on-/off-policy interpolated policy gradient; see docs/ipg_her.md."""

    eval_freq: int = 2500
    """evaluate the deterministic (mean) policy every this many env steps (0: only at the end)"""
    eval_episodes: int = 20
    """episodes per evaluation"""
    diagnostics_every: int = 10
    """log the gradient diagnostics ipg/* every this many updates (0: never); they draw from
    their own random stream, so the training is the same with or without them"""

    # Algorithm specific arguments
    env_id: str = "FetchReach-v4"
    """the id of the gymnasium environment"""
    total_timesteps: int = 30_000
    """environment steps to train for, counted over all parallel envs (whole batches)"""
    num_envs: int = 2
    """the number of parallel environments"""
    num_steps: int = 50
    """steps per environment per rollout (batch = num_envs * num_steps)"""
    learning_rate: float = 1e-3
    """the learning rate of Adam"""
    anneal_lr: bool = False
    """anneal the learning rate linearly to zero"""
    gamma: float = 0.98
    """the discount factor gamma (0.98: OpenAI's HER recipe)"""
    gae_lambda: float = 0.95
    """lam of GAE (eq. 4)"""
    num_minibatches: int = 1
    """the number of minibatches per epoch"""
    update_epochs: int = 10
    """passes over the batch per update"""
    norm_adv: bool = True
    """normalise the advantages of a batch to zero mean and unit std"""
    kl_target: float = 0.1
    """d_targ, the mean KL divergence per update that the beta rule aims for (looser than
    PPO-KL's: the off-policy end takes larger steps; docs/ipg_her.md)"""
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
    """width of the two hidden layers of every network"""
    norm_reward: bool = False
    """divide rewards by the running std of the discounted return"""

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
    """critic steps per iteration"""
    tau: float = 0.05
    """soft target update rate of eq. 6 (after every critic step; 0.05: OpenAI's HER recipe)"""
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
    """Bad input fails here, before anything runs (the shared checks: ``common/cli.py``)."""
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
def make_env(env_id: str):
    def thunk():
        return gym.wrappers.RecordEpisodeStatistics(gym.make(env_id))

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


# ALGO LOGIC: advantages by GAE (eq. 3-4), bootstrapping through truncation
def make_batch(agent: Agent, ro: dict, last_obs: torch.Tensor, gamma: float, gae_lambda: float):
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
        "obs": norm.inputs(data["obs"], goal),
        "next_obs": norm.inputs(data["next_obs"], goal),
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


# ALGO LOGIC: the IPG update (eq. 10) on the PPO-KL surrogate (eq. 5)
def ipg_update(agent: Agent, optimizer: optim.Optimizer, b: dict, beta: float, args: Args,
               qf: QNetwork | None = None, replay_states: Callable | None = None):  # fmt: skip
    """``update_epochs`` passes of minibatch Adam on the interpolated loss with the KL penalty,
    then the beta rule.

    ``b`` is ``make_batch``'s batch, with ``cv`` (A_bar) when ``args.use_cv``. The off-policy
    term's states s ~ beta are the minibatch's own (``--off-policy-states batch``) or a fresh
    draw ``replay_states()`` from the replay buffer for each minibatch. With nu = 0 and no
    control variate this is exactly ``ppo_kl_update``. Returns the new beta and the statistics.
    """
    batch_size = b["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    adv = b["advantages"] - b["cv"] if args.use_cv else b["advantages"]  # A_hat (- A_bar)
    off_scale, signal_std = 1.0, adv.std()  # on the raw scale
    if args.norm_adv:
        adv = (adv - adv.mean()) / (signal_std + 1e-8)
        if args.normalization == "unbiased":
            off_scale = 1.0 / (signal_std.item() + 1e-8)  # the same 1/sigma on both terms
    off_weight = 1.0 if args.use_cv else args.nu  # b = 1 with the control variate
    use_off_policy = qf is not None and off_weight > 0
    pi_old = Normal(b["mean"], b["std"])
    actor_params, critic_params = agent.actor_parameters(), list(agent.critic.parameters())
    on_term, off_term = torch.zeros(()), torch.zeros(())
    for epoch in range(args.update_epochs):
        # shuffle once per epoch: the minibatches are then slices (views), not gathers
        perm = torch.randperm(batch_size)
        keys = ("obs", "actions", "logprobs", "mean", "std", "returns")
        shuffled = {key: b[key][perm] for key in keys} | {"adv": adv[perm]}
        for start in range(0, batch_size, minibatch_size):
            mb = {key: v[start : start + minibatch_size] for key, v in shuffled.items()}
            pi = agent.dist(mb["obs"])
            kl = kl_divergence(Normal(mb["mean"], mb["std"]), pi).sum(-1).mean()  # analytic
            pg_loss = beta * kl
            if args.nu < 1:  # the likelihood-ratio part, eq. 5's (weight 0 at nu = 1: skipped)
                ratio = (pi.log_prob(mb["actions"]).sum(-1) - mb["logprobs"]).exp()  # r_t(theta)
                on_term = -(ratio * mb["adv"]).mean()
                pg_loss = pg_loss + (1.0 - args.nu) * on_term
            if use_off_policy:
                s_off = mb["obs"] if args.off_policy_states == "batch" else replay_states()
                a_off = agent.actor_mean(s_off)
                if args.q_bar == "sample":  # a = mu + sigma eps: the gradient reaches sigma too
                    a_off = a_off + agent.actor_logstd.exp() * torch.randn_like(a_off)
                off_term = -qf(s_off, a_off).mean()  # -Q_bar_w(s), s ~ beta (eq. 10)
                pg_loss = pg_loss + off_weight * off_scale * off_term
            v_loss = 0.5 * ((agent.get_value(mb["obs"]) - mb["returns"]) ** 2).mean()
            optimizer.zero_grad()
            (pg_loss + args.vf_coef * v_loss).backward()
            nn.utils.clip_grad_norm_(actor_params, args.max_grad_norm)  # policy and
            nn.utils.clip_grad_norm_(critic_params, args.max_grad_norm)  # V apart
            optimizer.step()
        if args.kl_early_stop is not None:
            with torch.no_grad():
                d = kl_divergence(pi_old, agent.dist(b["obs"])).sum(-1).mean().item()
            if d > args.kl_early_stop * args.kl_target:
                break
    with torch.no_grad():
        pi = agent.dist(b["obs"])
        d = kl_divergence(pi_old, pi).sum(-1).mean().item()  # d: mean KL[pi_old || pi]
        entropy = pi.entropy().sum(-1).mean().item()
    stats = {"losses/policy_loss": pg_loss.item(), "losses/value_loss": v_loss.item(),
             "losses/approx_kl": d, "losses/beta": beta, "losses/epochs": epoch + 1,
             "charts/policy_entropy": entropy, "ipg/signal_std": signal_std.item(),
             "ipg/on_policy_term": on_term.item(),
             "ipg/off_policy_term": off_term.item()}  # fmt: skip
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    return min(max(beta, BETA_MIN), BETA_MAX), stats


if __name__ == "__main__":
    args = cli.parse_args(Args)
    check_args(args, sys.argv[1:])
    batch_size = args.num_envs * args.num_steps
    minibatch_steps = args.update_epochs * args.num_minibatches  # per update
    num_iterations = args.total_timesteps // batch_size
    run = Run(args)  # TRY NOT TO MODIFY: run folder, TensorBoard, seeding (common/run.py)

    # ENV SETUP
    envs = gym.vector.SyncVectorEnv(
        [make_env(args.env_id) for _ in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    space = envs.single_observation_space
    goal_dim = space["desired_goal"].shape[0] if isinstance(space, gym.spaces.Dict) else 0
    obs_dim = space["observation"].shape[0] if goal_dim else space.shape[0]
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(run.streams.action_space_seed)

    # ALGO LOGIC: networks, optimisers, normalisers, replay (with HER on goal tasks)
    agent = Agent(obs_dim + goal_dim, act_dim, hidden=args.hidden, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    norm = InputNormalizer(obs_dim, goal_dim)
    low, high = envs.single_action_space.low, envs.single_action_space.high
    qf = QNetwork(obs_dim + goal_dim, act_dim, hidden=args.hidden, low=low, high=high)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    rb = ReplayBuffer(
        args.buffer_size, args.num_envs, obs_dim, act_dim, seed=run.streams.replay_seed
    )
    q_range = None  # the returns the reward allows, for clipping the critic's targets
    if goal_dim:  # hindsight relabelling needs the task's reward function
        reward_env = gym.make(args.env_id)  # gymnasium 1.x wrappers do not forward attributes
        compute_reward = lambda ag, g: reward_env.unwrapped.compute_reward(ag, g, None)
        q_range = (
            sparse_return_range(compute_reward, goal_dim, args.gamma)
            if args.clip_q_target
            else None
        )
        rb = HerReplayBuffer(
            args.buffer_size, args.num_envs, obs_dim, act_dim, goal_dim, compute_reward,
            n_sampled_goal=args.her_n_sampled_goal if args.her else 0,
            goal_selection_strategy=args.her_goal_selection_strategy, seed=run.streams.replay_seed,
        )  # fmt: skip
    reward_scaler = RewardScaler(args.num_envs, args.gamma)
    raw_obs, beta = run.start(
        envs, model=dict(agent=agent, normalizer=norm, qf=qf, qf_target=qf_target),
        training=dict(optimizer=optimizer, q_optimizer=q_optimizer, rb=rb,
                      reward_scaler=reward_scaler),
        beta=args.beta_init,
    )  # fmt: skip

    with run:  # TRY NOT TO MODIFY: Ctrl-C, kill or a NaN end the run cleanly
        for iteration in run.iterations(num_iterations):
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

            # ALGO LOGIC: rollout
            ro, raw_obs, episodes = collect_rollout(envs, agent, norm, raw_obs, args.num_steps, rb)
            global_step = run.record_episodes(episodes)

            # ALGO LOGIC: one reward scale for GAE and the critic
            reward_scale = 1.0
            if args.norm_reward:
                ro["rewards"] = reward_scaler(ro["rewards"], ro["episode_ends"])
                reward_scale = 1.0 / reward_scaler.std()

            # ALGO LOGIC: the critic first (eq. 6-7), so that A_bar and the off-policy term see
            # the new data; targets clipped to the returns the reward allows (scaled)
            learning = global_step >= args.learning_starts and rb.num_sampleable() > 0
            if learning and args.critic_steps > 0:
                target_range = None if q_range is None else (q_range[0] * reward_scale, 0.0)
                for data in sample_replay(
                    rb, norm, reward_scale, args.critic_batch_size, count=args.critic_steps
                ):
                    critic_loss, q_values = critic_step(
                        qf, qf_target, q_optimizer, agent, data, args.gamma, args.tau, target_range
                    )
                run.log({"losses/critic_loss": critic_loss, "losses/q_values": q_values})

            # ALGO LOGIC: advantages (eq. 3-4) and the control variate (eq. 9)
            b = make_batch(agent, ro, norm(raw_obs), args.gamma, args.gae_lambda)
            if args.use_cv:
                b["cv"] = control_variate(qf, agent, b["obs"], b["actions"])
                run.log({"ipg/cv_mean": b["cv"].mean().item()})

            # DIAGNOSTICS: gradient norms and variances before the update (ipg/*)
            if (
                args.diagnostics_every
                and (iteration - 1) % args.diagnostics_every == 0
                and learning
            ):
                off_states = b["obs"]
                if args.off_policy_states == "replay":
                    off_states = sample_replay(
                        rb, norm, 1.0, args.off_policy_batch_size, rng=run.diagnostics_rng
                    )[0]["obs"]
                diagnostics = gradient_diagnostics(
                    agent, qf, b, args, off_states, generator=run.diagnostics_generator
                )
                run.log({f"ipg/{key}": value for key, value in diagnostics.items()})

            # ALGO LOGIC: the IPG update (eq. 10 on eq. 5)
            states = replay_state_batches(rb, norm, args.off_policy_batch_size, minibatch_steps)
            beta, stats = ipg_update(agent, optimizer, b, beta, args, qf if learning else None,
                                     functools.partial(next, states))  # fmt: skip
            stats |= {"charts/learning_rate": optimizer.param_groups[0]["lr"], "ipg/nu": args.nu}
            run.end_iteration(stats, beta=beta)  # TRY NOT TO MODIFY: log, evaluate, save
