"""An SB3 ``VecEnv`` over the natively batched environment (:class:`envs.vector.BatchedCrowdNavEnv`).

:class:`BatchedVecEnv` steps N episodes in one call of the batched environment and hands SB3 what its
``DummyVecEnv`` over the training environments of :func:`agents.training.run.make_env` (``CrowdNavEnv`` with the optional
discrete action wrapper, the success flag and SB3's ``Monitor``) hands it: the same observations, rewards, dones and
per-environment info dicts, with ``info["TimeLimit.truncated"]``, and at an episode's end
``info["terminal_observation"]``, ``info["is_success"]`` and ``info["episode"]`` (return, length, time, as
``Monitor`` writes them); the environment is reset in the same step, as SB3 expects
(``tests/agents/test_batched_vec_env.py``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from envs.vector import BatchedCrowdNavEnv


class BatchedVecEnv(VecEnv):
    """``n_envs`` crowd-navigation environments stepped as one batch, for Stable-Baselines3.

    Args:
        n_envs: number of environments (at most 256).
        env_kwargs: keyword arguments of every environment (:class:`envs.crowd_nav.CrowdNavEnv`'s).
        actions: the discrete action set (:class:`agents.actions.GoalRelativeActions`); the vectorised environment
            then takes ``Discrete(n)`` actions. None: the environments' own (continuous) actions.
    """

    def __init__(self, n_envs: int, env_kwargs: Mapping[str, Any], actions: Any = None) -> None:
        self.venv = BatchedCrowdNavEnv(num_envs=n_envs, **dict(env_kwargs))
        self.action_set = actions
        action_space = gym.spaces.Discrete(actions.n) if actions is not None else self.venv.single_action_space
        super().__init__(n_envs, self.venv.single_observation_space, action_space)
        self._actions: np.ndarray | None = None
        self._obs: dict[str, np.ndarray] = {}
        self._returns = np.zeros(n_envs, dtype=np.float64)
        self._lengths = np.zeros(n_envs, dtype=np.int64)
        self._t_start = time.time()

    # ------------------------------------------------------------------ VecEnv API

    def reset(self) -> VecEnvObs:
        options = [dict(o) if o else None for o in self._options]
        if all(o == options[0] for o in options):
            obs, info = self.venv.reset(seed=list(self._seeds), options=options[0])
            self.reset_infos = _unbatch(info, self.num_envs)
        else:  # options differ between environments: one reset each, each keeping its own reset info
            self.reset_infos = [{} for _ in range(self.num_envs)]
            for i, opts in enumerate(options):
                mask = np.zeros(self.num_envs, dtype=bool)
                mask[i] = True
                obs, info = self.venv.reset(seed=list(self._seeds), options={**(opts or {}), "reset_mask": mask})
                self.reset_infos[i] = _unbatch(info, self.num_envs)[i]
        self._reset_seeds()
        self._reset_options()
        self._returns[:] = 0.0
        self._lengths[:] = 0
        self._obs = obs
        return {k: v.copy() for k, v in obs.items()}

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async first"
        actions = self._actions
        if self.action_set is not None:
            actions = self.action_set.to_env_actions(actions.reshape(-1), self._obs["robot"])
        obs, rewards, terminated, truncated, info = self.venv.step(actions)
        dones = terminated | truncated
        infos = _unbatch(info, self.num_envs)
        self._returns += rewards.astype(np.float64)
        self._lengths += 1
        for i in np.flatnonzero(dones).tolist():
            infos[i]["is_success"] = infos[i]["episode_metrics"]["outcome"] == "success"
            infos[i]["episode"] = {
                "r": round(float(self._returns[i]), 6),
                "l": int(self._lengths[i]),
                "t": round(time.time() - self._t_start, 6),
            }
            infos[i]["terminal_observation"] = {k: v[i].copy() for k, v in obs.items()}
            self._returns[i], self._lengths[i] = 0.0, 0
        for i in range(self.num_envs):
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if dones.any():
            obs, reset_info = self.venv.reset(options={"reset_mask": dones})
            for i, item in enumerate(_unbatch(reset_info, self.num_envs)):
                if dones[i]:
                    self.reset_infos[i] = item
        self._obs = obs
        return {k: v.copy() for k, v in obs.items()}, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The attribute of the batched environment (shared by all environments), once per index; the spaces are
        one environment's (``observation_space``, ``action_space``: this ``VecEnv``'s, as ``DummyVecEnv`` gives)."""
        if attr_name in ("observation_space", "action_space"):
            value = getattr(self, attr_name)
        else:
            value = getattr(self.venv, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute of the batched environment. It is shared by every environment, so ``indices`` must
        select all of them (``NotImplementedError`` otherwise: no attribute of some environments only)."""
        self._all_indices(indices, f"set_attr({attr_name!r})")
        setattr(self.venv, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of the batched environment once per index. ``reset``, ``step`` and ``close`` are refused
        (``NotImplementedError``): through this they would act on every environment behind this ``VecEnv``'s back;
        use its own ``reset``, ``step`` and ``close``."""
        if method_name in ("reset", "step", "close"):
            raise NotImplementedError(
                f"env_method({method_name!r}) on the batched environment would {method_name} all "
                f"{self.num_envs} environments behind this VecEnv (its observations and episode statistics would go "
                f"stale); call the VecEnv's own {method_name}()"
            )
        method = getattr(self.venv, method_name)
        return [method(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def _all_indices(self, indices: VecEnvIndices, what: str) -> None:
        chosen = set(self._get_indices(indices))
        if chosen != set(range(self.num_envs)):
            raise NotImplementedError(
                f"{what} with indices={indices!r}: the {self.num_envs} environments are one batched environment that "
                "shares its attributes, so they can be set for all of them only (indices=None)"
            )

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        return super().seed(seed)


def _unbatch(info: Mapping[str, Any], num: int) -> list[dict[str, Any]]:
    """Per-environment info dicts from a vector info (a dict of arrays with ``_key`` masks), with the values the
    single environment gives (Python scalars; None where a float array holds NaN for it). One ``tolist`` per key and
    the NaNs found by one ``isnan`` (a step's info has a dozen keys for every environment)."""
    out: list[dict[str, Any]] = [{} for _ in range(num)]
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info.get(f"_{key}")
        if mask is None:
            continue
        idx = np.flatnonzero(mask).tolist()
        if isinstance(value, Mapping):
            inner = _unbatch(value, num)
            for i in idx:
                out[i][key] = inner[i]
            continue
        for i, item in zip(idx, _values(value, idx), strict=True):
            out[i][key] = item
    return out


def _values(array: np.ndarray, idx: list[int]) -> list[Any]:
    """``array``'s entries at ``idx`` as Python values, a float NaN as None."""
    if array.dtype == object:
        return [None if isinstance(v, float) and math.isnan(v) else v for v in (array[i] for i in idx)]
    chosen = array if len(idx) == len(array) else array[idx]
    values = chosen.tolist()
    if chosen.dtype.kind == "f" and chosen.ndim == 1:  # (rows of a 2-D array are lists, never None)
        for j in np.flatnonzero(np.isnan(chosen)).tolist():
            values[j] = None
    return values
