"""A navigation policy for crowdnav-mesrnn, written as a user would: numpy only, the observation in, an action out.

``RepulsivePolicy`` heads for the goal at the preferred speed and is pushed away from every pedestrian it sees --
from where they are and, when the observation carries forecasts, from where they are forecast to be over the next
second -- each push growing as the surface gap shrinks. ``go_to_goal`` is the same rule without people, written as
a plain callable.

What it relies on (see crowdnav-mesrnn's docs/policies.md):

- ``obs["robot"][0:2]``: goal minus robot position, metres;
- ``obs["pedestrians"]``: K rows of (position minus robot, m; velocity minus robot's, m/s), flattened to (K * 4,);
- ``obs["mask"]``: (K,), 1 where a row holds a pedestrian;
- ``obs["forecasts"]`` (absent in the ``none`` arm): K x H forecast positions minus robot, flattened to (K * H * 2,);
- the action: 2 numbers in [-1, 1], the velocity over the preferred speed (holonomic robot, the default).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["RepulsivePolicy", "go_to_goal"]


def go_to_goal(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """Straight to the goal at the preferred speed: the smallest policy the bench accepts (a callable)."""
    offset = np.asarray(obs["robot"][:2], dtype=np.float64)
    dist = float(np.hypot(*offset))
    return (offset / dist).astype(np.float32) if dist > 1e-9 else np.zeros(2, np.float32)


class RepulsivePolicy:
    """Go to the goal, pushed away from people (a potential field).

    Args:
        config: the environment's settings (``crowdnav-mesrnn bench-policy`` passes them to a factory that asks);
            read for the preferred speed, the control step and the radii. Defaults are the environment's.
        push: strength of a pedestrian's push at contact, in preferred speeds.
        range_m: how fast the push fades with the surface gap, metres.
        lookahead_s: how far ahead the forecasts are read, seconds.
    """

    def __init__(self, config: Any = None, push: float = 1.5, range_m: float = 0.6, lookahead_s: float = 1.2) -> None:
        self.speed = float(getattr(config, "robot_pref_speed_mps", 1.0))
        self.dt = float(getattr(config, "dt_s", 0.4))
        self.radii = float(getattr(config, "robot_radius_m", 0.3)) + float(getattr(config, "pedestrian_radius_m", 0.3))
        self.push = push
        self.range_m = range_m
        self.lookahead_steps = max(1, round(lookahead_s / self.dt))

    def _obstacles(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """``(M, 2)`` points to keep away from, robot-relative metres: the pedestrians seen and their forecasts."""
        mask = np.asarray(obs["mask"]).astype(bool)
        k = mask.size
        rows = np.asarray(obs["pedestrians"], dtype=np.float64).reshape(k, -1)
        points = [rows[mask, :2]]
        if "forecasts" in obs:
            future = np.asarray(obs["forecasts"], dtype=np.float64).reshape(k, -1, 2)
            points.append(future[mask, : self.lookahead_steps].reshape(-1, 2))
        return np.concatenate(points)

    def predict(
        self, obs: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        """Stable-Baselines3's interface: one observation in, ``(action, state)`` out."""
        offset = np.asarray(obs["robot"][:2], dtype=np.float64)
        dist = float(np.hypot(*offset))
        speed = min(self.speed, dist / self.dt)
        velocity = offset / dist * speed if dist > 1e-9 else np.zeros(2)
        points = self._obstacles(obs)
        if len(points):
            d = np.hypot(points[:, 0], points[:, 1])
            near = d > 1e-6
            gap = np.maximum(d[near] - self.radii, 0.0)
            away = -points[near] / d[near, None]
            velocity = velocity + self.speed * self.push * (away * np.exp(-gap / self.range_m)[:, None]).sum(axis=0)
        norm = float(np.hypot(*velocity))
        if norm > self.speed:
            velocity = velocity * (self.speed / norm)
        return (velocity / self.speed).astype(np.float32), None
