"""Behaviour-cloning warm start: fit an SB3 policy to a planner's actions before reinforcement learning.

The teacher (the sampling planner by default) drives training-environment episodes with the same
observation the policy gets (the same forecast arm). The policy's action mean is then fitted to the
teacher's actions with a plain supervised loss, and optionally its value function to the teacher
episodes' discounted Monte-Carlo returns, so RL starts from a policy that already avoids most
collisions instead of from the standstill that the early reward favours. The whole procedure is
deterministic given the seed.

- PPO (``ActorCriticPolicy``): loss on the Gaussian's mean (``mse``: mean squared error to the
  teacher action; ``nll``: the Gaussian's negative log-likelihood of it); ``value`` fits
  ``predict_values``; then ``log_std`` is set to the configured value (exploration around the
  cloned behaviour).
- SAC: the actor's deterministic (squashed) action is fitted; ``value`` fits both critics
  ``Q(s, a_teacher)`` to the returns and copies them to the target critics; ``log_std`` does not
  apply (SAC's standard deviation depends on the state and is learned with its entropy target).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium import spaces as gym_spaces
from torch.nn import functional as F

from agents.actions import DiscretePolicy
from agents.planners import make_planner
from agents.rollout import SB3Policy, run_episodes

# The ``pretrain:`` section is read with the rest of the config file (without torch): agents.training.config.
from agents.training.config import ACTION_LOSSES as ACTION_LOSSES
from agents.training.config import PretrainConfig, teacher_class
from envs.config import config_from


def make_teacher(cfg: PretrainConfig, env_config: Any) -> Any:
    """The teacher of a warm start for an environment configuration (see :attr:`PretrainConfig.teacher`), planning
    with the true future when :attr:`PretrainConfig.teacher_predictor` is ``oracle`` (:class:`TrueFutureTeacher`)."""
    cls = teacher_class(cfg.teacher)
    if cls is None:
        teacher = make_planner(cfg.teacher, env_config, **dict(cfg.teacher_kwargs))
    else:
        teacher = cls(env_config, **dict(cfg.teacher_kwargs))
    return TrueFutureTeacher(teacher) if cfg.teacher_predictor == "oracle" else teacher


class TrueFutureTeacher:
    """A teacher that plans with the true future whatever the student's forecast arm (PRIVILEGED: it reads its
    environments; a teacher, never a policy that is evaluated).

    Before each batched ``predict`` the environment of every row is bound (``bind_envs``, as
    :func:`agents.rollout.run_episodes` and :func:`collect_teacher` do); ``predict`` then gives the wrapped teacher the
    observations with ``forecasts`` replaced (or, for the ``none`` arm, added) by each environment's
    :meth:`envs.crowd_nav.CrowdNavEnv.true_future_forecasts`: what the oracle arm would observe in the same state. So
    one teacher labels every arm's states, and the students differ only in their forecast input (issue 29 §3).
    """

    privileged = True

    def __init__(self, teacher: Any) -> None:
        self.teacher = teacher
        self.envs: list[Any] = []

    def bind_envs(self, envs: Sequence[Any]) -> None:
        self.envs = list(envs)
        bind = getattr(self.teacher, "bind_envs", None)
        if callable(bind):
            bind(envs)

    def predict(
        self, obs: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        rows = len(obs["mask"])
        if len(self.envs) != rows:
            raise RuntimeError(
                f"the true-future teacher has {len(self.envs)} bound environment(s) for {rows} observation row(s): "
                "bind_envs(envs) with one environment per row before every predict"
            )
        truth = np.stack([getattr(env, "unwrapped", env).true_future_forecasts() for env in self.envs])
        return self.teacher.predict({**obs, "forecasts": truth}, state, episode_start, deterministic)


class _Labelling:
    """A driver policy whose every batched ``predict`` also asks the teacher for its actions on the same observations
    (kept in order, for :func:`collect_teacher`'s step hook, which sees the rows in the same order)."""

    def __init__(self, driver: Any, teacher: Any) -> None:
        self.driver, self.teacher = driver, teacher
        self.pending: list[np.ndarray] = []

    def bind_envs(self, envs: Sequence[Any]) -> None:
        """The environments of the next batch's rows, for the teacher (and a driver that reads them too)."""
        for policy in {id(p): p for p in (self.teacher, self.driver)}.values():
            bind = getattr(policy, "bind_envs", None)
            if callable(bind):
                bind(envs)

    def predict(
        self, obs: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        labels = np.asarray(self.teacher.predict(obs)[0], dtype=np.float32)
        self.pending.extend(labels)
        if self.driver is self.teacher:
            return labels, None
        return self.driver.predict(obs, state, episode_start, deterministic)


def teacher_seeds(seed: int, episodes: int, round_: int = 0) -> list[int]:
    """Seeds of the warm start's episodes in DAgger round ``round_`` (0: the teacher's own episodes); a stream of
    their own, distinct from the evaluation lists."""
    rng = np.random.default_rng([int(seed), 0x5EED, 7] + ([int(round_)] if round_ else []))
    return [int(s) for s in rng.integers(0, 2**31, size=episodes)]


def discounted_returns(rewards: list[float], gamma: float) -> np.ndarray:
    """``G_t = r_t + gamma * G_{t+1}`` with ``G`` after the last step 0 (``(T,)``)."""
    out = np.zeros(len(rewards), dtype=np.float64)
    acc = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        acc = rewards[t] + gamma * acc
        out[t] = acc
    return out


@dataclass
class TeacherData:
    """Transitions of the teacher's episodes: observations (dict of ``(N, ...)``), actions ``(N, 2)``,
    Monte-Carlo returns ``(N,)``, and the episodes' outcomes."""

    observations: dict[str, np.ndarray]
    actions: np.ndarray
    returns: np.ndarray
    outcomes: list[str]

    def __len__(self) -> int:
        return len(self.actions)


def collect_teacher(
    cfg: PretrainConfig,
    env_kwargs: Mapping[str, Any],
    seed: int,
    gamma: float,
    progress: bool = False,
    driver: Any = None,
    round_: int = 0,
) -> TeacherData:
    """Gather labelled transitions: ``driver`` (default: the teacher) drives episodes on the training environments,
    and every observation it met is labelled with the teacher's action for it.

    Returns:
        the observations, the teacher's actions, the Monte-Carlo returns of the driver's episodes and their outcomes.
    """
    from envs.crowd_nav import CrowdNavEnv

    env_cfg = config_from(dict(env_kwargs), {})
    teacher = make_teacher(cfg, env_cfg)
    episodes = cfg.episodes if round_ == 0 else (cfg.dagger_episodes or cfg.episodes)
    envs = [CrowdNavEnv(**dict(env_kwargs)) for _ in range(max(1, min(cfg.n_envs, episodes)))]
    online = callable(getattr(teacher, "bind_envs", None))  # reads the environments: label before they move on
    labelling = _Labelling(teacher if driver is None else driver, teacher) if online else None
    per_episode: dict[int, tuple[list[dict[str, np.ndarray]], list[np.ndarray], list[float]]] = {}
    name = cfg.teacher + (f" ({cfg.teacher_predictor} forecasts)" if cfg.teacher_predictor else "")

    def record(k: int, obs: Mapping[str, np.ndarray], action: np.ndarray, reward: float, *_: bool) -> None:
        obs_list, act_list, rew_list = per_episode.setdefault(k, ([], [], []))
        obs_list.append(dict(obs))
        label = labelling.pending.pop(0) if labelling is not None else action
        act_list.append(np.asarray(label, dtype=np.float32))
        rew_list.append(reward)

    try:
        rows = run_episodes(
            labelling if labelling is not None else (teacher if driver is None else driver),
            envs,
            teacher_seeds(seed, episodes, round_),
            on_step=record,
            progress=progress,
            desc=f"warm start: {name} teacher's episodes"
            if driver is None
            else f"DAgger round {round_}/{cfg.dagger_rounds}: student's episodes, labelled by {name}",
        )
    finally:
        for env in envs:
            env.close()
    observations: list[dict[str, np.ndarray]] = []
    actions: list[np.ndarray] = []
    returns: list[np.ndarray] = []
    for k in sorted(per_episode):
        obs_list, act_list, rew_list = per_episode[k]
        observations.extend(obs_list)
        actions.extend(act_list)
        returns.append(discounted_returns(rew_list, gamma))
    if not actions:
        raise ValueError("the teacher produced no transitions (pretrain.episodes = 0?)")
    stacked = {key: np.stack([o[key] for o in observations]) for key in observations[0]}
    if driver is None or online:
        labels = np.stack(actions)
    else:  # the teacher's action for every observation the driver met, in chunks (its scoring is (B, C, K, L) wide)
        n = len(actions)
        labels = np.concatenate(
            [
                np.asarray(teacher.predict({k: v[i : i + 1024] for k, v in stacked.items()})[0], dtype=np.float32)
                for i in range(0, n, 1024)
            ]
        )
    return TeacherData(stacked, labels, np.concatenate(returns), [str(r["outcome"]) for r in rows])


def concatenate(parts: list[TeacherData]) -> TeacherData:
    """The transitions of several collections, in order."""
    return TeacherData(
        {k: np.concatenate([p.observations[k] for p in parts]) for k in parts[0].observations},
        np.concatenate([p.actions for p in parts]),
        np.concatenate([p.returns for p in parts]),
        [o for p in parts for o in p.outcomes],
    )


def student_policy(model: Any, vecnormalize: Any = None, actions: Any = None) -> Any:
    """The policy being warm-started, acting on plain environment observations like every policy of
    :mod:`agents.rollout` (normalised for it when training uses ``VecNormalize``; discrete choices mapped to
    environment actions)."""
    policy = SB3Policy(model, vecnormalize, source="warm start")
    return policy if actions is None else DiscretePolicy(policy, actions)


def _action_loss(policy: Any, obs: dict[str, torch.Tensor], target: torch.Tensor, loss: str) -> torch.Tensor:
    from stable_baselines3.common.policies import ActorCriticPolicy

    if isinstance(policy, ActorCriticPolicy):
        dist = policy.get_distribution(obs)
        if loss == "nll" or target.dtype == torch.int64:  # discrete actions: cross-entropy of the teacher's label
            return -dist.log_prob(target).mean()
        return F.mse_loss(dist.distribution.mean, target)
    if loss == "nll":
        raise ValueError("pretrain loss 'nll' is for PPO policies; use 'mse' with SAC")
    return F.mse_loss(policy.actor(obs, deterministic=True), target)


def _value_loss(
    policy: Any, obs: dict[str, torch.Tensor], actions: torch.Tensor, returns: torch.Tensor
) -> torch.Tensor:
    from stable_baselines3.common.policies import ActorCriticPolicy

    if isinstance(policy, ActorCriticPolicy):
        return F.smooth_l1_loss(policy.predict_values(obs).squeeze(-1), returns)
    qs = policy.critic(obs, actions)
    return sum(F.smooth_l1_loss(q.squeeze(-1), returns) for q in qs) / len(qs)


def fit_policy(
    model: Any,
    data: TeacherData,
    cfg: PretrainConfig,
    seed: int,
    vecnormalize: Any = None,
    actions: Any = None,
    epochs: int | None = None,
) -> dict[str, float]:
    """Fit ``model.policy`` to the teacher's data (in place); returns the first and last epochs' mean losses.

    With ``vecnormalize``, its observation statistics are first updated with the teacher's observations and the
    policy is fitted on normalised observations (as it will see them in training). With ``actions`` (a discrete
    set, :class:`agents.actions.GoalRelativeActions`) each teacher action is labelled with the nearest action of
    the set and the policy is fitted by cross-entropy (classification), whatever ``cfg.loss`` says.
    """
    from stable_baselines3.common.policies import ActorCriticPolicy

    policy = model.policy
    if actions is None and not isinstance(getattr(model, "action_space", None), gym_spaces.Box):
        raise ValueError(
            f"the policy's action space is {model.action_space}: pass the discrete action set (actions=...) to label "
            "the teacher's continuous actions"
        )
    obs_np = data.observations
    if vecnormalize is not None:
        for key in vecnormalize.norm_obs_keys or []:
            vecnormalize.obs_rms[key].update(obs_np[key])
        obs_np = vecnormalize.normalize_obs(dict(obs_np))
    device = policy.device
    obs_all = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32, device=device) for k, v in obs_np.items()}
    if callable(getattr(policy, "with_geometry", None)):  # inputs computed from the observation alone: once
        obs_all = policy.with_geometry(obs_all)
    if actions is not None:
        labels = actions.nearest(data.actions, data.observations["robot"])
        act_all = torch.as_tensor(labels, dtype=torch.int64, device=device)
    else:
        act_all = torch.as_tensor(np.clip(data.actions, -1.0, 1.0), device=device)
    ret_all = torch.as_tensor(data.returns, dtype=torch.float32, device=device)
    params = list(policy.parameters())
    if not isinstance(policy, ActorCriticPolicy):  # SAC: the targets follow the critics, not the optimiser
        target_ids = {id(p) for p in policy.critic_target.parameters()}
        params = [p for p in params if id(p) not in target_ids]
    optimiser = torch.optim.Adam(params, lr=cfg.lr)
    gen = torch.Generator().manual_seed(int(seed))
    n = len(data)
    history: list[float] = []
    policy.set_training_mode(True)
    for _ in range(cfg.epochs if epochs is None else epochs):
        order = torch.randperm(n, generator=gen)
        total, batches = 0.0, 0
        for start in range(0, n, cfg.batch_size):
            idx = order[start : start + cfg.batch_size].to(device)
            obs = {k: v[idx] for k, v in obs_all.items()}
            loss = _action_loss(policy, obs, act_all[idx], cfg.loss)
            if cfg.value:
                loss = loss + cfg.value_coef * _value_loss(policy, obs, act_all[idx], ret_all[idx])
            optimiser.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            optimiser.step()
            total += float(loss.detach())
            batches += 1
        history.append(total / max(batches, 1))
    policy.set_training_mode(False)
    if isinstance(policy, ActorCriticPolicy):
        if cfg.log_std is not None and hasattr(policy, "log_std") and isinstance(policy.log_std, torch.nn.Parameter):
            with torch.no_grad():
                policy.log_std.fill_(float(cfg.log_std))
    elif cfg.value:
        policy.critic_target.load_state_dict(policy.critic.state_dict())
    return {"loss_first_epoch": history[0], "loss_last_epoch": history[-1]}


def pretrain(
    model: Any,
    cfg: PretrainConfig,
    env_kwargs: Mapping[str, Any],
    seed: int,
    gamma: float,
    vecnormalize: Any = None,
    progress: bool = False,
    actions: Any = None,
) -> dict[str, Any]:
    """Collect the teacher's episodes and fit ``model``'s policy to them (see the module docstring).

    Args:
        model: an SB3 PPO or SAC model (its policy is changed in place).
        cfg: the warm-start settings.
        env_kwargs: keyword arguments of the training environments.
        seed: seeds the teacher's episodes and the minibatch order.
        gamma: discount of the Monte-Carlo returns (the algorithm's).
        vecnormalize: the training ``VecNormalize``, if any.
        progress: progress bar over the teacher's episodes.
        actions: the discrete action set the policy chooses from, or None (continuous actions).

    Returns:
        statistics: teacher episodes, transitions, success rate, losses, seconds.
    """
    started = time.perf_counter()
    torch.manual_seed(int(seed))
    data = collect_teacher(cfg, env_kwargs, seed, gamma, progress=progress)
    teacher_success = sum(o == "success" for o in data.outcomes) / max(len(data.outcomes), 1)
    losses = fit_policy(model, data, cfg, seed, vecnormalize, actions)
    rounds: list[dict[str, Any]] = []
    student = student_policy(model, vecnormalize, actions)
    for r in range(1, cfg.dagger_rounds + 1):
        new = collect_teacher(cfg, env_kwargs, seed, gamma, progress=progress, driver=student, round_=r)
        data = concatenate([data, new])
        losses = fit_policy(model, data, cfg, seed + r, vecnormalize, actions, epochs=cfg.dagger_epochs)
        rounds.append(
            {
                "round": r,
                "student_success_rate": sum(o == "success" for o in new.outcomes) / max(len(new.outcomes), 1),
                "transitions": len(data),
                **losses,
            }
        )
    return {
        "teacher": cfg.teacher,
        "episodes": cfg.episodes + cfg.dagger_rounds * (cfg.dagger_episodes or cfg.episodes),
        "transitions": len(data),
        "teacher_success_rate": teacher_success,
        "dagger": rounds,
        **losses,
        "seconds": round(time.perf_counter() - started, 3),
    }
