"""The declaration of the claims test: bins, thresholds, contrasts and verdict rules.

**Fixed before any claims figure was computed** (committed on its own, before the code that computes
them, in a commit whose message says so; see ``git log --follow -- crowdnav_mesrnn/studies/claims/declared.py``,
which was ``crowdnav_mesrnn/claims/declared.py`` then). A change to any value here after results exist must say so
in its commit message and on the page.

The three claims of the MESRNN paper tested here, beyond the ADE/FDE ordering:

- (a) MESRNN "produces more socially compliant trajectories in dense crowds" and adapts "when more
  pedestrians are present in the surrounding area";
- (b) it predicts "agents who do not move significantly ... much better than the baselines";
- (c) the UCY scenes are harder because they are denser.

Definitions (every one per scored pedestrian of a test window, i.e. present in all 20 steps):

- *Density* of a window: the number of **other** pedestrians present at the last observed step
  (``present[OBS_LEN - 1].sum() - 1``; context pedestrians count). It is the same for every scored
  pedestrian of the window, so a window falls in exactly one density bin and blocks of windows can be
  resampled as for the headline differences.
- *Motion type of the true future* (model-free: it reads the ground truth only, never a forecast, so no
  compared model, constant velocity included, defines the bins it is judged in):
  *near-stationary* when the true displacement from the last observed position to the last future
  position, divided by the horizon in seconds (12 steps x the recording's step: 4.8 s, eth 8 s), is
  below :attr:`ClaimsConfig.stationary_speed_mps`; otherwise *linear* when the true future is close to
  some constant-velocity motion from the last observed position — the mean distance over the 12 future
  steps between the true positions ``p_k`` and the least-squares fit ``p_0 + k v`` (``v`` fitted to
  the true future alone) is below :attr:`ClaimsConfig.linear_residual_m`; otherwise *non-linear*
  (turns, speed changes, stops).
- *Collision of a pair*: two scored pedestrians of one window whose trajectories (forecast, or the
  ground truth) come closer than :attr:`ClaimsConfig.collision_distance_m` at any of the 12 predicted
  annotation steps (centre to centre; no interpolation between annotations).
- *Dense window*: density at least :attr:`ClaimsConfig.dense_min_others`.
- *Pooled*: over the five test sets together, pedestrian-weighted (pair-weighted for collisions): the
  ratio of the summed errors (collisions) to the summed pedestrians (pairs); each split's windows are
  resampled independently by the block bootstrap and the resampled sums added.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass(frozen=True)
class ClaimsConfig:
    """Bins, thresholds and rules of the claims test (module docstring; fixed before any result)."""

    density_bins: tuple[tuple[int, int | None], ...] = ((1, 2), (3, 5), (6, 10), (11, None))
    """Density bins: inclusive ranges of other pedestrians present at the last observed step; ``None``
    is open-ended. Windows have at least 2 scored pedestrians, so every window has at least 1 other."""

    stationary_speed_mps: float = 0.2
    """Near-stationary: true displacement over the horizon / horizon seconds below this (m/s); 0.2 m/s
    is under 1 m in 4.8 s, a fifth of a slow walk."""

    linear_residual_m: float = 0.2
    """Linear (if not near-stationary): mean distance (m) over the 12 future steps between the true
    future and its least-squares constant-velocity fit from the last observed position below this."""

    collision_distance_m: float = 0.2
    """Two trajectories collide when closer than this (m, centre to centre) at any predicted step."""

    dense_min_others: int = 6
    """A dense window has at least this many other pedestrians at the last observed step (the two
    densest bins)."""

    min_cell_count: int = 20
    """A cell (bin x split) with fewer scored pedestrians (pairs, for collisions) is not reported: no
    figure, no interval, no verdict."""

    max_empty_resamples: float = 0.05
    """If a bin is empty in more than this share of the bootstrap resamples, its interval is not
    computed (too few windows in it for a block bootstrap)."""

    dominance_share: float = 2.0 / 3.0
    """A pooled cell is *dominated by one scene* when one split contributes at least this share of its
    scored pedestrians (pairs)."""

    matched_horizon_s: float = 4.8
    """Claim (c) across scenes: besides the 12-step ADE, the ADE over the predicted steps within this
    many seconds (eth: 7 steps = 4.67 s; other scenes: all 12), since eth's 12 steps last 8 s."""

    baselines: tuple[str, ...] = ("srnn", "vlstm", "cv")
    """MESRNN is compared with each of these: differences MESRNN − baseline (negative: MESRNN better)."""

    primary_metric: str = "ade_m"
    """The metric the verdicts read (FDE is reported beside it)."""

    ucy_splits: tuple[str, ...] = ("univ", "zara1", "zara2")
    """The UCY test sets of claim (c); the others (eth, hotel) are ETH."""

    verdict_rules: dict[str, str] = field(
        default_factory=lambda: {
            "density": (
                "Against each baseline B, pooled ADE: holds if MESRNN − B is detectably negative in the densest "
                "bin and the contrast (densest − sparsest bin of MESRNN − B) is detectably negative (the advantage "
                "grows with density); contradicted if either is detectably positive; otherwise not established. "
                "The claim holds overall only if it holds against every baseline."
            ),
            "motion": (
                "Against each baseline B, pooled ADE of near-stationary pedestrians: holds if MESRNN − B is "
                "detectably negative; contradicted if detectably positive; otherwise not established. Overall: "
                "holds only if it holds against every baseline."
            ),
            "collisions": (
                "Against each baseline B, in dense windows pooled: holds if MESRNN's collision share minus B's is "
                "detectably negative (fewer colliding pairs of forecasts); contradicted if detectably positive; "
                "otherwise not established. Each model's share is set beside the ground truth's."
            ),
            "difficulty": (
                "Claim (c) needs all three: every UCY test set denser (mean density per scored pedestrian) than "
                "every ETH test set; every UCY test set harder (constant velocity's ADE over the matched horizon, "
                "the one baseline no training choice affects) than every ETH test set; and, within scenes, error "
                "growing with density (constant velocity's ADE, densest − sparsest reported bin, detectably "
                "positive on every split where both bins are reported). Holds if all three; contradicted if the "
                "second fails (the UCY scenes are not harder); otherwise not established."
            ),
        }
    )
    """How each claim's verdict is read from the intervals (printed on the page)."""

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["density_bins"] = [list(b) for b in self.density_bins]
        return out


#: The declared test. Fixed before any claims figure was computed.
DECLARED = ClaimsConfig()
