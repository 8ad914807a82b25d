"""A user's policy from an import path, behind the ``predict`` that :func:`agents.rollout.run_episodes` calls.

The contract (also in ``docs/policies.md``):

- ``IMPORT_PATH`` is ``package.module:attr`` (``attr`` may be dotted: ``module:Class.factory``);
- ``attr`` is the policy -- an object with Stable-Baselines3's ``predict(obs, deterministic=True)`` (returning
  ``(action, state)`` like SB3, or the action alone), or a plain callable ``obs -> action`` -- or a *factory* of
  one: a class, or a function whose parameters all have defaults. A factory is called once per forecast arm, with
  ``config=`` (the arm's :class:`envs.config.CrowdNavConfig`) when it takes a parameter named ``config``;
- ``obs`` is one observation of ``CrowdNav-MESRNN-v0`` (a dict of float32 arrays without a batch dimension:
  ``robot``, ``pedestrians``, ``mask`` and, except in the ``none`` arm, ``forecasts``; see docs/env.md);
- the action is 2 finite numbers in [-1, 1] (holonomic: the velocity over ``robot_pref_speed_mps``; values outside
  are clipped by the environment). Anything else is an error naming the policy, the observation step and the value.
"""

from __future__ import annotations

import importlib
import inspect
import re
from collections.abc import Mapping
from typing import Any, Final

import numpy as np

#: ``package.module:attr`` with dotted identifiers on both sides.
IMPORT_PATH_RE: Final[re.Pattern[str]] = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")
#: What an import path must look like, for messages.
IMPORT_PATH_HELP: Final[str] = "package.module:attr (attr: a policy object, a callable obs -> action, or a factory)"


def check_import_path(path: str) -> tuple[str, str]:
    """``(module, attr)`` of a well-formed import path whose top-level package can be found, without importing it.

    Raises:
        ValueError: malformed, or the top-level package is not installed (the message says how to make it so).
    """
    import importlib.util

    if not IMPORT_PATH_RE.match(path):
        raise ValueError(f"policy {path!r} is not an import path {IMPORT_PATH_HELP}")
    module, attr = path.split(":", 1)
    top = module.split(".", 1)[0]
    if importlib.util.find_spec(top) is None:
        raise ValueError(
            f"policy {path!r}: no module named {top!r}; install your package (pip install -e PATH) or put its folder "
            "on PYTHONPATH"
        )
    return module, attr


def resolve(path: str) -> Any:
    """The object an import path names (the module imported)."""
    module, attr = check_import_path(path)
    try:
        obj: Any = importlib.import_module(module)
    except ImportError as exc:
        raise ValueError(f"policy {path!r}: importing {module!r} failed: {exc}") from exc
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"policy {path!r}: {module!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    return obj


def _is_factory(obj: Any) -> bool:
    """A class, or a function whose parameters all have defaults (a policy callable takes the observation)."""
    if inspect.isclass(obj):
        return True
    if not (inspect.isfunction(obj) or inspect.ismethod(obj)) or hasattr(obj, "predict"):
        return False
    params = inspect.signature(obj).parameters.values()
    return all(p.default is not inspect.Parameter.empty or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in params)


class UserPolicy:
    """A user's policy behind a batched ``predict``: each row of a batch goes to the user's policy alone.

    Args:
        path: the import path (for messages and the report).
        config: the arm's environment config, given to a factory that takes ``config``.
    """

    def __init__(self, path: str, config: Any = None) -> None:
        self.path = path
        target = resolve(path)
        self.factory = _is_factory(target)
        if self.factory:
            takes_config = "config" in inspect.signature(target).parameters
            target = target(config=config) if takes_config else target()
        if hasattr(target, "predict"):
            self.kind = "predict"
        elif callable(target):
            self.kind = "callable"
        else:
            raise ValueError(
                f"policy {path!r} is a {type(target).__name__}: give an object with predict(obs, deterministic=True), "
                "a callable obs -> action, or a factory of one"
            )
        self.policy = target
        self.calls = 0

    def act(self, obs: Mapping[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
        """The action for one observation, checked: ``(2,)`` finite float32."""
        self.calls += 1
        try:
            out = self.policy.predict(obs, deterministic=deterministic) if self.kind == "predict" else self.policy(obs)
        except Exception as exc:
            raise RuntimeError(f"policy {self.path!r} raised on observation {self.calls}: {exc!r}") from exc
        if self.kind == "predict" and isinstance(out, tuple) and len(out) == 2 and np.size(out[0]) == 2:
            out = out[0]  # SB3's (action, state)
        try:
            action = np.asarray(out, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            action = np.zeros(0)
        if action.shape != (2,) or not np.all(np.isfinite(action)):
            raise ValueError(
                f"policy {self.path!r} returned {out!r} for observation {self.calls}; an action is 2 finite numbers "
                "in [-1, 1]"
            )
        return action.astype(np.float32)

    def predict(
        self,
        obs: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """SB3's ``predict`` over a batch (a leading dimension on every key): one call of the user's policy per row."""
        batch = len(next(iter(obs.values())))
        actions = [self.act({k: np.asarray(v[i]) for k, v in obs.items()}, deterministic) for i in range(batch)]
        return np.stack(actions), None
