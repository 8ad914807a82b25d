"""A discrete action parameterisation: velocities relative to the goal direction.

The environment's action is a continuous velocity (``Box(-1, 1, (2,))``). Crowd-navigation work since
CADRL/SARL (Chen et al. 2017, 2019) usually lets the policy choose among a fixed set of velocities
instead; here the set is every heading in ``headings_deg`` (relative to the direction of the goal) at
every speed in ``speed_fractions`` (of the speed cap: the preferred speed, or what reaches the goal in
one step), plus standing still. By default it holds the sampling planner's 37 candidates plus five
headings behind the robot (57 actions), so the planner's choice is always one of the policy's
actions and behaviour cloning is a classification — a regression on the continuous action averages
"swerve left" and "swerve right" into "straight on", which is how the cloned policies collided.

Only the holonomic robot is supported (a unicycle cannot take a velocity in one step).

- :class:`GoalRelativeActions`: the action set: velocities, environment actions, the nearest action
  to a given environment action (to label a teacher's choices); :func:`action_set` builds it from a training
  config's ``action:`` section (None for continuous actions).
- :class:`DiscreteActionWrapper`: a Gymnasium wrapper exposing ``Discrete(n)`` to the learner.
- :class:`DiscretePolicy`: an SB3 model trained on the wrapper, acting on the plain environment
  (``predict(obs) -> env actions``), as :mod:`agents.rollout` expects of every policy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Final

import gymnasium as gym
import numpy as np

from agents.planners.base import velocities_to_actions
from agents.planners.sampling import DEFAULT_HEADINGS_DEG, DEFAULT_SPEED_FRACTIONS
from crowdnav_mesrnn.config import ConfigError, check_keys
from envs.config import CrowdNavConfig

#: Action parameterisations accepted by the training configuration (``action.kind``).
ACTION_KINDS: Final[tuple[str, ...]] = ("continuous", "discrete")
#: Default headings of the discrete set: the sampling planner's, then five behind the robot, degrees.
DISCRETE_HEADINGS_DEG: Final[tuple[float, ...]] = (*DEFAULT_HEADINGS_DEG, 120.0, -120.0, 150.0, -150.0, 180.0)


class GoalRelativeActions:
    """Headings (relative to the goal direction) x speed fractions (of the speed cap), then standing still.

    Action ``i < len(headings) * len(speeds)`` is heading ``i // len(speeds)`` at speed ``i % len(speeds)``
    (heading-major, as the sampling planner orders its candidates); the last action stands still.

    Args:
        env_config: the environment's configuration (holonomic kinematics).
        headings_deg: headings relative to the goal direction, degrees.
        speed_fractions: speeds as fractions of the speed cap, in (0, 1].
    """

    def __init__(
        self,
        env_config: CrowdNavConfig,
        headings_deg: Sequence[float] = DISCRETE_HEADINGS_DEG,
        speed_fractions: Sequence[float] = DEFAULT_SPEED_FRACTIONS,
    ) -> None:
        if env_config.kinematics != "holonomic":
            raise ConfigError(
                f"action kind 'discrete' needs kinematics 'holonomic', got {env_config.kinematics!r}; "
                "use action kind 'continuous' for the unicycle"
            )
        angles = np.deg2rad(np.asarray(headings_deg, dtype=np.float64).reshape(-1))
        speeds = np.asarray(speed_fractions, dtype=np.float64).reshape(-1)
        if not len(angles) or not len(speeds):
            raise ConfigError("action keys 'headings_deg' and 'speed_fractions' must not be empty")
        if not np.all(np.isfinite(angles)):
            raise ConfigError(f"action key 'headings_deg' must be finite numbers, got {list(headings_deg)!r}")
        if not np.all((speeds > 0) & (speeds <= 1)):
            raise ConfigError(f"action key 'speed_fractions' must lie in (0, 1], got {speeds.tolist()!r}")
        self.cfg = env_config
        self.angles = np.append(np.repeat(angles, len(speeds)), 0.0)  # (n,)
        self.fractions = np.append(np.tile(speeds, len(angles)), 0.0)  # (n,)

    @property
    def n(self) -> int:
        """Number of actions (standing still included)."""
        return len(self.angles)

    def velocities(self, robot: np.ndarray) -> np.ndarray:
        """World-frame velocities ``(B, n, 2)`` m/s of every action, for robot observations ``(B, R)``."""
        robot = np.asarray(robot, dtype=np.float64)
        offset = robot[:, :2]
        dist = np.hypot(offset[:, 0], offset[:, 1])
        cap = np.minimum(self.cfg.robot_pref_speed_mps, dist / self.cfg.dt_s)  # (B,)
        theta = np.arctan2(offset[:, 1], offset[:, 0])[:, None] + self.angles[None, :]
        speed = self.fractions[None, :] * cap[:, None]
        return np.stack([speed * np.cos(theta), speed * np.sin(theta)], axis=-1)

    def to_env_actions(self, index: np.ndarray, robot: np.ndarray) -> np.ndarray:
        """Environment actions ``(B, 2)`` float32 for action indices ``(B,)`` and robot observations ``(B, R)``."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        robot = np.asarray(robot).reshape(len(index), -1)
        if np.any((index < 0) | (index >= self.n)):
            raise ValueError(f"discrete action must be in 0..{self.n - 1}, got {index.tolist()!r}")
        vel = self.velocities(robot)[np.arange(len(index)), index]
        return velocities_to_actions(vel, robot, self.cfg)

    def nearest(self, env_actions: np.ndarray, robot: np.ndarray) -> np.ndarray:
        """Indices ``(B,)`` of the actions whose velocity is nearest to environment actions ``(B, 2)``."""
        wanted = np.asarray(env_actions, dtype=np.float64).reshape(-1, 2) * self.cfg.robot_pref_speed_mps
        diff = self.velocities(np.asarray(robot).reshape(len(wanted), -1)) - wanted[:, None, :]
        return np.argmin(np.einsum("bnd,bnd->bn", diff, diff), axis=1)


def make_actions(env_config: CrowdNavConfig, options: Mapping[str, Any]) -> GoalRelativeActions:
    """The action set of a training configuration's ``action`` section (without its ``kind``)."""
    check_keys(options, ("kind", "headings_deg", "speed_fractions"), "action")
    return GoalRelativeActions(env_config, **dict(options))


def action_set(action: Mapping[str, Any] | None, env_config: Any) -> Any:
    """The discrete action set an ``action:`` section describes for an environment configuration, or None."""
    options = dict(action or {})
    kind = options.pop("kind", "continuous")
    if kind not in ACTION_KINDS:
        raise ConfigError(f"unknown action kind {kind!r}; valid: {', '.join(ACTION_KINDS)}")
    if kind == "continuous":
        if options:
            raise ConfigError(f"action kind 'continuous' takes no options, got {', '.join(sorted(options))}")
        return None
    return make_actions(env_config, options)


class DiscreteActionWrapper(gym.ActionWrapper):
    """Exposes :class:`GoalRelativeActions` as ``Discrete(n)``; the environment still gets its continuous action."""

    def __init__(self, env: gym.Env, actions: GoalRelativeActions) -> None:
        super().__init__(env)
        self.actions = actions
        self.action_space = gym.spaces.Discrete(actions.n)
        self._robot: np.ndarray | None = None

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._robot = np.asarray(obs["robot"])
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(self.action(action))
        self._robot = np.asarray(obs["robot"])
        return obs, reward, terminated, truncated, info

    def action(self, action: Any) -> np.ndarray:
        if self._robot is None:
            raise RuntimeError("call reset() before step()")
        return self.actions.to_env_actions(np.asarray([int(np.asarray(action).reshape(()))]), self._robot[None])[0]


class DiscretePolicy:
    """An SB3 model with a ``Discrete`` action space, acting on the plain environment.

    ``predict`` takes one observation or a batch and returns environment actions (``(2,)`` or ``(B, 2)``),
    like :mod:`agents.planners`.
    """

    def __init__(self, model: Any, actions: GoalRelativeActions) -> None:
        self.model = model
        self.actions = actions

    def predict(
        self,
        obs: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        index, state = self.model.predict(dict(obs), state, episode_start, deterministic)
        single = np.ndim(obs["mask"]) == 1
        robot = np.asarray(obs["robot"])[None] if single else np.asarray(obs["robot"])
        env_actions = self.actions.to_env_actions(np.atleast_1d(index), robot)
        return (env_actions[0] if single else env_actions), state
