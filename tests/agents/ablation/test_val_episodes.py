"""agents.ablation on validation episodes (``evaluation: {episodes_from: val}``, issue 29 §4): every evaluation cell
replays the split's training scenes in their validation period, the summary says so, and every grid that does not
ask for it keeps the cell specs it had."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab
from crowdnav_mesrnn.config import ConfigError
from tests.agents.ablation.test_grid import _raw as grid_raw

REPO = Path(__file__).resolve().parents[3]

#: zara1's held-out scene is crowds_zara01; its episodes replay the other splits' held-out recordings (never
#: crowds_zara03 or uni_examples, which only ever train predictors).
ZARA1_TRAINING_RECORDINGS = {"biwi_eth", "biwi_hotel", "crowds_zara02", "students001", "students003"}


def _raw(tmp_path: Path, episodes_from: str | None = "val", **changes: Any) -> dict[str, Any]:
    """test_grid's tiny grid (its agent config selects on validation list 1, the default ``eval.seed``) on arms
    without weights, one seed, episode list 7, from ``episodes_from`` (None: the key left out)."""
    evaluation: dict[str, Any] = {"episodes": 3, "seed": 7}
    if episodes_from is not None:
        evaluation["episodes_from"] = episodes_from
    defaults = {"arms": ["none", "cv"], "seeds": [0], "comparisons": [["cv", "none"]], "evaluation": evaluation}
    return grid_raw(tmp_path, **{**defaults, **changes})


def test_the_shipped_grids_keep_their_cell_specs() -> None:
    """Only the pilot asks for validation episodes; every other shipped grid's cell specs carry no new key, so no
    committed cell goes stale (test_reactive.py checks the recorded specs themselves)."""
    pilots = []
    for path in sorted((REPO / "configs/ablation").glob("*.yaml")):
        cfg = ab.load_config(path)
        if cfg.episodes_from == "val":
            pilots.append(path.name)
            continue
        assert cfg.episodes_from == "test", path.name
        assert all("episodes_from" not in ab.cell_spec(cfg, c) for c in ab.expand(cfg)), path.name
    assert pilots == ["learned_pilot.yaml"]


def test_validation_episodes_change_only_the_evaluation_cells_specs(tmp_path: Path) -> None:
    held_out = ab.config_from_mapping(_raw(tmp_path, episodes_from=None))
    assert held_out.episodes_from == "test"
    assert ab.cell_spec(held_out, ab.expand(held_out)[0]) == ab.cell_spec(
        ab.config_from_mapping(_raw(tmp_path, episodes_from="test")), ab.expand(held_out)[0]
    )
    pilot = ab.config_from_mapping(_raw(tmp_path))
    for a, b in zip(ab.expand(held_out), ab.expand(pilot), strict=True):
        old, new = ab.cell_spec(held_out, a), ab.cell_spec(pilot, b)
        if a.kind == "train":  # the same training run either way
            assert new == old, a.name
        else:
            assert new == {**old, "episodes_from": "val"}, a.name


@pytest.mark.parametrize(
    ("evaluation", "words"),
    [
        ({"episodes": 3, "seed": 7, "episodes_from": "held"}, ["'evaluation.episodes_from'", "'held'", "test", "val"]),
        ({"episodes": 3, "seed": 7, "episodes_from": True}, ["'evaluation.episodes_from'", "True", "test", "val"]),
        # the learned policy selects its best model on validation list 1: a pilot on the same list is refused
        ({"episodes": 3, "seed": 1, "episodes_from": "val"}, ["'evaluation.seed'", "1", "eval.seed 1", "'ppo'"]),
    ],
)
def test_bad_values_are_refused_naming_the_key(tmp_path: Path, evaluation: dict[str, Any], words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(_raw(tmp_path, evaluation=evaluation))
    for word in words:
        assert word in str(err.value)
    # on the held-out scenes the validation list is another scene's: seed 1 is allowed there
    ab.config_from_mapping(_raw(tmp_path, evaluation={"episodes": 3, "seed": 1}))


def test_every_evaluation_cell_and_the_summary_say_validation(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import agents.evaluation.run as evaluation_run

    calls: dict[str, Any] = {}

    def train(task: ab.CellTask, folder: Path) -> dict[str, Any]:
        (folder / ab.TRAIN_RUN).mkdir(parents=True, exist_ok=True)
        (folder / ab.TRAIN_RUN / "best_model.zip").write_bytes(task.cell.name.encode())
        return {"run_dir": ab.TRAIN_RUN, "steps": 64}

    def evaluate(spec: str, predictor: str, split: str, episodes: int, **kw: Any) -> dict[str, Any]:
        calls[Path(kw["out_dir"]).relative_to(tmp_path / "runs").as_posix()] = kw.get("episodes_from")
        rows = [{"episode": i, "seed": i, "outcome": "success", "navigation_time_s": 9.0} for i in range(episodes)]
        with open(Path(kw["out_dir"]) / "episodes.csv", "w", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        return {"episodes": episodes}

    monkeypatch.setattr(ab.execute, "_run_train", train)
    monkeypatch.setattr(evaluation_run, "evaluate", evaluate)
    monkeypatch.setattr(ab.backends, "build_forecast_caches", lambda *a, **k: [])
    cfg = ab.config_from_mapping(_raw(tmp_path))
    lines: list[str] = []
    ab.dry_run(cfg, ab.expand(cfg), 1, out=lines.append)
    assert any(line.startswith("evaluation episodes: validation episodes of the training scenes") for line in lines)
    result = ab.run_grid(cfg, workers=1, out=lambda s: None)
    assert not result["failed"], result["failed"]
    assert calls == {
        "eval/zara1/ppo/none/seed0": "val",
        "eval/zara1/ppo/cv/seed0": "val",
        "eval/zara1/planner/none": "val",
        "eval/zara1/planner/cv": "val",
    }
    summary = json.loads((cfg.out_path() / "summary.json").read_text(encoding="utf-8"))
    episodes = summary["evaluation_episodes"]
    assert (episodes["from"], episodes["part"], episodes["episode_time"]) == ("val", "train", "val")
    assert episodes["description"].startswith("validation episodes of the training scenes of zara1")
    markdown = (cfg.out_path() / "summary.md").read_text(encoding="utf-8")
    assert "validation episodes of the training scenes of zara1" in markdown
    assert "not a held-out result" in markdown and "Held-out splits" not in markdown


def test_a_tiny_grid_on_validation_episodes_replays_the_training_scenes_validation_period(
    tmp_path: Path, data_dir: Path
) -> None:
    """Real episodes (ETH/UCY): every one replays a training recording of the split, starting inside the last
    ``val_fraction`` of that recording's duration."""
    from crowdnav_mesrnn.data.recordings import load_recording

    raw = _raw(tmp_path, arms=["none"], comparisons=[], evaluation={"episodes": 6, "seed": 7, "episodes_from": "val"})
    raw["policies"] = {"straight": {"kind": "straight"}}
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    result = ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert not result["failed"], result["failed"]
    rows = ab.read_episodes(ab.cell_dir(cfg, "eval/zara1/straight/none") / "episodes.csv")
    assert len(rows) == 6
    for row in rows:
        assert row["recording"] in ZARA1_TRAINING_RECORDINGS, row
        rec = load_recording(row["recording"], "all_data", data_dir)
        duration_s = (rec.frames[-1] - rec.frames[0]) / 10 * rec.step_s  # annotations every 10 frames
        assert 0.8 * duration_s - 1e-9 <= float(row["t0_s"]) <= duration_s, row


def test_the_pilot_runs_on_validation_episodes_and_its_declared_policies() -> None:
    from agents.training.config import load_train_config

    cfg = ab.load_config(REPO / "configs/ablation/learned_pilot.yaml")
    assert (cfg.episodes_from, cfg.splits, cfg.arm_labels) == ("val", ("univ",), ("mesrnn", "oracle"))
    v2 = ab.load_config(REPO / "configs/ablation/learned_v2.yaml")
    assert not set(cfg.seeds) & set(v2.seeds), "the final grid's runs are not the ones the choice was made on"
    evals = [c for c in ab.expand(cfg) if c.kind == "eval"]
    assert evals and all(ab.cell_spec(cfg, c)["episodes_from"] == "val" for c in evals)
    teachers = {}
    for policy in (p for p in cfg.policies if p.learned):
        arm = cfg.arm(policy.arms[0] if policy.arms else "mesrnn")
        train = load_train_config(
            policy.config, None, ab.train_overrides(ab.Cell("train", "univ", policy, arm, 10), {})
        )
        assert train.eval.seed != cfg.eval_seed, "the pilot's list is not the one the best model is selected on"
        teachers[policy.name] = (Path(policy.config).name, train.pretrain.teacher, train.pretrain.teacher_predictor)
    assert teachers == {
        "ppo": ("ppo_scoring.yaml", "planner", None),
        "ppo_fast": ("ppo_scoring_fast.yaml", "planner", None),
        "ppo_search": ("ppo_scoring.yaml", "search", None),
        "ppo_search_true": ("ppo_scoring.yaml", "search", "oracle"),
    }
    assert cfg.policy("ppo_search_true").arms == ("mesrnn",)


def test_learned_v2_evaluates_fresh_lists_of_all_five_scenes() -> None:
    """A new episode list no other grid uses, the held-out scenes, and learned.yaml's declared comparisons."""
    cfg = ab.load_config(REPO / "configs/ablation/learned_v2.yaml")
    learned = ab.load_config(REPO / "configs/ablation/learned.yaml")
    others = {p.name: ab.load_config(p).eval_seed for p in (REPO / "configs/ablation").glob("*.yaml")}
    del others["learned_v2.yaml"]
    assert cfg.eval_seed not in others.values(), others
    assert (cfg.episodes_from, cfg.episodes) == ("test", 500)
    assert cfg.splits == ("eth", "hotel", "univ", "zara1", "zara2") and cfg.seeds == (0, 1, 2, 3, 4)
    assert cfg.arm_labels == ("none", "cv", "mesrnn", "oracle")
    assert {p.name: p.kind for p in cfg.policies} == {"ppo": "ppo", "planner": "planner", "search": "search"}
    assert (cfg.comparisons, cfg.policy_comparisons) == (learned.comparisons, learned.policy_comparisons)
