"""PPO with an adaptive KL penalty (paper eq. 5) and GAE (eq. 3-4), for continuous actions.

Docs: docs/ppo_kl.md. Papers: Schulman et al. 2017, "Proximal Policy Optimization Algorithms",
sec. 4 (the adaptive KL penalty); Schulman et al. 2016 (GAE).

Each iteration collects num_envs * num_steps transitions with the Gaussian policy, computes GAE
advantages, then runs update_epochs passes of minibatch Adam on eq. 5's penalised surrogate:

    L(theta) = -E_t[r_t(theta) A_t] + beta KL[pi_old(.|s_t) || pi_theta(.|s_t)],
    r_t(theta) = pi_theta(a_t|s_t) / pi_old(a_t|s_t),

and adapts beta to the update's mean KL d (the PPO paper's rule, beta kept in DPPO's bounds).
"""

from dataclasses import dataclass

from common import cli  # isort: skip  (first: a Ctrl-C while torch loads is one line)

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions import Normal, kl_divergence

from common import tasks
from common.gae import gae
from common.normalizer import RewardScaler, RunningMeanStd
from common.run import Run, RunArgs

tasks.register_goal_tasks()
torch.distributions.Distribution.set_default_validate_args(False)  # its checks cost ~10% of a run
SUCCESS_KEYS = ("is_success", "success")  # a goal task's success flag: Fetch's, the mazes'
BETA_MIN, BETA_MAX = 1 / 35, 35.0  # DPPO's bounds on beta: a calm stretch cannot switch it off


@dataclass
class Args(RunArgs):
    """PPO with the adaptive KL penalty (PPO-KL) on a MuJoCo or Fetch task; see docs/ppo_kl.md."""

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


def check_args(args: Args) -> None:
    """Bad input fails here, before anything runs: one ``error:`` line (``common/cli.py``)."""
    cli.check_run(args)
    cli.check_ppo_kl(args)


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


# ALGO LOGIC: the rollout: T = num_steps steps of pi_theta in each of N = num_envs envs
def rollout(envs, agent: Agent, norm, raw_obs, num_steps: int, update_norm: bool = True):
    """Step ``envs`` ``num_steps`` times with a_t ~ pi_theta(.|s_t). Returns time-major ``(T, N,
    ...)`` tensors ``obs`` (normalised, as the policy saw them), ``actions``, ``rewards`` (raw),
    ``terminations``, ``episode_ends`` and ``final_obs``; the raw observation the envs stopped
    in; the finished episodes ``(t, env, return, length, success or None)``.

    The envs reset SAME_STEP: where an episode ends at step t, the observation returned is the
    next episode's first, and the true last one is in ``infos["final_obs"]``. It is kept
    (``final_obs``, zeros elsewhere) so that GAE can bootstrap a truncated episode from V(s_T).
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
        for i in np.flatnonzero(ended):  # next_raw_obs[i] is the next episode's first
            traj["final_obs"][t, i] = norm(infos["final_obs"][i])
            info = infos["final_info"]
            success = next((float(info[k][i]) for k in SUCCESS_KEYS if k in info), None)
            episodes.append((t, i, float(info["episode"]["r"][i]), int(info["episode"]["l"][i]), success))
        raw_obs = next_raw_obs
    return traj, raw_obs, episodes


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


# ALGO LOGIC: the PPO-KL update (eq. 5)
def ppo_kl_update(agent: Agent, optimizer: optim.Optimizer, batch: dict, beta: float, args: Args):
    """``update_epochs`` passes of minibatch Adam on eq. 5 over ``make_batch``'s ``batch``, then
    the beta rule. Returns the new beta and the statistics to log."""
    batch_size = batch["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    adv = batch["advantages"]
    if args.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pi_old = Normal(batch["mean"], batch["std"])
    actor_params, critic_params = agent.actor_parameters(), list(agent.critic.parameters())
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        keys = ("obs", "actions", "logprobs", "mean", "std", "returns")
        shuffled = {key: batch[key][perm] for key in keys} | {"adv": adv[perm]}
        for start in range(0, batch_size, minibatch_size):
            mb = {key: v[start : start + minibatch_size] for key, v in shuffled.items()}
            pi = agent.dist(mb["obs"])
            ratio = (pi.log_prob(mb["actions"]).sum(-1) - mb["logprobs"]).exp()  # r_t(theta)
            kl = kl_divergence(Normal(mb["mean"], mb["std"]), pi).sum(-1).mean()
            pg_loss = -(ratio * mb["adv"]).mean() + beta * kl  # eq. 5, negated
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
    }
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    return min(max(beta, BETA_MIN), BETA_MAX), stats


if __name__ == "__main__":
    args = cli.parse_args(Args)
    check_args(args)
    batch_size = args.num_envs * args.num_steps
    num_iterations = args.total_timesteps // batch_size
    run = Run(args)  # TRY NOT TO MODIFY: run folder, TensorBoard, seeding (common/run.py)

    # ENV SETUP: N envs stepped in turn, SAME_STEP autoreset (see rollout)
    envs = gym.vector.SyncVectorEnv([make_env(args.env_id)] * args.num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    obs_dim = envs.single_observation_space.shape[0]
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(run.streams.action_space_seed)

    # ALGO LOGIC: networks, optimiser, normalisers
    agent = Agent(obs_dim, act_dim, init_log_std=args.init_log_std)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    norm = RunningMeanStd((obs_dim,))
    reward_scaler = RewardScaler(args.num_envs, args.gamma)
    # what model.pt keeps, and what else resume.pt needs to go on
    model = dict(agent=agent, normalizer=norm)
    training = dict(optimizer=optimizer, reward_scaler=reward_scaler)
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
            traj, raw_obs, episodes = rollout(envs, agent, norm, raw_obs, args.num_steps, update_norm=args.norm_obs)
            global_step += args.num_envs * args.num_steps
            run.record_episodes(episodes, global_step)

            # ALGO LOGIC: advantages (eq. 3-4) on scaled rewards
            if args.norm_reward:
                traj["rewards"] = reward_scaler(traj["rewards"], traj["episode_ends"])
            batch = make_batch(agent, traj, norm(raw_obs), args.gamma, args.gae_lambda)

            # ALGO LOGIC: the PPO-KL update (eq. 5)
            beta, stats = ppo_kl_update(agent, optimizer, batch, beta, args)
            stats |= {"charts/learning_rate": optimizer.param_groups[0]["lr"]}
            run.end_iteration(stats, beta=beta)  # TRY NOT TO MODIFY: log, evaluate, save
