"""Online conformal calibration with delayed feedback: a quantile tracker per horizon step and level.

Split conformal (:mod:`crowdnav_mesrnn.uncertainty.calibration`) fixes each step's threshold ``q_h(c)`` on the validation
windows of the other scenes; a held-out scene is not exchangeable with them, and coverage misses the level on
some scenes. Adaptive conformal inference (Gibbs & Candès 2021) instead moves the threshold while the scene is
watched, from the coverage it has realised; its guarantee on the long-run miss rate holds for any sequence of
scores, exchangeable or not. This module implements its form on the score scale, the quantile tracker (online
subgradient descent on the pinball loss; Angelopoulos, Candès & Tibshirani 2023, "Conformal PID control", the
``P`` term alone). ACI's own update of the miss level ``alpha_t`` reads thresholds off a fixed calibration set and
gives an infinite region once ``alpha_t < 0``; the tracker's regions stay finite, which a planner needs.

**Delayed feedback, and when an outcome counts as revealed.** The windows of a test scene are taken in the scene's
time order. A window's forecast time ``t`` is the annotation index of its last observed frame; the truth of its step
``h`` (1 to ``PRED_LEN`` = 12) is at ``t + h``. Which pedestrians a window scores is known later still: a window
scores the pedestrians present in all of its frames (:func:`crowdnav_mesrnn.data.windows.windows_from_recording`),
through ``t + PRED_LEN``, so "pedestrian ``i``'s step ``h`` counts in window ``t``" is settled only at
``t + PRED_LEN``. Three reveal rules (:data:`REVEAL_RULES`):

- ``"window"`` (the default; what a robot could run): every step's outcome of the window at ``t`` is used from
  ``t + PRED_LEN`` on, once the window's scored set is determined. The threshold used at ``t`` depends only on
  windows at ``t' ≤ t − PRED_LEN``, whose positions and membership are both observed by ``t``.
- ``"step"`` (optimistic): step ``h``'s outcome is used from ``t + h`` on. No position is used before it is
  observed, but the update at ``t + h`` already counts only the pedestrians that will still be present at
  ``t + PRED_LEN``, information from the future for ``h < PRED_LEN``.
- ``"observed"`` (strictly causal, learns sooner; with the step-size experts only): step ``h`` of the forecast at
  ``t`` is used from ``t + h`` on, over every pedestrian present in every frame from the window's first through
  ``t + h`` (:class:`Feedback`): scored or not, so membership is known when the outcome is. It learns from every
  window of the scene, with or without a scored pedestrian (whether a window has one is settled only at
  ``t + PRED_LEN``), and its thresholds are read at the scored windows, where coverage is measured as for the others.

Each outcome is judged against the threshold that was used for it. A scene's recordings are one stream,
in the split's order, all outcomes of one recording revealed before the next begins (:func:`window_clock`).

**The update** of step ``h`` at level ``c`` for a revealed window ``j`` with ``n_j`` scored pedestrians of which
``m_j`` fell outside their region (score above the threshold used)::

    q_h <- max(0, q_h + γ q_h^0 (m_j − (1 − c) n_j) / (d n̄))

``q_h^0`` is the offline (split-conformal, validation) threshold the tracker starts from, so ``γ`` is free of the
score's units; ``n̄`` is the mean number of scored pedestrians of the windows revealed so far (known online; under
``"observed"``, of the feedback rows observed at the step, over the windows with one), so ``γ`` is the step per
typical window in sparse and in dense scenes alike. ``d`` is the delay of the reveal rule: ``h`` for ``"step"`` and
``"observed"``, ``PRED_LEN`` for every step under ``"window"``. The division by the delay keeps the feedback
loop of every step equally damped: ``d`` updates are already under way when the first of them shows in an
outcome, and a fixed step large enough for step 1 makes step 12's threshold oscillate and the regions swell
(with the division, a stationary stream's thresholds stay near the true quantile at every step:
``tests/uncertainty/test_online_conformal.py``). The pooled miss fraction over the positions tends to ``1 − c`` on any
stream where ``q_h`` stays bounded (the ``P`` controller's guarantee; a delay changes only the constant).

**Choosing γ** (fixed before any test coverage was measured; the test scene is never read): per split and level,
on the split's validation windows, leave one validation scene out: start from the split-conformal thresholds of
the other validation scenes, track over the left-out scene's validation windows (its own stream), and take its
mean over the 12 steps of ``|coverage_h − c|``; ``γ``'s validation deviation is the worst over the left-out
scenes, tracked with the same reveal rule as the test scene. The chosen ``γ`` is the smallest of
:data:`GAMMA_GRID` whose deviation is at most :data:`GAMMA_TOLERANCE` (the goal's ±0.03: the steadiest tracker that
holds the level on the validation scenes), or, when none is, the one with the smallest deviation.

**Experts instead of a chosen γ** (``gamma_rule="experts"``; the rule and its rates are declared in
``docs/results/uncertainty.md``). Choosing one ``γ`` on validation fails where the validation scenes cannot tell the
candidates apart (their deviations tie, and a tie goes to the smallest ``γ``, the slowest tracker). Following the
dynamically-tuned ACI of Gibbs & Candès (2022, "Conformal inference for online prediction with arbitrary
distribution shifts"), every ``γ`` of :data:`GAMMA_GRID` runs its own tracker (each updated on its own thresholds'
outcomes, exactly as above), and the threshold used is their weighted mean. The weights follow the experts' pinball
loss on the revealed outcomes, ``ρ_c(s − q) / q_h^0`` averaged over a window's scored pedestrians, by exponential
weights with a fixed share (Herbster & Warmuth): ``log w_k −= η loss_k``, then ``w ← (1 − σ) w + σ / K``. The rates
are DtACI's for an interval of :data:`EXPERT_INTERVAL` windows (:func:`expert_rates`; at 90 % ``η ≈ 5.6``,
``σ = 0.005``), fixed before any test run. Validation is not read at all; outcomes are revealed with the same rule
and delay as the single tracker's.

No maintained library fits this as it stands (checked): scipy has no conformal prediction; MAPIE's time-series
regressor implements ACI around a scikit-learn regressor of a scalar target, updated one observation at a time,
with no per-horizon delay and no external scores. The tracker is a few lines of numpy.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, RECORDINGS
from crowdnav_mesrnn.data.recordings import Recording, load_split
from crowdnav_mesrnn.data.windows import Window
from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.uncertainty.conformal import (
    Calibration,
    Coverage,
    conformal_thresholds,
    gaussians_of,
    level_key,
    region_scores,
)

#: Step sizes ``γ`` the validation rule chooses from (module docstring).
GAMMA_GRID: Final[tuple[float, ...]] = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
#: Largest validation deviation (worst left-out scene's mean over steps of ``|coverage_h − c|``) a ``γ`` may have to
#: be chosen: the goal's ±0.03.
GAMMA_TOLERANCE: Final[float] = 0.03
#: Methods of ``predictor calibrate``.
METHODS: Final[tuple[str, ...]] = ("split", "online")
#: When an outcome updates the tracker (module docstring); the first is the default.
REVEAL_RULES: Final[tuple[str, ...]] = ("window", "step", "observed")
#: How the step size is set (module docstring): one ``γ`` chosen on validation (the default), or every ``γ`` of the grid
#: as experts mixed online.
GAMMA_RULES: Final[tuple[str, ...]] = ("validation", "experts")
#: The interval ``I`` (windows) the experts' rates are set for: DtACI's ``η`` and ``σ = 1 / (2 I)`` (:func:`expert_rates`).
EXPERT_INTERVAL: Final[int] = 100


def window_clock(windows: Sequence[Window], recordings: Sequence[Recording]) -> np.ndarray:
    """``(W,)`` int64 forecast times of ``windows`` on one clock: the annotation index of each window's last observed
    frame in its recording, the recordings (in ``recordings``' order, which ``windows`` must follow) placed one
    after another with ``PRED_LEN + 1`` annotations between them, so every outcome of a recording is revealed before
    the next one's first forecast."""
    offset, start = {}, 0
    for rec in recordings:
        offset[rec.name] = (start, rec)
        start += len(rec.frames) + PRED_LEN + 1
    out = np.empty(len(windows), dtype=np.int64)
    for i, w in enumerate(windows):
        if w.recording not in offset:
            raise ValueError(f"window {i} is from recording {w.recording!r}, not one of {', '.join(offset)}")
        base, rec = offset[w.recording]
        idx = int(np.searchsorted(rec.frames, w.start_frame))
        if idx >= len(rec.frames) or rec.frames[idx] != w.start_frame:
            raise ValueError(f"window {i} starts at frame {w.start_frame}, which recording {rec.name!r} does not have")
        out[i] = base + idx + OBS_LEN - 1
    if np.any(np.diff(out) < 0):
        raise ValueError("windows must be in time order (recording by recording, as split_windows gives them)")
    return out


def track_thresholds(
    scores: np.ndarray,
    window: np.ndarray,
    time: np.ndarray,
    start: np.ndarray,
    level: float,
    gamma: float,
    reveal: str = REVEAL_RULES[0],
) -> np.ndarray:
    """The quantile tracker with delayed feedback (module docstring) over one stream.

    Args:
        scores: ``(M, P)`` conformal scores of the scored pedestrians, rows grouped by window (``window`` sorted).
        window: ``(M,)`` window index of each row, in ``[0, W)``, non-decreasing.
        time: ``(W,)`` forecast time of each window (annotation steps), non-decreasing; step ``h`` (0-based ``j``
            in ``[0, P)``, ``h = j + 1`` annotations ahead) of a window at ``t`` is observed at ``t + h``.
        start: ``(P,)`` starting thresholds (the offline ones); an infinite one stays infinite.
        level: coverage level ``c`` in (0, 1).
        gamma: step size (per typical window, relative to ``start``), > 0.
        reveal: one of :data:`REVEAL_RULES`: ``"window"`` uses every step of the window at ``t`` from ``t + P`` on
            (when its scored set is determined), ``"step"`` uses step ``h`` from ``t + h`` on, and so does
            ``"observed"``, whose rows are every pedestrian present through the step (scored or not): a NaN score
            marks a step not observed, which is skipped (:class:`Stream`'s ``feedback``).

    Returns:
        ``(W, P)`` the threshold used for each window and step.
    """
    scores = np.asarray(scores, dtype=np.float64)
    window = np.asarray(window, dtype=np.int64)
    time = np.asarray(time, dtype=np.int64)
    start = np.asarray(start, dtype=np.float64)
    n_windows, n_steps = len(time), scores.shape[1]
    if not 0.0 < level < 1.0 or not gamma > 0.0:
        raise ValueError(f"need 0 < level < 1 and gamma > 0, got level {level!r}, gamma {gamma!r}")
    if reveal not in REVEAL_RULES:
        raise ValueError(f"unknown reveal rule {reveal!r}; valid: {', '.join(REVEAL_RULES)}")
    if start.shape != (n_steps,) or window.shape != (len(scores),):
        raise ValueError(f"start {start.shape} and window {window.shape} must match scores {scores.shape}")
    if np.any(np.diff(window) < 0) or np.any(np.diff(time) < 0):
        raise ValueError("rows must be grouped by window and windows in time order")
    if len(window) and (window[0] < 0 or window[-1] >= n_windows):
        raise ValueError(f"window indices must lie in [0, {n_windows})")
    miss_rate = 1.0 - level
    out = np.empty((n_windows, n_steps))
    for j in range(n_steps):
        q, q0, delay = start[j], start[j], _delay(reveal, j, n_steps)
        if not np.isfinite(q0):
            out[:, j] = q0
            continue
        revealed_rows, revealed_windows = 0, 0
        for k, revealed in _revealed_before(scores[:, j], window, time, delay, reveal):
            for i, rows in revealed:
                revealed_rows += len(rows)
                revealed_windows += 1
                missed = np.count_nonzero(rows > out[i, j])
                q = tracker_update(q, q0, missed, len(rows), revealed_rows / revealed_windows, miss_rate, gamma, delay)
            out[k, j] = q
    return out


def tracker_update(
    q: Any, q0: float, missed: Any, n: int, mean_n: float, miss_rate: float, gamma: Any, delay: int
) -> Any:
    """One revealed window's update of a step's tracker (module docstring): ``max(0, q + γ q0 (m − (1 − c) n) /
    (d n̄))``, with ``missed`` (``m``) of the window's ``n`` rows above the threshold that was used for them, ``mean_n``
    (``n̄``) the mean rows per window revealed so far (this one included), ``miss_rate`` ``1 − c`` and ``delay``
    ``d``. ``q``, ``missed`` and ``gamma`` may be arrays of one length (one tracker per step size, updated at once)."""
    return np.maximum(q + gamma * q0 * (missed - miss_rate * n) / (delay * mean_n), 0.0)


def _delay(reveal: str, j: int, n_steps: int) -> int:
    """Annotations from a forecast until step ``j + 1`` (0-based ``j``) updates a tracker under ``reveal``."""
    return j + 1 if reveal in ("step", "observed") else n_steps


def _revealed_before(
    step_scores: np.ndarray, window: np.ndarray, time: np.ndarray, delay: int, reveal: str
) -> Iterator[tuple[int, list[tuple[int, np.ndarray]]]]:
    """For each window ``k`` in time order: ``(k, [(i, scores), ...])``, the earlier windows ``i`` whose outcomes
    (``delay`` annotations after their forecast) are revealed by ``time[k]`` and not before, oldest first, each with
    its rows' scores of one step (``step_scores (M,)``; NaN rows, steps not observed under ``"observed"``, dropped;
    windows left without a row skipped). The one place the trackers read outcomes: :func:`track_thresholds` and
    :func:`aggregate_thresholds` update from exactly these."""
    bounds = np.searchsorted(window, np.arange(len(time) + 1))
    has_gaps = reveal == "observed"
    nxt = 0
    for k in range(len(time)):
        revealed = []
        while nxt < k and time[nxt] + delay <= time[k]:
            rows = step_scores[bounds[nxt] : bounds[nxt + 1]]
            if has_gaps:
                rows = rows[~np.isnan(rows)]
            if len(rows):
                revealed.append((nxt, rows))
            nxt += 1
        yield k, revealed


def expert_rates(experts: int, level: float, interval: int = EXPERT_INTERVAL) -> tuple[float, float]:
    """``(η, σ)`` of the expert mixture (module docstring) for ``experts`` experts, coverage ``level`` and an interval
    of ``interval`` windows: DtACI's ``η = sqrt(3 / I) sqrt((ln(K I) + 2) / ((1 − α)² α³ + α² (1 − α)³))`` with
    ``α = 1 − level``, and ``σ = 1 / (2 I)``."""
    if experts < 1 or interval < 1:
        raise ValueError(f"need at least one expert and a positive interval, got {experts} and {interval}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"need 0 < level < 1, got {level!r}")
    a = 1.0 - level
    eta = math.sqrt(3.0 / interval) * math.sqrt(
        (math.log(experts * interval) + 2.0) / ((1 - a) ** 2 * a**3 + a**2 * (1 - a) ** 3)
    )
    return eta, 1.0 / (2.0 * interval)


def aggregate_thresholds(
    scores: np.ndarray,
    window: np.ndarray,
    time: np.ndarray,
    start: np.ndarray,
    level: float,
    gammas: Sequence[float] = GAMMA_GRID,
    reveal: str = REVEAL_RULES[0],
    interval: int = EXPERT_INTERVAL,
) -> tuple[np.ndarray, np.ndarray]:
    """The expert mixture of the module docstring over one stream: a tracker per step size of ``gammas``
    (:func:`track_thresholds`), weighted by their pinball loss on the outcomes revealed so far.

    Args: as :func:`track_thresholds` (NaN scores skipped under ``"observed"``, by the experts and their losses
    alike), with ``gammas`` the experts' step sizes and ``interval`` the windows the rates are set for
    (:func:`expert_rates`).

    Returns:
        ``(W, P)`` the thresholds used (each the weighted mean of the experts' for that window and step, with the
        weights known at its forecast time) and ``(P, K)`` the experts' weights after the last window.
    """
    if not len(gammas):
        raise ValueError("need at least one step size")
    experts = np.stack([track_thresholds(scores, window, time, start, level, g, reveal) for g in gammas])  # (K, W, P)
    scores = np.asarray(scores, dtype=np.float64)
    window = np.asarray(window, dtype=np.int64)
    time = np.asarray(time, dtype=np.int64)
    start = np.asarray(start, dtype=np.float64)
    k_count, n_windows, n_steps = experts.shape
    eta, share = expert_rates(k_count, level, interval)
    out = np.empty((n_windows, n_steps))
    weights_end = np.full((n_steps, k_count), 1.0 / k_count)
    for j in range(n_steps):
        q0, delay = start[j], _delay(reveal, j, n_steps)
        if not np.isfinite(q0):
            out[:, j] = q0
            continue
        unit = q0 if q0 > 0 else 1.0
        log_w = np.full(k_count, -math.log(k_count))
        w = np.exp(log_w)
        for k, revealed in _revealed_before(scores[:, j], window, time, delay, reveal):
            for i, rows in revealed:
                log_w = expert_weights_update(log_w, rows, experts[:, i, j], level, unit, eta, share)
                w = np.exp(log_w)
            out[k, j] = float(w @ experts[:, k, j])
        weights_end[j] = w
    return out, weights_end


def expert_weights_update(
    log_w: np.ndarray, rows: np.ndarray, used: np.ndarray, level: float, unit: float, eta: float, share: float
) -> np.ndarray:
    """One revealed window's update of the experts' log-weights ``(K,)`` of a step (module docstring): each expert's
    pinball loss on the window's scores ``rows (n,)`` against the threshold it used for them, ``used (K,)``, in units of
    ``unit`` (the starting threshold, or 1 where it is 0), then exponential weights with rate ``eta`` and fixed share
    ``share``."""
    diff = rows[None, :] - used[:, None]  # (K, n): score minus each expert's threshold
    loss = np.where(diff > 0, level * diff, (level - 1.0) * diff).mean(1) / unit
    log_w = log_w - eta * loss
    mixed = np.exp(log_w - log_w.max())
    return np.log((1.0 - share) * mixed / mixed.sum() + share / len(log_w))


class ExpertTracker:
    """The expert mixture of the module docstring run one window at a time: for every horizon step, a tracker per step
    size of ``gammas`` and their weights, updated as the caller reveals outcomes.

    The caller keeps the clock: at each forecast time it first reveals every outcome that has become known
    (:meth:`reveal`, the window's scores of one step with the thresholds the experts used for it, :attr:`experts` as they
    were at its forecast time), then reads the thresholds to use (:meth:`thresholds`). Run over a stream with the
    reveal rule's delays it gives the thresholds of :func:`aggregate_thresholds` (``tests/uncertainty``); the environment runs it
    over an episode's annotations (``forecast_uncertainty_method="online"``, :mod:`envs.forecasting.uncertainty`).

    Args:
        start: ``(P,)`` starting thresholds (the offline ones); a step with an infinite one stays infinite.
        level: coverage level ``c`` in (0, 1).
        gammas: the experts' step sizes.
        reveal: the reveal rule whose delay damps the updates (:func:`_delay`): ``"observed"`` and ``"step"`` update
            step ``h`` ``h`` annotations after the forecast, ``"window"`` every step ``P`` after it.
        interval: the windows the rates are set for (:func:`expert_rates`).
    """

    def __init__(
        self,
        start: np.ndarray,
        level: float,
        gammas: Sequence[float] = GAMMA_GRID,
        reveal: str = "observed",
        interval: int = EXPERT_INTERVAL,
    ) -> None:
        self.start = np.asarray(start, dtype=np.float64).copy()
        if self.start.ndim != 1 or not len(gammas):
            raise ValueError(f"need (P,) starting thresholds and at least one step size, got {self.start.shape}")
        if not 0.0 < level < 1.0 or not all(g > 0.0 for g in gammas):
            raise ValueError(f"need 0 < level < 1 and step sizes > 0, got level {level!r}, gammas {list(gammas)!r}")
        if reveal not in REVEAL_RULES:
            raise ValueError(f"unknown reveal rule {reveal!r}; valid: {', '.join(REVEAL_RULES)}")
        steps, k = len(self.start), len(gammas)
        self.level = float(level)
        self.gammas = np.asarray(gammas, dtype=np.float64)
        self.delays = [_delay(reveal, j, steps) for j in range(steps)]
        self.eta, self.share = expert_rates(k, level, interval)
        # (K, P) each expert's threshold per step; a step's column is a strided vector, as the batch's is, so that
        # the weighted mean is summed in the same order (a contiguous one may be summed otherwise in the last bit)
        self._q = np.repeat(self.start[None, :], k, axis=0)
        self._log_w = np.full((steps, k), -math.log(k))
        # the weights of a step never updated: exp of the starting log-weights (1 / K where the start is infinite)
        self._w = np.where(np.isfinite(self.start)[:, None], np.exp(self._log_w), 1.0 / k)
        self._rows = np.zeros(steps, dtype=np.int64)
        self._windows = np.zeros(steps, dtype=np.int64)

    @property
    def experts(self) -> np.ndarray:
        """``(K, P)`` every expert's current threshold of each step (a copy)."""
        return self._q.copy()

    @property
    def weights(self) -> np.ndarray:
        """``(P, K)`` the experts' current weights per step (a copy)."""
        return self._w.copy()

    def thresholds(self) -> np.ndarray:
        """``(P,)`` the thresholds to use now: per step the experts' weighted mean, or the start where it is infinite or
        nothing has been revealed yet (where the mean of the equal experts could differ from it in the last bit)."""
        out = self.start.copy()
        for j in np.flatnonzero(np.isfinite(self.start) & (self._windows > 0)):
            out[j] = float(self._w[j] @ self._q[:, j])
        return out

    def reveal(self, step: int, scores: np.ndarray, used: np.ndarray) -> None:
        """Learn from one window's outcomes of step ``step`` (0-based): ``scores (n,)`` its rows' conformal scores
        (NaN rows, not observed, are dropped; a window left without a row changes nothing) and ``used (K,)`` the
        thresholds the experts used for that window (:attr:`experts` at its forecast time, column ``step``)."""
        q0 = self.start[step]
        rows = np.asarray(scores, dtype=np.float64)
        rows = rows[~np.isnan(rows)]
        if not np.isfinite(q0) or not len(rows):
            return
        used = np.asarray(used, dtype=np.float64)
        self._rows[step] += len(rows)
        self._windows[step] += 1
        missed = np.count_nonzero(rows[None, :] > used[:, None], axis=1)
        mean_n = int(self._rows[step]) / int(self._windows[step])
        self._q[:, step] = tracker_update(
            self._q[:, step], q0, missed, len(rows), mean_n, 1.0 - self.level, self.gammas, self.delays[step]
        )
        unit = q0 if q0 > 0 else 1.0
        self._log_w[step] = expert_weights_update(self._log_w[step], rows, used, self.level, unit, self.eta, self.share)
        self._w[step] = np.exp(self._log_w[step])


@dataclass(frozen=True)
class Feedback:
    """What the ``"observed"`` rule learns from on one stream: every window of the scene (whether or not it has a
    scored pedestrian, so that no window's presence depends on the future), each with every pedestrian present in
    all its observed frames, a step's score NaN unless the pedestrian is present in every frame through it.

    Attributes:
        scores: ``(M', P)`` conformal scores, NaN where not observed; rows grouped by ``window``.
        window: ``(M',)`` index of each row's feedback window, non-decreasing.
        time: ``(F,)`` forecast times of the feedback windows (:func:`window_clock`, the same clock as the stream's).
        index: ``(W,)`` the feedback window of each of the stream's windows (the same recording and first frame).
    """

    scores: np.ndarray
    window: np.ndarray
    time: np.ndarray
    index: np.ndarray


@dataclass(frozen=True)
class Stream:
    """The forecasts of one stream (a scene's windows in time order) and their conformal scores.

    Attributes:
        scored: the forecasts (:func:`crowdnav_mesrnn.evaluation.metrics.collect_forecasts` order).
        scores: ``(M, P)`` conformal scores.
        time: ``(W,)`` forecast times (:func:`window_clock`).
        feedback: what the ``"observed"`` rule learns from, or None: the :class:`Feedback` of the same scene.
    """

    scored: ScoredForecasts
    scores: np.ndarray
    time: np.ndarray
    feedback: Feedback | None = None

    def thresholds(self, start: np.ndarray, level: float, gamma: float, reveal: str = REVEAL_RULES[0]) -> np.ndarray:
        """``(W, P)`` thresholds the tracker uses (:func:`track_thresholds`; under ``"observed"`` run over the
        feedback stream and read at this stream's windows)."""
        if reveal == "observed":
            fb = self._feedback()
            return track_thresholds(fb.scores, fb.window, fb.time, start, level, gamma, reveal)[fb.index]
        return track_thresholds(self.scores, self.scored.window, self.time, start, level, gamma, reveal)

    def _feedback(self) -> Feedback:
        if self.feedback is None:
            raise ValueError("the reveal rule 'observed' needs the stream's feedback rows (Stream.feedback)")
        return self.feedback

    def covered(self, thresholds: np.ndarray) -> np.ndarray:
        """``(M, P)`` bool: each true position inside its window's region."""
        return self.scores <= thresholds[self.scored.window]

    def subset(self, rows: np.ndarray) -> Stream:
        """The stream of the windows holding ``rows`` (a boolean ``(M,)`` mask that keeps whole windows)."""
        if self.feedback is not None:
            raise ValueError("a stream with feedback rows cannot be subset (its windows would lose them)")
        keep = np.unique(self.scored.window[rows])
        remap = np.full(self.scored.num_windows, -1, np.int64)
        remap[keep] = np.arange(len(keep))
        s = self.scored
        scored = ScoredForecasts(
            s.error[rows],
            s.speed[rows],
            remap[s.window[rows]],
            len(keep),
            None if s.sigma is None else s.sigma[rows],
            None if s.rho is None else s.rho[rows],
        )
        return Stream(scored, self.scores[rows], self.time[keep])


def scene_streams(
    windows: Sequence[Window], scored: ScoredForecasts, scores: np.ndarray, recordings: Sequence[Recording]
) -> dict[str, Stream]:
    """Scene label (``RECORDINGS``) -> the stream of that scene's windows (its recordings in ``recordings`` order)."""
    whole = Stream(scored, scores, window_clock(windows, recordings))
    base = {rec.name: rec.base_name for rec in recordings}
    scene_of_window = np.array([RECORDINGS[base[w.recording]] for w in windows])
    row_scene = scene_of_window[scored.window]
    return {scene: whole.subset(row_scene == scene) for scene in dict.fromkeys(row_scene.tolist())}


def validation_deviation(
    streams: dict[str, Stream], level: float, gamma: float, reveal: str = REVEAL_RULES[0]
) -> float:
    """The worst over left-out validation scenes of the mean over steps of ``|coverage_h − level|``, each scene
    tracked from the split-conformal thresholds of the others with the reveal rule ``reveal`` (module
    docstring)."""
    key = level_key(level)
    worst = 0.0
    for scene, stream in streams.items():
        others = np.concatenate([s.scores for name, s in streams.items() if name != scene])
        start = np.asarray(conformal_thresholds(others, (level,))[key])
        per_step = stream.covered(stream.thresholds(start, level, gamma, reveal)).mean(0)
        worst = max(worst, float(np.mean(np.abs(per_step - level))))
    return worst


def choose_gamma(
    streams: dict[str, Stream],
    level: float,
    grid: Sequence[float] = GAMMA_GRID,
    tolerance: float = GAMMA_TOLERANCE,
    reveal: str = REVEAL_RULES[0],
) -> tuple[float, list[float]]:
    """The rule of the module docstring, the validation streams tracked with ``reveal``: ``(γ, the validation
    deviation of every γ of grid)``."""
    if len(streams) < 2:
        raise ValueError(f"choosing gamma needs at least two validation scenes, got {list(streams)}")
    deviations = [validation_deviation(streams, level, g, reveal) for g in grid]
    within = [g for g, d in zip(grid, deviations, strict=True) if d <= tolerance]
    return (min(within) if within else grid[int(np.argmin(deviations))]), deviations


@dataclass(frozen=True)
class OnlineResult:
    """The tracker's regions on one test stream.

    Attributes:
        coverage: the online regions' coverage (the same shape as split conformal's, for the same rows).
        gamma: level key -> the chosen step size (``gamma_rule="experts"``: the experts' step sizes weighted by
            their final weights, averaged over the steps).
        gamma_deviation: level key -> the validation deviation of each ``γ`` of :data:`GAMMA_GRID` (empty for
            ``"experts"``, which reads no validation stream).
        thresholds_end: level key -> ``(P,)`` the thresholds after the last window.
        second_half: level key -> pooled coverage over the later half of the windows (time order).
        radius_diff: level key -> per-window sums over positions and steps of the online minus the split-conformal
            equivalent radius, metres (``(W,)``, for a paired interval).
    """

    coverage: Coverage
    gamma: dict[str, float]
    gamma_deviation: dict[str, list[float]]
    thresholds_end: dict[str, list[float]]
    second_half: dict[str, float]
    radius_diff: dict[str, np.ndarray]
    expert_weights_end: dict[str, list[list[float]]] | None = None


def online_coverage(
    calibration: Calibration,
    val_streams: dict[str, Stream],
    test: Stream,
    split_coverage: Coverage,
    levels: Sequence[float],
    reveal: str = REVEAL_RULES[0],
    gamma_rule: str = GAMMA_RULES[0],
) -> OnlineResult:
    """Choose ``γ`` on the validation streams (or, ``gamma_rule="experts"``, mix every ``γ`` of the grid online), track
    over the test stream from ``calibration``'s (split-conformal) thresholds, both with the reveal rule ``reveal``,
    and measure the coverage and the size of the regions. ``split_coverage`` is split conformal's
    on the same test rows; its raw coverage and NLL (the model's own regions, which tracking does not change)
    are carried over."""
    scored = test.scored
    keep = scored.counts > 0
    late = np.arange(int(keep.sum())) >= int(keep.sum()) // 2  # the later half of the (time-ordered) windows
    unit = unit_radius(scored, calibration)
    if gamma_rule not in GAMMA_RULES:
        raise ValueError(f"unknown gamma rule {gamma_rule!r}; valid: {', '.join(GAMMA_RULES)}")
    if reveal == "observed" and gamma_rule != "experts":
        raise ValueError("the reveal rule 'observed' runs with the step-size experts only (gamma rule 'experts')")
    covered, radius, gammas, devs, ends, half, diff, weights = {}, {}, {}, {}, {}, {}, {}, {}
    for c in levels:
        key = level_key(c)
        start = calibration.threshold(c)
        if gamma_rule == "experts":
            if reveal == "observed":
                fb = test._feedback()
                thr_fb, w_end = aggregate_thresholds(fb.scores, fb.window, fb.time, start, c, GAMMA_GRID, reveal)
                thr = thr_fb[fb.index]
            else:
                thr, w_end = aggregate_thresholds(test.scores, scored.window, test.time, start, c, GAMMA_GRID, reveal)
            weights[key] = w_end.tolist()
            gammas[key], devs[key] = float(np.mean(w_end @ np.asarray(GAMMA_GRID))), []
        else:
            gammas[key], devs[key] = choose_gamma(val_streams, c, reveal=reveal)
            thr = test.thresholds(start, c, gammas[key], reveal)
        ends[key] = thr[-1].tolist()
        inside = test.covered(thr)
        covered[key] = scored.window_sums(inside)[keep]
        size = thr[scored.window] * unit
        radius[key] = float(np.mean(size))
        diff[key] = scored.window_sums(size - start[None, :] * unit).sum(1)[keep]
        half[key] = float(covered[key][late].sum() / (split_coverage.counts[late].sum() * inside.shape[1]))
    coverage = Coverage(covered, split_coverage.raw, split_coverage.counts, radius, split_coverage.nll_m)
    return OnlineResult(coverage, gammas, devs, ends, half, diff, weights if gamma_rule == "experts" else None)


def unit_radius(scored: ScoredForecasts, calibration: Calibration) -> np.ndarray:
    """``(M, P)`` equivalent radius in metres (the disc of equal area) of the region of threshold 1: 1 m for the
    ``radius`` score, the Gaussian's (the forecast's own or the error model's) for ``scaled``."""
    if calibration.score == "radius":
        return np.ones(scored.error.shape[:2])
    sigma, rho = gaussians_of(scored, calibration.error_model)
    return gaussian.equivalent_radius(sigma, rho)


def online_for_split(
    calibration: Calibration,
    val_windows: Sequence[Window],
    val: ScoredForecasts,
    val_scores: np.ndarray,
    test_windows: Sequence[Window],
    test: ScoredForecasts,
    split_coverage: Coverage,
    levels: Sequence[float],
    data_dir: str | os.PathLike[str] | None = None,
    reveal: str = REVEAL_RULES[0],
    gamma_rule: str = GAMMA_RULES[0],
    feedback_forecasts: tuple[Sequence[Window], ScoredForecasts] | None = None,
) -> OnlineResult:
    """:func:`online_coverage` on ``calibration.split``: its validation scenes choose ``γ``, its test scene (one
    stream, its recordings in order) is tracked; both with the reveal rule ``reveal``; ``gamma_rule`` as
    :func:`online_coverage`. ``feedback_forecasts`` (``reveal="observed"`` only): every test window (``min_scored``
    0) and its forecasts collected with ``rows="observed"`` (:func:`crowdnav_mesrnn.evaluation.metrics.collect_forecasts`)."""
    split = calibration.split
    val_streams = scene_streams(val_windows, val, val_scores, load_split(split, "val", data_dir))
    scores = region_scores(test, calibration.score, calibration.error_model)
    recordings = load_split(split, "test", data_dir)
    feedback = None
    if reveal == "observed":
        if feedback_forecasts is None or feedback_forecasts[1].observed is None:
            raise ValueError("the reveal rule 'observed' needs every test window's forecasts with rows='observed'")
        feedback = feedback_stream(*feedback_forecasts, test_windows, recordings, calibration)
    stream = Stream(test, scores, window_clock(test_windows, recordings), feedback)
    return online_coverage(calibration, val_streams, stream, split_coverage, levels, reveal, gamma_rule)


def feedback_stream(
    windows: Sequence[Window],
    forecasts: ScoredForecasts,
    scored_windows: Sequence[Window],
    recordings: Sequence[Recording],
    calibration: Calibration,
) -> Feedback:
    """The :class:`Feedback` of a scene from all its ``windows`` (``min_scored`` 0, time order) and their ``forecasts``
    (``rows="observed"``), for the stream of ``scored_windows`` (each must be among ``windows``)."""
    if forecasts.observed is None:
        raise ValueError("feedback forecasts must be collected with rows='observed'")
    raw = region_scores(forecasts, calibration.score, calibration.error_model)
    bad = np.argwhere(forecasts.observed & np.isnan(raw))
    if len(bad):  # NaN marks a step not observed: an observed step's NaN score would be skipped as one, silently
        row, step = (int(x) for x in bad[0])
        w = windows[int(forecasts.window[row])]
        raise ValueError(
            f"{len(bad)} observed step(s) have a NaN conformal score, the first at step {step + 1} of row {row} "
            f"(window of {w.recording!r} from frame {w.start_frame}): check the forecasts' errors and Gaussians"
        )
    position = {(w.recording, w.start_frame): i for i, w in enumerate(windows)}
    try:
        index = np.array([position[(w.recording, w.start_frame)] for w in scored_windows], dtype=np.int64)
    except KeyError as err:
        raise ValueError(f"scored window {err.args[0]} is not among the feedback windows") from None
    return Feedback(
        np.where(forecasts.observed, raw, np.nan), forecasts.window, window_clock(windows, recordings), index
    )
