"""The shipped pretrained predictors: all 15 load, are lean, and reproduce the published results page; the 15 fitted
Gaussian heads ship beside them and join them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from crowdnav_mesrnn import load_pretrained
from crowdnav_mesrnn.data import SPLITS
from crowdnav_mesrnn.evaluation.protocol import evaluate_model
from crowdnav_mesrnn.models.pretrained import PretrainedNotFoundError, available, pretrained_path

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results" / "predictors.json"


@pytest.mark.parametrize("model", ["mesrnn", "srnn", "vlstm"])
def test_all_splits_shipped_and_lean(model: str) -> None:
    assert available()[model] == list(SPLITS)
    for split in SPLITS:
        path = pretrained_path(model, split)
        assert path.stat().st_size < 3_000_000, path
        ck = torch.load(path, weights_only=True)
        assert "optimizer" not in ck
        assert all(v.dtype == torch.float32 for v in ck["state_dict"].values())
        assert ck["train_config"]["split"] == split
        assert ck["selection"]["note"].startswith("lowest val ADE")
        pred = load_pretrained(model, split)
        assert pred.name == model and pred.split == split


@pytest.mark.parametrize("model", ["mesrnn", "srnn", "vlstm"])
def test_gaussian_heads_shipped_small_and_joined_to_the_point_weights(model: str) -> None:
    """Every model and split has its fitted head (``predictor fit-head``): a file of a few kB holding only the head and
    the point weights' SHA-256; loaded, its trunk is the point weights' to the bit."""
    assert available("gaussian")[model] == list(SPLITS)
    for split in SPLITS:
        path = pretrained_path(model, split, "gaussian")
        assert path.stat().st_size < 20_000, path
        ck = torch.load(path, weights_only=True)
        assert sorted(ck["state_dict"]) == ["scale_head.bias", "scale_head.weight", "step_bias"]
        assert ck["base"]["file"] == pretrained_path(model, split).name
        point, head = load_pretrained(model, split), load_pretrained(model, split, head="gaussian")
        assert head.has_distribution and not point.has_distribution
        joined, trunk = head.net.state_dict(), point.net.state_dict()
        assert set(joined) - set(trunk) == {"scale_head.bias", "scale_head.weight", "step_bias"}
        assert all(torch.equal(joined[k], v) for k, v in trunk.items())


def test_missing_weights_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import crowdnav_mesrnn.models.pretrained as pre

    monkeypatch.setattr(pre, "PRETRAINED_DIR", tmp_path)
    pre._CACHE.clear()
    with pytest.raises(PretrainedNotFoundError, match="predictor train --model srnn --split eth"):
        pre.load_pretrained("srnn", "eth")
    with pytest.raises(ValueError, match="valid: mesrnn, srnn, vlstm"):
        pre.load_pretrained("sgan", "eth")


@pytest.mark.slow
@pytest.mark.parametrize("model", ["cv", "vlstm", "srnn", "mesrnn"])
def test_results_page_is_reproduced(model: str, data_dir: Path) -> None:
    published = json.loads(RESULTS.read_text())[model]["splits"]
    got = evaluate_model(model, "all", data_dir=data_dir)["splits"]
    for split in (*SPLITS, "average"):
        for key in ("ade_m", "fde_m", "ade_norm", "fde_norm"):
            assert got[split][key] == pytest.approx(published[split][key], rel=1e-4, abs=1e-5), (split, key)
        assert got[split]["pedestrians"] == published[split]["pedestrians"]
