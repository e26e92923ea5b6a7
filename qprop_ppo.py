"""Q-Prop (paper eq. 6-9) with a PPO-KL on-policy part (eq. 5) and a DDPG-style critic.

Docs: docs/qprop.md. Papers: Gu et al. 2017, "Q-Prop: Sample-Efficient Policy Gradient with an
Off-Policy Critic"; Tucker et al. 2018, "The Mirage of Action-Dependent Baselines".

Q-Prop subtracts from the advantage A_hat a control variate built from an off-policy critic Q_w
and adds back its expectation analytically, so the gradient stays unbiased:

    A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))                           (eq. 9)
    grad J = E[grad log pi(a|s) (A_hat - eta A_bar)] + E[eta grad_a Q_w(s, mu(s)) grad mu(s)]

(eq. 8). Inside PPO-KL one minibatch loss is -E[r_t (A_hat - eta A_bar)] - E[eta Q_w(s, mu(s))]
+ beta KL[pi_old || pi]. The critic learns off-policy (DDPG's, eq. 6) before the policy update.
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

from common import diagnostics, tasks
from common.gae import gae
from common.normalizer import RewardScaler, RunningMeanStd
from common.replay import ReplayBuffer, buffer_refusal, sample_replay
from common.run import Run, RunArgs

tasks.register_goal_tasks()
torch.distributions.Distribution.set_default_validate_args(False)  # its checks cost ~10% of a run
SUCCESS_KEYS = ("is_success", "success")  # a goal task's success flag: Fetch's, the mazes'
BETA_MIN, BETA_MAX = 1 / 35, 35.0  # DPPO's bounds on beta: a calm stretch cannot switch it off


@dataclass
class Args(RunArgs):
    """Q-Prop: PPO-KL with an off-policy critic's control variate; see docs/qprop.md."""

    env_id: str = "Hopper-v5"
    """the id of the gymnasium environment"""
    total_timesteps: int = 1_000_000
    """environment steps to train for, counted over all parallel envs (whole batches)"""
    num_envs: int = 4
    """the number of parallel environments"""
    num_steps: int = 512
    """steps per env per rollout (batch = num_envs * num_steps)"""
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
    """d_targ, the mean KL per update the beta rule aims for"""
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
    """normalise observations (and goals) by running mean and std (saved with the model)"""
    norm_reward: bool = True
    """divide rewards by the running std of the discounted return (not Fetch's 0 / -1)"""

    # Q-Prop arguments
    eta_mode: Literal["batch-conservative", "batch-aggressive", "conservative", "aggressive", "ones", "none"] = (
        "batch-conservative"
    )
    """control-variate weight eta: the batch covariance's sign (unbiased), per sample (the paper's, biased), 1, or none"""
    normalization: Literal["paper", "unbiased"] = "unbiased"
    """normalise the learning signal only (paper, biased) or the critic's term with it (unbiased)"""
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
    """soft target update rate of eq. 6, after every critic step"""
    learning_starts: int = 1000
    """environment steps before the critic, and what uses it, starts"""


def check_args(args: Args, argv: list[str]) -> None:
    """Bad input fails here, before anything runs: one ``error:`` line (``common/cli.py``)."""
    cli.check_run(args)
    cli.check_ppo_kl(args)
    cli.check_non_negative(args, "critic_steps", "learning_starts")
    critic_flags = (
        "--critic-learning-rate --critic-batch-size --critic-steps --tau --buffer-size "
        "--learning-starts --critic-hidden --normalization"
    )
    cli.refuse_ignored(
        argv,
        cli.ignored(
            (not args.norm_adv, "--normalization", "--no-norm-adv: nothing to normalise"),
            (args.eta_mode == "none", critic_flags, "--eta-mode none trains no critic"),
        ),
    )
    cli.check_positive(args, "critic_learning_rate", "critic_batch_size", "buffer_size")
    cli.check_positive(args, "critic_hidden")
    hidden, batch = args.critic_hidden, args.critic_batch_size
    cli.check_memory(4 * hidden * (20 * hidden + 16 * batch), f"--critic-hidden {hidden} with --critic-batch-size {batch:,}")
    cli.check_range(args, "tau", 0.0, 1.0, open_low=True)
    cli.refuse(buffer_refusal(args.buffer_size, args.num_envs, args.env_id))


# ENV SETUP
def make_env(env_id: str):
    def thunk():
        env = gym.make(env_id)
        if isinstance(env.observation_space, gym.spaces.Dict):
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
    """Critic Q_w(s, a) of the executed action: a clipped to the action bounds, as the env does."""

    def __init__(self, obs_dim, act_dim, hidden=128, low=-np.inf, high=np.inf):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)
        )
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).expand(act_dim))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).expand(act_dim))

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x, torch.clamp(a, self.low, self.high)], -1)).squeeze(-1)


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
        real_next_obs = next_raw_obs.copy()  # where an episode ended: its true last state
        for i in np.flatnonzero(ended):
            real_next_obs[i] = infos["final_obs"][i]
            traj["final_obs"][t, i] = norm(infos["final_obs"][i])
            info = infos["final_info"]
            success = next((float(info[k][i]) for k in SUCCESS_KEYS if k in info), None)
            episodes.append((t, i, float(info["episode"]["r"][i]), int(info["episode"]["l"][i]), success))
        rb.add(raw_obs, executed, reward, real_next_obs, terminated, truncated)
        raw_obs = next_raw_obs
    return traj, raw_obs, episodes


# ALGO LOGIC: the critic step: DDPG's TD learning, eq. 6's soft target update
def critic_step(
    qf: QNetwork, qf_target: QNetwork, q_optimizer: optim.Optimizer, agent: Agent, data: dict, gamma: float, tau: float
) -> tuple[float, float]:
    """One step of TD learning on a replay batch ``data``, then the soft target update (eq. 6)."""
    with torch.no_grad():  # Q_w'(s', mu(s'))
        next_q = qf_target(data["next_obs"], agent.actor_mean(data["next_obs"]))
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


# ALGO LOGIC: the control variate (eq. 9) and its weight eta
def control_variate(qf: QNetwork, agent: Agent, obs: torch.Tensor, actions: torch.Tensor):
    """A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))   (eq. 9), no gradient to theta."""
    mu = agent.actor_mean(obs).detach().requires_grad_(True)  # a leaf: grad_a, not theta's
    (grad_q,) = torch.autograd.grad(qf(obs, mu).sum(), mu)
    return (grad_q * (actions - mu)).sum(-1).detach()


def compute_eta(advantages: torch.Tensor, cv: torch.Tensor, mode: str) -> torch.Tensor:
    """eta_t for every sample: one per batch from the sign of Cov(A_hat, A_bar) (``batch-*``:
    eq. 8 stays unbiased), or per sample from A_hat_t A_bar_t (the paper's: biased)."""
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


def qprop_loss(agent: Agent, qf: QNetwork, pi: Normal, mb: dict, analytic_scale: float = 1.0):
    """Eq. 8 on a minibatch ``mb`` as a loss (``pi = agent.dist(mb["obs"])``): -E[r_t adv_t] -
    analytic_scale E[eta Q_w(s, mu(s))], ``mb["adv"]`` the learning signal A_hat - eta A_bar;
    at theta_old, the likelihood-ratio gradient and the deterministic one (eq. 7)."""
    ratio = (pi.log_prob(mb["actions"]).sum(-1) - mb["logprobs"]).exp()  # r_t(theta)
    loss = -(ratio * mb["adv"]).mean()
    if torch.any(mb["eta"] != 0):  # the analytic term of eq. 8
        q = qf(mb["obs"], agent.actor_mean(mb["obs"]))  # Q_w(s, mu(s)): its gradient is eq. 7
        loss = loss - analytic_scale * (mb["eta"] * q).mean()
    return loss


def learning_signal(batch: dict, args: Args):
    """The update's weights by name: the learning signal ``adv``, normalised, its raw ``std`` sigma, and the critic's
    term's weights: ``eta`` (the signal is A_hat - eta A_bar) and its scale (``normalization``)."""
    eta = batch["eta"] if "eta" in batch else torch.zeros_like(batch["advantages"])
    adv = batch["advantages"]
    adv = adv - eta * batch["cv"] if "cv" in batch else adv  # A_hat - eta A_bar
    analytic_scale, signal_std = 1.0, adv.std()
    if args.norm_adv:
        adv = (adv - adv.mean()) / (signal_std + 1e-8)
        if args.normalization == "unbiased":
            analytic_scale = 1.0 / (signal_std.item() + 1e-8)  # the same 1/sigma on both terms
    return dict(adv=adv, std=signal_std, eta=eta, analytic_scale=analytic_scale)


# DIAGNOSTICS: does the control variate reduce variance? Measured before the update
def qprop_report(agent: Agent, qf: QNetwork, batch: dict, generator=None, chunks: int = 8) -> dict:
    """Q-Prop's claim on ``batch`` (with ``cv`` = A_bar) at theta = theta_old: the gradient
    variances of ``qprop_loss`` at eta = 0 and eta = 1 (eq. 8: the same expectation), over
    ``chunks`` chunks of the batch (``common/diagnostics.py``); random draws from ``generator``."""

    def estimate(mb: dict, with_cv: bool):  # eq. 8 at eta = 1 or 0, on the raw scale
        eta = torch.full_like(mb["cv"], float(with_cv))
        mb |= {"adv": mb["advantages"] - eta * mb["cv"], "eta": eta}
        return qprop_loss(agent, qf, agent.dist(mb["obs"]), mb)

    return diagnostics.variance_report(agent, batch, batch["cv"], estimate, chunks, generator)


# ALGO LOGIC: the Q-Prop update: PPO-KL (eq. 5) with the control variate (eq. 8)
def qprop_update(agent: Agent, optimizer: optim.Optimizer, batch: dict, beta: float, args: Args, qf: QNetwork | None = None):
    """``update_epochs`` passes of minibatch Adam on eq. 8 inside eq. 5 over ``make_batch``'s
    ``batch`` (with ``cv`` = A_bar and ``eta`` once the critic learns), then the beta rule.
    Without a critic, or with eta = 0, this is ``ppo_kl_update``. Returns the new beta and the
    statistics."""
    batch_size = batch["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    signal = learning_signal(batch, args)
    pi_old = Normal(batch["mean"], batch["std"])
    actor_params, critic_params = agent.actor_parameters(), list(agent.critic.parameters())
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        keys = ("obs", "actions", "logprobs", "mean", "std", "returns")
        shuffled = {key: batch[key][perm] for key in keys} | {"adv": signal["adv"][perm], "eta": signal["eta"][perm]}
        for start in range(0, batch_size, minibatch_size):
            mb = {key: v[start : start + minibatch_size] for key, v in shuffled.items()}
            pi = agent.dist(mb["obs"])
            surrogate = qprop_loss(agent, qf, pi, mb, signal["analytic_scale"])  # eq. 8, negated
            kl = kl_divergence(Normal(mb["mean"], mb["std"]), pi).sum(-1).mean()
            pg_loss = surrogate + beta * kl  # inside eq. 5
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
        "qprop/signal_std": signal["std"].item(),
    }
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    return min(max(beta, BETA_MIN), BETA_MAX), stats


if __name__ == "__main__":
    args = cli.parse_args(Args)
    check_args(args, sys.argv[1:])
    batch_size = args.num_envs * args.num_steps
    num_iterations = args.total_timesteps // batch_size
    run = Run(args)  # TRY NOT TO MODIFY: run folder, TensorBoard, seeding (common/run.py)

    # ENV SETUP: N envs stepped in turn, SAME_STEP autoreset (see rollout)
    envs = gym.vector.SyncVectorEnv([make_env(args.env_id)] * args.num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    obs_dim = envs.single_observation_space.shape[0]
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(run.streams.action_space_seed)

    # ALGO LOGIC: networks, optimisers, normalisers, replay
    agent = Agent(obs_dim, act_dim, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    norm = RunningMeanStd((obs_dim,))
    low, high = envs.single_action_space.low, envs.single_action_space.high
    qf = QNetwork(obs_dim, act_dim, args.critic_hidden, low, high)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    rb = ReplayBuffer(args.buffer_size, args.num_envs, obs_dim, act_dim, run.streams.replay_seed)
    reward_scaler = RewardScaler(args.num_envs, args.gamma)
    # what model.pt keeps, and what else resume.pt needs to go on
    model = dict(agent=agent, normalizer=norm, qf=qf, qf_target=qf_target)
    training = dict(optimizer=optimizer, reward_scaler=reward_scaler, q_optimizer=q_optimizer, rb=rb)
    run.start(envs, model, training)  # TRY NOT TO MODIFY: --resume restores them all

    # TRY NOT TO MODIFY: start the game (a resumed run goes on where its resume point left it)
    global_step, beta = run.global_step, run.restored("beta", args.beta_init)
    if run.resumed:
        raw_obs = run.resumed_obs
    else:
        raw_obs, _ = envs.reset(seed=run.streams.env_seeds)

    with run:  # TRY NOT TO MODIFY: Ctrl-C, kill or a NaN end the run cleanly
        for iteration in run.iterations(num_iterations):
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

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
            # variate and the critic's term in the update see the new data
            critic_ready = args.eta_mode != "none" and global_step >= args.learning_starts
            critic_ready = critic_ready and rb.num_sampleable() > 0
            if critic_ready and args.critic_steps > 0:
                for data in sample_replay(rb, norm, reward_scale, args.critic_batch_size, args.critic_steps):
                    q_loss, q_mean = critic_step(qf, qf_target, q_optimizer, agent, data, args.gamma, args.tau)
                run.log({"losses/critic_loss": q_loss, "losses/q_values": q_mean})

            # ALGO LOGIC: advantages (eq. 3-4), the control variate (eq. 9) and eta
            batch = make_batch(agent, traj, norm(raw_obs), args.gamma, args.gae_lambda)
            if critic_ready:
                batch["cv"] = control_variate(qf, agent, batch["obs"], batch["actions"])
                batch["eta"] = compute_eta(batch["advantages"], batch["cv"], args.eta_mode)
                cov = batch_covariance(batch["advantages"], batch["cv"])
                # DIAGNOSTICS: does the control variate reduce variance? (qprop/*; own streams)
                measured = qprop_report(agent, qf, batch, run.diagnostics_generator)
                measured |= {"eta": batch["eta"].mean().item(), "cov": cov}
                run.log({f"qprop/{key}": value for key, value in measured.items()})

            # ALGO LOGIC: the Q-Prop update (eq. 8 inside eq. 5)
            critic = qf if critic_ready else None
            beta, stats = qprop_update(agent, optimizer, batch, beta, args, critic)
            stats |= {"charts/learning_rate": optimizer.param_groups[0]["lr"]}
            run.end_iteration(stats, beta=beta)  # TRY NOT TO MODIFY: log, evaluate, save
