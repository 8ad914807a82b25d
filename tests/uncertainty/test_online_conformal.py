"""Online conformal calibration (``predictor calibrate --method online``): delayed feedback under both reveal rules,
the window rule's causality given the window membership rule, convergence under a shifted error scale where split
conformal fails, the window clock, the step-size rule, and the default output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.data.windows import Window, windows_from_recording
from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts
from crowdnav_mesrnn.uncertainty.calibration import Forecaster
from crowdnav_mesrnn.uncertainty.conformal import Calibration, conformal_quantile
from crowdnav_mesrnn.uncertainty.online_conformal import (
    GAMMA_GRID,
    REVEAL_RULES,
    Feedback,
    Stream,
    aggregate_thresholds,
    choose_gamma,
    expert_rates,
    track_thresholds,
    window_clock,
)

REPO = Path(__file__).resolve().parents[2]
#: The 0.9 quantile of a Rayleigh(1) score (the Mahalanobis radius of a standard bivariate Gaussian).
RAYLEIGH_Q90 = float(np.sqrt(-2 * np.log(0.1)))
#: The reveal rules that learn from the scored rows themselves (``"observed"`` learns from a Feedback stream).
SCORED_RULES = tuple(r for r in REVEAL_RULES if r != "observed")


def rayleigh_stream(windows: int, per_window: int, steps: int, scale: float, seed: int) -> tuple[np.ndarray, ...]:
    """``(scores (M, P), window (M,), time (W,))``: Rayleigh(scale) scores, one window per annotation step."""
    rng = np.random.default_rng(seed)
    scores = scale * np.sqrt(-2 * np.log(rng.uniform(size=(windows * per_window, steps))))
    return scores, np.repeat(np.arange(windows), per_window), np.arange(windows)


def reveal_delay(reveal: str, j: int, steps: int) -> int:
    """Annotations from a forecast until its step ``j + 1`` (0-based ``j``) updates the tracker."""
    return j + 1 if reveal == "step" else steps


@pytest.mark.parametrize("reveal", SCORED_RULES)
def test_a_threshold_never_depends_on_an_outcome_revealed_after_it_is_used(reveal: str) -> None:
    """Change the outcome of one window at t_k: the threshold of step h may change only from the reveal on (t_k + h
    for the step rule, t_k + 12 for the window rule), and does change there. An update without delay (or off by
    one) changes it earlier and fails."""
    scores, window, time = rayleigh_stream(80, 2, 12, 1.0, seed=0)
    time = time * 2  # gaps between forecast times: the delay is in annotations, not in windows
    start = np.full(12, RAYLEIGH_Q90)
    base = track_thresholds(scores, window, time, start, 0.9, 0.5, reveal)
    for k in (5, 30, 61):
        changed = scores.copy()
        changed[window == k] = 100.0  # both pedestrians of window k miss every step
        thr = track_thresholds(changed, window, time, start, 0.9, 0.5, reveal)
        for j in range(12):
            revealed = time[k] + reveal_delay(reveal, j, 12)
            before = time < revealed
            np.testing.assert_array_equal(thr[before, j], base[before, j])
            first_after = np.flatnonzero(~before)
            if len(first_after):
                assert thr[first_after[0], j] > base[first_after[0], j]  # the miss raised it as soon as revealed


@pytest.mark.parametrize("reveal", SCORED_RULES)
def test_the_first_windows_use_the_starting_threshold_until_an_outcome_is_revealed(reveal: str) -> None:
    scores, window, time = rayleigh_stream(30, 3, 12, 2.0, seed=1)
    start = np.linspace(1.0, 2.0, 12)
    thr = track_thresholds(scores, window, time, start, 0.9, 0.2, reveal)
    for j in range(12):
        # the window at t = 0 is revealed at t = d (h = j + 1 for the step rule, 12 for the window rule): the
        # windows before it have nothing revealed
        d = reveal_delay(reveal, j, 12)
        np.testing.assert_array_equal(thr[:d, j], start[j])
        assert thr[d, j] != start[j]


def membership_recording(gone: tuple[int, int] | None = None) -> Recording:
    """Six pedestrians walking with noise through 60 frames; ``gone = (frame index, pedestrian)`` removes one
    annotation (the pedestrian missing from that frame)."""
    rng = np.random.default_rng(7)
    frames, peds = 60, 6
    velocity = rng.normal(0.0, 0.5, (1, peds, 2))
    positions = np.cumsum(velocity + rng.normal(0.0, 0.15, (frames, peds, 2)), axis=0)
    present = np.ones((frames, peds), bool)
    if gone is not None:
        present[gone] = False
        positions[gone] = 0.0
    return Recording(
        "crowds_zara01", Path("synthetic"), 0.4, np.arange(frames) * 10, np.arange(peds), positions, present
    )


def membership_stream(rec: Recording, reveal: str) -> tuple[np.ndarray, np.ndarray]:
    """``(time (W,), thresholds (W, 12))``: the tracker over ``rec``'s windows, the score of a scored pedestrian's
    step h its distance at t + h from its constant-velocity forecast made at t (known at t + h)."""
    windows = windows_from_recording(rec)
    scores, window = [], []
    for k, w in enumerate(windows):
        pos = w.positions[:, w.scored].astype(np.float64)  # (20, n, 2)
        last, vel = pos[OBS_LEN - 1], pos[OBS_LEN - 1] - pos[OBS_LEN - 2]
        forecast = last[None] + np.arange(1, PRED_LEN + 1)[:, None, None] * vel[None]
        scores.append(np.linalg.norm(pos[OBS_LEN:] - forecast, axis=-1).T)  # (n, 12)
        window += [k] * w.num_scored
    time = window_clock(windows, [rec])
    start = np.linspace(0.2, 1.0, PRED_LEN)  # fixed in advance, as the offline thresholds are
    return time, track_thresholds(np.concatenate(scores), np.asarray(window), time, start, 0.9, 1.0, reveal)


def test_window_rule_uses_no_window_before_its_scored_pedestrians_are_known() -> None:
    """A window scores the pedestrians present in all 20 frames, so whether a pedestrian counts is settled at the
    window's last frame, t + 12. Remove one pedestrian from one frame f: the windows whose scored set changes are
    those with f among their frames (forecast times f − 12 to f + 7). Under the window rule no threshold used
    before f changes (the first affected window is revealed at f, when frame f is observed). The step rule uses
    that window's step 1 at f − 11 with the changed scored set: thresholds used before f change, and this test's
    assertion fails on it."""
    f = 40  # frame index; the affected windows' forecast times are 28..47
    base = {r: membership_stream(membership_recording(), r) for r in SCORED_RULES}
    gone = {r: membership_stream(membership_recording(gone=(f, 2)), r) for r in SCORED_RULES}
    time = base["window"][0]
    for r in SCORED_RULES:  # every window keeps some scored pedestrian: the same windows, the same clock
        np.testing.assert_array_equal(gone[r][0], time)
    before = time < f
    assert before.sum() > 2 * PRED_LEN  # outcomes revealed before f exist and have moved the thresholds
    np.testing.assert_array_equal(gone["window"][1][before], base["window"][1][before])
    assert not np.array_equal(gone["window"][1], base["window"][1])  # the change shows once revealed
    # the step rule leaks: a threshold used before f already depends on the pedestrian's absence at f
    assert not np.array_equal(gone["step"][1][before], base["step"][1][before])


@pytest.mark.parametrize("reveal", SCORED_RULES)
def test_on_a_shifted_error_scale_online_coverage_converges_and_split_conformal_does_not(reveal: str) -> None:
    """Calibrated on scale-1 scores, tested on scale-1.6: split conformal's coverage is far below 0.9 at every
    step; the tracker's reaches 0.9 at every step, with thresholds near the shifted scores' true quantile (it does
    not cover by making the regions huge)."""
    cal, _, _ = rayleigh_stream(2000, 1, 3, 1.0, seed=2)
    start = np.array([conformal_quantile(cal[:, j], 0.9) for j in range(3)])
    scores, window, time = rayleigh_stream(4000, 5, 3, 1.6, seed=3)
    split_cov = (scores <= start[None, :]).mean(0)
    assert np.all(split_cov < 0.7)
    thr = track_thresholds(scores, window, time, start, 0.9, 0.2, reveal)
    online_cov = (scores <= thr[window]).mean(0)
    np.testing.assert_allclose(online_cov, 0.9, atol=0.01)
    late = thr[len(thr) // 2 :]
    np.testing.assert_allclose(late.mean(0), 1.6 * RAYLEIGH_Q90, rtol=0.05)


@pytest.mark.parametrize("reveal", SCORED_RULES)
def test_a_stationary_stream_keeps_every_step_near_the_true_quantile(reveal: str) -> None:
    """The division of the step by the delay: even a large step leaves step 12 steady (a fixed step oscillates)."""
    scores, window, time = rayleigh_stream(1500, 3, 12, 1.0, seed=4)
    thr = track_thresholds(scores, window, time, np.full(12, RAYLEIGH_Q90), 0.9, 1.0, reveal)
    np.testing.assert_allclose(thr.mean(0), RAYLEIGH_Q90, rtol=0.08)
    np.testing.assert_allclose((scores <= thr[window]).mean(0), 0.9, atol=0.015)


def test_tracker_rejects_out_of_order_input() -> None:
    scores, window, time = rayleigh_stream(5, 1, 2, 1.0, seed=0)
    with pytest.raises(ValueError, match="time order"):
        track_thresholds(scores, window, time[::-1], np.ones(2), 0.9, 0.1)
    with pytest.raises(ValueError, match="gamma"):
        track_thresholds(scores, window, time, np.ones(2), 0.9, 0.0)
    with pytest.raises(ValueError, match="reveal rule 'later'; valid: window, step"):
        track_thresholds(scores, window, time, np.ones(2), 0.9, 0.1, "later")


def test_window_clock_follows_recordings_and_separates_them() -> None:
    def rec(name: str, frames: list[int]) -> Recording:
        n = len(frames)
        zeros, ones = np.zeros((n, 1, 2)), np.ones((n, 1), bool)
        return Recording(name, Path(name), 0.4, np.asarray(frames), np.zeros(1, np.int64), zeros, ones)

    a, b = rec("crowds_zara01", [0, 10, 20, 40, 50]), rec("students001", [100, 110])

    def win(name: str, start: int) -> Window:
        return Window(
            np.zeros((20, 1, 2), np.float32),
            np.ones((20, 1), bool),
            np.ones(1, bool),
            name,
            start,
            np.zeros(1, np.int64),
        )

    clock = window_clock([win("crowds_zara01", 0), win("crowds_zara01", 40), win("students001", 110)], [a, b])
    assert clock.tolist() == [OBS_LEN - 1, 3 + OBS_LEN - 1, 5 + PRED_LEN + 1 + 1 + OBS_LEN - 1]
    # every outcome of the first recording (last forecast time + PRED_LEN) is revealed before the second's first
    assert clock[2] > clock[1] + PRED_LEN
    with pytest.raises(ValueError, match="does not have"):
        window_clock([win("crowds_zara01", 30)], [a, b])
    with pytest.raises(ValueError, match="time order"):
        window_clock([win("students001", 100), win("crowds_zara01", 0)], [a, b])


def stream_of(scores: np.ndarray, window: np.ndarray, time: np.ndarray) -> Stream:
    m, p = scores.shape
    scored = ScoredForecasts(np.zeros((m, p, 2)), np.zeros(m), window, len(time))
    return Stream(scored, scores, time)


def test_gamma_rule_picks_the_smallest_step_within_tolerance() -> None:
    """Exchangeable validation scenes need no adaptation: the smallest step of the grid. One scene with errors
    twice as large needs a fast tracker over a short stream: a larger step."""
    same = {f"s{i}": stream_of(*rayleigh_stream(400, 3, 2, 1.0, seed=10 + i)) for i in range(3)}
    gamma, devs = choose_gamma(same, 0.9)
    assert gamma == GAMMA_GRID[0] and len(devs) == len(GAMMA_GRID)
    shifted = dict(same, s2=stream_of(*rayleigh_stream(150, 3, 2, 2.0, seed=20)))
    gamma_shifted, devs_shifted = choose_gamma(shifted, 0.9)
    assert gamma_shifted > GAMMA_GRID[1]
    assert devs_shifted[0] > 0.1  # split conformal's start is far off on the shifted scene
    with pytest.raises(ValueError, match="two validation scenes"):
        choose_gamma({"s0": same["s0"]}, 0.9)


def test_default_method_output_is_unchanged(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The default (split conformal) row equals the committed result of the command before the online method."""
    assert main(["predictor", "calibrate", "--model", "cv", "--split", "zara1", "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["splits"]["zara1"]
    committed = json.loads((REPO / "docs/results/calibration_cv_scaled.json").read_text())["splits"]["zara1"]
    assert row == committed


def test_online_cli_reports_coverage_sizes_and_split_conformal_beside(
    data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["predictor", "calibrate", "--model", "cv", "--split", "zara1", "--json", "--resamples", "200"]
    assert main([*args, "--method", "online"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["method"] == "online"
    assert res["reveal"] == "window"  # the strictly causal rule is the default
    row = res["splits"]["zara1"]
    assert main(args) == 0
    split_row = json.loads(capsys.readouterr().out)["splits"]["zara1"]
    # split conformal's figures beside it are the default method's own
    assert row["split_conformal"]["coverage"] == split_row["coverage"]
    assert row["split_conformal"]["mean_radius_m"] == split_row["mean_radius_m"]
    assert row["thresholds"] == split_row["thresholds"]  # the tracker starts from them
    assert row["raw_coverage"] == split_row["raw_coverage"]
    for key in ("0.5", "0.9", "0.95"):
        assert row["gamma"][key] in GAMMA_GRID
        assert len(row["gamma_validation_deviation"][key]) == len(GAMMA_GRID)
        steps = row["coverage_per_step"][key]
        assert np.mean(steps) == pytest.approx(row["coverage"][key])
        assert row["coverage_min_step"][key] == min(steps)
        lo, hi = row["mean_radius_diff_ci"][key]
        assert lo <= row["mean_radius_diff_m"][key] <= hi
        assert row["mean_radius_diff_m"][key] == pytest.approx(
            row["mean_radius_m"][key] - split_row["mean_radius_m"][key]
        )
        assert row["thresholds_end"][key] != row["thresholds"][key]


def test_reveal_applies_to_the_online_method_only(data_dir: Path) -> None:
    from crowdnav_mesrnn.uncertainty.calibration import calibrate_model

    with pytest.raises(ValueError, match="reveal='step' applies to method 'online' only"):
        calibrate_model("cv", "zara1", reveal="step")
    with pytest.raises(ValueError, match="reveal rule 'soon'; valid: window, step"):
        calibrate_model("cv", "zara1", method="online", reveal="soon")


@pytest.mark.parametrize("reveal", SCORED_RULES)
def test_the_expert_mixture_uses_no_outcome_before_it_is_revealed(reveal: str) -> None:
    """As for the single tracker: changing one window's outcome changes the mixture's threshold of step h only from
    its reveal on (the weights and every expert see it then), and changes it there."""
    scores, window, time = rayleigh_stream(80, 2, 12, 1.0, seed=0)
    time = time * 2
    start = np.full(12, RAYLEIGH_Q90)
    base, _ = aggregate_thresholds(scores, window, time, start, 0.9, reveal=reveal)
    for k in (5, 30, 61):
        changed = scores.copy()
        changed[window == k] = 100.0
        thr, _ = aggregate_thresholds(changed, window, time, start, 0.9, reveal=reveal)
        for j in range(12):
            before = time < time[k] + reveal_delay(reveal, j, 12)
            np.testing.assert_array_equal(thr[before, j], base[before, j])
            first_after = np.flatnonzero(~before)
            if len(first_after):
                assert thr[first_after[0], j] > base[first_after[0], j]


def test_the_expert_mixture_moves_weight_to_the_step_size_that_tracks_a_shift() -> None:
    """Calibrated on scale 1, tested on a scale that jumps to 1.8 for a short stream: the slowest tracker alone stays
    far below 0.9, the mixture reaches what the fast trackers reach and ends with most weight on steps of 0.2 or
    more. Its thresholds always lie between the experts' smallest and largest."""
    start = np.full(2, RAYLEIGH_Q90)
    scores, window, time = rayleigh_stream(300, 4, 2, 1.8, seed=7)
    slow = track_thresholds(scores, window, time, start, 0.9, GAMMA_GRID[0], "window")
    fast = track_thresholds(scores, window, time, start, 0.9, 1.0, "window")
    mixed, w_end = aggregate_thresholds(scores, window, time, start, 0.9, reveal="window")
    cov = {name: float((scores <= t[window]).mean()) for name, t in (("slow", slow), ("fast", fast), ("mix", mixed))}
    assert cov["slow"] < 0.75
    assert cov["mix"] > cov["fast"] - 0.03 and cov["mix"] > 0.85
    np.testing.assert_allclose(w_end.sum(1), 1.0)
    assert np.all(w_end[:, np.asarray(GAMMA_GRID) >= 0.2].sum(1) > 0.5)
    experts = np.stack([track_thresholds(scores, window, time, start, 0.9, g, "window") for g in GAMMA_GRID])
    assert np.all(mixed >= experts.min(0) - 1e-12) and np.all(mixed <= experts.max(0) + 1e-12)


def test_on_an_exchangeable_stream_the_mixture_stays_at_the_level() -> None:
    scores, window, time = rayleigh_stream(1500, 3, 12, 1.0, seed=4)
    thr, _ = aggregate_thresholds(scores, window, time, np.full(12, RAYLEIGH_Q90), 0.9)
    np.testing.assert_allclose((scores <= thr[window]).mean(0), 0.9, atol=0.015)


def test_expert_rates_are_the_declared_ones() -> None:
    """DtACI's rates for I = 100 windows and the 7 step sizes: at 90 %, 0.17 * sqrt((ln 700 + 2) / 0.0081)."""
    eta, share = expert_rates(len(GAMMA_GRID), 0.9)
    assert eta == pytest.approx(np.sqrt(0.03) * np.sqrt((np.log(700) + 2) / (0.81e-3 + 0.729e-2)))
    assert 5.5 < eta < 5.7 and share == pytest.approx(0.005)
    with pytest.raises(ValueError, match="at least one expert"):
        expert_rates(0, 0.9)
    with pytest.raises(ValueError, match="0 < level < 1"):
        expert_rates(7, 1.0)


@pytest.mark.slow
def test_online_cli_with_experts_reports_their_weights(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["predictor", "calibrate", "--model", "cv", "--split", "zara1", "--json", "--resamples", "200"]
    assert main([*args, "--method", "online", "--gamma", "experts"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["gamma_rule"] == "experts" and res["expert_interval"] == 100
    assert "as an expert" in res["calibration"]
    row = res["splits"]["zara1"]
    for key in ("0.5", "0.9", "0.95"):
        weights = np.asarray(row["expert_weights_end"][key])
        assert weights.shape == (PRED_LEN, len(GAMMA_GRID))
        np.testing.assert_allclose(weights.sum(1), 1.0)
        assert min(GAMMA_GRID) <= row["gamma"][key] <= max(GAMMA_GRID)
        assert row["gamma_validation_deviation"][key] == []
    assert main([*args, "--method", "online"]) == 0
    chosen = json.loads(capsys.readouterr().out)
    assert "gamma_rule" not in chosen and "expert_weights_end" not in chosen["splits"]["zara1"]
    from crowdnav_mesrnn.uncertainty.calibration import calibrate_model

    with pytest.raises(ValueError, match="gamma_rule='experts' applies to method 'online' only"):
        calibrate_model("cv", "zara1", gamma_rule="experts")
    with pytest.raises(ValueError, match="unknown gamma rule 'fast'; valid: validation, experts"):
        calibrate_model("cv", "zara1", method="online", gamma_rule="fast")


def observed_stream(rec: Recording) -> tuple[Stream, list[Window]]:
    """The scored stream of ``rec`` (windows with a scored pedestrian; constant-velocity distance scores) with its
    :class:`Feedback` (every window, every pedestrian present through the observation, NaN where not observed)."""
    from crowdnav_mesrnn.evaluation.metrics import collect_forecasts, cv_predict_batch

    scored_windows = windows_from_recording(rec)
    every = windows_from_recording(rec, min_scored=0)
    scored = collect_forecasts(scored_windows, cv_predict_batch)
    rows = collect_forecasts(every, cv_predict_batch, rows="observed")
    assert rows.observed is not None
    fb_scores = np.where(rows.observed, np.linalg.norm(rows.error, axis=-1), np.nan)
    position = {w.start_frame: i for i, w in enumerate(every)}
    index = np.array([position[w.start_frame] for w in scored_windows])
    feedback = Feedback(fb_scores, rows.window, window_clock(every, [rec]), index)
    stream = Stream(scored, np.linalg.norm(scored.error, axis=-1), window_clock(scored_windows, [rec]), feedback)
    return stream, scored_windows


def test_observed_rows_are_everyone_present_through_the_observation_marked_while_they_stay() -> None:
    """Pedestrian 2 misses frame 40: in the window whose observation ends at frame 35 it is a feedback row (present
    in all 8 observed frames) observed at steps 1-4 only, not a scored one; the scored rows are all observed."""
    from crowdnav_mesrnn.evaluation.metrics import collect_forecasts, cv_predict_batch

    rec = membership_recording(gone=(40, 2))
    every = windows_from_recording(rec, min_scored=0)
    k = next(i for i, w in enumerate(every) if w.start_frame == rec.frames[35 - OBS_LEN + 1])
    rows = collect_forecasts(every, cv_predict_batch, rows="observed")
    assert rows.observed is not None
    mine = rows.observed[rows.window == k]  # the window's six pedestrians, in column order
    assert mine.shape == (6, PRED_LEN) and every[k].num_scored == 5
    np.testing.assert_array_equal(mine[2], np.arange(1, PRED_LEN + 1) <= 4)
    assert mine[np.arange(6) != 2].all()
    np.testing.assert_array_equal(rows.error[rows.window == k][2, 4:], 0.0)  # unobserved steps carry no error
    with pytest.raises(ValueError, match="takes no samples"):
        collect_forecasts(every, cv_predict_batch, rows="observed", samples=2, sample=lambda *a: None)
    with pytest.raises(ValueError, match="unknown rows 'all'"):
        collect_forecasts(every, cv_predict_batch, rows="all")


def test_observed_rule_uses_nothing_before_it_is_observed() -> None:
    """Remove pedestrian 2 from frame f: under the observed rule no threshold used before f changes (its rows, their
    presence and the feedback windows themselves are all settled by what is observed up to each step), and
    thresholds change soon after f. Its feedback comes faster than the window rule's: the first threshold to move
    from the start moves at t = 1 (step 1 of the window at 0), the window rule's at t = 12."""
    f = 40
    base, _ = observed_stream(membership_recording())
    gone, _ = observed_stream(membership_recording(gone=(f, 2)))
    start = np.linspace(0.2, 1.0, PRED_LEN)
    thr = {name: s.thresholds(start, 0.9, 1.0, "observed") for name, s in (("base", base), ("gone", gone))}
    np.testing.assert_array_equal(gone.time, base.time)
    before = base.time < f
    np.testing.assert_array_equal(thr["gone"][before], thr["base"][before])
    assert not np.array_equal(thr["gone"][base.time < f + 2], thr["base"][base.time < f + 2])
    moved = np.flatnonzero(np.any(thr["base"] != start, axis=1))
    window_moved = np.flatnonzero(np.any(base.thresholds(start, 0.9, 1.0, "window") != start, axis=1))
    assert base.time[moved[0]] == base.time[0] + 1 and base.time[window_moved[0]] == base.time[0] + PRED_LEN
    with pytest.raises(ValueError, match="needs the stream's feedback rows"):
        Stream(base.scored, base.scores, base.time).thresholds(start, 0.9, 1.0, "observed")


@pytest.mark.slow
def test_observed_rule_runs_with_experts_only_and_the_cli_records_it(
    data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from crowdnav_mesrnn.uncertainty.calibration import calibrate_model

    with pytest.raises(ValueError, match=r"reveal='observed' runs with the step-size experts only: .*--gamma experts"):
        calibrate_model("cv", "zara1", method="online", reveal="observed")
    args = ["predictor", "calibrate", "--model", "cv", "--split", "zara1", "--json", "--resamples", "200"]
    assert main([*args, "--method", "online", "--gamma", "experts", "--reveal", "observed"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["reveal"] == "observed" and "present from the window's first frame through t + h" in res["calibration"]
    row = res["splits"]["zara1"]
    assert main([*args, "--method", "online", "--gamma", "experts"]) == 0
    window_row = json.loads(capsys.readouterr().out)["splits"]["zara1"]
    assert row["windows"] == window_row["windows"] and row["pedestrians"] == window_row["pedestrians"]
    assert row["split_conformal"] == window_row["split_conformal"]  # the same scored windows, the same start
    assert row["coverage"] != window_row["coverage"]


def test_feedback_refuses_a_nan_score_at_an_observed_step() -> None:
    """NaN marks a step not observed in the feedback rows; a NaN score at an observed step (a broken forecast or
    Gaussian) must not be skipped as if unobserved, silently: it is an error naming the row and step. A NaN where the
    step is not observed is what the mask says and passes."""
    import dataclasses

    from crowdnav_mesrnn.evaluation.metrics import collect_forecasts, cv_predict_batch
    from crowdnav_mesrnn.uncertainty.online_conformal import feedback_stream

    rec = membership_recording(gone=(40, 2))
    every = windows_from_recording(rec, min_scored=0)
    rows = collect_forecasts(every, cv_predict_batch, rows="observed")
    assert rows.observed is not None and not rows.observed.all()
    cal = Calibration("cv", "point", "zara1", "radius", {"0.9": (1.0,) * PRED_LEN}, None, 1, 1)
    unobserved = tuple(int(x) for x in np.argwhere(~rows.observed)[0])
    err = rows.error.copy()
    err[unobserved] = np.nan
    fb = feedback_stream(every, dataclasses.replace(rows, error=err), every, [rec], cal)
    assert np.isnan(fb.scores[unobserved]) and not np.isnan(fb.scores[rows.observed]).any()
    err[3, 5, 0] = np.nan
    assert rows.observed[3, 5]
    with pytest.raises(
        ValueError, match=r"1 observed step\(s\) have a NaN conformal score, the first at step 6 of row 3"
    ):
        feedback_stream(every, dataclasses.replace(rows, error=err), every, [rec], cal)


def observed_thresholds(
    recordings: list[Recording], forecaster: Forecaster, calibration: Calibration, level: float = 0.9
) -> tuple[list[tuple[str, int]], np.ndarray, np.ndarray]:
    """The ``"observed"`` rule's expert-mixture thresholds over every window of ``recordings``: ``((recording, first
    frame) of each window, (W, P) thresholds used, (W,) forecast times)``."""
    from crowdnav_mesrnn.uncertainty.online_conformal import feedback_stream

    every = [w for rec in recordings for w in windows_from_recording(rec, min_scored=0)]
    scored = [w for rec in recordings for w in windows_from_recording(rec, min_scored=2)]
    rows = forecaster.collect(every, rows="observed")
    fb = feedback_stream(every, rows, scored, recordings, calibration)
    start = np.asarray(calibration.threshold(level))
    thr = aggregate_thresholds(fb.scores, fb.window, fb.time, start, level, GAMMA_GRID, "observed")[0]
    return [(w.recording, w.start_frame) for w in every], thr, fb.time


def future_changed(rec: Recording, last: int, truncate: bool, seed: int) -> Recording:
    """``rec`` with everything after annotation ``last`` changed: cut off (``truncate``), or every later position
    moved, 40 % of the pedestrians gone, presence gaps, and two new pedestrians."""
    import dataclasses

    if truncate:
        k = last + 1
        return dataclasses.replace(rec, frames=rec.frames[:k], positions=rec.positions[:k], present=rec.present[:k])
    rng = np.random.default_rng(seed)
    pos, pres = rec.positions.copy(), rec.present.copy()
    pos[last + 1 :] += rng.normal(0.0, 0.7, pos[last + 1 :].shape)
    pres[last + 1 :, rng.random(pres.shape[1]) < 0.4] = False
    pres[last + 1 :] &= rng.random(pres[last + 1 :].shape) > 0.1
    new_pres = np.zeros((len(rec.frames), 2), bool)
    new_pres[last + 3 : last + 30] = True
    new_pos = np.where(new_pres[..., None], rng.normal(5.0, 3.0, (len(rec.frames), 2, 2)), 0.0)
    return dataclasses.replace(
        rec,
        positions=np.concatenate([np.where(pres[..., None], pos, 0.0), new_pos], axis=1),
        present=np.concatenate([pres, new_pres], axis=1),
        ped_ids=np.concatenate([rec.ped_ids, rec.ped_ids.max() + 1 + np.arange(2)]),
    )


@pytest.mark.slow
def test_observed_rule_on_zara1_uses_nothing_after_the_forecast_time(data_dir: Path) -> None:
    """Brute force on a real scene: change (or cut off) everything in ZARA1's test recording after annotation T;
    every threshold used at a forecast time <= T stays bit-identical, and thresholds used soon after T change."""
    from crowdnav_mesrnn.data.recordings import load_split
    from crowdnav_mesrnn.uncertainty.calibration import fit_calibration, forecaster_for

    forecaster = forecaster_for("cv", "zara1")
    cal = fit_calibration(forecaster, "zara1", data_dir=data_dir)
    (rec,) = load_split("zara1", "test", data_dir)
    keys, base, time = observed_thresholds([rec], forecaster, cal)
    for last in (150, 433, 700):
        for truncate in (False, True):
            changed_keys, changed, _ = observed_thresholds([future_changed(rec, last, truncate, last)], forecaster, cal)
            position = {k: i for i, k in enumerate(changed_keys)}
            before = [i for i in np.flatnonzero(time <= last) if keys[i] in position]
            assert len(before) >= last - OBS_LEN + 1 - (PRED_LEN if truncate else 0)
            np.testing.assert_array_equal(changed[[position[keys[i]] for i in before]], base[before])
            if not truncate:
                soon = np.flatnonzero((time > last) & (time <= last + 3))
                assert not np.array_equal(changed[[position[keys[i]] for i in soon]], base[soon])


def test_calibrate_learns_the_observed_rule_from_every_window_of_the_test_scene(data_dir: Path) -> None:
    """The feedback windows are every start of the test recording, those without a scored pedestrian included
    (whether a window has one is settled only at t + 12: keeping only those would make the clock's windows depend on
    the future), with their forecasts collected over every pedestrian present through the observation."""
    from crowdnav_mesrnn.data.recordings import load_split
    from crowdnav_mesrnn.uncertainty.calibration import _feedback_forecasts, forecaster_for

    (rec,) = load_split("zara1", "test", data_dir)
    windows, rows = _feedback_forecasts(forecaster_for("cv", "zara1"), "zara1", data_dir)
    assert [w.start_frame for w in windows] == rec.frames[: len(rec.frames) - OBS_LEN - PRED_LEN + 1].tolist()
    assert any(w.num_scored == 0 for w in windows)
    assert rows.observed is not None and rows.num_windows == len(windows)
