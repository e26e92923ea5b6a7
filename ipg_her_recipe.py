"""Interpolated Policy Gradient (paper eq. 10; Gu et al. 2017) on PPO-KL, with Hindsight Experience
Replay (Fig. 2; Andrychowicz et al. 2017). Docs: docs/ipg_her.md. IPG mixes the likelihood-ratio
gradient with an off-policy one through a critic Q_w:

    grad J = (1 - nu) E_{rho, pi}[grad log pi(a|s) A_hat(s, a)] + nu E_{s ~ beta}[grad Q_bar_w(s)]

(eq. 10), Q_bar_w(s) = E_{a ~ pi}[Q_w(s, a)] taken as Q_w(s, mu(s)) or one reparameterised sample:
nu = 0 is PPO-KL, nu = 1 DDPG with a stochastic policy, both inside PPO-KL's KL penalty (whose
coefficient is ``beta``; the paper's state distribution beta is ``--off-policy-states``). HER
relabels what the critic and the off-policy term see; the likelihood-ratio term keeps real goals.

The variant: ``ipg_her.py`` plus a recipe for the harder goal tasks (docs/ipg_her_recipe.md),
each addition measured on the Fetch tasks: twin critics (TD3, Fujimoto et al. 2018), an
entropy-targeted sigma (SAC's alpha rule, Haarnoja et al. 2018), an action penalty (OpenAI's HER)
and a bounds loss (rl_games), annealed learning rates and grasped starts (HER sec. 4.1). Its
defaults are its Args' (``--help``); three follow from the task and are filled in at start
(``fill_in``): the sigma rule's targets, one per action dimension, the horizon's discount and,
where an object can be held, grasped starts. The targets narrow over the first 100k steps to a
floor and the learning rates anneal: wide exploration while nothing is learnt, narrow where
precision pays, one set for every goal task, chosen on tuning seeds 11 and 12
(docs/ipg_her_recipe.md).
"""

import copy
import sys
from dataclasses import dataclass
from typing import Literal

from common import cli  # isort: skip  (first: a Ctrl-C while torch loads is one line)

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import diagnostics, her, tasks
from common.gae import gae
from common.grasped_start import GraspedStart, refusal
from common.her import HerReplayBuffer, goal_task_reward, sparse_return_range
from common.normalizer import InputNormalizer, RewardScaler
from common.replay import ReplayBuffer, buffer_refusal, sample_replay
from common.run import Run, RunArgs

tasks.register_goal_tasks()
torch.distributions.Distribution.set_default_validate_args(False)  # its checks cost ~10% of a run
SUCCESS_KEYS = ("is_success", "success")  # a goal task's success flag: Fetch's, the mazes'
BETA_MIN, BETA_MAX = 1 / 35, 35.0  # DPPO's bounds on beta: a calm stretch cannot switch it off


@dataclass
class Args(her.HerArgs, RunArgs):  # HER's flags: common/her.py
    """IPG with HER and a recipe for the harder goal tasks (docs/ipg_her_recipe.md); what follows from the task is
    filled in at start."""

    env_id: str = "FetchReach-v4"
    """the id of the gymnasium environment"""
    total_timesteps: int = 30_000
    """environment steps to train for, counted over all parallel envs (whole batches)"""
    num_envs: int = 2
    """the number of parallel environments"""
    num_steps: int = 50
    """steps per env per rollout (batch = num_envs * num_steps; 50: a Fetch episode)"""
    learning_rate: float = 1e-3
    """the learning rate of Adam (1e-3: OpenAI's HER recipe)"""
    anneal_lr: bool = True
    """anneal the learning rates (the policy's and the critic's) linearly to zero"""
    gamma: float | None = None
    """the discount factor gamma (None: 1 - 1/H for H-step episodes, at most 0.995, else 0.98; filled in at start)"""
    gae_lambda: float = 0.95
    """lam of GAE (eq. 4)"""
    num_minibatches: int = 1
    """the number of minibatches per epoch (1: the batch is one episode per env)"""
    update_epochs: int = 10
    """passes over the batch per update"""
    norm_adv: bool = True
    """normalise the advantages of a batch to zero mean and unit std"""
    kl_target: float = 0.1
    """d_targ, the mean KL per update the beta rule aims for (0.1: a step size for nu = 1)"""
    beta_init: float = 1.0
    """initial KL penalty coefficient beta (the PPO paper: insensitive)"""
    kl_early_stop: float | None = None
    """stop an update's epochs once the mean KL exceeds this many times kl_target (None: never)"""
    init_log_std: float = 0.0
    """initial log std of the Gaussian policy (0: goals need wide exploration)"""
    vf_coef: float = 0.5
    """coefficient of the value loss"""
    max_grad_norm: float = 0.5
    """the maximum gradient norm, of the policy and of V each (clipped separately)"""
    norm_obs: bool = True
    """normalise observations (and goals) by running mean and std (saved with the model)"""
    norm_reward: bool = False
    """divide rewards by the running std of the discounted return (not Fetch's 0 / -1)"""
    eval_freq: int = 2500  # these two: RunArgs' help (common/run.py), defaults here
    eval_episodes: int = 20
    diagnostics_every: int = 10
    """log the diagnostics ipg/* every this many updates (0: never; they leave training as is)"""

    # IPG arguments
    nu: float = 1.0
    """nu of eq. 10: weight of the off-policy term (0: PPO-KL, 1: DDPG-like, stochastic policy)"""
    use_cv: bool = False
    """control variate: learning signal A_hat - A_bar (eq. 9) and off-policy weight 1"""
    off_policy_states: Literal["replay", "batch"] = "replay"
    """the off-policy term's states: uniform from the replay buffer, or the on-policy batch"""
    q_bar: Literal["mean", "sample"] = "mean"
    """Q_bar_w(s) as Q_w(s, mu(s)) (mean) or Q_w(s, mu(s) + sigma eps), a reparameterised sample"""
    off_policy_batch_size: int = 256
    """replay states per policy minibatch for the off-policy term"""
    normalization: Literal["paper", "unbiased"] = "paper"
    """normalise the learning signal only (paper, biased) or the critic's term with it (unbiased)"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    critic_learning_rate: float = 1e-3
    """the learning rate of the critic Q_w"""
    critic_batch_size: int = 256
    """transitions per critic step"""
    critic_steps: int = 50
    """critic steps per iteration (50 per 100 env steps: OpenAI's HER recipe)"""
    hidden: int = 256
    """width of the two hidden layers of every network (policy, V and Q_w)"""
    tau: float = 0.05
    """soft target update rate of eq. 6, after every critic step (0.05: OpenAI's HER)"""
    learning_starts: int = 100
    """environment steps before the critic, and what uses it, starts"""

    # the recipe
    target_std: float | tuple[float, ...] | None = None
    """the sigma rule's targets: one sigma per action dimension, or one (None: min(1, 2/sqrt(d)) each; filled in at start)"""
    grasped_start: float | None = None
    """share of episodes begun with the object held (None: 0.5 where the gripper can hold it, else 0; filled in at start)"""
    action_l2: float = 1.0
    """weight of the penalty mean(mu(s)^2) beside the off-policy term (OpenAI's HER: 1)"""
    bounds_loss: float = 0.0
    """weight of the penalty mean((mu(s) beyond the action bounds)^2) (rl_games' bounds loss)"""
    twin_critic: bool = True
    """two critics, the target the smaller of their Q_w' (TD3's clipped double Q)"""
    target_std_decay: float = 0.3
    """the sigma rule's targets go geometrically to this multiple of --target-std (1: held; DrQ-v2 anneals 1 -> 0.1)"""
    target_std_decay_steps: int = 100_000
    """environment steps the targets take to get there, then held"""
    target_std_floor: float = 0.3
    """no target decays below this sigma (a target given below it is held)"""


def check_args(args: Args, argv: list[str]) -> None:
    """Bad input fails here, before anything runs: one ``error:`` line (``common/cli.py``)."""
    goal_task = cli.check_run(args)
    cli.check_ppo_kl(args)
    cli.check_range(args, "nu", 0.0, 1.0)
    cli.check_non_negative(args, "critic_steps", "learning_starts", "action_l2", "bounds_loss")
    cli.check_range(args, "target_std_decay", 0.0, 1.0, open_low=True)
    cli.check_positive(args, "target_std_decay_steps")
    cli.check_non_negative(args, "target_std_floor")
    critic_flags = "--critic-learning-rate --critic-batch-size --critic-steps --tau --buffer-size --learning-starts --q-bar "
    critic_flags += f"--off-policy-states --off-policy-batch-size --normalization --diagnostics-every {her.FLAGS}"
    critic_flags += " --action-l2 --bounds-loss --twin-critic"
    no_critic = args.nu == 0 and not args.use_cv
    ignored = her.ignored(args, args.env_id, goal_task) | cli.ignored(
        (not args.norm_adv, "--normalization", "--no-norm-adv: nothing to normalise"),
        (args.off_policy_states == "batch", "--off-policy-batch-size", "--off-policy-states batch"),
        (args.nu == 1 and args.use_cv, "--use-cv", "at --nu 1 its on-policy term has weight 0"),
        (no_critic, critic_flags, "at --nu 0 without --use-cv no term uses the critic"),
        (args.target_std_decay == 1, "--target-std-decay-steps --target-std-floor", "--target-std-decay 1 holds the targets"),
    )
    cli.refuse_ignored(argv, ignored)
    cli.check_positive(args, "critic_learning_rate", "critic_batch_size", "buffer_size")
    cli.check_positive(args, "hidden", "off_policy_batch_size")
    batch = max(args.off_policy_batch_size, args.critic_batch_size, args.num_envs * args.num_steps)
    cli.check_memory(
        4 * args.hidden * (20 * args.hidden + 16 * batch),
        f"--hidden {args.hidden} with batches of {batch:,} (the largest of "
        "--off-policy-batch-size, --critic-batch-size and the rollout)",
    )
    cli.check_range(args, "tau", 0.0, 1.0, open_low=True)
    cli.refuse(buffer_refusal(args.buffer_size, args.num_envs, args.env_id))
    cli.refuse(her.check(args, args.env_id, goal_task))  # and on a task without goals: HER is off
    stds = () if args.target_std is None else tuple(np.atleast_1d(args.target_std))
    if min(stds, default=1.0) <= 0:
        cli.fail(f"--target-std must be positive, got {' '.join(map(str, stds))}")
    if args.target_std is not None and len(stds) != 1:
        if len(stds) != (dims := gym.make(args.env_id).action_space.shape[0]):
            cli.fail(f"--target-std takes one sigma or one per action dimension ({dims} on {args.env_id}), not {len(stds)}")
    if args.grasped_start is not None:
        cli.check_range(args, "grasped_start", 0.0, 1.0)
        cli.refuse(args.grasped_start and refusal(args.env_id))


def fill_in(args: Args) -> dict:
    """The values that follow from the task, for the fields left at None (CleanRL's "filled in at runtime"): one sigma
    rule per action dimension at min(1, 2 / sqrt(d)) on its d dimensions (a noise vector of length 2, no dimension's sigma
    above 1), the discount 1 - 1/H of its H-step episodes, at most 0.995 (0.98 without them), and grasped starts for
    half of the episodes where the gripper can hold the object. Returns what it filled in."""
    env = gym.make(args.env_id)
    d, horizon = env.action_space.shape[0], env.spec.max_episode_steps or 0
    env.close()
    task = dict(target_std=(round(min(1.0, 2 / d**0.5), 3),) * d, gamma=min(0.995, 1 - 1 / horizon) if horizon > 1 else 0.98)
    task |= dict(grasped_start=0.5 if refusal(args.env_id) is None else 0.0)
    filled = {name: value for name, value in task.items() if getattr(args, name) is None}
    for name, value in filled.items():
        setattr(args, name, value)
    return filled


# ENV SETUP
def make_env(env_id: str, grasped_start: float = 0.0):
    def thunk():
        env = gym.make(env_id)  # a goal task keeps its Dict: HER needs the goals apart
        env = GraspedStart(env, grasped_start) if grasped_start else env  # HER's sec. 4.1
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
            layer_init(nn.Linear(obs_dim, hidden)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden, act_dim), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.full((1, act_dim), init_log_std))

    def actor_parameters(self) -> list[nn.Parameter]:
        return [*self.actor_mean.parameters(), self.actor_logstd]

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def dist(self, x: torch.Tensor) -> Normal:
        mean = self.actor_mean(x)
        return Normal(mean, self.actor_logstd.expand_as(mean).exp())


class QNetwork(nn.Module):
    """Critic Q_w(s, a) of the executed (clipped) action; ``twin``: TD3's second (Fujimoto 2018)."""

    def __init__(self, obs_dim, act_dim, hidden=128, low=-np.inf, high=np.inf, twin=False):
        super().__init__()
        self.net, *twin_net = [
            nn.Sequential(
                nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)
            )
            for _ in range(1 + twin)
        ]
        self.twin = nn.ModuleList(twin_net)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).expand(act_dim))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).expand(act_dim))

    def forward(self, x: torch.Tensor, a: torch.Tensor, both: bool = False):  # both: [Q_1, Q_2]
        xa = torch.cat([x, torch.clamp(a, self.low, self.high)], -1)
        qs = [net(xa).squeeze(-1) for net in (self.net, *self.twin)[: 2 if both else 1]]
        return qs if both else qs[0]


# ALGO LOGIC: the rollout: T = num_steps steps of pi_theta in each of N = num_envs envs
def rollout(envs, agent: Agent, norm, raw_obs, num_steps: int, rb, update_norm: bool = True):
    """Step ``envs`` ``num_steps`` times with a_t ~ pi_theta(.|s_t). Returns time-major ``(T, N,
    ...)`` tensors ``obs`` (normalised, as the policy saw them), ``actions``, ``rewards`` (raw),
    ``terminations``, ``episode_ends`` and ``final_obs``; the raw observation the envs stopped
    in; the finished episodes ``(t, env, return, length, success or None)``.

    Every raw transition also goes into the replay buffer ``rb``, with the action executed
    (clipped to the bounds: the critic learns its Q) and its real next observation.

    The envs reset SAME_STEP: where an episode ends at step t, the observation returned is the
    next episode's first, and the true last one is in ``infos["final_obs"]``. It is kept
    (``final_obs``, zeros elsewhere) so that GAE can bootstrap a truncated episode from V(s_T),
    and the replay never stores a transition that crosses a reset.
    """
    T, N, act_dim = num_steps, envs.num_envs, envs.single_action_space.shape[0]
    low, high = envs.single_action_space.low, envs.single_action_space.high
    obs_dim = norm(raw_obs).shape[-1]
    traj = {
        "obs": torch.zeros((T, N, obs_dim)),
        "final_obs": torch.zeros((T, N, obs_dim)),
        "actions": torch.zeros((T, N, act_dim)),
        "rewards": torch.zeros((T, N)),
        "terminations": torch.zeros((T, N)),
        "episode_ends": torch.zeros((T, N)),
    }
    episodes = []
    for t in range(T):
        if update_norm:
            norm.update(raw_obs)
        traj["obs"][t] = norm(raw_obs)
        with torch.no_grad():
            traj["actions"][t] = agent.dist(traj["obs"][t]).sample()  # a_t ~ pi_theta(.|s_t)
        executed = np.clip(traj["actions"][t].numpy(), low, high)
        next_raw_obs, reward, terminated, truncated, infos = envs.step(executed)
        ended = terminated | truncated
        traj["rewards"][t] = torch.as_tensor(reward)
        traj["terminations"][t] = torch.as_tensor(terminated)
        traj["episode_ends"][t] = torch.as_tensor(ended)
        real_next_obs = copy.deepcopy(next_raw_obs) if ended.any() else next_raw_obs
        for i in np.flatnonzero(ended):  # next_raw_obs[i] is the next episode's first
            final = infos["final_obs"][i]
            if isinstance(real_next_obs, dict):
                for key in real_next_obs:
                    real_next_obs[key][i] = final[key]
            else:
                real_next_obs[i] = final
            traj["final_obs"][t, i] = norm(final)
            info = infos["final_info"]
            success = next((float(info[k][i]) for k in SUCCESS_KEYS if k in info), None)
            episodes.append((t, i, float(info["episode"]["r"][i]), int(info["episode"]["l"][i]), success))
        rb.add(raw_obs, executed, reward, real_next_obs, terminated, truncated)
        raw_obs = next_raw_obs
    return traj, raw_obs, episodes


# ALGO LOGIC: the critic step: DDPG's TD learning, eq. 6's soft target update
def critic_step(qf, qf_target, q_optimizer, agent, data, gamma, tau, target_range=None):
    """One step of TD learning on a replay batch ``data``, then the soft target update (eq. 6)."""
    with torch.no_grad():  # Q_w'(s', mu(s')); twin: the smaller of the two (TD3)
        next_q = qf_target(data["next_obs"], agent.actor_mean(data["next_obs"]), both=True)
        next_q = torch.stack(next_q).min(0).values
        target = data["rewards"] + gamma * (1.0 - data["terminations"]) * next_q
        target = target.clamp(*target_range) if target_range else target  # OpenAI's HER
    qs = qf(data["obs"], data["actions"], both=True)
    loss = sum(0.5 * ((q - target) ** 2).mean() for q in qs)  # twin: each network its own
    q_optimizer.zero_grad()
    loss.backward()
    q_optimizer.step()
    with torch.no_grad():
        for p, p_target in zip(qf.parameters(), qf_target.parameters(), strict=True):
            p_target.lerp_(p, tau)  # w' <- tau w + (1 - tau) w'   (eq. 6)
    return loss.item(), qs[0].mean().item()


# ALGO LOGIC: advantages by GAE (eq. 3-4), bootstrapping through truncation
def make_batch(agent: Agent, traj: dict, last_obs: torch.Tensor, gamma: float, lam: float):
    """GAE advantages (eq. 4, ``common/gae.py``) and pi_old's statistics of a rollout ``traj``, as
    one flat batch. Where an episode ended at step t, s_{t+1} is its true last state
    (``final_obs``): a truncation bootstraps from its value, a termination from none."""
    with torch.no_grad():
        values = agent.get_value(traj["obs"])
        next_values = torch.cat([values[1:], agent.get_value(last_obs)[None]])
        ended = traj["episode_ends"].bool()
        next_values = torch.where(ended, agent.get_value(traj["final_obs"]), next_values)
        rewards, terminated = traj["rewards"], traj["terminations"]
        advantages = gae(rewards, values, next_values, terminated, ended, gamma, lam)  # eq. 4
        pi_old = agent.dist(traj["obs"])
        return {
            "obs": traj["obs"].flatten(0, 1),
            "actions": traj["actions"].flatten(0, 1),
            "logprobs": pi_old.log_prob(traj["actions"]).sum(-1).flatten(),
            "mean": pi_old.mean.flatten(0, 1),
            "std": pi_old.stddev.flatten(0, 1),
            "advantages": advantages.flatten(),
            "returns": (advantages + values).flatten(),
        }


# ALGO LOGIC: the control variate (eq. 9)
def control_variate(qf: QNetwork, agent: Agent, obs: torch.Tensor, actions: torch.Tensor):
    """A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))   (eq. 9), no gradient to theta."""
    mu = agent.actor_mean(obs).detach().requires_grad_(True)  # a leaf: grad_a, not theta's
    (grad_q,) = torch.autograd.grad(qf(obs, mu).sum(), mu)
    return (grad_q * (actions - mu)).sum(-1).detach()


def ipg_loss(
    agent: Agent, qf: QNetwork, pi: Normal, mb: dict, adv=None, s_off=None, q_bar: str = "mean", generator=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 10's two terms on a minibatch ``mb`` as losses (``pi = agent.dist(mb["obs"])``): -E[r_t
    adv_t] (eq. 5's; 0 without ``adv``) and -E_{s ~ beta}[Q_bar_w(s)] on ``s_off`` (0 without)."""
    on_term = off_term = torch.zeros(())
    if adv is not None:
        ratio = (pi.log_prob(mb["actions"]).sum(-1) - mb["logprobs"]).exp()  # r_t(theta)
        on_term = -(ratio * adv).mean()
    if s_off is not None:
        a_off = agent.actor_mean(s_off)
        if q_bar == "sample":  # a = mu + sigma eps: the gradient reaches sigma too
            a_off = a_off + agent.actor_logstd.exp() * torch.randn(a_off.shape, generator=generator)
        off_term = -qf(s_off, a_off).mean()  # -Q_bar_w(s), s ~ beta (eq. 10): eq. 7's gradient
    return on_term, off_term


def learning_signal(batch: dict, args: Args):
    """The update's weights by name: ``adv`` (normalised) and its raw ``std``; the critic term's b and scale."""
    adv = batch["advantages"] - batch["cv"] if "cv" in batch else batch["advantages"]  # A_hat, or A_hat - A_bar (eq. 9)
    off_scale, signal_std = 1.0, adv.std()
    if args.norm_adv:
        adv = (adv - adv.mean()) / (signal_std + 1e-8)
        if args.normalization == "unbiased":
            off_scale = 1.0 / (signal_std.item() + 1e-8)  # the same 1/sigma on both terms
    return dict(adv=adv, std=signal_std, off_weight=1.0 if args.use_cv else args.nu, off_scale=off_scale)


# DIAGNOSTICS: the mixture, measured on the batch before the update
def interpolation_report(agent: Agent, qf: QNetwork, batch: dict, args: Args, replay, run, chunks: int = 4) -> dict:
    """The update's two weighted terms on ``batch`` at theta = theta_old, through its own
    ``learning_signal`` and ``ipg_loss``: their gradient norms (1 - nu) |g_on| and b |g_off|, and
    ``effective_nu`` = |off| / (|on| + |off|), the share the off-policy term really has; then
    the control variate's variance (eq. 8 at eta = 0 and 1, ``common/diagnostics.py``). The
    off-policy states: the batch's, or one draw of ``replay``; random draws from ``run``'s
    diagnostics streams, so that measuring never moves the training's."""
    generator = run.diagnostics_generator
    cv = batch["cv"] if args.use_cv else control_variate(qf, agent, batch["obs"], batch["actions"])
    off_states = batch["obs"] if args.off_policy_states == "batch" else replay(1, run.diagnostics_rng)[0]["obs"]
    params = agent.actor_parameters()
    signal = learning_signal(batch, args)
    on_term, off_term = ipg_loss(agent, qf, agent.dist(batch["obs"]), batch, signal["adv"], off_states, args.q_bar, generator)
    on = (1.0 - args.nu) * diagnostics.flat_grad(on_term, params).norm().item()
    off = signal["off_weight"] * diagnostics.flat_grad(off_term * signal["off_scale"], params).norm().item()

    def estimate(mb: dict, with_cv: bool):  # eq. 8 at eta = 1 or 0, on the raw scale
        adv = mb["advantages"] - mb["cv"] if with_cv else mb["advantages"]
        on_term, off_term = ipg_loss(agent, qf, agent.dist(mb["obs"]), mb, adv, mb["obs"] if with_cv else None)
        return on_term + off_term

    measured = {"on_grad_norm": on, "off_grad_norm": off, "effective_nu": off / (on + off + 1e-12)}
    return measured | diagnostics.variance_report(agent, batch, cv, estimate, chunks, generator)


# ALGO LOGIC: the IPG update (eq. 10) on the PPO-KL surrogate (eq. 5)
def ipg_update(
    agent: Agent,
    optimizer: optim.Optimizer,
    batch: dict,
    beta: float,
    args: Args,
    qf: QNetwork | None = None,
    replay=None,
    alpha=0.0,
):
    """Eq. 10 inside eq. 5: ``update_epochs`` passes of Adam, then the beta rule."""
    batch_size = batch["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    signal = learning_signal(batch, args)
    use_off_policy = qf is not None and signal["off_weight"] > 0
    from_replay = use_off_policy and args.off_policy_states == "replay"
    replayed = iter(replay(args.update_epochs * args.num_minibatches) if from_replay else ())
    pi_old = Normal(batch["mean"], batch["std"])
    actor_params, critic_params = agent.actor_parameters(), list(agent.critic.parameters())
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        keys = ("obs", "actions", "logprobs", "mean", "std", "returns")
        shuffled = {key: batch[key][perm] for key in keys} | {"adv": signal["adv"][perm]}
        for start in range(0, batch_size, minibatch_size):
            mb = {key: v[start : start + minibatch_size] for key, v in shuffled.items()}
            pi = agent.dist(mb["obs"])
            kl = kl_divergence(Normal(mb["mean"], mb["std"]), pi).sum(-1).mean()
            s_off = next(replayed)["obs"] if from_replay else mb["obs"] if use_off_policy else None
            on_term, off_term = ipg_loss(agent, qf, pi, mb, mb["adv"] if args.nu < 1 else None, s_off, args.q_bar)
            pg_loss = beta * kl + (1.0 - args.nu) * on_term + signal["off_weight"] * signal["off_scale"] * off_term
            if s_off is not None and (args.action_l2 or args.bounds_loss):
                mu = agent.actor_mean(s_off)  # OpenAI's HER: l2 mu(s)^2; rl_games: beyond bounds
                beyond = mu - mu.clamp(qf.low, qf.high)  # zero inside: there Q_w's gradient lives
                pg_loss += args.action_l2 * (mu**2).mean() + args.bounds_loss * (beyond**2).mean()
            h = pi.entropy().mean(0) if np.ndim(alpha) else pi.entropy().sum(-1).mean()
            pg_loss = pg_loss - (h.new_tensor(alpha) * h).sum()  # the sigma rule's bonus
            v_loss = 0.5 * ((agent.get_value(mb["obs"]) - mb["returns"]) ** 2).mean()
            optimizer.zero_grad()
            (pg_loss + args.vf_coef * v_loss).backward()
            nn.utils.clip_grad_norm_(actor_params, args.max_grad_norm)
            nn.utils.clip_grad_norm_(critic_params, args.max_grad_norm)
            optimizer.step()
        if args.kl_early_stop is not None:
            with torch.no_grad():
                d = kl_divergence(pi_old, agent.dist(batch["obs"])).sum(-1).mean().item()
            if d > args.kl_early_stop * args.kl_target:
                break
    with torch.no_grad():
        pi = agent.dist(batch["obs"])
        d = kl_divergence(pi_old, pi).sum(-1).mean().item()  # d: mean KL[pi_old || pi]
        entropy = pi.entropy().sum(-1).mean().item()
    stats = {
        "losses/policy_loss": pg_loss.item(),
        "losses/value_loss": v_loss.item(),
        "losses/approx_kl": d,
        "losses/beta": beta,
        "losses/epochs": epoch + 1,
        "charts/policy_entropy": entropy,
        "ipg/signal_std": signal["std"].item(),
        "ipg/on_policy_term": on_term.item(),
        "ipg/nu": args.nu,
        "ipg/off_policy_term": off_term.item(),
        "ipg/alpha": np.mean(alpha),
    }
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    return min(max(beta, BETA_MIN), BETA_MAX), stats


def annealed(target_std, decay: float, progress: float, floor: float = 0.0):
    """The target(s) ``target_std`` times ``decay ** min(1, progress)``, never below ``floor`` (one below it is held)."""
    if decay == 1:
        return target_std
    return np.maximum(np.asarray(target_std) * decay ** min(1.0, progress), np.minimum(target_std, floor))


def sigma_rule(alpha, entropy: float, log_std: np.ndarray, target_std):
    """SAC's alpha rule (Haarnoja 2018, eq. 18), two-sided: alpha += 0.01 (H_target - H(pi))."""
    if np.ndim(target_std):  # H(N(0, t_i^2)) - H(pi_i) = log t_i - log sigma_i
        return alpha + 0.01 * (np.log(target_std) - log_std)
    h_target = len(log_std) * (0.5 * np.log(2 * np.pi * np.e) + np.log(target_std))
    return alpha + 0.01 * (h_target - entropy)


if __name__ == "__main__":
    args = cli.parse_args(Args)
    check_args(args, sys.argv[1:])
    if filled := fill_in(args):  # what follows from the task, as one would type it
        print(f"filled in from {args.env_id}: {cli.spelled(filled)}", flush=True)
    batch_size = args.num_envs * args.num_steps
    num_iterations = args.total_timesteps // batch_size
    run = Run(args)  # TRY NOT TO MODIFY: run folder, TensorBoard, seeding (common/run.py)

    # ENV SETUP: N envs stepped in turn, SAME_STEP autoreset (see rollout)
    envs = gym.vector.SyncVectorEnv(
        [make_env(args.env_id, args.grasped_start)] * args.num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
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
    qf = QNetwork(obs_dim + goal_dim, act_dim, args.hidden, low, high, args.twin_critic)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    rb = ReplayBuffer(args.buffer_size, args.num_envs, obs_dim, act_dim, run.streams.replay_seed)
    q_range = None  # the returns the reward allows: the critic's targets are clipped to them
    if goal_dim:  # hindsight relabelling (Figure 2) needs the task's reward function
        compute_reward = goal_task_reward(args.env_id, args.her)
        q_range = sparse_return_range(compute_reward, goal_dim, args.gamma)
        rb = HerReplayBuffer(
            args.buffer_size,
            args.num_envs,
            obs_dim,
            act_dim,
            goal_dim,
            compute_reward,
            args.her_n_sampled_goal if args.her else 0,
            args.her_goal_selection_strategy,
            run.streams.replay_seed,
        )
    replay = lambda n, rng=None: sample_replay(rb, norm, 1.0, args.off_policy_batch_size, n, rng)
    reward_scaler = RewardScaler(args.num_envs, args.gamma)
    # what model.pt keeps, and what else resume.pt needs to go on
    model = dict(agent=agent, normalizer=norm, qf=qf, qf_target=qf_target)
    training = dict(optimizer=optimizer, reward_scaler=reward_scaler, q_optimizer=q_optimizer, rb=rb)
    run.start(envs, model, training)  # TRY NOT TO MODIFY: --resume restores them all

    # TRY NOT TO MODIFY: start the game (a resumed run goes on where its resume point left it)
    global_step, beta = run.global_step, run.restored("beta", args.beta_init)
    alpha = run.restored("alpha", 0.0)  # the sigma rule's multiplier (sigma_rule)
    if run.resumed:
        raw_obs = run.resumed_obs
    else:
        raw_obs, _ = envs.reset(seed=run.streams.env_seeds)

    with run:  # TRY NOT TO MODIFY: Ctrl-C, kill or a NaN end the run cleanly
        for iteration in run.iterations(num_iterations):
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate
                q_optimizer.param_groups[0]["lr"] = frac * args.critic_learning_rate

            # ALGO LOGIC: rollout
            traj, raw_obs, episodes = rollout(envs, agent, norm, raw_obs, args.num_steps, rb, update_norm=args.norm_obs)
            global_step += args.num_envs * args.num_steps
            run.record_episodes(episodes, global_step)

            # ALGO LOGIC: one reward scale for GAE and the critic
            reward_scale = 1.0
            if args.norm_reward:
                traj["rewards"] = reward_scaler(traj["rewards"], traj["episode_ends"])
                reward_scale = 1.0 / reward_scaler.std()

            # ALGO LOGIC: the critic first (eq. 6; Q-Prop's Algorithm 1), so that the control
            # variate and the critic's term see the new data; at nu = 0 without them, no critic
            critic_ready = (args.nu > 0 or args.use_cv) and global_step >= args.learning_starts
            critic_ready = critic_ready and rb.num_sampleable() > 0
            if critic_ready and args.critic_steps > 0:
                target_range = (q_range[0] * reward_scale, 0.0) if q_range else None
                for data in sample_replay(rb, norm, reward_scale, args.critic_batch_size, args.critic_steps):
                    q_loss, q_mean = critic_step(qf, qf_target, q_optimizer, agent, data, args.gamma, args.tau, target_range)
                run.log({"losses/critic_loss": q_loss, "losses/q_values": q_mean})

            # ALGO LOGIC: advantages (eq. 3-4) and the control variate (eq. 9)
            batch = make_batch(agent, traj, norm(raw_obs), args.gamma, args.gae_lambda)
            if args.use_cv and critic_ready:  # with the critic and the term that offsets it (eq. 8)
                batch["cv"] = control_variate(qf, agent, batch["obs"], batch["actions"])
                run.log({"ipg/cv_mean": batch["cv"].mean().item()})
            diagnose = args.diagnostics_every and (iteration - 1) % args.diagnostics_every == 0
            if critic_ready and diagnose:  # DIAGNOSTICS: the mixture, before the update (ipg/*)
                measured = interpolation_report(agent, qf, batch, args, replay, run)
                run.log({f"ipg/{key}": value for key, value in measured.items()})

            # ALGO LOGIC: the IPG update (eq. 10 on eq. 5)
            critic = qf if critic_ready else None
            beta, stats = ipg_update(agent, optimizer, batch, beta, args, critic, replay, alpha)
            stats |= {"charts/learning_rate": optimizer.param_groups[0]["lr"]}
            # the sigma rule: SAC's eq. 18, two-sided (docs), towards targets that decay over training
            progress = global_step / args.target_std_decay_steps
            target_std = annealed(args.target_std, args.target_std_decay, progress, args.target_std_floor)
            alpha = sigma_rule(alpha, stats["charts/policy_entropy"], agent.actor_logstd.detach().numpy()[0], target_std)
            run.end_iteration(stats, beta=beta, alpha=alpha)  # TRY NOT TO MODIFY: log, save
