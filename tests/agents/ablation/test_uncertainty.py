"""The ablation's uncertainty arms (``<source>_unc``): parsing and refusals, cell specs (the point arms' unchanged),
what a cell gives the environment and the planner, the shared forecast cache, and a tiny real grid."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agents.ablation as ab
from crowdnav_mesrnn.config import ConfigError

REPO = Path(__file__).resolve().parents[3]
TINY_AGENT = "CrowdNav-CV-v0: {policy: MultiInputPolicy, n_timesteps: 64, n_steps: 64}\ncrowdnav_mesrnn: {algo: ppo}\n"


def _raw(tmp_path: Path, **changes: Any) -> dict[str, Any]:
    raw: dict[str, Any] = {
        "name": "tiny_unc",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["zara1"],
        "arms": ["cv", "cv_unc", "mesrnn", "mesrnn_unc"],
        "seeds": [0],
        "policies": {"planner": {"kind": "planner"}, "search": {"kind": "search"}},
        "evaluation": {"episodes": 2, "seed": 0},
        "comparisons": [["cv_unc", "cv"], ["mesrnn_unc", "mesrnn"], ["mesrnn_unc", "cv_unc"]],
    }
    raw.update(changes)
    return raw


def test_uncertainty_arms_use_their_sources_forecasts_with_regions(tmp_path: Path) -> None:
    arms = ["cv", "cv_unc", "mesrnn", "mesrnn_unc", "srnn_unc", "vlstm_unc"]
    cfg = ab.config_from_mapping(_raw(tmp_path, arms=arms))
    assert cfg.arm_labels == tuple(arms)
    assert [a.predictor for a in cfg.arms] == ["cv", "cv", "mesrnn", "mesrnn", "srnn", "vlstm"]
    assert [a.uncertainty for a in cfg.arms] == [False, True, False, True, True, True]
    assert cfg.arm("cv").env_overrides() == {} and cfg.arm("cv").planner_options() == {}
    assert cfg.arm("cv_unc").env_overrides() == {"forecast_uncertainty": True}
    assert cfg.arm("cv_unc").planner_options() == {"uncertainty": True}
    assert {c.name for c in ab.expand(cfg)} >= {"eval/zara1/planner/cv_unc", "eval/zara1/search/mesrnn_unc"}
    assert cfg.comparisons == (("cv_unc", "cv"), ("mesrnn_unc", "mesrnn"), ("mesrnn_unc", "cv_unc"))


@pytest.mark.parametrize(
    ("arm", "words"),
    [
        ("none_unc", ["'arms'", "'none_unc'", "cv_unc, mesrnn_unc, srnn_unc, vlstm_unc", "no forecast"]),
        ("oracle_unc", ["'oracle_unc'", "cv_unc, mesrnn_unc, srnn_unc, vlstm_unc", "regions are 0"]),
        ("noisy_oracle_unc", ["'noisy_oracle_unc'", "cv_unc, mesrnn_unc", "known noise"]),
        ("sgan_unc", ["'sgan_unc'", "cv_unc, mesrnn_unc", "no calibrated regions"]),
        (
            "sgan",
            ["'sgan'", "none, cv, cv_gaussian, mesrnn", "an uncertainty arm (cv_unc, mesrnn_unc, srnn_unc, vlstm_unc,"],
        ),
    ],
)
def test_uncertainty_arms_of_sources_without_calibrated_regions_are_refused(
    tmp_path: Path, arm: str, words: list[str]
) -> None:
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(_raw(tmp_path, arms=["cv", arm], comparisons=[]))
    for word in words:
        assert word in str(err.value)


def test_only_the_planners_with_the_option_run_uncertainty_arms(tmp_path: Path) -> None:
    agent_yaml = tmp_path / "ppo.yaml"
    agent_yaml.write_text(TINY_AGENT, encoding="utf-8")
    raw = _raw(tmp_path, arms=["cv", "cv_unc"], comparisons=[])
    raw["policies"]["ppo"] = {"kind": "ppo", "config": str(agent_yaml), "timesteps": 64}
    with pytest.raises(ConfigError) as err:  # learned policies with uncertainty arms: out of scope
        ab.config_from_mapping(raw)
    for word in ("'policies.ppo.arms'", "cv_unc", "learned 'ppo'", "out of scope", "planner and search", "[cv]"):
        assert word in str(err.value)
    raw["policies"]["ppo"]["arms"] = ["cv"]  # ... fine when it runs only the point arms
    cfg = ab.config_from_mapping(raw)
    assert cfg.policy("ppo").arms == ("cv",) and cfg.policy("planner").arms == ()
    for kind in ("straight", "privileged"):  # policies that do not read the forecasts' regions
        raw = _raw(tmp_path, arms=["cv", "cv_unc"], comparisons=[])
        raw["policies"][kind] = {"kind": kind}
        with pytest.raises(ConfigError, match=rf"'policies.{kind}.arms'.*cv_unc.*does not plan with uncertainty"):
            ab.config_from_mapping(raw)
    raw = _raw(tmp_path)
    raw["policies"]["planner"]["options"] = {"uncertainty": True}  # the arm sets it, not the policy
    with pytest.raises(ConfigError, match=r"'policies.planner.options.uncertainty'.*an uncertainty arm sets it"):
        ab.config_from_mapping(raw)


def test_a_policys_arms_name_an_uncertainty_arm_by_its_label_only(tmp_path: Path) -> None:
    raw = _raw(tmp_path)
    raw["policies"]["search"]["arms"] = ["mesrnn", "mesrnn_unc"]
    raw["policies"]["planner"]["arms"] = ["cv"]
    cfg = ab.config_from_mapping(raw)
    assert cfg.policy("search").arms == ("mesrnn", "mesrnn_unc")
    assert cfg.policy("planner").arms == ("cv",)  # the source cv does not also name cv_unc
    raw = _raw(tmp_path, arms=["cv_unc"], comparisons=[])
    raw["policies"]["planner"]["arms"] = ["cv"]  # cv is no arm of this grid; its uncertainty arm is not named by it
    with pytest.raises(ConfigError, match=r"'policies.planner.arms'.*'cv'.*allowed: cv_unc$"):
        ab.config_from_mapping(raw)


def test_point_arms_keep_their_cell_specs_and_uncertainty_arms_say_so(tmp_path: Path) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    plain = ab.config_from_mapping(_raw(tmp_path, arms=["cv", "mesrnn"], comparisons=[]))
    for cell in ab.expand(plain):
        assert ab.cell_spec(cfg, cell) == ab.cell_spec(plain, cell)
        assert "uncertainty" not in ab.cell_spec(cfg, cell)
    unc = next(c for c in ab.expand(cfg) if c.name == "eval/zara1/search/mesrnn_unc")
    spec = ab.cell_spec(cfg, unc)
    assert spec["arm"] == "mesrnn_unc" and spec["predictor"] == "mesrnn" and spec["uncertainty"] is True
    point = next(c for c in ab.expand(cfg) if c.name == "eval/zara1/search/mesrnn")
    assert {k for k in spec if spec[k] != ab.cell_spec(cfg, point).get(k)} == {"arm", "uncertainty"}


def test_the_committed_planner_grids_cells_keep_their_specs() -> None:
    """The planners grid's finished cells (``results/ablation/planners/cells.json``) have the specs the code gives
    them now, so they stay ``done`` (a change of the environment's revision makes every cell stale on purpose: left
    out here)."""
    cfg = ab.load_config(REPO / "configs/ablation/planners.yaml")
    records = json.loads((REPO / "results/ablation/planners/cells.json").read_text(encoding="utf-8"))
    cells = {c.name: c for c in ab.expand(cfg)}
    checked = 0
    for rec in records:
        want = {k: v for k, v in ab.cell_spec(cfg, cells[rec["cell"]]).items() if k != "env_revision"}
        assert {k: v for k, v in rec["spec"].items() if k != "env_revision"} == want, rec["cell"]
        checked += 1
    assert checked == len(cells)


def test_the_uncertainty_grid_shares_the_planner_grids_point_cells() -> None:
    cfg = ab.load_config(REPO / "configs/ablation/uncertainty.yaml")
    planners = ab.load_config(REPO / "configs/ablation/planners.yaml")
    assert cfg.splits == ("eth", "hotel", "univ", "zara1", "zara2")
    assert cfg.arm_labels == ("cv", "cv_unc", "mesrnn", "mesrnn_unc")
    assert cfg.comparisons == (("cv_unc", "cv"), ("mesrnn_unc", "mesrnn"), ("mesrnn_unc", "cv_unc"))
    assert (cfg.episodes, cfg.eval_seed) == (500, 0)
    assert cfg.runs_path() == planners.runs_path() and cfg.out_path() != planners.out_path()
    theirs = {c.name: c for c in ab.expand(planners)}
    shared = [c for c in ab.expand(cfg) if not c.arm.uncertainty]
    assert len(shared) == 20
    for cell in shared:  # same folder, same spec: a finished cell of the planners grid is a finished cell here
        assert ab.cell_spec(cfg, cell) == ab.cell_spec(planners, theirs[cell.name])
    assert all(c.name not in theirs for c in ab.expand(cfg) if c.arm.uncertainty)


def test_the_forecast_cache_of_an_uncertainty_arm_is_its_sources(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import envs.forecasting.build

    calls: list[tuple[str, str | None]] = []
    monkeypatch.setattr(
        envs.forecasting.build,
        "build_forecast_cache",
        lambda predictor, split=None, part="all": calls.append((predictor, split)),
        raising=False,
    )
    cfg = ab.config_from_mapping(_raw(tmp_path, splits=["univ", "zara1"]))
    assert ab.build_forecast_caches(cfg, ab.expand(cfg), out=lambda s: None) == [
        ("mesrnn", "univ"),
        ("mesrnn", "zara1"),
    ]
    only_unc = [c for c in ab.expand(cfg) if c.arm.label == "mesrnn_unc"]
    assert ab.build_forecast_caches(cfg, only_unc, out=lambda s: None) == [("mesrnn", "univ"), ("mesrnn", "zara1")]
    assert calls == [("mesrnn", "univ"), ("mesrnn", "zara1")] * 2


def test_a_cell_gives_the_environment_and_the_planner_the_uncertainty_option(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import agents.evaluation.run as evaluation_run

    calls: dict[str, Any] = {}

    def evaluate(spec: str, predictor: str, split: str, episodes: int, **kw: Any) -> dict[str, Any]:
        calls[Path(kw["out_dir"]).relative_to(tmp_path / "runs").as_posix()] = (
            spec,
            predictor,
            kw.get("env_overrides"),
            kw.get("planner_kwargs"),
        )
        (Path(kw["out_dir"]) / "episodes.csv").write_text("episode,seed,outcome\n0,1,success\n", encoding="utf-8")
        return {"episodes": 1}

    monkeypatch.setattr(evaluation_run, "evaluate", evaluate)
    monkeypatch.setattr(ab.backends, "build_forecast_caches", lambda *a, **k: [])
    raw = _raw(tmp_path, arms=["cv", "cv_unc"], comparisons=[], env={"crowd": "synthetic"})
    raw["policies"]["planner"]["options"] = {"candidates": "dense"}
    ab.run_grid(ab.config_from_mapping(raw), workers=1, summarize_after=False, out=lambda s: None)
    assert calls == {
        "eval/zara1/planner/cv": ("planner", "cv", {"crowd": "synthetic"}, {"candidates": "dense"}),
        "eval/zara1/planner/cv_unc": (
            "planner",
            "cv",
            {"crowd": "synthetic", "forecast_uncertainty": True},
            {"candidates": "dense", "uncertainty": True},
        ),
        "eval/zara1/search/cv": ("search", "cv", {"crowd": "synthetic"}, None),
        "eval/zara1/search/cv_unc": (
            "search",
            "cv",
            {"crowd": "synthetic", "forecast_uncertainty": True},
            {"uncertainty": True},
        ),
    }


@pytest.mark.slow
def test_a_tiny_grid_with_an_uncertainty_arm_plans_with_the_regions(
    tmp_path: Path, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import agents.evaluation.run as evaluation_run

    seen: dict[tuple[str, str], dict[str, Any]] = {}
    original = evaluation_run.run_episodes

    def run_episodes(policy: Any, envs: Any, seeds: Any, **kw: Any) -> Any:
        key = (type(policy).__name__, envs[0].config.predictor)
        record = seen.setdefault(
            (key[0], "unc" if envs[0].config.forecast_uncertainty else "point"),
            {
                "planner_uncertainty": policy.uncertainty,
                "env_key": "forecast_uncertainty" in envs[0].observation_space.spaces,
            },
        )
        predict = policy.predict

        def watched(obs: Any, *a: Any, **k: Any) -> Any:
            if "forecast_uncertainty" in obs:
                record["max_radius_m"] = max(
                    record.get("max_radius_m", 0.0), float(np.max(obs["forecast_uncertainty"]))
                )
            return predict(obs, *a, **k)

        policy.predict = watched
        return original(policy, envs, seeds, **kw)

    monkeypatch.setattr(evaluation_run, "run_episodes", run_episodes)
    cfg = ab.config_from_mapping(_raw(tmp_path, arms=["cv", "cv_unc"], comparisons=[["cv_unc", "cv"]]))
    result = ab.run_grid(cfg, workers=1, out=lambda s: None)
    assert not result["failed"], result["failed"]
    assert len(result["ran"]) == 4
    for planner in ("SamplingPlanner", "SearchPlanner"):
        assert seen[(planner, "point")] == {"planner_uncertainty": False, "env_key": False}
        unc = seen[(planner, "unc")]
        assert unc["planner_uncertainty"] is True and unc["env_key"] is True
        assert unc["max_radius_m"] > 0.1, "the observation carried calibrated regions"
    summary = json.loads((cfg.out_path() / "summary.json").read_text(encoding="utf-8"))
    for policy in ("planner", "search"):
        arms = summary["policies"][policy]["arms"]
        assert arms["cv_unc"]["predictor"] == "cv" and arms["cv_unc"]["uncertainty"] is True
        assert "uncertainty" not in arms["cv"] and arms["cv_unc"]["episodes"] == cfg.episodes
    assert {(t["a"]["arm"], t["b"]["arm"]) for t in summary["tests"]} == {("cv_unc", "cv")}
    assert "cv_unc" in (cfg.out_path() / "summary.md").read_text(encoding="utf-8")
