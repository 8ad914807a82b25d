"""Forecasting test windows shows a labelled progress bar on stderr once it takes over two seconds, and nothing when
it is quick."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.windows import Window
from crowdnav_mesrnn.evaluation.metrics import cv_predict_batch, predicted_batches


def _windows(n: int) -> list[Window]:
    t = OBS_LEN + PRED_LEN
    out = []
    for k in range(n):
        positions = (np.cumsum(np.full((t, 2, 2), 0.4), axis=0) + k).astype(np.float32)
        present = np.ones((t, 2), bool)
        out.append(Window(positions, present, present.all(axis=0), "test", k, np.arange(2)))
    return out


@pytest.mark.parametrize("seconds_per_batch", [0.0, 0.9])
def test_a_long_forecast_says_what_it_does(seconds_per_batch: float, capsys: pytest.CaptureFixture) -> None:
    def predict(pos: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        time.sleep(seconds_per_batch)
        return cv_predict_batch(pos, mask)

    assert len(list(predicted_batches(predict, _windows(12), batch_size=4))) == 3
    err = capsys.readouterr().err
    if seconds_per_batch:
        assert "forecasting 12 windows" in err and "batch" in err
    else:
        assert err == ""
