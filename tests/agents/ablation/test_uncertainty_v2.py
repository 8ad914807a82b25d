"""The ablation's online-region arms (``<source>_unc_online``) and samples arms (``<source>_samples``, issue 30): what
they give the environment and the planner, cell specs (every other arm's unchanged), refusals, and the declared grid
``configs/ablation/uncertainty_v2.yaml``."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab
from crowdnav_mesrnn.config import ConfigError
from tests.agents.ablation.test_uncertainty import _raw as unc_raw

REPO = Path(__file__).resolve().parents[3]


def _raw(tmp_path: Path, **changes: Any) -> dict[str, Any]:
    """The uncertainty arms' tiny grid (:func:`tests.agents.ablation.test_uncertainty._raw`) with online and samples
    arms on the search planner."""
    return unc_raw(
        tmp_path,
        **{
            "name": "tiny_v2",
            "arms": ["mesrnn", "mesrnn_unc", "mesrnn_unc_online", "mesrnn_samples", "cv_gaussian_samples"],
            "policies": {"search": {"kind": "search"}},
            "comparisons": [["mesrnn_samples", "mesrnn"], ["mesrnn_unc_online", "mesrnn_unc"]],
            **changes,
        },
    )


def test_online_and_samples_arms_set_the_environment_and_the_planner(tmp_path: Path) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    assert [a.predictor for a in cfg.arms] == ["mesrnn", "mesrnn", "mesrnn", "mesrnn", "cv_gaussian"]
    online, samples = cfg.arm("mesrnn_unc_online"), cfg.arm("mesrnn_samples")
    assert online.env_overrides() == {"forecast_uncertainty": True, "forecast_uncertainty_method": "online"}
    assert online.planner_options() == {"uncertainty": True}
    assert cfg.arm("mesrnn_unc").env_overrides() == {"forecast_uncertainty": True}
    assert samples.env_overrides() == {"forecast_samples": ab.ARM_SAMPLES} and ab.ARM_SAMPLES == 20
    assert samples.planner_options() == {"samples": True}
    assert cfg.arm("cv_gaussian_samples").env_overrides() == {"forecast_samples": 20}


def test_point_and_split_region_arms_keep_their_specs(tmp_path: Path) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    before = ab.config_from_mapping(_raw(tmp_path, arms=["mesrnn", "mesrnn_unc"], comparisons=[]))
    for cell in ab.expand(before):
        assert ab.cell_spec(cfg, cell) == ab.cell_spec(before, cell)
    cells = {c.name: c for c in ab.expand(cfg)}
    spec = ab.cell_spec(cfg, cells["eval/zara1/search/mesrnn_unc_online"])
    assert spec["uncertainty"] is True and spec["uncertainty_method"] == "online"
    spec = ab.cell_spec(cfg, cells["eval/zara1/search/mesrnn_samples"])
    assert spec["samples"] == 20 and "uncertainty" not in spec


@pytest.mark.parametrize(
    ("arm", "words"),
    [
        ("cv_samples", ["'cv_samples'", "cv_gaussian_samples, mesrnn_samples", "no distribution"]),
        ("oracle_samples", ["'oracle_samples'", "no distribution"]),
        ("oracle_unc_online", ["'oracle_unc_online'", "cv_unc_online", "oracle_unc_online would be the oracle arm"]),
        ("sgan", ["a samples arm (cv_gaussian_samples, mesrnn_samples, srnn_samples, vlstm_samples)"]),
    ],
)
def test_arms_without_what_they_need_are_refused(tmp_path: Path, arm: str, words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(_raw(tmp_path, arms=["mesrnn", arm], comparisons=[]))
    for word in words:
        assert word in str(err.value), (word, str(err.value))


def test_samples_arms_run_on_the_search_planner_only(tmp_path: Path) -> None:
    raw = _raw(tmp_path, arms=["mesrnn", "mesrnn_samples"], comparisons=[])
    raw["policies"]["planner"] = {"kind": "planner"}
    with pytest.raises(ConfigError, match=r"'policies.planner.arms'.*mesrnn_samples.*search kind runs them"):
        ab.config_from_mapping(raw)
    raw["policies"]["planner"]["arms"] = ["mesrnn"]
    assert ab.config_from_mapping(raw).policy("planner").arms == ("mesrnn",)  # the source does not name its samples
    raw["policies"]["search"]["options"] = {"samples": True}
    with pytest.raises(ConfigError, match=r"'policies.search.options.samples'.*a samples arm sets it"):
        ab.config_from_mapping(raw)


def test_the_declared_v2_grid_loads_with_its_arms_and_comparisons(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # its reuse folders are relative to the working directory
    cfg = ab.load_config(REPO / "configs/ablation/uncertainty_v2.yaml")
    assert sorted(cfg.splits) == ["eth", "hotel", "univ", "zara1", "zara2"]
    assert {"mesrnn", "cv_gaussian", "cv", "mesrnn_samples", "cv_gaussian_samples"} <= set(cfg.arm_labels)
    assert ("mesrnn_samples", "mesrnn") in cfg.comparisons
    assert ("mesrnn_samples", "cv_gaussian_samples") in cfg.comparisons
    assert any(a.endswith("_unc_online") and b.endswith("_unc") for a, b in cfg.comparisons)
    # the cells it shares with the planners and uncertainty grids have their specs there (the same folder of cells)
    planners = ab.load_config(REPO / "configs/ablation/uncertainty.yaml")
    assert cfg.runs_path() == planners.runs_path()
    theirs = {c.name: ab.cell_spec(planners, c) for c in ab.expand(planners)}
    shared = [c for c in ab.expand(cfg) if c.name in theirs]
    assert len(shared) == 5 * 2 * 3  # cv, mesrnn, mesrnn_unc on both planners and five scenes
    for cell in shared:
        assert ab.cell_spec(cfg, cell) == theirs[cell.name], cell.name
    samples = next(c for c in ab.expand(cfg) if c.name == "eval/univ/search/mesrnn_samples")
    assert ab.estimate_seconds(cfg, samples, {}) == (500 / 0.75, "config")  # its own rate, not the point arm's


def test_a_fresh_clone_of_the_v2_grid_takes_its_shared_cells_from_the_other_grids_results(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(REPO)
    cfg = ab.load_config("configs/ablation/uncertainty_v2.yaml")
    assert cfg.reuse == ("results/ablation/planners", "results/ablation/uncertainty")
    fresh = dataclasses.replace(cfg, runs_dir=str(tmp_path / "runs"), out_dir=str(tmp_path / "results"))
    states = ab.plan(fresh)
    taken = {st.cell.name: st.source for st in states if st.state == "done"}
    pairs = [(split, policy) for split in cfg.splits for policy in ("search", "planner")]
    assert taken == {
        **{f"eval/{sp}/{p}/{arm}": "results/ablation/planners" for sp, p in pairs for arm in ("cv", "mesrnn")},
        **{f"eval/{sp}/{p}/mesrnn_unc": "results/ablation/uncertainty" for sp, p in pairs},
    }
    assert {st.state for st in states if st.cell.name not in taken} == {"todo"}
