"""An evaluation's episodes in aggregate: rates and means with intervals, the ceiling fraction, the files.

:func:`summarise` turns the rows of :func:`agents.rollout.run_episodes` into outcome rates with 95 % Wilson
intervals and metric means with bootstrap intervals (:mod:`agents.stats`); :func:`ceiling_fraction` pairs them with
the privileged ceiling's episodes; :func:`episodes_csv` and :func:`read_episodes` write and read ``episodes.csv``;
:func:`format_summary` prints a summary.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from agents.rollout import EPISODE_COLUMNS, METRICS, recorded_metrics
from agents.stats import bootstrap_mean_ci, wilson_interval

#: Outcomes of an episode, each reported as a rate with a Wilson interval.
OUTCOMES: Final[tuple[str, ...]] = ("success", "collision", "timeout")
#: Metrics averaged over successful episodes only (a collision cuts a trip short; a timeout has no arrival time).
SUCCESS_ONLY_METRICS: Final[tuple[str, ...]] = (
    "navigation_time_s",
    "path_length_m",
    "path_ratio",
    "path_ratio_required",
)


def _number(value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        return math.nan
    return x


def _json_float(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def summarise(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95, seed: int = 0) -> dict[str, Any]:
    """Aggregates of per-episode rows.

    Returns:
        ``episodes``; for each outcome ``<outcome>_rate``, ``<outcome>_ci`` ([lo, hi], Wilson) and
        ``<outcome>_count`` (summaries written before this name held ``successs``, ``collisions`` and
        ``timeouts``; nothing in the project reads the counts back); ``popin_episodes`` (episodes with at least
        one pop-in event, see :mod:`envs.popin`) and ``popin_events`` (their total); for each of :data:`METRICS`
        the rows record (:func:`agents.rollout.recorded_metrics`: a metric added since older episode files were
        written is absent from their summaries) ``<metric>_mean``, ``<metric>_ci`` (bootstrap over episodes,
        seeded: BCa, percentile where BCa degenerates; both are quantiles of resampled means, so an interval
        never leaves the range of the values averaged) and ``<metric>_n`` (episodes it is defined for: all, or the
        successful ones for :data:`SUCCESS_ONLY_METRICS`; ``None`` values such as the ``none`` arm's forecast ADE
        are left out). Undefined means and intervals are ``None``.
    """
    n = len(rows)
    out: dict[str, Any] = {"episodes": n}
    outcomes = [str(r.get("outcome")) for r in rows]
    for name in OUTCOMES:
        count = sum(o == name for o in outcomes)
        out[f"{name}_rate"] = count / n if n else None
        out[f"{name}_ci"] = list(wilson_interval(count, n, confidence)) if n else None
        out[f"{name}_count"] = count
    popins = np.array([_number(r.get("popin_events")) for r in rows], dtype=np.float64)
    out["popin_episodes"] = int(np.sum(popins > 0))  # episodes in which a track began on the robot (envs.popin)
    out["popin_events"] = int(np.nansum(popins)) if n else 0
    for metric in recorded_metrics(rows):
        use = [r for r in rows if metric not in SUCCESS_ONLY_METRICS or r.get("outcome") == "success"]
        values = np.array([_number(r.get(metric)) for r in use], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[f"{metric}_n"] = len(values)
        out[f"{metric}_mean"] = float(values.mean()) if len(values) else None
        lo, hi = bootstrap_mean_ci(values, confidence=confidence, seed=seed) if len(values) else (math.nan, math.nan)
        out[f"{metric}_ci"] = [_json_float(lo), _json_float(hi)] if len(values) else None
    return out


def read_episodes(path: str | Path) -> list[dict[str, Any]]:
    """The rows of an ``episodes.csv`` (``path`` is the file or an evaluation folder holding it), as strings."""
    p = Path(path)
    if p.is_dir():
        p = p / "episodes.csv"
    if not p.is_file():
        raise FileNotFoundError(f"no episodes.csv at {path} (give the file or an evaluation folder with --out)")
    with open(p, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for key in ("seed", "outcome"):
        if rows and key not in rows[0]:
            raise ValueError(f"{p}: no {key!r} column; not an episodes.csv of agents.evaluate")
    return rows


def ceiling_fraction(
    rows: Sequence[Mapping[str, Any]],
    ceiling_rows: Sequence[Mapping[str, Any]],
    confidence: float = 0.95,
    seed: int = 0,
    n_resamples: int = 2000,
) -> dict[str, Any]:
    """A policy's success as a fraction of the privileged ceiling's (:mod:`agents.planners.privileged`) on the same
    episodes.

    Episodes are paired by seed (rows of the same evaluation list); a pair whose recording or start time differ
    is an error (the two evaluations ran different environment settings).

    Args:
        rows: the policy's episodes (``seed``, ``outcome``; ``recording``, ``t0_s`` checked when both have them).
        ceiling_rows: the ceiling's episodes.
        confidence: level of the interval.
        seed: seed of the bootstrap.
        n_resamples: bootstrap resamples.

    Returns:
        ``episodes`` (pairs), ``success_rate`` and ``ceiling_success_rate`` on them, ``fraction`` (their ratio;
        None when the ceiling never succeeds), ``fraction_ci`` (paired bootstrap over episodes, percentile, from
        ``scipy.stats.bootstrap``), and ``success_where_ceiling_succeeds`` (the policy's success rate on the
        episodes the ceiling solves).
    """
    from scipy import stats

    ceiling = {int(r["seed"]): r for r in ceiling_rows}
    mine, theirs = [], []
    for r in rows:
        other = ceiling.get(int(r["seed"]))
        if other is None:
            continue
        for key in ("recording", "t0_s"):
            a, b = r.get(key), other.get(key)
            if a not in (None, "") and b not in (None, "") and str(a) != str(b) and _number(a) != _number(b):
                raise ValueError(
                    f"episode seed {r['seed']}: {key} {a!r} here but {b!r} in the ceiling's episodes; the two "
                    "evaluations ran different episodes (split, require_pedestrians or env settings differ)"
                )
        mine.append(r.get("outcome") == "success")
        theirs.append(other.get("outcome") == "success")
    n = len(mine)
    a, c = np.array(mine, dtype=np.float64), np.array(theirs, dtype=np.float64)
    out: dict[str, Any] = {"episodes": n, "success_rate": None, "ceiling_success_rate": None, "fraction": None}
    out.update(fraction_ci=None, success_where_ceiling_succeeds=None)
    if n == 0:
        return out
    out["success_rate"], out["ceiling_success_rate"] = float(a.mean()), float(c.mean())
    if c.any():
        out["fraction"] = float(a.mean() / c.mean())
        out["success_where_ceiling_succeeds"] = float(a[c > 0].mean())

        def ratio(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
            den = y.mean(axis=axis)
            return np.divide(x.mean(axis=axis), den, out=np.full(np.shape(den), np.nan), where=den > 0)

        if np.all(a == a[0]) and np.all(c == c[0]):
            out["fraction_ci"] = [out["fraction"], out["fraction"]]
        else:
            res = stats.bootstrap(
                (a, c), ratio, paired=True, vectorized=True, method="percentile", n_resamples=n_resamples,
                confidence_level=confidence, rng=np.random.default_rng(seed),
            )  # fmt: skip
            out["fraction_ci"] = [_json_float(res.confidence_interval.low), _json_float(res.confidence_interval.high)]
    return out


def episodes_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """``episodes.csv`` text (columns :data:`EPISODE_COLUMNS`; empty cells where a metric is undefined)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(EPISODE_COLUMNS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in EPISODE_COLUMNS})
    return buf.getvalue()


#: What the interval of each line of :func:`format_summary` is.
_RATE_NOTE: Final[str] = "Wilson interval"


def format_summary(summary: Mapping[str, Any]) -> str:
    """A short human-readable table of a summary: one line per rate and metric, named by its key -- the key of
    ``info["episode_metrics"]``, of ``episodes.csv`` and (with ``_rate``/``_mean`` and ``_ci``) of the summary's
    JSON -- then its value, interval, episodes and readable label (:data:`envs.rewards.METRIC_LABELS`)."""
    from envs.rewards import METRIC_LABELS

    def ci(key: str) -> str:
        value = summary.get(key)
        return "" if not value or value[0] is None else f"[{value[0]:.3f}, {value[1]:.3f}]"

    def num(value: Any) -> str:
        return "-" if value is None else f"{value:.3f}"

    n = summary.get("episodes", 0)
    rows = [(f"{name}_rate", num(summary.get(f"{name}_rate")), ci(f"{name}_ci"), n, _RATE_NOTE) for name in OUTCOMES]
    for metric in METRICS:
        if f"{metric}_mean" not in summary:
            continue  # a metric the episodes did not record (added since they were written)
        label = METRIC_LABELS.get(metric, metric) + ("; successes only" if metric in SUCCESS_ONLY_METRICS else "")
        rows.append((metric, num(summary.get(f"{metric}_mean")), ci(f"{metric}_ci"), summary.get(f"{metric}_n"), label))
    width = max(len(r[0]) for r in rows) + 2
    crowd = summary.get("crowd") or {}
    validation = (summary.get("env") or {}).get("part") == "train"  # episodes_from="val": no held-out scene
    if crowd.get("kind") == "replay" and validation:
        where = (
            f"{summary.get('split')}'s training scenes in their validation period (NOT a held-out result; ETH/UCY "
            f"replay from {crowd.get('data_dir')})"
        )
    elif crowd.get("kind") == "replay":
        where = f"{summary.get('split')} (held-out scene, ETH/UCY replay from {crowd.get('data_dir')})"
    elif crowd:
        where = f"the {crowd.get('kind')} crowd (not an ETH/UCY scene; split {summary.get('split')})"
    else:  # a summary written before crowds were named
        where = f"{summary.get('split')} (held-out scene)"
    lines = [
        f"{summary.get('policy')} on {where}, forecasts {summary.get('predictor')}, "
        f"{summary['episodes']} episodes in {summary.get('seconds', 0):.1f} s"
    ]
    if summary.get("privileged") and (summary.get("planner") or {}).get("reactive"):
        lines.append(
            "  PRIVILEGED: rolls the reaction model forward for every candidate plan (a ceiling, not a policy)"
        )
    elif summary.get("privileged"):
        lines.append("  PRIVILEGED: reads every pedestrian's true future from the replay (a ceiling, not a policy)")
    lines.append(f"  {'key':<{width}}{'value':<9}{'[95 % interval]':<18}{'n':>5}  what")
    for key, value, interval, count, label in rows:
        lines.append(f"  {key:<{width}}{value:<9}{interval:<18}{'' if count is None else count:>5}  {label}")
        if key == f"{OUTCOMES[-1]}_rate":
            ceiling = summary.get("ceiling")
            if ceiling and ceiling.get("fraction") is not None:
                lo, hi = ceiling["fraction_ci"]
                lines.append(
                    f"  {'ceiling.fraction':<{width}}{ceiling['fraction']:<9.3f}{f'[{lo:.3f}, {hi:.3f}]':<18}"
                    f"{ceiling['episodes']:>5}  success / ceiling (the privileged ceiling succeeds in "
                    f"{ceiling['ceiling_success_rate']:.3f} of these episodes; paired bootstrap)"
                )
    return "\n".join(lines)
