"""A vectorised environment for training: every environment in this process, stepped in lockstep, with the
per-environment wrappers of :func:`agents.training.run.make_env` done once for the whole batch.

``vec_env: dummy`` wraps each :class:`~envs.crowd_nav.CrowdNavEnv` in the discrete action wrapper, a success flag
and SB3's ``Monitor``, then steps them with SB3's ``DummyVecEnv``, which also deep-copies every step's infos. For
environments this cheap, that bookkeeping is a good part of a step. :class:`CrowdVecEnv` (``vec_env: batched``)
does the same things once per batch: the discrete actions of all environments are mapped to velocities in one
vectorised call, the episode return, length and time (SB3's ``info["episode"]``, as ``Monitor`` writes it) and
``info["is_success"]`` are written at an episode's end, and infos are handed over without copying (the
environment returns fresh dicts every step). Observations, rewards, dones, truncation flags, terminal
observations and resets are those of ``DummyVecEnv`` over the wrapped environments, step for step
(``tests/agents/test_vec_env.py``). ``vec_env: vector`` (``auto``'s choice where it applies) steps the natively
batched environment instead: :mod:`agents.batched_vec_env`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn


class CrowdVecEnv(DummyVecEnv):
    """``n`` environments in this process, stepped in lockstep, with the training wrappers' work batched.

    Args:
        env_fns: functions making the bare environments (:class:`~envs.crowd_nav.CrowdNavEnv`, no wrappers).
        actions: the discrete action set (:class:`agents.actions.GoalRelativeActions`); the vectorised environment
            then takes ``Discrete(n)`` actions. None: the environments' own (continuous) actions.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], actions: Any = None) -> None:
        super().__init__(list(env_fns))
        self.action_set = actions
        if actions is not None:
            self.action_space = gym.spaces.Discrete(actions.n)
        self._returns = np.zeros(self.num_envs, dtype=np.float64)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._t_start = time.time()

    def reset(self) -> Any:
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return super().reset()

    def step_wait(self) -> VecEnvStepReturn:
        actions = self.actions
        if self.action_set is not None:
            actions = self.action_set.to_env_actions(np.asarray(actions).reshape(-1), self.buf_obs["robot"])
        infos: list[dict[str, Any]] = []
        for i, env in enumerate(self.envs):
            obs, reward, terminated, truncated, info = env.step(actions[i])
            self.buf_rews[i] = reward
            done = terminated or truncated
            self.buf_dones[i] = done
            info["TimeLimit.truncated"] = truncated and not terminated
            self._returns[i] += float(reward)
            self._lengths[i] += 1
            if done:
                info["is_success"] = info["episode_metrics"]["outcome"] == "success"
                info["episode"] = {
                    "r": round(float(self._returns[i]), 6),
                    "l": int(self._lengths[i]),
                    "t": round(time.time() - self._t_start, 6),
                }
                self._returns[i], self._lengths[i] = 0.0, 0
                info["terminal_observation"] = obs
                obs, self.reset_infos[i] = env.reset()
            self._save_obs(i, obs)
            infos.append(info)
        self.buf_infos = infos
        return self._obs_from_buf(), np.copy(self.buf_rews), np.copy(self.buf_dones), infos
