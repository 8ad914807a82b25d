"""The reactive grid (issue 28): policies keyed ``<planner>@<reaction>`` with their own environment, cell specs that
name the reaction and its parameters, the order of running, disturbance metrics in the archive and the summary, and
the across-reaction tests on synthetic cells whose answer is known."""

from __future__ import annotations

import csv
import gzip
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats as sps

import agents.ablation as ab
from agents.ablation.stats import percentile_mean_ci, sign_flip_exact
from agents.rollout import DISTURBANCE_METRICS, EPISODE_COLUMNS, episode_row
from crowdnav_mesrnn.config import ConfigError
from envs.reaction import MODEL_REVISIONS, ReactionParams

REPO = Path(__file__).resolve().parents[3]
REACTIVE = REPO / "configs/ablation/reactive.yaml"
GAINS = [["oracle", "none"], ["mesrnn", "cv"], ["mesrnn", "none"]]


def _raw(tmp_path: Path, **changes: Any) -> dict[str, Any]:
    raw: dict[str, Any] = {
        "name": "tiny_reactive",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["univ", "zara1"],
        "arms": ["none", "cv", "mesrnn", "oracle"],
        "seeds": [0],
        "policies": {
            "planner@none": {"kind": "planner", "env": {"reaction": "none"}},
            "planner@orca": {"kind": "planner", "env": {"reaction": "orca"}},
            "planner@pause": {"kind": "planner", "env": {"reaction": "pause"}, "priority": 1},
            "search@none": {"kind": "search", "env": {"reaction": "none"}, "arms": ["cv", "mesrnn", "oracle"]},
            "search@orca": {"kind": "search", "env": {"reaction": "orca"}, "arms": ["cv", "mesrnn", "oracle"]},
        },
        "evaluation": {"episodes": 60, "seed": 0},
        "comparisons": GAINS,
        "reaction_comparisons": [["orca", "none"], ["pause", "none"]],
        "disturbance_comparisons": [["oracle", "none"], ["mesrnn", "none"]],
    }
    raw.update(changes)
    return raw


# ----------------------------------------------------------------------------- the config


def test_the_reactive_config_declares_the_issue_grid() -> None:
    cfg = ab.load_config(REACTIVE)
    planners = ab.load_config(REPO / "configs/ablation/planners.yaml")
    assert set(cfg.splits) == set(planners.splits) and cfg.splits[:2] == ("univ", "zara1")
    assert (cfg.episodes, cfg.eval_seed) == (planners.episodes, planners.eval_seed) == (500, 0)
    assert cfg.arm_labels == ("none", "cv", "mesrnn", "oracle")
    reactions = ("none", "pause", "orca", "social_force")
    for base, kind in (("planner", "planner"), ("search", "search")):
        for r in reactions:
            p = cfg.policy(f"{base}@{r}")
            assert p.kind == kind and cfg.reaction(p) == r and p.uses(cfg.arm("none"))
    assert cfg.policy("privileged@none").kind == "privileged" and cfg.policy("privileged@none").arms == ("oracle",)
    for r in reactions[1:]:  # the reactive ceilings: the reaction model rolled forward (agents.planners)
        p = cfg.policy(f"privileged@{r}")
        assert p.options == {"reactive": True} and cfg.reaction(p) == r and p.arms == ("oracle",)
    assert cfg.comparisons == (("oracle", "none"), ("mesrnn", "cv"), ("mesrnn", "none"))
    assert cfg.reaction_comparisons == (("orca", "none"), ("pause", "none"), ("social_force", "none"))
    assert cfg.disturbance_comparisons == (("cv", "none"), ("mesrnn", "none"), ("oracle", "none"))
    cells = ab.expand(cfg)
    assert len(cells) == 2 * 4 * 4 * 5 + 4 * 5 and all(c.kind == "eval" for c in cells)
    names = [c.name for c in cells]
    assert len(set(names)) == len(names) and "eval/univ/search@orca/mesrnn" in names
    # the order of running: replay and ORCA (sampling, then search) before pause and social force; univ, zara1 first
    assert [c.name for c in cells[:8]] == [
        f"eval/univ/planner@{r}/{a}" for r in ("none", "orca") for a in cfg.arm_labels
    ]
    assert [c.split for c in cells[8:16]] == ["zara1"] * 8
    first = {name.split("/")[2]: i for i, name in reversed(list(enumerate(names)))}
    last = {name.split("/")[2]: i for i, name in enumerate(names)}
    assert last["planner@orca"] < first["search@none"] and last["search@orca"] < first["planner@pause"]
    assert last["planner@social_force"] < first["search@pause"] < first["privileged@none"]


def test_a_cells_spec_names_its_reaction_and_every_parameter(tmp_path: Path) -> None:
    cfg = ab.load_config(REACTIVE)
    cell = next(c for c in ab.expand(cfg) if c.name == "eval/univ/search@orca/mesrnn")
    spec = ab.cell_spec(cfg, cell)
    assert spec["env"] == {"reaction": "orca", "reaction_params": ReactionParams().to_dict()}
    assert spec["policy"] == "search@orca" and spec["policy_kind"] == "search"
    # the replay cell of the same planner differs in the environment only (same episodes, arm and predictor)
    replay = next(c for c in ab.expand(cfg) if c.name == "eval/univ/search@none/mesrnn")
    other = ab.cell_spec(cfg, replay)
    assert {k for k in spec if spec[k] != other[k]} == {"policy", "env"}
    assert other["env"]["reaction"] == "none"
    # a model past its first revision is named (its earlier cells are stale); the others' specs stay as they were
    sf = next(c for c in ab.expand(cfg) if c.name == "eval/univ/search@social_force/mesrnn")
    assert ab.cell_spec(cfg, sf)["reaction_revision"] == MODEL_REVISIONS["social_force"] == 2
    assert "reaction_revision" not in spec and "reaction_revision" not in other
    # an overridden parameter is in the spec (the rest are the defaults), so the cell's identity changes with it
    raw = _raw(tmp_path)
    raw["policies"]["planner@orca"]["env"]["reaction_params"] = {"trigger_distance_m": 2.0}
    changed = ab.config_from_mapping(raw)
    params = changed.env_for(changed.policy("planner@orca"))["reaction_params"]
    assert params == {**ReactionParams().to_dict(), "trigger_distance_m": 2.0}
    base = ab.config_from_mapping(_raw(tmp_path))
    c1 = next(c for c in ab.expand(base) if c.name == "eval/univ/planner@orca/cv")
    c2 = next(c for c in ab.expand(changed) if c.name == "eval/univ/planner@orca/cv")
    assert ab.cell_spec(base, c1) != ab.cell_spec(changed, c2)
    # a policy without an environment of its own keeps the grid's (the specs of every existing grid stay)
    plain = ab.config_from_mapping(_raw(tmp_path, policies={"planner": {"kind": "planner"}}, reaction_comparisons=[]))
    assert ab.cell_spec(plain, ab.expand(plain)[0])["env"] == {}


def test_the_committed_grids_keep_their_cell_specs_and_order() -> None:
    """Every finished cell the committed results record (``cells.json``) has the spec the code gives it now and the
    grid's cells run in the recorded order (the planning-aid grid's records predate specs)."""
    for name in ("planners", "learned", "uncertainty", "planning_aid"):
        cfg = ab.load_config(REPO / f"configs/ablation/{name}.yaml")
        records = json.loads((REPO / f"results/ablation/{name}/cells.json").read_text(encoding="utf-8"))
        cells = {c.name: c for c in ab.expand(cfg)}
        assert [c.name for c in ab.expand(cfg)] == [r["cell"] for r in records], name
        for rec in records:
            if rec.get("spec") is not None:
                assert rec["spec"] == ab.cell_spec(cfg, cells[rec["cell"]]), rec["cell"]


@pytest.mark.parametrize(
    ("policy", "words"),
    [
        ({"kind": "planner", "env": {"reaction": "pause"}}, ["'policies.planner@orca'", "reaction: orca", "'pause'"]),
        ({"kind": "planner"}, ["'policies.planner@orca'", "reaction: orca", "None"]),
        (
            {"kind": "planner", "env": {"reaction": "panic"}},
            ["'policies.planner@orca.env.reaction'", "'panic'", "orca"],
        ),
        (
            {"kind": "planner", "env": {"reaction": "orca", "reaction_params": {"trigger_m": 2}}},
            ["'policies.planner@orca.env.reaction_params'", "'trigger_m'", "trigger_distance_m"],
        ),
        (
            {"kind": "planner", "env": {"reaction": "orca", "reaction_params": {"max_speed_mps": -1}}},
            ["'policies.planner@orca.env.reaction_params'", "max_speed_mps", "-1"],
        ),
        ({"kind": "planner", "env": {"reaction": "orca", "split": "eth"}}, ["'policies.planner@orca.env'", "split"]),
        ({"kind": "planner", "env": ["reaction"]}, ["'policies.planner@orca.env'", "a mapping"]),
        ({"kind": "planner", "env": {"reaction": "orca"}, "priority": "high"}, ["'policies.planner@orca.priority'"]),
        (
            {"kind": "privileged", "env": {"reaction": "orca"}, "options": {"reactive": True, "beam": 0}},
            ["'policies.planner@orca.options'", "'beam'", "'privileged' planner"],
        ),
    ],
)
def test_bad_policy_environments_name_the_key(tmp_path: Path, policy: dict[str, Any], words: list[str]) -> None:
    raw = _raw(tmp_path, reaction_comparisons=[])
    raw["policies"]["planner@orca"] = policy
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(raw)
    for word in words:
        assert word in str(err.value)


def test_more_refusals(tmp_path: Path) -> None:
    raw = _raw(tmp_path, reaction_comparisons=[])
    raw["policies"]["planner"] = {"kind": "planner", "env": {"reaction": "orca"}}  # a reaction its key does not name
    with pytest.raises(ConfigError, match=r"'policies.planner.env.reaction'.*planner@orca"):
        ab.config_from_mapping(raw)
    raw = _raw(tmp_path, env={"reaction_params": {"trigger_distance_m": 2.0}}, reaction_comparisons=[])
    with pytest.raises(ConfigError, match=r"'env.reaction_params'.*only with a reaction"):
        ab.config_from_mapping(raw)
    with pytest.raises(ConfigError, match=r"'reaction_comparisons'.*'social_force'.*none, orca, pause"):
        ab.config_from_mapping(_raw(tmp_path, reaction_comparisons=[["social_force", "none"]]))
    with pytest.raises(ConfigError, match=r"'reaction_comparisons'.*without comparisons"):
        ab.config_from_mapping(_raw(tmp_path, comparisons=[]))
    with pytest.raises(ConfigError, match=r"'disturbance_comparisons'.*'sgan'"):
        ab.config_from_mapping(_raw(tmp_path, disturbance_comparisons=[["sgan", "none"]]))
    tiny_agent = tmp_path / "ppo.yaml"
    tiny_agent.write_text("CrowdNav-CV-v0: {policy: MultiInputPolicy}\ncrowdnav_mesrnn: {algo: ppo}\n")
    raw = _raw(tmp_path, reaction_comparisons=[])
    raw["policies"]["ppo"] = {"kind": "ppo", "config": str(tiny_agent), "timesteps": 64, "env": {"reaction": "orca"}}
    with pytest.raises(ConfigError, match=r"'policies.ppo.env'.*learned policy"):
        ab.config_from_mapping(raw)
    # an option the planner knows is accepted, and part of the spec as before
    raw = _raw(tmp_path, reaction_comparisons=[])
    raw["policies"]["planner@orca"]["options"] = {"candidates": "dense"}
    assert ab.config_from_mapping(raw).policy("planner@orca").options == {"candidates": "dense"}


# ----------------------------------------------------------------------------- running: the environment a cell gets


def test_a_cell_gets_its_policys_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import agents.evaluation.run as evaluation_run

    calls: dict[str, Any] = {}

    def evaluate(spec: str, predictor: str, split: str, episodes: int, **kw: Any) -> dict[str, Any]:
        calls[Path(kw["out_dir"]).relative_to(tmp_path / "runs").as_posix()] = kw.get("env_overrides")
        (Path(kw["out_dir"]) / "episodes.csv").write_text("episode,seed,outcome\n0,1,success\n", encoding="utf-8")
        return {"episodes": 1}

    monkeypatch.setattr(evaluation_run, "evaluate", evaluate)
    monkeypatch.setattr(ab.backends, "build_forecast_caches", lambda *a, **k: [])
    # the environment's own check of `reaction` arrives with the environment's wiring; here it is the contract's
    monkeypatch.setattr(ab.backends, "check_environments", lambda *a, **k: None)
    raw = _raw(tmp_path, splits=["zara1"], arms=["none", "oracle"], comparisons=[], reaction_comparisons=[])
    raw["policies"] = {k: v for k, v in raw["policies"].items() if k.startswith("planner@")}
    raw["policies"]["planner@orca"]["env"]["reaction_params"] = {"trigger_distance_m": 2.0}
    raw["env"] = {"crowd": "synthetic"}
    raw["disturbance_comparisons"] = []
    ab.run_grid(ab.config_from_mapping(raw), workers=1, summarize_after=False, out=lambda s: None)
    defaults = ReactionParams().to_dict()
    assert calls["eval/zara1/planner@orca/oracle"] == {
        "crowd": "synthetic",
        "reaction": "orca",
        "reaction_params": {**defaults, "trigger_distance_m": 2.0},
    }
    assert calls["eval/zara1/planner@none/none"] == {
        "crowd": "synthetic",
        "reaction": "none",
        "reaction_params": defaults,
    }
    assert len(calls) == 6


def test_settings_the_environment_refuses_stop_the_grid_before_any_cell(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import agents.evaluation.run as evaluation_run

    started: list[str] = []
    monkeypatch.setattr(evaluation_run, "evaluate", lambda *a, **k: started.append("eval"))
    raw = _raw(tmp_path, splits=["zara1"], comparisons=[], reaction_comparisons=[], disturbance_comparisons=[])
    raw["policies"] = {"planner": {"kind": "planner", "env": {"crowd": "synthetic", "sensor_rang_m": 5.0}}}
    cfg = ab.config_from_mapping(raw)
    with pytest.raises(ConfigError, match=r"'policies.planner.env'.*eval/zara1/planner/none.*'sensor_rang_m'"):
        ab.run_grid(cfg, workers=1, out=lambda s: None)
    assert started == [] and not cfg.runs_path().exists()
    path = tmp_path / "grid.yaml"
    path.write_text(json.dumps(raw), encoding="utf-8")
    assert ab.main([str(path), "--dry-run"]) == 0  # the dry run lists the cells and says the grid would not run
    assert "WARNING: the grid would not run" in capsys.readouterr().out


# ----------------------------------------------------------------------------- episodes and the archive


def test_episode_rows_carry_the_disturbance_metrics_when_the_environment_reports_them() -> None:
    assert EPISODE_COLUMNS[-2:] == ("steps", "return")
    assert EPISODE_COLUMNS[-6:-2] == DISTURBANCE_METRICS
    metrics = {"outcome": "success", "ped_disturbed": 2, "ped_deviation_mean_m": 0.3}
    row = episode_row(0, 7, {"recording": "students001"}, metrics, 1.0)
    assert row["ped_disturbed"] == 2 and row["ped_deviation_mean_m"] == 0.3
    assert row["ped_delay_s"] is None  # not reported: absent, not zero


def _cell(cfg: ab.AblationConfig, name: str, outcomes: np.ndarray, disturbed: np.ndarray | None = None) -> None:
    """A finished evaluation cell with these outcomes (True = success, else collision) and, when given, these
    ``ped_disturbed`` counts (the other disturbance metrics derived from them)."""
    cell = next(c for c in ab.expand(cfg) if c.name == name)
    folder = ab.cell_dir(cfg, cell)
    folder.mkdir(parents=True)
    columns = ["episode", "seed", "outcome", "navigation_time_s", "crowd_density"]
    columns += list(DISTURBANCE_METRICS) if disturbed is not None else []
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for i, ok in enumerate(outcomes):
        values = [i, 100 + i, "success" if ok else "collision", 12.0, float(i % 7)]
        if disturbed is not None:
            k = int(disturbed[i])
            values += [k, 0.25 * min(k, 1) + 0.05 * k, 0.6 * min(k, 1) + 0.1 * k, 1.5 * k]
        writer.writerow(values)
    (folder / "episodes.csv").write_text(buf.getvalue(), encoding="utf-8")
    spec = {"spec": ab.cell_spec(cfg, cell), "weights": {}, "wall_s": 1.0}
    (folder / ab.CELL_JSON).write_text(json.dumps(spec), encoding="utf-8")
    (folder / ab.DONE).write_text("now\n", encoding="utf-8")


@pytest.fixture
def no_weights(monkeypatch: pytest.MonkeyPatch) -> None:
    for module in (ab, ab.cells, ab.backends, ab.execute, ab.results):
        monkeypatch.setattr(module, "weights_fingerprint", lambda p: {})


def _known_grid(tmp_path: Path) -> ab.AblationConfig:
    """Synthetic cells with a known answer, 60 episodes per split (univ, zara1):

    - sampling planner on the replay: none = cv = mesrnn succeed where u < 0.6, oracle where u < 0.9 (oracle - none
      = +30 points on average; the learned forecast gains nothing);
    - under ORCA: every arm as the replay's none (the oracle's gain VANISHES: its change is -30 points);
    - under pause: the replay's outcomes of a shuffled episode list (every gain unchanged in distribution: a null whose
      episodes still move both ways), and for the search planner (arms cv, mesrnn, oracle) the replay's pattern under
      both reactions (no change);
    - disturbance under ORCA: none and mesrnn disturb 0-6 people per episode, oracle 0-2 (oracle disturbs LESS);
      under pause every arm alike (null); under none 0 (the replay disturbs nobody).
    """
    cfg = ab.config_from_mapping(_raw(tmp_path))
    rng = np.random.default_rng(7)
    for split in cfg.splits:
        u = rng.random(60)
        base = u < 0.6
        shuffled = rng.permutation(60)
        many, few = rng.integers(0, 7, 60), rng.integers(0, 3, 60)
        same = rng.integers(0, 4, 60)
        for arm in cfg.arm_labels:
            replay = u < 0.9 if arm == "oracle" else base
            _cell(cfg, f"eval/{split}/planner@none/{arm}", replay, np.zeros(60))
            _cell(cfg, f"eval/{split}/planner@orca/{arm}", base, few if arm == "oracle" else many)
            _cell(cfg, f"eval/{split}/planner@pause/{arm}", replay[shuffled], same)
            if arm != "none":
                _cell(cfg, f"eval/{split}/search@none/{arm}", replay, np.zeros(60))
                _cell(cfg, f"eval/{split}/search@orca/{arm}", replay, same)
    return cfg


def test_across_reaction_tests_find_a_vanishing_gain_and_not_a_null(tmp_path: Path, no_weights: None) -> None:
    cfg = _known_grid(tmp_path)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    tests = summary["reaction_tests"]
    # orca first; per reaction pair: the sampling planner's three gains, the search planner's mesrnn - cv (it has no
    # none arm; and no pause policy)
    assert [(t["reaction"], t["planner"], t["gain"]["a"], t["gain"]["b"]) for t in tests] == [
        ("orca", "planner", "oracle", "none"),
        ("orca", "planner", "mesrnn", "cv"),
        ("orca", "planner", "mesrnn", "none"),
        ("orca", "search", "mesrnn", "cv"),
        ("pause", "planner", "oracle", "none"),
        ("pause", "planner", "mesrnn", "cv"),
        ("pause", "planner", "mesrnn", "none"),
    ]
    fam = summary["multiple_comparisons"]["family_sizes"]
    assert fam["success_gain_change"] == 7 and all(t["family_size"] == 7 for t in tests)
    vanished = tests[0]
    gain = vanished["gain_baseline"]
    assert vanished["n"] == 120 and 0.2 < gain < 0.4 and vanished["gain_reaction"] == 0.0
    assert vanished["difference"] == pytest.approx(-gain)
    assert vanished["d_counts"] == {"-1": round(gain * 120), "0": 120 - round(gain * 120)}
    lo, hi = vanished["difference_ci"]
    assert lo <= vanished["difference"] <= hi < 0 and lo >= -2
    # all the d's are -1: the exact test is McNemar's, p = 2 / 2**k
    assert vanished["p_value"] == pytest.approx(sps.binomtest(0, round(gain * 120)).pvalue)
    assert vanished["significant"] is True and vanished["p_holm"] == pytest.approx(7 * vanished["p_value"])
    assert set(vanished["by_split"]) == {"univ", "zara1"} and vanished["by_split"]["univ"]["n"] == 60
    for t in tests[1:]:  # the learned forecast's gain is 0 everywhere; the pause null moves episodes both ways
        assert t["significant"] is False and t["p_holm"] > 0.05
    null = tests[4]
    assert null["difference"] == pytest.approx(0.0) and null["p_value"] == 1.0
    assert null["d_counts"].get("-1", 0) + null["d_counts"].get("-2", 0) > 10  # not a trivial null
    # within each reaction the declared comparisons as before: 3 gains x 3 sampling policies + 1 x 2 search, 2 splits
    assert fam["success"] == fam["navigation_time_s"] == (3 * 3 + 2) * 2


def test_each_reaction_is_divided_by_its_own_ceiling_and_the_reactive_one_says_what_it_reads(
    tmp_path: Path, no_weights: None
) -> None:
    policies = {
        "planner@none": {"kind": "planner", "env": {"reaction": "none"}},
        "planner@orca": {"kind": "planner", "env": {"reaction": "orca"}},
        "privileged@none": {"kind": "privileged", "env": {"reaction": "none"}, "arms": ["oracle"]},
        "privileged@orca": {
            "kind": "privileged",
            "env": {"reaction": "orca"},
            "options": {"reactive": True},
            "arms": ["oracle"],
        },
    }
    raw = _raw(tmp_path, arms=["none", "oracle"], policies=policies, comparisons=[["oracle", "none"]])
    raw.update(reaction_comparisons=[["orca", "none"]], disturbance_comparisons=[["oracle", "none"]])
    cfg = ab.config_from_mapping(raw)
    ok = np.arange(60) < 45
    for split in cfg.splits:
        for arm in ("none", "oracle"):
            _cell(cfg, f"eval/{split}/planner@none/{arm}", ok, np.zeros(60))
            _cell(cfg, f"eval/{split}/planner@orca/{arm}", ok, np.ones(60))
        _cell(cfg, f"eval/{split}/privileged@none/oracle", np.ones(60, dtype=bool), np.zeros(60))
        _cell(cfg, f"eval/{split}/privileged@orca/oracle", np.arange(60) < 50, np.ones(60))
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    replay, orca = summary["ceilings"]
    assert (
        replay["policy"] == "privileged@none"
        and "reactive" not in replay
        and list(replay["fractions"]) == ["planner@none"]
    )
    assert orca["policy"] == "privileged@orca" and orca["reactive"] is True
    assert orca["fractions"]["planner@orca"]["none"]["univ"] == pytest.approx(45 / 50)
    text = (cfg.out_path() / "summary.md").read_text(encoding="utf-8")
    assert "`privileged@orca` is PRIVILEGED: it rolls the reaction model forward" in text
    assert "`privileged@none` is PRIVILEGED: it reads the replay's true future" in text
    # each failure classed by its own environment's ceiling: planner@orca fails episodes 45-59 of each split, the ORCA
    # ceiling succeeds in 0-49: 45-49 avoidable, 50-59 not shown avoidable; the replay ceiling succeeds everywhere
    replay_cls, orca_cls = summary["avoidable_failures"]
    assert replay_cls["policy"] == "privileged@none" and orca_cls["policy"] == "privileged@orca"
    n = len(cfg.splits)
    assert orca_cls["ceiling_failures"] == {sp: 10 for sp in cfg.splits} and set(orca_cls["classes"]) == {
        "planner@orca"
    }
    c = orca_cls["classes"]["planner@orca"]["oracle"]
    assert (c["failures"], c["avoidable"], c["not_shown_avoidable"], c["unmatched"]) == (15 * n, 5 * n, 10 * n, 0)
    assert c["by_split"][cfg.splits[0]] == {"failures": 15, "avoidable": 5, "not_shown_avoidable": 10, "unmatched": 0}
    r = replay_cls["classes"]["planner@none"]["none"]
    assert (r["failures"], r["avoidable"], r["not_shown_avoidable"]) == (15 * n, 15 * n, 0)
    assert (
        "## Failures the ceiling avoided" in text and f"| planner@orca | oracle | {15 * n} | {5 * n} (33 %) |" in text
    )


def test_disturbance_means_intervals_and_tests(tmp_path: Path, no_weights: None) -> None:
    cfg = _known_grid(tmp_path)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    orca = summary["policies"]["planner@orca"]
    assert orca["reaction"] == "orca" and orca["env"]["reaction_params"] == ReactionParams().to_dict()
    for arm, e in orca["arms"].items():
        for m in DISTURBANCE_METRICS:
            lo, hi = e[f"{m}_ci"]
            assert 0.0 <= lo <= e[f"{m}_mean"] <= hi and e[f"{m}_n"] == 120, (arm, m)
        assert 0 < e["disturbed_episode_rate"] < 1 and e["by_split"]["univ"]["ped_disturbed_n"] == 60
    replay = summary["policies"]["planner@none"]["arms"]["none"]
    assert replay["ped_disturbed_mean"] == 0.0 and replay["ped_disturbed_ci"] == [0.0, 0.0]
    assert replay["disturbed_episode_rate"] == 0.0
    tests = summary["disturbance_tests"]
    # reacting policies only (not @none): planner@orca, planner@pause (2 comparisons), search@orca (oracle - none has no
    # none arm there: mesrnn - none neither), 4 metrics each
    assert {(t["policy"], t["a"], t["b"]) for t in tests} == {
        ("planner@orca", "oracle", "none"),
        ("planner@orca", "mesrnn", "none"),
        ("planner@pause", "oracle", "none"),
        ("planner@pause", "mesrnn", "none"),
    }
    fam = summary["multiple_comparisons"]["family_sizes"]
    assert all(fam[m] == 4 for m in DISTURBANCE_METRICS)
    less = next(
        t for t in tests if t["policy"] == "planner@orca" and t["a"] == "oracle" and t["endpoint"] == "ped_disturbed"
    )
    assert less["significant"] is True and less["difference"] < 0 and less["difference_ci"][1] < 0
    assert less["population"] == "episodes both arms finished successfully" and less["pairs"] == less["n"]
    for t in tests:
        if not (t["policy"] == "planner@orca" and t["a"] == "oracle"):
            assert t["significant"] is False, t
    md = (cfg.out_path() / "summary.md").read_text(encoding="utf-8")
    assert "## Reacting crowds" in md and "### Does a forecast's gain survive when people react?" in md
    assert "| planner | oracle - none | orca vs none | 120 |" in md
    assert "### What the robot does to people" in md and "| planner@orca | oracle |" in md
    assert "Holm-Bonferroni over the 7 tests" in md and "4 for `ped_disturbed`" in md
    # the archive holds the metrics exactly, read back as written
    rows = ab.archive.read_rows(cfg.out_path())
    assert list(rows[0])[-4:] == list(DISTURBANCE_METRICS)
    assert {r["ped_disturbed"] for r in rows if r["policy"] == "planner@none"} == {"0"}


def test_archives_without_disturbance_metrics_read_them_as_absent(tmp_path: Path, no_weights: None) -> None:
    raw = _raw(tmp_path, splits=["zara1"], arms=["none", "oracle"], comparisons=[["oracle", "none"]])
    raw.update(reaction_comparisons=[], disturbance_comparisons=[])
    raw["policies"] = {"planner": {"kind": "planner"}}
    cfg = ab.config_from_mapping(raw)
    outcomes = np.arange(60) % 3 > 0
    _cell(cfg, "eval/zara1/planner/none", outcomes)
    _cell(cfg, "eval/zara1/planner/oracle", outcomes)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    with gzip.open(cfg.out_path() / "episodes" / "planner.csv.gz", "rt") as fh:
        header = next(csv.reader(fh))
    assert not set(DISTURBANCE_METRICS) & set(header)  # written as before
    entry = summary["policies"]["planner"]
    assert "reaction" not in entry and not any(k.startswith("ped_") for k in entry["arms"]["none"])
    assert "reaction_tests" not in summary and "disturbance_tests" not in summary and "ceilings" not in summary
    assert "avoidable_failures" not in summary
    assert set(summary["multiple_comparisons"]["family_sizes"]) == {
        "success",
        "navigation_time_s",
        "success_seed_level",
    }
    # one cell that reports them beside one that does not: the other's are blank in the archive, absent in the summary
    raw["policies"] = {"planner@orca": {"kind": "planner", "env": {"reaction": "orca"}}}
    cfg = ab.config_from_mapping({**raw, "runs_dir": str(tmp_path / "runs2"), "out_dir": str(tmp_path / "out2")})
    _cell(cfg, "eval/zara1/planner@orca/none", outcomes, np.arange(60) % 4)
    _cell(cfg, "eval/zara1/planner@orca/oracle", outcomes)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    arms = summary["policies"]["planner@orca"]["arms"]
    assert arms["none"]["ped_disturbed_mean"] == pytest.approx(1.5) and "ped_disturbed_mean" not in arms["oracle"]
    rows = ab.archive.read_rows(cfg.out_path())
    assert {r["ped_disturbed"] for r in rows if r["arm"] == "oracle"} == {""}


# ----------------------------------------------------------------------------- the statistics


def test_the_sign_flip_test_is_exact() -> None:
    # magnitude 1 only: McNemar's exact test
    d = np.array([1] * 9 + [-1] * 3 + [0] * 30)
    assert sign_flip_exact(d)["p_value"] == pytest.approx(sps.binomtest(9, 12, 0.5).pvalue)
    # mixed magnitudes: scipy's exact enumeration of the 2**12 sign vectors
    d = np.array([2, 2, 1, 1, 1, 2, -1, 1, -2, 1, 2, 1, 0, 0, 0])
    want = sps.permutation_test(
        (d,), lambda x, axis: np.sum(x, axis=axis), permutation_type="samples", n_resamples=np.inf
    ).pvalue
    got = sign_flip_exact(d)
    assert got["p_value"] == pytest.approx(want) and got["statistic"] == 11 and got["n_nonzero"] == 12
    assert got["counts"] == {"-2": 1, "-1": 1, "0": 3, "1": 6, "2": 4}
    assert sign_flip_exact(np.zeros(5))["p_value"] == 1.0
    assert sign_flip_exact([-2, 2, 1, -1])["p_value"] == 1.0
    with pytest.raises(ValueError, match="integer"):
        sign_flip_exact([0.5, 1.0])


def test_percentile_intervals_stay_within_the_range() -> None:
    zero_heavy = np.concatenate([np.zeros(95), [0.1, 3.0, 5.0, 0.2, 7.0]])
    lo, hi = percentile_mean_ci(zero_heavy)
    assert 0.0 <= lo < zero_heavy.mean() < hi
    assert percentile_mean_ci(np.full(4, 2.5)) == (2.5, 2.5)
    assert all(np.isnan(percentile_mean_ci([])))


# ----------------------------------------------------------------------------- end to end (reaction none only)


def test_a_tiny_real_grid_on_the_replay_names_its_reaction(tmp_path: Path, data_dir: Path) -> None:
    from envs.config import config_from

    try:
        config_from({"reaction": "none"}, {})
    except ConfigError:
        pytest.skip("the environment does not take `reaction` yet (its wiring is another change of issue 28)")
    raw = _raw(tmp_path, splits=["zara1"], arms=["none", "cv"], comparisons=[["cv", "none"]])
    raw.update(reaction_comparisons=[], disturbance_comparisons=[], evaluation={"episodes": 2, "seed": 0})
    raw["policies"] = {"planner@none": {"kind": "planner", "env": {"reaction": "none"}}}
    cfg = ab.config_from_mapping(raw)
    result = ab.run_grid(cfg, workers=1, out=lambda s: None)
    assert not result["failed"], result["failed"]
    summary = json.loads((cfg.out_path() / "summary.json").read_text(encoding="utf-8"))
    arm = summary["policies"]["planner@none"]["arms"]["none"]
    assert all(arm[f"{m}_mean"] == 0.0 for m in DISTURBANCE_METRICS)  # the replay disturbs nobody
    cells = json.loads((cfg.out_path() / "cells.json").read_text(encoding="utf-8"))
    assert cells[0]["spec"]["env"]["reaction"] == "none"


@pytest.mark.slow
def test_the_committed_planner_grid_rerenders_unchanged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--summarize-only`` on a copy of the planners grid's config and results in a fresh clone (no run folders):
    "up to date", no file changed -- the disturbance columns and the reaction sections leave a grid without reactions
    as it was."""
    import shutil

    for sub in ("configs/ablation/planners.yaml", "results/ablation/planners"):
        (tmp_path / sub).parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if (REPO / sub).is_dir() else shutil.copy)(REPO / sub, tmp_path / sub)
    monkeypatch.chdir(tmp_path)
    results = tmp_path / "results/ablation/planners"
    before = {p: p.read_bytes() for p in results.rglob("*") if p.is_file()}  # the archive's files in episodes/ too
    assert ab.main(["configs/ablation/planners.yaml", "--summarize-only"]) == 0
    assert "is up to date" in capsys.readouterr().out
    assert {p: p.read_bytes() for p in results.rglob("*") if p.is_file()} == before


@pytest.mark.slow
def test_the_gains_by_reaction_plot_is_drawn_for_a_reacting_grid_only(tmp_path: Path, no_weights: None) -> None:
    from agents.ablation.plots import write_plots

    cfg = _known_grid(tmp_path)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    written = write_plots(summary, tmp_path)
    assert str(tmp_path / "gains_by_reaction.png") in written
    assert (tmp_path / "gains_by_reaction.png").stat().st_size > 1000
    replay_only = {**summary, "reaction_tests": [{**t, "missing": True} for t in summary["reaction_tests"]]}
    assert not any(p.endswith("gains_by_reaction.png") for p in write_plots(replay_only, tmp_path / "other"))
