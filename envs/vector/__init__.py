"""The batched environment: N episodes of :class:`envs.crowd_nav.CrowdNavEnv` stepped at once in one process
(:class:`BatchedCrowdNavEnv`), and :func:`make_vector_env`, the ``vector_entry_point`` of every environment id."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium

from envs.vector.batched import BatchedCrowdNavEnv, NotBatchedError, check_max_episode_steps

__all__ = ["BatchedCrowdNavEnv", "NotBatchedError", "make_vector_env"]


def make_vector_env(num_envs: int = 1, render_mode: str | None = None, **kwargs: Any) -> gymnasium.vector.VectorEnv:
    """``gymnasium.make_vec(id, num_envs=N)`` (the ``vector_entry_point`` of every id): the batched environment, or,
    for what it does not step (``reaction`` other than ``none``, a ``render_mode``), a ``SyncVectorEnv`` of single
    environments with the same arguments (the same episodes, stepped one after another), with a warning that says
    why. ``BatchedCrowdNavEnv`` itself refuses those settings (:class:`NotBatchedError`)."""
    try:
        return BatchedCrowdNavEnv(num_envs=num_envs, render_mode=render_mode, **kwargs)
    except NotBatchedError as exc:
        reason = str(exc).split(";")[0]
    from envs.crowd_nav import CrowdNavEnv

    warnings.warn(
        f"{reason}: gymnasium.make_vec steps {num_envs} single environments one after another instead "
        "(a SyncVectorEnv: the same episodes, without the batched speed-up)",
        UserWarning,
        stacklevel=2,
    )
    limit = check_max_episode_steps(kwargs.pop("max_episode_steps", None))

    def make() -> gymnasium.Env:
        env = CrowdNavEnv(render_mode=render_mode, **kwargs)
        return env if limit is None else gymnasium.wrappers.TimeLimit(env, limit)

    return gymnasium.vector.SyncVectorEnv(
        [make] * int(num_envs), autoreset_mode=gymnasium.vector.AutoresetMode.NEXT_STEP
    )
