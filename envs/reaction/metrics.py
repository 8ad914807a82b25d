"""What the robot does to people: disturbance metrics of one episode, measured against the recording.

Definitions (``tol`` = :attr:`~envs.reaction.params.ReactionParams.on_track_tolerance_m`; the times are those at which
:meth:`DisturbanceMetrics.update` is called, the environment's control steps):

* **deviation** of a pedestrian at a time: distance from its actual position to its recorded position at the same
  time, where both exist.
* ``ped_disturbed``: pedestrians whose deviation ever exceeded ``tol``.
* ``ped_deviation_mean_m``: mean deviation over the (pedestrian, time) pairs of disturbed pedestrians at which it
  exceeded ``tol`` (the mean distance from the recording while off it).
* ``ped_deviation_max_m``: the largest deviation.
* ``ped_delay_s``: the sum over disturbed pedestrians of their delay at their last time in the episode (the
  episode's end, or the end of their track): the time they still need, beyond the recording, to reach their recorded
  end point. It is the pedestrian's time shift (``pause``: the time it waited; it then walks its recording that
  much later) plus its lag behind that shifted track: ``t - s - tau``, ``tau`` the latest recorded time (up to
  ``t - s``, over the episode's times) at which the recording passes nearest to the pedestrian's position (on the
  recorded polyline, interpolated between times). The lag is 0 for a pedestrian on its (shifted) track within
  ``tol``: one that caught up with its recording (``orca``, ``social_force``: a rejoined pedestrian is back at its
  recorded position at the recorded time) has no delay, only the deviation it had on the way.

All four are 0 under ``none``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.reaction.base import CrowdStep


class DisturbanceMetrics:
    """Accumulates the disturbance of one episode (see the module docstring).

    Args:
        tolerance_m: distance from the recording beyond which a pedestrian is disturbed, metres.
    """

    def __init__(self, tolerance_m: float) -> None:
        self.tolerance_m = float(tolerance_m)
        self.reset()

    def reset(self) -> None:
        """Forget the episode."""
        self._times: list[float] = []
        self._recorded: list[np.ndarray] = []
        self._recorded_present: list[np.ndarray] = []
        self._disturbed = np.zeros(0, dtype=bool)
        # each pedestrian at its last time: position, shift, distance from its shifted track, the time
        self._pos = np.zeros((0, 2))
        self._shift = np.zeros(0)
        self._offtrack = np.zeros(0)
        self._last_t = np.zeros(0)
        self._sum = 0.0
        self._count = 0
        self._max = 0.0

    def update(self, t_s: float, crowd: CrowdStep, recorded: np.ndarray, recorded_present: np.ndarray) -> None:
        """Record the pedestrians at ``t_s``.

        Args:
            t_s: the time, seconds (increasing over the calls).
            crowd: the reaction model's state at ``t_s`` (its last :class:`~envs.reaction.base.CrowdStep`).
            recorded: ``(N, 2)`` recorded positions at ``t_s``, metres.
            recorded_present: ``(N,)`` recorded presence at ``t_s``.
        """
        n = len(crowd.present)
        if not self._times:
            self._disturbed = np.zeros(n, dtype=bool)
            self._pos, self._shift, self._offtrack, self._last_t = (
                np.zeros((n, 2)),
                np.zeros(n),
                np.zeros(n),
                np.zeros(n),
            )
        self._times.append(float(t_s))
        self._recorded.append(np.array(recorded, dtype=np.float64))
        self._recorded_present.append(np.array(recorded_present, dtype=bool))
        dev = np.where(crowd.present & recorded_present, crowd.deviation_m, 0.0)
        off = dev > self.tolerance_m
        if off.any():
            self._disturbed |= off
            self._sum += float(dev[off].sum())
            self._count += int(off.sum())
            self._max = max(self._max, float(dev[off].max()))
        here = crowd.present
        self._pos[here] = crowd.positions[here]
        self._shift[here] = crowd.shift_s[here]
        self._offtrack[here] = crowd.offtrack_m[here]
        self._last_t[here] = t_s

    def delays_s(self) -> np.ndarray:
        """``(N,)`` every pedestrian's delay at its last time (0 for the undisturbed), seconds."""
        out = np.where(self._disturbed, self._shift, 0.0)
        lagging = np.flatnonzero(self._disturbed & (self._offtrack > self.tolerance_m))
        if len(lagging):
            times = np.array(self._times)
            rec = np.stack(self._recorded)
            rec_present = np.stack(self._recorded_present)
            for i in lagging.tolist():
                t_ref = self._last_t[i] - self._shift[i]
                tau = nearest_time(self._pos[i], times, rec[:, i], rec_present[:, i], t_ref)
                if tau is not None:
                    out[i] += max(0.0, t_ref - tau)
        return out

    def summary(self) -> dict[str, Any]:
        """``ped_disturbed``, ``ped_deviation_mean_m``, ``ped_deviation_max_m``, ``ped_delay_s`` (see the module)."""
        disturbed = int(self._disturbed.sum())
        return {
            "ped_disturbed": disturbed,
            "ped_deviation_mean_m": self._sum / self._count if self._count else 0.0,
            "ped_deviation_max_m": self._max,
            "ped_delay_s": float(self.delays_s().sum()) if disturbed else 0.0,
        }


def nearest_time(
    point: np.ndarray, times: np.ndarray, track: np.ndarray, present: np.ndarray, t_max: float
) -> float | None:
    """The latest time ``<= t_max`` at which a recorded track passes nearest to ``point``.

    Args:
        point: ``(2,)`` metres.
        times: ``(T,)`` seconds, increasing.
        track: ``(T, 2)`` recorded positions at ``times``, metres; consecutive present times are joined by segments
            (positions in between interpolated in time).
        present: ``(T,)`` bool.
        t_max: latest time considered, seconds.

    Returns:
        the time, or None when the track has no position by ``t_max``.
    """
    idx = np.flatnonzero(present & (times <= t_max + 1e-9))
    if not len(idx):
        return None
    # a segment from each kept time to the next when that one is kept too, else a single point
    nxt = np.minimum(idx + 1, len(times) - 1)
    joined = np.isin(nxt, idx) & (nxt != idx)
    end = np.where(joined, nxt, idx)
    a, b = track[idx], track[end]
    ab = b - a
    den = np.einsum("kc,kc->k", ab, ab)
    u = np.clip(np.einsum("kc,kc->k", point - a, ab) / np.where(den > 0.0, den, 1.0), 0.0, 1.0)
    u = np.where(den > 0.0, u, 0.0)
    q = a + u[:, None] * ab
    d = np.hypot(q[:, 0] - point[0], q[:, 1] - point[1])
    t = times[idx] + u * (times[end] - times[idx])
    best = np.flatnonzero(d <= d.min() + 1e-9)
    return float(t[best].max())
