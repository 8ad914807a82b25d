"""Paired comparisons of two predictors on the same windows (``predictor evaluate --versus``): known answers on
synthetic sums, and the command on the shipped Gaussian heads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.evaluation.protocol import evaluate_model, evaluate_versus, paired_differences
from crowdnav_mesrnn.evaluation.statistics import PairedErrors, block_bootstrap_ci


def sums(values: np.ndarray, count: np.ndarray) -> PairedErrors:
    return PairedErrors(values * count, count)


def test_paired_difference_of_a_constant_shift_is_exact_and_narrower_than_either_model() -> None:
    rng = np.random.default_rng(0)
    count = rng.integers(1, 6, size=200).astype(float)
    # A window-level error shared by both models (a hard scene) plus a constant 0.05 m advantage of B.
    shared = np.repeat(rng.gamma(2.0, 0.2, size=20), 10)
    a = {"eth": {"min_ade_m": sums(shared + 0.05, count)}, "hotel": {"min_ade_m": sums(2 * shared + 0.05, count)}}
    b = {"eth": {"min_ade_m": sums(shared, count)}, "hotel": {"min_ade_m": sums(2 * shared, count)}}
    diff = paired_differences(a, b, n_resamples=500)
    for split in ("eth", "hotel", "average"):
        assert diff[split]["min_ade_m"] == pytest.approx(0.05)
        assert diff[split]["min_ade_m_ci"] == pytest.approx([0.05, 0.05])
    # Unpaired, the two models' own intervals overlap: only the pairing shows the difference.
    lo_a, _ = block_bootstrap_ci(a["eth"]["min_ade_m"], n_resamples=500)
    _, hi_b = block_bootstrap_ci(b["eth"]["min_ade_m"], n_resamples=500)
    assert lo_a < hi_b
    assert set(diff["eth"]) == {"min_ade_m", "min_ade_m_ci"}


def test_paired_differences_refuse_different_windows_and_average_only_complete_metrics() -> None:
    count = np.full(30, 2.0)
    one = {"eth": {"nll_m": sums(np.ones(30), count)}}
    with pytest.raises(ValueError, match="different pedestrians per window"):
        paired_differences(one, {"eth": {"nll_m": sums(np.ones(30), np.full(30, 3.0))}})
    with pytest.raises(ValueError, match="different splits"):
        paired_differences(one, {"hotel": one["eth"]})
    a = {"eth": {"nll_m": sums(np.ones(30), count)}, "hotel": {}}
    diff = paired_differences(a, a, n_resamples=50)
    assert diff["eth"]["nll_m"] == 0.0 and "nll_m" not in diff["average"]


@pytest.mark.slow
def test_versus_gives_each_models_own_figures_and_their_paired_differences(
    data_dir: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    kwargs = {"data_dir": data_dir, "samples": 3, "head": "gaussian", "n_resamples": 200}
    res = evaluate_versus("mesrnn", ["vlstm"], splits="hotel", **kwargs)
    alone = evaluate_model("vlstm", "hotel", **kwargs)
    assert res["versus"]["vlstm"]["result"]["splits"] == alone["splits"]
    own = evaluate_model("mesrnn", "hotel", **kwargs)
    assert {k: v for k, v in res.items() if k != "versus"} == own
    diff = res["versus"]["vlstm"]["difference"]["hotel"]
    for key in ("ade_m", "fde_m", "nll_m", "min_ade_m", "min_fde_m"):
        assert diff[key] == pytest.approx(own["splits"]["hotel"][key] - alone["splits"]["hotel"][key])
        lo, hi = diff[f"{key}_ci"]
        assert lo <= diff[key] <= hi
    with pytest.raises(ValueError, match="other models than 'mesrnn'"):
        evaluate_versus("mesrnn", ["mesrnn"], splits="hotel", **kwargs)
    with pytest.raises(ValueError, match="takes no checkpoint_for"):
        evaluate_versus("mesrnn", ["vlstm"], splits="hotel", checkpoint_for=lambda s: None)

    out = tmp_path / "v.json"
    argv = ["predictor", "evaluate", "--model", "mesrnn", "--split", "hotel", "--samples", "3", "--resamples", "200"]
    assert main([*argv, "--versus", "vlstm", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "paired differences mesrnn − vlstm" in printed
    assert json.loads(out.read_text())["versus"]["vlstm"]["difference"]["hotel"] == diff
    assert main([*argv, "--versus", "vlstm", "--checkpoint", "x.pt"]) != 0
    assert "takes no --checkpoint" in capsys.readouterr().err
