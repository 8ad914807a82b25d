"""Splits, windows and normalisation, on the real ETH/UCY files and on small synthetic recordings."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.data import (
    EXPECTED_TEST_WINDOWS,
    SPLITS,
    STEP_S,
    MinMax,
    collate,
    load_split,
    split_recordings,
    split_windows,
    windows_from_recording,
)
from crowdnav_mesrnn.data.recordings import Recording


def synthetic_recording(present: np.ndarray) -> Recording:
    f, p = present.shape
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(f, p, 2)) * present[..., None]
    return Recording("toy", __import__("pathlib").Path("toy.txt"), 0.4, np.arange(f) * 10, np.arange(p), pos, present)


def test_window_scored_and_context() -> None:
    present = np.zeros((22, 4), dtype=bool)
    present[:, 0] = True  # always there: scored in every window
    present[0:21, 1] = True  # scored in windows 0 and 1, context in window 2
    present[5:7, 2] = True  # context only
    # pedestrian 3 never present: never in any window
    wins = windows_from_recording(synthetic_recording(present))
    assert len(wins) == 3
    assert wins[0].ped_ids.tolist() == [0, 1, 2]
    assert wins[0].scored.tolist() == [True, True, False]
    assert wins[2].scored.tolist() == [True, False, False]
    assert wins[2].present[:, 1].sum() == 19
    assert len(windows_from_recording(synthetic_recording(present), min_scored=2)) == 2


def test_collate_pads_with_masks() -> None:
    present = np.ones((20, 3), dtype=bool)
    a = windows_from_recording(synthetic_recording(present))[0]
    b = windows_from_recording(synthetic_recording(present[:, :1]))[0]
    pos, pres, scored = collate([a, b])
    assert pos.shape == (2, 20, 3, 2) and pres.shape == (2, 20, 3) and scored.shape == (2, 3)
    assert not pres[1, :, 1:].any() and not scored[1, 1:].any()
    assert np.all(pos[1, :, 1:] == 0)


def test_split_parts_follow_protocol() -> None:
    for split in SPLITS:
        test = {name for name, _ in split_recordings(split, "test")}
        train = {name for name, _ in split_recordings(split, "train")}
        assert not test & train
        assert {"crowds_zara03", "uni_examples"} <= train
        assert test | train == set(STEP_S)
    with pytest.raises(ValueError, match="valid splits: eth, hotel, univ, zara1, zara2"):
        split_recordings("zara3", "test")
    with pytest.raises(ValueError, match="valid parts"):
        split_recordings("eth", "dev")


def test_minmax_roundtrip_numpy_and_torch() -> None:
    pts = np.array([[0.0, -2.0], [10.0, 6.0], [5.0, 1.0]])
    mm = MinMax.fit(pts)
    n = mm.normalise(pts)
    np.testing.assert_allclose(n.min(0), [-1, -1])
    np.testing.assert_allclose(n.max(0), [1, 1])
    np.testing.assert_allclose(mm.denormalise(n), pts)
    t = torch.tensor(pts, dtype=torch.float32)
    torch.testing.assert_close(mm.denormalise(mm.normalise(t)), t)
    assert MinMax.from_dict(mm.to_dict()) == mm
    with pytest.raises(ValueError, match="degenerate"):
        MinMax.fit(np.ones((3, 2)))


@pytest.mark.parametrize("split", SPLITS)
def test_standard_test_window_counts(data_dir, split: str) -> None:
    wins = split_windows(split, "test", min_scored=2, data_dir=data_dir)
    assert len(wins) == EXPECTED_TEST_WINDOWS[split]
    assert all(w.num_scored >= 2 for w in wins)
    # Context pedestrians exist and are partly absent.
    assert any((~w.scored).any() for w in wins)


def test_step_times_and_train_parts(data_dir) -> None:
    recs = load_split("zara1", "train", data_dir)
    assert {r.name for r in recs} == {
        "biwi_eth_train",
        "biwi_hotel_train",
        "crowds_zara02_train",
        "crowds_zara03_train",
        "students001_train",
        "students003_train",
        "uni_examples_train",
    }
    steps = {r.base_name: r.step_s for r in recs}
    assert steps["biwi_eth"] == pytest.approx(0.6667, abs=1e-3)
    assert steps["biwi_hotel"] == pytest.approx(0.4)
    # Normalisation is fitted on train data only and maps it into [-1, 1].
    mm = MinMax.fit_recordings(recs)
    allp = np.concatenate([mm.normalise(r.positions[r.present]) for r in recs])
    assert allp.min() >= -1 - 1e-9 and allp.max() <= 1 + 1e-9
