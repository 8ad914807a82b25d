"""The shipped pretrained predictors: all 15 load, are lean, and reproduce the published results page."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from crowdnav_mesrnn import load_pretrained
from crowdnav_mesrnn.data import SPLITS
from crowdnav_mesrnn.evaluation import evaluate_model
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
