"""agents.ablation: grid expansion, config errors, skip/resume/stale cells, and the summary on hand-made episodes.

Cells run in this process (``workers=1``) with the training and evaluation functions replaced by fakes, so
these tests need neither SB3 training nor the ETH/UCY data; ``test_ablation_e2e.py`` runs the real ones.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import gzip
import json
import math
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats as sps

import agents.ablation as ab
from agents.stats import holm, wilson_interval
from crowdnav_mesrnn.config import ConfigError

EPISODE_COLUMNS = ("episode", "seed", "recording", "outcome", "navigation_time_s", "path_ratio", "crowd_density")
#: A valid agent config for every arm of the tiny grids (the grid checks it, with its overrides, when loaded).
TINY_AGENT = """\
CrowdNav-MESRNN-v0: &ppo {policy: MultiInputPolicy, n_timesteps: 64, n_steps: 64}
CrowdNav-NoPred-v0: *ppo
CrowdNav-CV-v0: *ppo
CrowdNav-Oracle-v0: *ppo
crowdnav_mesrnn: {algo: ppo, pretrain: {episodes: 2}}
"""


def _raw(tmp_path: Path, **changes: Any) -> dict[str, Any]:
    agent_yaml = tmp_path / "ppo.yaml"
    agent_yaml.write_text(TINY_AGENT, encoding="utf-8")
    raw: dict[str, Any] = {
        "name": "tiny",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["zara1"],
        "arms": ["none", "mesrnn"],
        "seeds": [0, 1],
        "policies": {
            "ppo": {"kind": "ppo", "config": str(agent_yaml), "timesteps": 256, "n_envs": 1},
            "planner": {"kind": "planner"},
        },
        "evaluation": {"episodes": 4, "seed": 0},
        "comparisons": [["mesrnn", "none"]],
        "policy_comparisons": [["ppo", "planner"]],
    }
    raw.update(changes)
    return raw


# ----------------------------------------------------------------------------- config and expansion


def test_planning_aid_config_expands_to_the_issue_grid() -> None:
    cfg = ab.load_config(Path(__file__).resolve().parents[3] / "configs/ablation/planning_aid.yaml")
    cells = ab.expand(cfg)
    train = [c for c in cells if c.kind == "train"]
    evals = [c for c in cells if c.kind == "eval"]
    # PPO: 2 splits x 4 main arms x 3 seeds; planner: 2 splits x (6 arms + 4 noisy oracles)
    assert len(train) == 24
    assert len([c for c in evals if c.policy.name == "ppo"]) == 24
    assert len([c for c in evals if c.policy.name == "planner"]) == 20
    assert {c.arm.label for c in train} == {"none", "cv", "mesrnn", "oracle"}
    noisy = sorted(c.arm.noisy_oracle_ade_m for c in evals if c.arm.predictor == "noisy_oracle" and c.split == "univ")
    assert noisy == [0.1, 0.25, 0.5, 1.0]
    names = [c.name for c in cells]
    assert len(set(names)) == len(names)
    assert "train/zara1/ppo/mesrnn/seed2" in names and "eval/univ/planner/noisy_oracle-0.25" in names
    assert ab.Cell("eval", "zara1", cfg.policy("ppo"), cfg.arm("cv"), 1).needs == "train/zara1/ppo/cv/seed1"


def test_expansion_counts_and_noisy_sweep(tmp_path: Path) -> None:
    raw = _raw(tmp_path, splits=["univ", "zara1"], arms=["none", "cv", "noisy_oracle"], seeds=[0, 1, 2], comparisons=[])
    raw["noisy_oracle_ade_m"] = [0.1, 0.3, 0.6, 1.2]
    cfg = ab.config_from_mapping(raw)
    assert cfg.arm_labels == (
        "none",
        "cv",
        "noisy_oracle-0.1",
        "noisy_oracle-0.3",
        "noisy_oracle-0.6",
        "noisy_oracle-1.2",
    )
    assert cfg.arm("noisy_oracle-0.6").env_overrides() == {"noisy_oracle_ade_m": 0.6}
    cells = ab.expand(cfg)
    assert sum(c.kind == "train" for c in cells) == 2 * 6 * 3
    assert sum(c.kind == "eval" and c.policy.name == "ppo" for c in cells) == 2 * 6 * 3
    assert sum(c.kind == "eval" and c.policy.name == "planner" for c in cells) == 2 * 6
    assert all(c.seed is None for c in cells if c.policy.name == "planner")
    # a policy restricted to some arms; "noisy_oracle" names the whole sweep
    raw["policies"]["ppo"]["arms"] = ["none", "noisy_oracle"]
    cfg = ab.config_from_mapping(raw)
    assert cfg.policy("ppo").arms == (
        "none",
        "noisy_oracle-0.1",
        "noisy_oracle-0.3",
        "noisy_oracle-0.6",
        "noisy_oracle-1.2",
    )
    assert sum(c.kind == "train" for c in ab.expand(cfg)) == 2 * 5 * 3


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"arms": ["none", "sgan"]}, ["'arms'", "'sgan'", "mesrnn"]),
        ({"splits": ["zara3"]}, ["'splits'", "'zara3'", "univ"]),
        ({"seeds": [0, 0]}, ["'seeds'", "distinct"]),
        ({"arms": ["noisy_oracle"]}, ["'noisy_oracle_ade_m'", "None"]),
        ({"comparisons": [["oracle", "none"]]}, ["'comparisons'", "'oracle'", "none, mesrnn"]),
        ({"evaluation": {"episodes": 0}}, ["'evaluation.episodes'", "0", ">= 1"]),
        ({"evaluation": {"episodes": 5, "sed": 1}}, ["'sed'", "episodes, episodes_from, seed"]),
        ({"density_bins": [3, 1]}, ["'density_bins'", "increasing"]),
        ({"alpha": 5}, ["'alpha'", "(0, 1)"]),
        ({"env": {"predictor": "cv"}}, ["'env'", "predictor"]),
        ({"colour": "red"}, ["'colour'", "valid keys", "splits"]),
    ],
)
def test_bad_config_names_key_value_and_allowed(tmp_path: Path, change: dict[str, Any], words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(_raw(tmp_path, **change))
    for word in words:
        assert word in str(err.value)


def test_bad_policy_entries(tmp_path: Path) -> None:
    raw = _raw(tmp_path)
    raw["policies"]["ppo"]["kind"] = "dqn"
    with pytest.raises(ConfigError, match=r"'policies.ppo.kind'.*'dqn'.*ppo, sac, planner, search, privileged"):
        ab.config_from_mapping(raw)
    raw = _raw(tmp_path)
    raw["policies"]["planner"]["timesteps"] = 10
    with pytest.raises(ConfigError, match=r"'policies.planner.timesteps'.*not trained"):
        ab.config_from_mapping(raw)
    raw = _raw(tmp_path)
    del raw["policies"]["ppo"]["timesteps"]
    with pytest.raises(ConfigError, match=r"'policies.ppo.timesteps'.*None"):
        ab.config_from_mapping(raw)
    raw = _raw(tmp_path)
    raw["policies"]["ppo"]["arms"] = ["oracle"]
    with pytest.raises(ConfigError, match=r"'policies.ppo.arms'.*'oracle'.*none, mesrnn"):
        ab.config_from_mapping(raw)


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        ({"pretrain.episode": 3}, ["'policies.ppo.overrides'", "'episode'", "did you mean 'pretrain.episodes'?"]),
        ({"learning_rat": 1e-3}, ["'policies.ppo.overrides'", "'learning_rat'", "did you mean 'learning_rate'?"]),
        ({"eval.episode": 3}, ["eval key 'episode'", "did you mean 'eval.episodes'?"]),
        ({"pretrain.episodes": -1}, ["'policies.ppo.overrides'", "episodes"]),
        ({"n_timesteps": 5}, ["'policies.ppo.overrides.n_timesteps'", "policies.ppo.timesteps"]),
        ({"seed": 5}, ["'policies.ppo.overrides.seed'", "seeds"]),
    ],
)
def test_policy_overrides_are_checked_when_the_grid_is_loaded(
    tmp_path: Path, overrides: dict[str, Any], words: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    raw = _raw(tmp_path)
    raw["policies"]["ppo"]["overrides"] = overrides
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(raw)
    for word in words:
        assert word in str(err.value)
    # ... and so before a dry run lists the cells
    (tmp_path / "g.yaml").write_text(json.dumps(raw), encoding="utf-8")
    assert ab.main([str(tmp_path / "g.yaml"), "--dry-run"]) == 2
    assert "policies.ppo.overrides" in capsys.readouterr().err
    raw["policies"]["ppo"]["overrides"] = {"pretrain.episodes": 3, "learning_rate": 1e-3}
    assert ab.config_from_mapping(raw).policy("ppo").overrides["pretrain.episodes"] == 3
    raw["policies"]["ppo"]["config"] = str(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match=r"'policies.ppo.config'.*missing.yaml.*working directory"):
        ab.config_from_mapping(raw)


def test_only_selects_cells_and_their_training(tmp_path: Path) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    chosen = ab.select(ab.expand(cfg), "eval/zara1/ppo/mesrnn/seed1")
    assert [c.name for c in chosen] == ["train/zara1/ppo/mesrnn/seed1", "eval/zara1/ppo/mesrnn/seed1"]
    assert len(ab.select(ab.expand(cfg), "eval/*/planner/*, train/*/ppo/none/*")) == 2 + 2
    with pytest.raises(ValueError, match="matches no cell"):
        ab.select(ab.expand(cfg), "nothing*")


# ----------------------------------------------------------------------------- running cells with fakes


class Fakes:
    """Stand-ins for training and evaluation (agents.training, agents.evaluation) that record their calls."""

    def __init__(self) -> None:
        self.train_calls: list[tuple[str, bool]] = []
        self.eval_calls: list[str] = []
        self.fail: set[str] = set()

    def train(self, task: ab.CellTask, folder: Path) -> dict[str, Any]:
        run = folder / ab.TRAIN_RUN
        self.train_calls.append((task.cell.name, run.exists()))
        if task.cell.name in self.fail:
            run.mkdir(parents=True, exist_ok=True)
            raise RuntimeError("boom")
        assert (folder / "agent_config.yaml").read_text(encoding="utf-8").startswith("CrowdNav-MESRNN-v0")
        run.mkdir(parents=True, exist_ok=True)
        for which in ("best", "final"):
            (run / f"{which}_model.zip").write_bytes(f"{task.cell.name} {len(self.train_calls)}".encode())
        return {"run_dir": ab.TRAIN_RUN, "steps": task.cell.policy.timesteps}

    def evaluate(self, task: ab.CellTask, folder: Path) -> dict[str, Any]:
        self.eval_calls.append(task.cell.name)
        if task.cell.policy.learned:
            assert task.model is not None and Path(task.model).is_file()
        rows = [
            {
                "episode": i,
                "seed": 100 + i,
                "outcome": "success" if i % 2 else "collision",
                "navigation_time_s": 10.0,
                "crowd_density": 2.0,
                "return": 1.5,
            }
            for i in range(task.episodes)
        ]
        _write_csv(folder / "episodes.csv", rows)
        return {"episodes": task.episodes}


@pytest.fixture
def fakes(monkeypatch: pytest.MonkeyPatch) -> Fakes:
    f = Fakes()
    monkeypatch.setattr(ab.execute, "_run_train", f.train)
    monkeypatch.setattr(ab.execute, "_run_eval", f.evaluate)
    # the package, and where cell states, the grid's tasks and the cell runner look it up
    for module in (ab, ab.cells, ab.backends, ab.execute, ab.results):
        monkeypatch.setattr(module, "weights_fingerprint", lambda p: {"mesrnn_zara1.pt": "v1"} if p == "mesrnn" else {})
    monkeypatch.setattr(ab.backends, "build_forecast_caches", lambda *a, **k: [])
    return f


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _states(cfg: ab.AblationConfig) -> dict[str, str]:
    return {st.cell.name: st.state for st in ab.plan(cfg)}


def test_run_skips_done_cells_and_redoes_interrupted_ones(tmp_path: Path, fakes: Fakes) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    cells = ab.expand(cfg)
    assert set(_states(cfg).values()) == {"todo"}
    result = ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert not result["failed"] and len(result["ran"]) == len(cells) == 4 + 4 + 2
    assert set(_states(cfg).values()) == {"done"}
    assert all(not resumed for _, resumed in fakes.train_calls)
    meta = json.loads((ab.cell_dir(cfg, "eval/zara1/ppo/mesrnn/seed0") / ab.CELL_JSON).read_text())
    assert meta["weights"] == {"mesrnn_zara1.pt": "v1"} and meta["model_sha256"] and meta["episodes_per_s"] > 0
    # its cost in CPU seconds too (what the dry run's estimates use: wall time stretches when others share the cores)
    assert meta["cpu_s"] == meta["attempts"][-1]["cpu_s"] >= 0 and meta["episodes_per_cpu_s"] > 0

    # nothing to do on a second run
    fakes.train_calls.clear()
    fakes.eval_calls.clear()
    assert ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)["ran"] == []
    assert fakes.train_calls == [] and fakes.eval_calls == []

    # an interrupted training run (no DONE) resumes; an interrupted evaluation is redone from scratch
    (ab.cell_dir(cfg, "train/zara1/ppo/none/seed1") / ab.DONE).unlink()
    ev = ab.cell_dir(cfg, "eval/zara1/planner/none")
    (ev / ab.DONE).unlink()
    (ev / "leftover.tmp").write_text("x")
    states = _states(cfg)
    assert states["train/zara1/ppo/none/seed1"] == "partial" and states["eval/zara1/planner/none"] == "partial"
    assert states["eval/zara1/ppo/none/seed1"] == "stale"  # its training is being redone
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert fakes.train_calls == [("train/zara1/ppo/none/seed1", True)]
    assert sorted(fakes.eval_calls) == ["eval/zara1/planner/none", "eval/zara1/ppo/none/seed1"]
    assert not (ev / "leftover.tmp").exists() and (ev / ab.DONE).is_file()
    meta = json.loads((ab.cell_dir(cfg, "train/zara1/ppo/none/seed1") / ab.CELL_JSON).read_text())
    assert len(meta["attempts"]) == 2


def test_changed_weights_or_spec_make_cells_stale(
    tmp_path: Path, fakes: Fakes, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    for module in (ab, ab.cells, ab.backends, ab.execute):
        monkeypatch.setattr(module, "weights_fingerprint", lambda p: {"mesrnn_zara1.pt": "v2"} if p == "mesrnn" else {})
    states = ab.plan(cfg)
    stale = sorted(st.cell.name for st in states if st.state == "stale")
    assert stale == [
        "eval/zara1/planner/mesrnn",
        "eval/zara1/ppo/mesrnn/seed0",
        "eval/zara1/ppo/mesrnn/seed1",
        "train/zara1/ppo/mesrnn/seed0",
        "train/zara1/ppo/mesrnn/seed1",
    ]
    assert {st.reason for st in states if st.state == "stale"} == {"predictor weights changed"}
    fakes.train_calls.clear()
    fakes.eval_calls.clear()
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert sorted(fakes.train_calls) == [
        ("train/zara1/ppo/mesrnn/seed0", False),
        ("train/zara1/ppo/mesrnn/seed1", False),
    ]
    assert len(fakes.eval_calls) == 3
    assert set(_states(cfg).values()) == {"done"}

    # a different episode count makes every evaluation stale, not the training runs
    cfg2 = ab.config_from_mapping(_raw(tmp_path, evaluation={"episodes": 6, "seed": 0}))
    states = {st.cell.name: st for st in ab.plan(cfg2)}
    assert states["eval/zara1/planner/none"].state == "stale"
    assert "episodes" in states["eval/zara1/planner/none"].reason
    assert states["train/zara1/ppo/none/seed0"].state == "done"


def test_planner_options_and_the_environment_revision_are_part_of_a_cells_spec(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import agents.evaluation.run as evaluation_run
    import envs.crowd_nav

    calls: dict[str, Any] = {}

    def evaluate(spec: str, predictor: str, split: str, episodes: int, **kw: Any) -> dict[str, Any]:
        calls[f"{Path(kw['out_dir']).parent.name}/{predictor}"] = kw.get("planner_kwargs")
        _write_csv(Path(kw["out_dir"]) / "episodes.csv", _episode_rows("SC", [1.0, 1.0], [1.0, 2.0]))
        return {"episodes": 2}

    monkeypatch.setattr(evaluation_run, "evaluate", evaluate)
    raw = _raw(tmp_path, seeds=[0], arms=["none", "cv"], comparisons=[["cv", "none"]])
    raw["policies"] = {"planner": {"kind": "planner"}, "dense": {"kind": "planner", "options": {"candidates": "dense"}}}
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert calls == {
        "planner/none": None,
        "planner/cv": None,
        "dense/none": {"candidates": "dense"},
        "dense/cv": {"candidates": "dense"},
    }
    raw["policies"]["dense"]["options"] = {"candidates": "default"}
    states = {st.cell.name: st.state for st in ab.plan(ab.config_from_mapping(raw))}
    assert states["eval/zara1/dense/none"] == "stale" and states["eval/zara1/planner/none"] == "done"
    monkeypatch.setattr(envs.crowd_nav, "ENV_REVISION", envs.crowd_nav.ENV_REVISION + 1)
    assert {st.state for st in ab.plan(cfg)} == {"stale"}, "cells of another environment revision are stale"
    raw["policies"]["dense"]["options"] = ["dense"]
    with pytest.raises(ConfigError, match=r"'policies.dense.options'"):
        ab.config_from_mapping(raw)


def test_failed_cell_is_reported_and_its_evaluation_skipped(tmp_path: Path, fakes: Fakes) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    fakes.fail.add("train/zara1/ppo/mesrnn/seed0")
    result = ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert list(result["failed"]) == ["train/zara1/ppo/mesrnn/seed0"]
    assert "RuntimeError: boom" in result["failed"]["train/zara1/ppo/mesrnn/seed0"]
    assert result["skipped"] == ["eval/zara1/ppo/mesrnn/seed0"]
    meta = json.loads((ab.cell_dir(cfg, "train/zara1/ppo/mesrnn/seed0") / ab.CELL_JSON).read_text())
    assert meta["status"] == "failed"
    fakes.fail.clear()
    fakes.train_calls.clear()
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    assert fakes.train_calls == [("train/zara1/ppo/mesrnn/seed0", True)]  # the partial run resumes


def test_a_first_ctrl_c_waits_for_the_running_cells_and_a_second_stops_them(
    tmp_path: Path, fakes: Fakes, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os
    import signal

    cfg = ab.config_from_mapping(_raw(tmp_path))
    original = fakes.train
    presses = {"train/zara1/ppo/none/seed0": 1, "train/zara1/ppo/none/seed1": 2}

    def train(task: ab.CellTask, folder: Path) -> dict[str, Any]:  # Ctrl-C pressed while the cell runs
        (folder / ab.TRAIN_RUN).mkdir(parents=True, exist_ok=True)  # it has begun its run folder
        for _ in range(presses.get(task.cell.name, 0)):
            os.kill(os.getpid(), signal.SIGINT)
        return original(task, folder)

    monkeypatch.setattr(ab.execute, "_run_train", train)
    lines: list[str] = []
    only = "train/zara1/ppo/none/seed0,eval/zara1/planner/*"
    result = ab.run_grid(cfg, workers=1, only=only, out=lines.append)
    text = "\n".join(lines)
    assert "waiting for the 1 running cell(s) to finish: train/zara1/ppo/none/seed0" in text
    assert "Interrupt again (Ctrl-C) to stop them now" in text
    assert result["ran"] == ["train/zara1/ppo/none/seed0"]  # it finished; nothing else started
    assert result["interrupted"] == ["eval/zara1/planner/mesrnn", "eval/zara1/planner/none"]
    assert result["summary"] is None and "summary not updated (interrupted)" in text
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    (tmp_path / "g.yaml").write_text(json.dumps(_raw(tmp_path)), encoding="utf-8")
    presses["train/zara1/ppo/mesrnn/seed0"] = 1
    only = "train/zara1/ppo/mesrnn/seed0,eval/zara1/planner/none"
    assert ab.main([str(tmp_path / "g.yaml"), "--workers", "1", "--only", only]) == 130  # a cell was not started

    lines.clear()
    with pytest.raises(KeyboardInterrupt):
        ab.run_grid(cfg, workers=1, only="train/zara1/ppo/none/seed1", out=lines.append)
    assert "stopping 1 running cell(s) now: train/zara1/ppo/none/seed1" in "\n".join(lines)
    meta = json.loads((ab.cell_dir(cfg, "train/zara1/ppo/none/seed1") / ab.CELL_JSON).read_text())
    assert meta["status"] == "interrupted" and meta["attempts"][-1]["ok"] is False
    assert _states(cfg)["train/zara1/ppo/none/seed1"] == "partial"  # resumed by the next run
    fakes.train_calls.clear()
    presses.clear()
    ab.run_grid(cfg, workers=1, only="train/zara1/ppo/none/seed1", summarize_after=False, out=lambda s: None)
    assert fakes.train_calls == [("train/zara1/ppo/none/seed1", True)]


class _QueueBackend(ab.execute._Backend):
    """A backend that runs a cell only when the grid waits for it (as a process pool does), of ``capacity`` 2."""

    capacity = 2

    def __init__(self) -> None:
        self.tasks: dict[int, ab.CellTask] = {}
        self.submitted = 0
        self.most_outstanding = 0

    def submit(self, task: ab.CellTask) -> Any:
        self.submitted += 1
        self.tasks[self.submitted] = task
        self.most_outstanding = max(self.most_outstanding, len(self.tasks))
        return self.submitted

    def wait_one(self, handles: Any) -> tuple[Any, dict[str, Any]]:
        handle = next(iter(handles))
        return handle, ab.execute.execute_cell(self.tasks.pop(handle))


def test_a_pool_is_handed_no_more_cells_than_it_runs_so_a_first_ctrl_c_starts_no_other(
    tmp_path: Path, fakes: Fakes, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    backend = _QueueBackend()
    monkeypatch.setattr(ab.backends, "_runner", lambda *a, **k: backend)
    original = fakes.train

    def train(task: ab.CellTask, folder: Path) -> dict[str, Any]:
        if task.cell.name == "train/zara1/ppo/none/seed0":
            os.kill(os.getpid(), signal.SIGINT)  # the first Ctrl-C, while two cells are with the backend
        return original(task, folder)

    monkeypatch.setattr(ab.execute, "_run_train", train)
    lines: list[str] = []
    result = ab.run_grid(cfg, workers=2, out=lines.append)
    assert backend.most_outstanding == 2  # before the fix every ready cell (here 6) was queued at once
    text = "\n".join(lines)
    assert "waiting for the 2 running cell(s) to finish" in text
    assert sorted(result["ran"]) == ["train/zara1/ppo/none/seed0", "train/zara1/ppo/none/seed1"]
    assert len(result["interrupted"]) == len(ab.expand(cfg)) - 2


@pytest.mark.slow
def test_pool_workers_are_fresh_processes_for_every_cell() -> None:
    pool = ab.backends._Pool(1)
    try:
        assert pool.capacity == 1
        pids = [pool._pool.submit(os.getpid).result(timeout=120) for _ in range(2)]
    finally:
        pool.close()
    assert pids[0] != pids[1]  # a reused worker kept what every earlier cell left in memory


def test_dry_run_lists_states_and_uses_measured_rates(tmp_path: Path, fakes: Fakes) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    lines: list[str] = []
    ab.dry_run(cfg, ab.expand(cfg), workers=1, out=lines.append)
    assert any(line.startswith("todo") and "train/zara1/ppo/none/seed0" in line for line in lines)
    assert "10 cells (4 train, 6 eval): done 0, partial 0, stale 0, todo 10" in lines
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    (ab.cell_dir(cfg, "eval/zara1/ppo/none/seed1") / ab.DONE).unlink()
    lines.clear()
    ab.dry_run(cfg, ab.expand(cfg), workers=1, out=lines.append)
    row = next(line for line in lines if "eval/zara1/ppo/none/seed1" in line)
    assert row.startswith("partial") and "runs" in row
    assert ab.measured_rates(cfg)[("train", "ppo", "mesrnn")] > 0


def _set_wall(cfg: ab.AblationConfig, name: str, wall_s: float) -> None:
    """Make a finished training cell look as if it took ``wall_s`` seconds (of wall and of CPU time)."""
    path = ab.cell_dir(cfg, name) / ab.CELL_JSON
    meta = json.loads(path.read_text())
    meta.update(wall_s=wall_s, steps_per_s=meta["steps"] / wall_s, cpu_s=wall_s, steps_per_cpu_s=meta["steps"] / wall_s)
    path.write_text(json.dumps(meta))


def test_dry_run_calibrates_from_finished_cells_then_the_results_then_the_config(tmp_path: Path, fakes: Fakes) -> None:
    import shutil

    cfg = ab.config_from_mapping(_raw(tmp_path))
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    for name, wall in (("none/seed0", 400.0), ("none/seed1", 200.0), ("mesrnn/seed0", 500.0), ("mesrnn/seed1", 500.0)):
        _set_wall(cfg, f"train/zara1/ppo/{name}", wall)  # none: 256 steps in 400 s and in 200 s, 300 s per run
    ab.summarize(cfg, out=lambda s: None, plots=False)  # the committed record of the finished cells
    shutil.rmtree(cfg.runs_path())  # a fresh clone
    # of a grid on another episode list: its committed cells are not its cells (each evaluation and so its training run)
    cfg = dataclasses.replace(cfg, eval_seed=1)

    def rows() -> dict[str, str]:
        lines: list[str] = []
        ab.dry_run(cfg, ab.expand(cfg), workers=1, out=lines.append)
        table = {line.split()[-1]: line for line in lines if line.startswith("todo")}
        table["totals"] = "\n".join(lines[-2:])
        return table

    table = rows()
    # the results' record: steps over seconds of that (kind, policy kind, forecast source), pooled over cells
    assert "5 min" in table["train/zara1/ppo/none/seed1"] and "results" in table["train/zara1/ppo/none/seed1"]
    assert "8 min" in table["train/zara1/ppo/mesrnn/seed1"] and "results" in table["train/zara1/ppo/mesrnn/seed1"]
    assert "results" in table["eval/zara1/planner/none"]
    assert "10 cells (4 train, 6 eval) from the finished cells recorded in" in table["totals"]
    assert "cells.json" in table["totals"]
    # a finished cell of this grid counts before the results' record
    ab.run_grid(cfg, workers=1, only="train/zara1/ppo/none/seed0", summarize_after=False, out=lambda s: None)
    _set_wall(cfg, "train/zara1/ppo/none/seed0", 60.0)
    table = rows()
    assert "60 s" in table["train/zara1/ppo/none/seed1"] and "runs" in table["train/zara1/ppo/none/seed1"]
    assert "results" in table["train/zara1/ppo/mesrnn/seed1"]
    # without either: the config's estimates, and the dry run says so
    shutil.rmtree(cfg.runs_path())
    (cfg.out_path() / "cells.json").unlink()
    table = rows()
    assert "config" in table["train/zara1/ppo/none/seed1"]
    assert "10 cells (4 train, 6 eval) from the config's estimates" in table["totals"]


def test_a_cells_rate_is_per_cpu_second_where_it_recorded_one(tmp_path: Path, fakes: Fakes) -> None:
    """A cell that waited for the cores (wall 400 s) but computed for 100 s is estimated at its CPU rate; a record from
    before CPU time was recorded falls back to its wall rate; both in run folders and in the committed record."""
    cfg = ab.config_from_mapping(_raw(tmp_path))
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    for name in ("none/seed0", "none/seed1"):
        path = ab.cell_dir(cfg, f"train/zara1/ppo/{name}") / ab.CELL_JSON
        meta = json.loads(path.read_text())
        meta.update(wall_s=400.0, steps_per_s=meta["steps"] / 400.0, cpu_s=100.0, steps_per_cpu_s=meta["steps"] / 100.0)
        path.write_text(json.dumps(meta))
        steps = meta["steps"]
    assert ab.measured_rates(cfg)[("train", "ppo", "none")] == pytest.approx(steps / 100.0)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    records = {r["cell"]: r for r in json.loads((cfg.out_path() / "cells.json").read_text())}
    assert records["train/zara1/ppo/none/seed0"]["steps_per_cpu_s"] == pytest.approx(steps / 100.0)
    assert ab.recorded_rates(cfg)[("train", "ppo", "none")] == pytest.approx(steps / 100.0)
    for name in ("none/seed0", "none/seed1"):  # an older cell.json: no CPU time
        path = ab.cell_dir(cfg, f"train/zara1/ppo/{name}") / ab.CELL_JSON
        meta = json.loads(path.read_text())
        for key in ("cpu_s", "steps_per_cpu_s"):
            meta.pop(key)
        path.write_text(json.dumps(meta))
    assert ab.measured_rates(cfg)[("train", "ppo", "none")] == pytest.approx(steps / 400.0)


def test_the_configs_training_estimates_are_looked_up_by_policy_and_arm(tmp_path: Path) -> None:
    """A training run's fallback throughput: ``<policy>/<arm>``, arm label, arm source, policy name, ``default``
    (e.g. a policy whose slower teacher makes its every arm slower)."""
    raw = _raw(tmp_path)
    raw["policies"]["slow"] = {**raw["policies"]["ppo"]}
    rates = {"default": 256.0, "slow": 128.0, "slow/none": 64.0}
    cfg = ab.config_from_mapping({**raw, "estimates": {"train_steps_per_s": rates}})
    seconds = {
        c.name: ab.estimate_seconds(cfg, c, {}) for c in ab.expand(cfg) if c.kind == "train" and c.seed == 0
    }  # 256 steps per run
    assert seconds == {
        "train/zara1/ppo/none/seed0": (1.0, "config"),
        "train/zara1/ppo/mesrnn/seed0": (1.0, "config"),
        "train/zara1/slow/none/seed0": (4.0, "config"),
        "train/zara1/slow/mesrnn/seed0": (2.0, "config"),
    }
    cfg = ab.config_from_mapping({**raw, "estimates": {"train_steps_per_s": {**rates, "mesrnn": 512.0}}})
    assert ab.estimate_seconds(cfg, ab.Cell("train", "zara1", cfg.policy("slow"), cfg.arm("mesrnn"), 0), {}) == (
        0.5,
        "config",
    ), "an arm's estimate comes before the policy's"


# ----------------------------------------------------------------------------- the summary


def _episode_rows(outcomes: str, times: list[float], density: list[float]) -> list[dict[str, Any]]:
    code = {"S": "success", "C": "collision", "T": "timeout"}
    return [
        {
            "episode": i,
            "seed": 1000 + i,
            "recording": "crowds_zara01",
            "outcome": code[o],
            "navigation_time_s": t,
            "path_ratio": 1.1,
            "crowd_density": d,
        }
        for i, (o, t, d) in enumerate(zip(outcomes, times, density, strict=True))
    ]


def _fake_done_cell(cfg: ab.AblationConfig, name: str, rows: list[dict[str, Any]]) -> None:
    cell = next(c for c in ab.expand(cfg) if c.name == name)
    folder = ab.cell_dir(cfg, cell)
    _write_csv(folder / "episodes.csv", rows)
    meta = {"spec": ab.cell_spec(cfg, cell), "weights": ab.weights_fingerprint(cell.arm.predictor), "wall_s": 2.0}
    (folder / ab.CELL_JSON).write_text(json.dumps(meta))
    (folder / ab.DONE).write_text("now\n")


def test_summary_statistics_on_hand_made_episodes(tmp_path: Path, fakes: Fakes) -> None:
    raw = _raw(tmp_path, arms=["none", "cv", "oracle"], comparisons=[["cv", "none"], ["oracle", "none"]])
    raw["policies"] = {"planner": {"kind": "planner"}}
    raw["evaluation"] = {"episodes": 12, "seed": 0}
    raw["density_bins"] = 3
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    density = [
        float(v) for v in range(12)
    ]  # terciles 3.67, 7.33, rounded to whole pedestrians: [0, 4), [4, 7), [7, 11]
    #            episode: 0123456789ab
    none_outcomes = "SCCSCCTSCSCS"  # 5 successes
    cv_outcomes = "SSSSCSSSCSSS"  # 10 successes
    oracle_outcomes = "SCCSCCTSCSCS"  # identical to none: no discordant pair
    times_none = [10.0 + i for i in range(12)]
    times_cv = [t - (0.5 if i % 2 else 1.0) for i, t in enumerate(times_none)]
    _fake_done_cell(cfg, "eval/zara1/planner/none", _episode_rows(none_outcomes, times_none, density))
    _fake_done_cell(cfg, "eval/zara1/planner/cv", _episode_rows(cv_outcomes, times_cv, density))
    _fake_done_cell(cfg, "eval/zara1/planner/oracle", _episode_rows(oracle_outcomes, times_none, density))
    summary = ab.summarize(cfg, out=lambda s: None)
    on_disk = json.loads((cfg.out_path() / "summary.json").read_text())
    assert on_disk["policies"]["planner"]["arms"]["cv"]["success_rate"] == pytest.approx(10 / 12)
    assert summary["complete"] is True

    none = summary["policies"]["planner"]["arms"]["none"]
    assert none["episodes"] == 12 and none["seeds"] == []
    assert none["success_rate"] == pytest.approx(5 / 12)
    assert none["success_ci"] == pytest.approx(list(wilson_interval(5, 12)))
    assert none["collision_rate"] == pytest.approx(6 / 12) and none["timeout_rate"] == pytest.approx(1 / 12)
    # navigation time averages the successful episodes only
    succ = [t for t, o in zip(times_none, none_outcomes, strict=True) if o == "S"]
    assert none["navigation_time_s_mean"] == pytest.approx(np.mean(succ))
    assert none["forecast_ade_m_mean"] is None  # no such column: undefined, not zero

    # density terciles over the 12 episodes in whole pedestrians, computed once for every arm
    assert summary["density_bins"] == [0.0, 4.0, 7.0, 11.0]
    bins = none["by_density"]
    assert [b["episodes"] for b in bins] == [4, 3, 5]
    assert bins[0]["success_rate"] == pytest.approx(2 / 4)  # episodes 0-3: S C C S

    tests = summary["tests"]
    assert summary["multiple_comparisons"]["family_sizes"] == {
        "success": 2,
        "navigation_time_s": 2,
        "success_seed_level": 0,  # a planner has no training seeds: no seed-level test
    }
    assert all("seed_level" not in t for t in summary["tests"])
    cv_vs_none = next(t for t in tests if t["a"]["arm"] == "cv" and t["endpoint"] == "success")
    # cv-only successes: episodes 1, 2, 5, 6, 10 (b10 = 5); none-only: none (b01 = 0)
    assert (cv_vs_none["b10"], cv_vs_none["b01"], cv_vs_none["n"]) == (5, 0, 12)
    p = 2 * sps.binom.cdf(0, 5, 0.5)
    assert cv_vs_none["p_value"] == pytest.approx(p)
    oracle_vs_none = next(t for t in tests if t["a"]["arm"] == "oracle" and t["endpoint"] == "success")
    assert oracle_vs_none["p_value"] == 1.0 and oracle_vs_none["mdd"] is None
    assert cv_vs_none["p_holm"] == pytest.approx(holm([p, 1.0])[0])
    assert cv_vs_none["family_size"] == 2
    assert cv_vs_none["mdd"] is None  # 12 pairs reach 80 % power for no difference this discordance allows
    # Wilcoxon on the 5 episodes both finished (0, 3, 7, 9, 11), cv faster by 1.0, 0.5, 0.5, 0.5, 0.5
    wx = next(t for t in tests if t["a"]["arm"] == "cv" and t["endpoint"] == "navigation_time_s")
    assert wx["n"] == 5 and wx["median_difference"] == pytest.approx(-0.5)
    assert wx["mean_difference"] == pytest.approx(-3.0 / 5)
    assert wx["p_value"] == pytest.approx(sps.wilcoxon([-1.0, -0.5, -0.5, -0.5, -0.5]).pvalue)

    archived = ab.archive.read_rows(cfg.out_path())
    assert len(archived) == 36 and archived[0]["policy"] == "planner" and archived[0]["seed"] == ""
    cv_rows = [r for r in archived if r["arm"] == "cv"]
    assert [r["outcome"][0].upper() for r in cv_rows] == list(cv_outcomes)
    cells = json.loads((cfg.out_path() / "cells.json").read_text())
    assert {c["cell"]: c["state"] for c in cells} == {
        "eval/zara1/planner/none": "done",
        "eval/zara1/planner/cv": "done",
        "eval/zara1/planner/oracle": "done",
    }

    md = (cfg.out_path() / "summary.md").read_text()
    assert "2 success tests and 2 navigation-time tests" in md
    assert "| zara1 | planner/cv | planner/none | 12 | 5 | 0 |" in md
    for png in ("rates_by_arm.png", "rates_vs_ade.png", "rates_by_density.png"):
        assert (cfg.out_path() / png).stat().st_size > 1000


def test_summary_pairs_ppo_seeds_with_the_planner_and_counts_missing(tmp_path: Path, fakes: Fakes) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path, evaluation={"episodes": 3, "seed": 0}))
    d = [1.0, 2.0, 3.0]
    _fake_done_cell(cfg, "eval/zara1/planner/none", _episode_rows("SSS", [1, 1, 1], d))
    _fake_done_cell(cfg, "eval/zara1/planner/mesrnn", _episode_rows("SSS", [1, 1, 1], d))
    for seed, outcomes in ((0, "SCS"), (1, "CCS")):
        cells = [f"train/zara1/ppo/none/seed{seed}", f"eval/zara1/ppo/none/seed{seed}"]
        folder = ab.cell_dir(cfg, cells[0])
        (folder / ab.TRAIN_RUN).mkdir(parents=True)
        (folder / ab.TRAIN_RUN / "best_model.zip").write_bytes(b"m")
        _fake_done_cell(cfg, cells[0], [{"episode": 0}])
        _fake_done_cell(cfg, cells[1], _episode_rows(outcomes, [2, 2, 2], d))
        meta = json.loads((ab.cell_dir(cfg, cells[1]) / ab.CELL_JSON).read_text())
        meta["model_sha256"] = ab.cells._file_sha256(folder / ab.TRAIN_RUN / "best_model.zip")
        (ab.cell_dir(cfg, cells[1]) / ab.CELL_JSON).write_text(json.dumps(meta))
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    ppo = summary["policies"]["ppo"]["arms"]["none"]
    assert ppo["seeds"] == [0, 1] and ppo["episodes"] == 6 and ppo["success_rate"] == pytest.approx(3 / 6)
    assert "mesrnn" not in summary["policies"]["ppo"]["arms"]
    assert not summary["complete"] and "train/zara1/ppo/mesrnn/seed0" in summary["missing_cells"]
    vs = next(t for t in summary["tests"] if t["comparison"] == "policies" and t["a"]["arm"] == "none")
    # each of the planner's 3 episodes once (not 6 (seed, episode) pairs): PPO's successes summed over its 2 seeds
    # (1, 0, 2) minus 2 x the planner's (1, 1, 1) give d = (-1, -2, 0); the exact sign-flip test of S = -3 over
    # magnitudes {1, 2}: S in {-3, -1, 1, 3} with probability 1/4 each, so p = P(|S| >= 3) = 1/2
    assert vs["test"] == "exact sign-flip over episodes (seeds summed)" and "b01" not in vs
    assert (vs["n"], vs["seeds"], vs["d_counts"]) == (3, 2, {"-2": 1, "-1": 1, "0": 1})
    assert vs["difference"] == pytest.approx(-0.5) and vs["p_value"] == pytest.approx(0.5)
    assert (vs["rate_a"], vs["rate_b"]) == (pytest.approx(0.5), pytest.approx(1.0))
    lo, hi = vs["difference_ci"]
    assert -1.0 <= lo <= -0.5 <= hi <= 0.0
    # seed level: per-seed rates 2/3 and 1/3 against the planner's fixed 1.0; difference -1/2, standard
    # error sqrt(var / 2) = sqrt((1/18) / 2) = 1/6, t = -3 on 1 degree of freedom (a Cauchy distribution:
    # two-sided p = 1 - 2 atan(3) / pi)
    sl = vs["seed_level"]
    assert sl["test"] == "one-sample t of per-seed rates against the fixed rate" and sl["seeds"] == [0, 1]
    assert sl["rates_a"] == pytest.approx([2 / 3, 1 / 3]) and sl["rates_b"] == pytest.approx([1.0])
    assert sl["difference"] == pytest.approx(-0.5) and sl["df"] == pytest.approx(1.0)
    assert sl["statistic"] == pytest.approx(-3.0)
    assert sl["p_value"] == pytest.approx(1 - 2 * math.atan(3) / math.pi)
    half = math.tan(math.pi * (0.975 - 0.5)) / 6  # t quantile on 1 df = Cauchy quantile
    assert sl["difference_ci"] == pytest.approx([-0.5 - half, -0.5 + half])
    assert sl["family_size"] == 1 and sl["p_holm"] == pytest.approx(sl["p_value"])
    missing = [t for t in summary["tests"] if t.get("missing")]
    assert {(t["a"]["policy"], t["a"]["arm"], t["b"]["policy"], t["b"]["arm"]) for t in missing} == {
        ("ppo", "mesrnn", "ppo", "none"),
        ("ppo", "mesrnn", "planner", "mesrnn"),
    }
    assert summary["multiple_comparisons"]["family_sizes"]["success"] == 2
    # the seed-level note counts this grid's seeds (it said "three" whatever the grid: learned.yaml has five)
    md = (cfg.out_path() / "summary.md").read_text()
    assert "With two seeds per arm these intervals are wide" in md and "three seeds" not in md


def test_episode_unit_counts_each_episode_once_for_seeded_policies(tmp_path: Path, fakes: Fakes) -> None:
    # test_unit: episode (learned_v2): two seeded arms are tested by the sign-flip test of each episode's successes
    # summed over the seeds, navigation time by Wilcoxon over each episode's mean difference over the seeds both
    # sides finished; planner against planner stays McNemar, a grid without the key keeps (seed, episode) pairs
    raw = _raw(tmp_path, evaluation={"episodes": 3, "seed": 0}, test_unit="episode")
    cfg = ab.config_from_mapping(raw)
    d = [1.0, 2.0, 3.0]
    _fake_done_cell(cfg, "eval/zara1/planner/none", _episode_rows("SSS", [10.0, 11.0, 12.0], d))
    _fake_done_cell(cfg, "eval/zara1/planner/mesrnn", _episode_rows("SCS", [10.0, 11.0, 12.0], d))
    runs = {  # (arm, seed): outcomes, times
        ("none", 0): ("SCS", [10.0, 11.0, 12.0]),
        ("none", 1): ("CCS", [10.0, 11.0, 12.0]),
        ("mesrnn", 0): ("SSS", [10.0, 11.0, 12.0]),
        ("mesrnn", 1): ("SCS", [10.4, 11.0, 12.8]),
    }
    for (arm, seed), (outcomes, times) in runs.items():
        cells = [f"train/zara1/ppo/{arm}/seed{seed}", f"eval/zara1/ppo/{arm}/seed{seed}"]
        folder = ab.cell_dir(cfg, cells[0])
        (folder / ab.TRAIN_RUN).mkdir(parents=True)
        (folder / ab.TRAIN_RUN / "best_model.zip").write_bytes(b"m")
        _fake_done_cell(cfg, cells[0], [{"episode": 0}])
        _fake_done_cell(cfg, cells[1], _episode_rows(outcomes, times, d))
        meta = json.loads((ab.cell_dir(cfg, cells[1]) / ab.CELL_JSON).read_text())
        meta["model_sha256"] = ab.cells._file_sha256(folder / ab.TRAIN_RUN / "best_model.zip")
        (ab.cell_dir(cfg, cells[1]) / ab.CELL_JSON).write_text(json.dumps(meta))
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    assert summary["multiple_comparisons"]["test_unit"] == "episode"

    def test(endpoint: str, pa: str, aa: str, pb: str, ab_: str) -> dict[str, Any]:
        return next(
            t for t in summary["tests"]
            if t["endpoint"] == endpoint and (t["a"]["policy"], t["a"]["arm"], t["b"]["policy"], t["b"]["arm"])
            == (pa, aa, pb, ab_)
        )  # fmt: skip

    # mesrnn's successes per episode over the 2 seeds (2, 1, 2), none's (1, 0, 2): d = (1, 1, 0), S = 2 over two
    # magnitudes of 1, so p = P(|S| >= 2) = 1/2, difference (2/3) / 2 = 1/3, n = 3 episodes (not 6 pairs)
    arms = test("success", "ppo", "mesrnn", "ppo", "none")
    assert arms["test"] == "exact sign-flip over episodes (seeds summed)" and "b01" not in arms
    assert (arms["n"], arms["seeds"], arms["d_counts"]) == (3, 2, {"0": 1, "1": 2})
    assert arms["difference"] == pytest.approx(1 / 3) and arms["p_value"] == pytest.approx(0.5)
    assert (arms["rate_a"], arms["rate_b"]) == (pytest.approx(5 / 6), pytest.approx(3 / 6))
    assert arms["seed_level"]["rates_a"] == pytest.approx([1.0, 2 / 3])  # the secondary test is unchanged
    # navigation time: seed 0 finished episodes 0 and 2 on both sides (differences 0, 0), seed 1 episode 2 only
    # (12.8 - 12.0): episode means 0 (episode 0) and (0 + 0.8) / 2 (episode 2); episode 1 none finished both
    nav = test("navigation_time_s", "ppo", "mesrnn", "ppo", "none")
    assert (nav["n"], nav["n_nonzero"]) == (2, 1) and nav["mean_difference"] == pytest.approx(0.2)
    assert nav["population"].startswith("episodes with a seed both sides finished")
    # against the planner: PPO none finished episodes 0, 2 (seed 0) and 2 (seed 1), the planner all: 2 episodes
    assert test("navigation_time_s", "ppo", "none", "planner", "none")["n"] == 2
    # two policies without seeds: McNemar on the episodes, as before
    assert "b01" in test("success", "planner", "mesrnn", "planner", "none")
    md = (cfg.out_path() / "summary.md").read_text()
    assert "The unit of every success and navigation-time test below is the episode" in md
    assert "| split | a | b | episodes | median diff |" in md
    assert "(or no pair is discordant); McNemar rows only." in md
    assert "Rows marked †: the sign-flip test of d" in md
    # PPO's intervals resample episodes with all their seeds: with 2 seeds of identical outcomes per episode the
    # interval is the episodes' (3 of them), not the 6 rows' Wilson one; the planner keeps Wilson
    ppo = summary["policies"]["ppo"]["arms"]["mesrnn"]
    assert (
        ppo["intervals"].startswith("percentile bootstrap over episodes")
        and "intervals" not in (summary["policies"]["planner"]["arms"]["mesrnn"])
    )
    assert ppo["by_split"]["zara1"]["intervals"] == ppo["intervals"]
    assert "Intervals of `ppo` (training seeds" in md
    # the same cells under the default unit: McNemar over 6 (seed, episode) pairs, navigation time over 3 pairs
    pairs = ab.summarize(ab.config_from_mapping({**raw, "test_unit": "pair"}), out=lambda s: None, plots=False,
                         force=True)  # fmt: skip
    old = next(t for t in pairs["tests"] if t["endpoint"] == "success" and t["a"]["arm"] == "mesrnn"
               and t["b"]["policy"] == "ppo")  # fmt: skip
    assert (old["n"], old["b10"], old["b01"]) == (6, 2, 0) and "test_unit" not in pairs["multiple_comparisons"]
    with pytest.raises(ConfigError, match=r"'test_unit': got 'seed'; allowed: pair, episode"):
        ab.config_from_mapping({**raw, "test_unit": "seed"})


def test_seeds_summed_with_one_seed_is_mcnemar_and_counts_episodes_with_every_seed() -> None:
    from agents.ablation.stats import seeds_summed
    from agents.stats import mcnemar_exact

    rng = np.random.default_rng(3)
    sa, sb = rng.random(40) < 0.7, rng.random(40) < 0.5
    keys = [(0, e) for e in range(40)]
    one = seeds_summed(keys, sa, sb)
    assert one["p_value"] == pytest.approx(mcnemar_exact(sa, sb)["p_value"], rel=1e-12)
    assert one["difference"] == pytest.approx(sa.mean() - sb.mean())
    # an episode one seed lacks (an unfinished cell) is left out, not counted with fewer seeds
    keys2 = keys + [(1, e) for e in range(39)]
    two = seeds_summed(keys2, np.concatenate([sa, sa[:39]]), np.concatenate([sb, sb[:39]]))
    assert (two["n"], two["seeds"]) == (39, 2)


def test_episode_intervals_resample_episodes_with_all_their_seeds() -> None:
    from agents.ablation.episodes import _Episodes, aggregate, episode_intervals

    rng = np.random.default_rng(5)
    outcomes = np.where(rng.random(200) < 0.7, "success", "collision")
    times = np.round(rng.uniform(8, 20, 200) / 0.4) * 0.4

    def episodes(seeds: int) -> _Episodes:
        eps = _Episodes()
        for seed in range(seeds):  # every seed the same outcome on an episode: the most clustered case
            rows = [{"episode": str(e), "outcome": o, "navigation_time_s": str(t)}
                    for e, (o, t) in enumerate(zip(outcomes, times, strict=True))]  # fmt: skip
            eps.add("zara1", seed, rows)
        return eps

    one, five = episodes(1), episodes(5)
    a1, a5 = episode_intervals(one, aggregate(one)), episode_intervals(five, aggregate(five))
    # five copies of each episode carry no more information than one: the same interval, not a narrower one
    assert a5["success_ci"] == pytest.approx(a1["success_ci"]) and a5["success_rate"] == a1["success_rate"]
    assert a5["navigation_time_s_ci"] == pytest.approx(a1["navigation_time_s_ci"])
    wilson = wilson_interval(int((outcomes == "success").sum()) * 5, 1000)
    assert (a5["success_ci"][1] - a5["success_ci"][0]) > 1.8 * (wilson[1] - wilson[0])
    assert aggregate(five)["success_ci"] == pytest.approx(list(wilson))  # what the pooled rows would have said


def test_success_is_reported_as_a_fraction_of_the_privileged_ceiling(tmp_path: Path, fakes: Fakes) -> None:
    raw = _raw(tmp_path, arms=["none", "oracle"], comparisons=[["oracle", "none"]], seeds=[0])
    raw["policies"] = {"planner": {"kind": "planner"}, "ceiling": {"kind": "privileged", "arms": ["oracle"]}}
    raw["evaluation"] = {"episodes": 4, "seed": 0}
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    density = [1.0, 2.0, 3.0, 4.0]
    _fake_done_cell(cfg, "eval/zara1/planner/none", _episode_rows("SCCS", [1.0] * 4, density))
    _fake_done_cell(cfg, "eval/zara1/planner/oracle", _episode_rows("SSCS", [1.0] * 4, density))
    _fake_done_cell(cfg, "eval/zara1/ceiling/oracle", _episode_rows("SSSS", [1.0] * 4, density))
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    ceiling = summary["ceiling"]
    assert ceiling["policy"] == "ceiling" and ceiling["by_split"] == {"zara1": 1.0}
    assert ceiling["fractions"] == {"planner": {"none": {"zara1": 0.5}, "oracle": {"zara1": 0.75}}}
    text = (cfg.out_path() / "summary.md").read_text()
    assert "## Fraction of the privileged ceiling" in text and "PRIVILEGED" in text
    assert "| planner | oracle | 0.750 |" in text
    raw["policies"] = {"planner": {"kind": "planner"}}
    assert ab.summarize(ab.config_from_mapping(raw), out=lambda s: None, plots=False, force=True)["ceiling"] is None


def test_popin_events_are_archived_and_counted_per_cell(tmp_path: Path, fakes: Fakes) -> None:
    raw = _raw(tmp_path, arms=["none", "oracle"], comparisons=[["oracle", "none"]], seeds=[0])
    raw["policies"] = {"planner": {"kind": "planner"}}
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    for arm, events in (("none", [0, 2, 0, 1]), ("oracle", [0, 0, 0, 0])):
        rows = _episode_rows("SCCS", [1.0] * 4, [1.0, 2.0, 3.0, 4.0])
        for row, n in zip(rows, events, strict=True):
            row["popin_events"] = n
        _fake_done_cell(cfg, f"eval/zara1/planner/{arm}", rows)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    none = summary["policies"]["planner"]["arms"]["none"]
    assert (none["popin_episodes"], none["popin_events"]) == (2, 3)
    assert none["by_split"]["zara1"]["popin_episodes"] == 2
    assert summary["policies"]["planner"]["arms"]["oracle"]["popin_episodes"] == 0
    with gzip.open(cfg.out_path() / "episodes" / "planner.csv.gz", "rt") as fh:
        assert next(csv.reader(fh))[-1] == "popin_events"


def test_json_has_no_nan(tmp_path: Path, fakes: Fakes) -> None:
    raw = _raw(tmp_path, arms=["none"], comparisons=[])
    raw["policies"] = {"planner": {"kind": "planner"}}
    del raw["policy_comparisons"]
    cfg = ab.config_from_mapping(raw)
    _fake_done_cell(cfg, "eval/zara1/planner/none", _episode_rows("CCCC", [1, 1, 1, 1], [1.0, 1.0, 1.0, 1.0]))
    ab.summarize(cfg, out=lambda s: None, plots=False)
    text = (cfg.out_path() / "summary.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    entry = json.loads(text)["policies"]["planner"]["arms"]["none"]
    assert entry["navigation_time_s_mean"] is None and entry["success_ci"][0] == pytest.approx(0.0, abs=1e-12)
    assert math.isclose(entry["collision_rate"], 1.0)


def test_forecast_cache_built_once_per_learned_source_and_split(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import envs.forecasting.build

    calls: list[tuple[str, str | None, str]] = []
    monkeypatch.setattr(
        envs.forecasting.build,
        "build_forecast_cache",
        lambda predictor, split=None, part="all": calls.append((predictor, split, part)),
        raising=False,
    )
    cfg = ab.config_from_mapping(
        _raw(tmp_path, splits=["univ", "zara1"], arms=["none", "cv", "mesrnn"], comparisons=[])
    )
    built = ab.build_forecast_caches(cfg, ab.expand(cfg), out=lambda s: None)
    assert built == [("mesrnn", "univ"), ("mesrnn", "zara1")]
    assert calls == [("mesrnn", "univ", "all"), ("mesrnn", "zara1", "all")]


def test_replicate_reruns_cells_in_a_scratch_folder_and_compares_episodes(
    tmp_path: Path, fakes: Fakes, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = ab.config_from_mapping(_raw(tmp_path))
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    grid_files = {p: p.read_bytes() for p in cfg.runs_path().rglob("*") if p.is_file()}
    fakes.train_calls.clear()
    lines: list[str] = []
    scratch = tmp_path / "replica"
    assert ab.replicate(cfg, "eval/zara1/ppo/mesrnn/seed1", scratch, workers=1, out=lines.append) == 0
    assert [name for name, _ in fakes.train_calls] == ["train/zara1/ppo/mesrnn/seed1"]  # retrained, not reused
    assert (scratch / "runs" / "eval" / "zara1" / "ppo" / "mesrnn" / "seed1" / "episodes.csv").is_file()
    assert "eval/zara1/ppo/mesrnn/seed1: 4/4 episodes identical in all 6 columns, 4/4 outcomes" in "\n".join(lines)
    assert {p: p.read_bytes() for p in cfg.runs_path().rglob("*") if p.is_file()} == grid_files  # grid untouched
    with pytest.raises(ConfigError, match="not empty"):  # a replicate starts afresh
        ab.replicate(cfg, "eval/zara1/ppo/mesrnn/seed1", scratch, workers=1)

    # A replicate that behaves differently, in any column, is reported and counted.
    original = fakes.evaluate

    def changed(column: str, value: str) -> Any:
        def evaluate(task: ab.CellTask, folder: Path) -> dict[str, Any]:
            info = original(task, folder)
            rows = ab.read_episodes(folder / "episodes.csv")
            rows[0][column] = value
            _write_csv(folder / "episodes.csv", rows)
            return info

        return evaluate

    monkeypatch.setattr(ab.execute, "_run_eval", changed("outcome", "timeout"))
    lines.clear()
    assert ab.replicate(cfg, "eval/zara1/planner/none", tmp_path / "replica2", workers=1, out=lines.append) == 1
    assert "eval/zara1/planner/none: 3/4 episodes identical in all 6 columns, 3/4 outcomes" in "\n".join(lines)
    monkeypatch.setattr(ab.execute, "_run_eval", changed("return", "99.0"))
    lines.clear()
    assert ab.replicate(cfg, "eval/zara1/planner/none", tmp_path / "replica3", workers=1, out=lines.append) == 1
    assert "3/4 episodes identical in all 6 columns, 4/4 outcomes" in "\n".join(lines)

    # A grid cell that is not done (here: its model changed since it was evaluated) is not compared.
    monkeypatch.setattr(ab.execute, "_run_eval", original)
    (ab.cell_dir(cfg, "train/zara1/ppo/none/seed0") / ab.TRAIN_RUN / "best_model.zip").write_bytes(b"retrained")
    lines.clear()
    assert ab.replicate(cfg, "eval/zara1/ppo/none/seed0", tmp_path / "replica4", workers=1, out=lines.append) == 1
    assert "eval/zara1/ppo/none/seed0: not compared: the grid's cell is stale" in "\n".join(lines)

    for folder in (cfg.runs_path(), tmp_path, cfg.runs_path() / "sub"):  # the grid's folder, a parent, a child
        with pytest.raises(ConfigError, match="overlaps the grid's folder"):
            ab.replicate(cfg, "eval/zara1/planner/none", folder, workers=1)
    with pytest.raises(ConfigError, match="selects no evaluation cell"):
        ab.replicate(cfg, "train/zara1/ppo/none/seed0", tmp_path / "replica5", workers=1)
    (tmp_path / "g.yaml").write_text(json.dumps(_raw(tmp_path)), encoding="utf-8")  # JSON is YAML
    args = {
        "workers": None,
        "address": None,
        "backend": "local",
        "dry_run": False,
        "summarize_only": False,
        "force": False,
    }
    base = {"config": str(tmp_path / "g.yaml"), "replicate": str(tmp_path / "replica6"), "only": "eval/*"}
    for change, message in (
        ({"only": None}, "--replicate needs --only"),
        ({"backend": "ray"}, "local backend"),
        ({"dry_run": True}, "cannot be combined"),
    ):
        with pytest.raises(ConfigError, match=message):
            ab.run_from_args(argparse.Namespace(**{**args, **base, **change}))


# ----------------------------------------------------------------------------- the committed results


def _planner_grid(tmp_path: Path, arms: tuple[str, ...] = ("none", "cv")) -> tuple[ab.AblationConfig, Path]:
    """A planner-only grid written to a YAML file, its cells done with full-precision metrics and start times."""
    raw = _raw(tmp_path, arms=list(arms), comparisons=[["cv", "none"]])
    raw["policies"] = {"planner": {"kind": "planner"}}
    del raw["policy_comparisons"]
    path = tmp_path / "grid.yaml"
    path.write_text(json.dumps(raw), encoding="utf-8")  # JSON is YAML
    cfg = ab.load_config(path)
    for k, arm in enumerate(arms):
        rows = _episode_rows("SCSS", [10.123456789012345 + k, 11.5, 9.25, 12.0], [1.0 / 3, 2.0, 3.0, 4.0])
        name = f"eval/zara1/planner/{arm}"
        _fake_done_cell(cfg, name, rows)
        meta = json.loads((ab.cell_dir(cfg, name) / ab.CELL_JSON).read_text())
        meta["attempts"] = [
            {"started": f"2026-01-0{k + 1}T10:00:00+0000", "finished": f"2026-01-0{k + 1}T10:00:02+0000"}
        ]
        (ab.cell_dir(cfg, name) / ab.CELL_JSON).write_text(json.dumps(meta))
    return cfg, path


def _results(cfg: ab.AblationConfig) -> dict[str, bytes]:
    """Every result file by its path in ``out_dir`` (the archive's as ``episodes/<policy>.csv.gz``)."""
    out = cfg.out_path()
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.fixture
def pinned(monkeypatch: pytest.MonkeyPatch) -> None:
    """The summary's stamps (code version, time) fixed, so that two renders of the same data compare byte by byte."""
    monkeypatch.setattr(ab.summary, "code_version", lambda: "0.0.0+gtest")
    monkeypatch.setattr(ab.summary, "_now", lambda: "2026-01-09T00:00:00+0000")


def test_summarize_only_in_a_fresh_clone_keeps_the_shipped_results(
    tmp_path: Path, fakes: Fakes, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg, path = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None)
    shipped = _results(cfg)
    assert {"summary.json", "summary.md", "cells.json", "episodes/planner.csv.gz", "rates_by_arm.png"} <= set(shipped)
    # summarising the same finished cells again changes no file (not even the time stamp)
    stamps = {p: p.stat().st_mtime_ns for p in cfg.out_path().rglob("*")}
    ab.summarize(cfg, out=lambda s: None)
    assert {p: p.stat().st_mtime_ns for p in cfg.out_path().rglob("*")} == stamps
    # a fresh clone: the results are committed, the run folders are not
    import shutil

    shutil.rmtree(cfg.runs_path())
    assert ab.main([str(path), "--summarize-only"]) == 0
    assert _results(cfg) == shipped
    assert "up to date" in capsys.readouterr().out


def test_the_archive_alone_rerenders_the_summary_identically(tmp_path: Path, fakes: Fakes, pinned: None) -> None:
    import shutil

    cfg, _ = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None)
    shipped = _results(cfg)
    assert {"rates_by_arm.png", "rates_by_density.png"} <= set(shipped)
    rows = ab.archive.read_rows(cfg.out_path())  # every value as the evaluation wrote it
    assert [r["navigation_time_s"] for r in rows][:1] == [repr(10.123456789012345 + 1)]
    cells = json.loads((cfg.out_path() / "cells.json").read_text())
    assert cells[0]["attempts"] == [{"started": "2026-01-01T10:00:00+0000", "finished": "2026-01-01T10:00:02+0000"}]
    shutil.rmtree(cfg.runs_path())
    for name in ("summary.json", "summary.md", "rates_by_arm.png"):
        (cfg.out_path() / name).unlink()
    lines: list[str] = []
    summary = ab.summarize(cfg, out=lines.append)
    assert _results(cfg) == shipped
    assert summary["complete"] and summary["wall_time"]["first_start"] == "2026-01-01T10:00:00+00:00"
    assert "2 cell(s) from the archive" in "\n".join(lines)


def _to_legacy(folder: Path) -> Path:
    """Turn the archive in ``folder`` into the older single ``episodes.csv.gz`` its rows once were: the header, then
    every file's rows in the order of their policies' names."""
    import shutil

    files = ab.archive.read_files(folder)
    texts = [gzip.decompress(files[n]).decode() for n in sorted(files, key=ab.archive.archive_policy)]
    header = texts[0].split("\n", 1)[0] + "\n"
    legacy = folder / "episodes.csv.gz"
    legacy.write_bytes(gzip.compress((header + "".join(t.split("\n", 1)[1] for t in texts)).encode(), mtime=0))
    shutil.rmtree(folder / "episodes")
    return legacy


def test_an_older_single_archive_is_read_and_moved_by_a_summary_that_changes_nothing_else(
    tmp_path: Path, fakes: Fakes, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    cfg, path = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None)
    shipped = _results(cfg)
    shutil.rmtree(cfg.runs_path())
    legacy = _to_legacy(cfg.out_path())  # results written before the archive was split per policy
    other = _other_grid(tmp_path, cfg.out_path())  # another grid reuses them as they are
    assert {st.cell.name: st.source for st in ab.plan(other)}["eval/zara1/planner/cv"] == str(cfg.out_path())
    assert ab.main([str(path), "--summarize-only"]) == 0
    out = capsys.readouterr().out
    assert f"2 cell(s) from the archive {legacy}" in out and "but for the archive's layout" in out
    assert f"removed {legacy}" in out
    assert _results(cfg) == shipped  # every other file untouched (stamps too); the archive as the summary writes it


def test_an_older_archive_of_other_episodes_is_left_with_a_warning_and_readers_then_refuse(
    tmp_path: Path, fakes: Fakes, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    cfg, path = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    legacy = _to_legacy(cfg.out_path())
    _fake_done_cell(cfg, "eval/zara1/planner/cv", _episode_rows("CCCC", [1, 1, 1, 1], [1.0, 2.0, 3.0, 4.0]))
    lines: list[str] = []
    ab.summarize(cfg, out=lines.append, plots=False)
    assert legacy.is_file() and any(line.startswith(f"warning: left {legacy} as it is") for line in lines)
    assert ab.archive.read_files(cfg.out_path())  # the new archive beside it
    shutil.rmtree(cfg.runs_path())
    assert ab.main([str(path), "--summarize-only"]) == 2
    err = capsys.readouterr().err
    assert f"{cfg.out_path() / 'episodes'}/ (8 rows)" in err and f"older {legacy} (8 rows)" in err


def test_an_incomplete_grid_never_replaces_a_complete_summary(
    tmp_path: Path, fakes: Fakes, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg, path = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    shipped = _results(cfg)
    # an interrupted re-run of one cell: its folder has no DONE any more
    (ab.cell_dir(cfg, "eval/zara1/planner/cv") / ab.DONE).unlink()
    assert ab.main([str(path), "--summarize-only"]) == 1
    err = capsys.readouterr().err
    assert "eval/zara1/planner/cv" in err and "--force" in err
    assert _results(cfg) == shipped
    lines: list[str] = []  # a grid run ends with the same check (and says so, without failing the run)
    ab.run_grid(cfg, workers=1, only="eval/zara1/planner/none", out=lines.append)
    assert "missing 1 cell(s): eval/zara1/planner/cv" in "\n".join(lines)
    assert _results(cfg) == shipped
    # a grid that grew (a new arm) is incomplete too; the message names the cells it lacks
    grown = ab.config_from_mapping({**json.loads(path.read_text()), "arms": ["none", "cv", "oracle"]})
    (ab.cell_dir(cfg, "eval/zara1/planner/cv") / ab.DONE).write_text("now\n")
    with pytest.raises(ab.ResultsKept, match="eval/zara1/planner/oracle"):
        ab.summarize(grown, out=lambda s: None, plots=False)
    assert _results(cfg) == shipped
    # --force replaces them, and the new summary says it is incomplete
    assert ab.main([str(path), "--summarize-only"]) == 0  # the cell is done again: nothing lost
    summary = ab.summarize(grown, out=lambda s: None, plots=False, force=True)
    assert summary["missing_cells"] == ["eval/zara1/planner/oracle"]
    assert json.loads((cfg.out_path() / "summary.json").read_text())["complete"] is False


def test_a_legacy_archive_is_kept_and_the_reason_given(
    tmp_path: Path, fakes: Fakes, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    cfg, path = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    # the records of an older version: no attempts (start times), no spec
    cells = json.loads((cfg.out_path() / "cells.json").read_text())
    for c in cells:
        del c["attempts"], c["spec"]
    (cfg.out_path() / "cells.json").write_text(json.dumps(cells, indent=2) + "\n")
    shutil.rmtree(cfg.runs_path())
    shipped = _results(cfg)
    assert ab.main([str(path), "--summarize-only"]) == 1
    err = capsys.readouterr().err
    assert "start times" in err and "wall_time.first_start" in err and "--force" in err
    assert _results(cfg) == shipped
    assert ab.main([str(path), "--summarize-only", "--force"]) == 0
    assert json.loads((cfg.out_path() / "summary.json").read_text())["wall_time"]["first_start"] is None


def test_result_files_are_all_rendered_before_any_is_replaced(
    tmp_path: Path, fakes: Fakes, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg, _ = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    shipped = _results(cfg)
    _fake_done_cell(cfg, "eval/zara1/planner/cv", _episode_rows("CCCC", [1, 1, 1, 1], [1.0, 2.0, 3.0, 4.0]))

    def broken(*args: Any, **kwargs: Any) -> str:
        raise RuntimeError("disk full")

    monkeypatch.setattr(ab.summary, "summary_markdown", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        ab.summarize(cfg, out=lambda s: None, plots=False)
    assert _results(cfg) == shipped  # all or nothing: the summary, cells and archive still agree
    assert not [p for p in cfg.out_path().iterdir() if p.name.startswith(".")]  # no temporary file left


# ----------------------------------------------------------------------------- cells taken from committed results


def test_a_fresh_clone_runs_none_of_the_cells_its_committed_results_hold(tmp_path: Path, fakes: Fakes) -> None:
    import shutil

    cfg, _ = _planner_grid(tmp_path)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    shipped = _results(cfg)
    shutil.rmtree(cfg.runs_path())  # a fresh clone: the results are committed, the run folders are not
    states = ab.plan(cfg)
    assert [(st.state, st.source) for st in states] == [("done", str(cfg.out_path()))] * 2
    lines: list[str] = []
    result = ab.run_grid(cfg, workers=1, out=lines.append)
    assert result["ran"] == [] and fakes.eval_calls == [] and not cfg.runs_path().exists()
    assert "2 cells, 2 done (2 of them from committed results), 0 to run" in lines[0]
    assert _results(cfg) == shipped  # and the summary is the committed one
    lines.clear()
    ab.dry_run(cfg, ab.expand(cfg), workers=1, out=lines.append)
    assert any(
        line.startswith("done") and line.endswith(f"eval/zara1/planner/cv  (from {cfg.out_path()})") for line in lines
    )
    assert f"todo 0; done from committed results: 2 in {cfg.out_path()}" in "\n".join(lines)


def test_a_learned_evaluation_is_taken_from_the_results_only_with_its_training(tmp_path: Path, fakes: Fakes) -> None:
    import shutil

    raw = _raw(tmp_path)
    cfg = ab.config_from_mapping(raw)
    ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)
    ab.summarize(cfg, out=lambda s: None, plots=False)
    model = (ab.cell_dir(cfg, "train/zara1/ppo/none/seed0") / ab.TRAIN_RUN / "best_model.zip").read_bytes()
    shutil.rmtree(cfg.runs_path())
    fakes.train_calls.clear()
    fakes.eval_calls.clear()
    # a training cell's model is not committed: it is done only as the training of its evaluation, taken with it
    states = {st.cell.name: st for st in ab.plan(cfg)}
    assert {st.state for st in states.values()} == {"done"}
    assert "with its evaluation" in states["train/zara1/ppo/none/seed0"].reason
    assert ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)["ran"] == []
    assert fakes.train_calls == [] and fakes.eval_calls == []
    # a training run here (its model not the one the record names): its evaluation runs again
    elsewhere = dataclasses.replace(cfg, out_dir=str(tmp_path / "elsewhere"))
    ab.run_grid(elsewhere, workers=1, only="train/zara1/ppo/none/seed0", summarize_after=False, out=lambda s: None)
    assert not ab.cell_dir(cfg, "eval/zara1/ppo/none/seed0").exists()
    (ab.cell_dir(cfg, "train/zara1/ppo/none/seed0") / ab.TRAIN_RUN / "best_model.zip").write_bytes(b"another model")
    states = {st.cell.name: st.state for st in ab.plan(cfg)}
    assert states["train/zara1/ppo/none/seed0"] == "done" and states["eval/zara1/ppo/none/seed0"] == "todo"
    (ab.cell_dir(cfg, "train/zara1/ppo/none/seed0") / ab.TRAIN_RUN / "best_model.zip").write_bytes(model)
    assert {st.cell.name: st.state for st in ab.plan(cfg)}["eval/zara1/ppo/none/seed0"] == "done"  # the model it names
    # a changed training (its spec; the evaluation's own spec is the same): neither is taken from the results
    shutil.rmtree(cfg.runs_path())
    longer = ab.config_from_mapping(
        {**raw, "policies": {**raw["policies"], "ppo": {**raw["policies"]["ppo"], "timesteps": 512}}}
    )
    states = {st.cell.name: st.state for st in ab.plan(longer)}
    assert {n: s for n, s in states.items() if "/ppo/" in n} == dict.fromkeys(
        [n for n in states if "/ppo/" in n], "todo"
    )
    assert states["eval/zara1/planner/mesrnn"] == "done"
    records = {r["cell"]: r for r in ab.results.gather(longer)[0]}
    assert records["eval/zara1/ppo/none/seed0"]["state"] == "stale"  # recorded done, but its training changed


def _other_grid(tmp_path: Path, source: Path, **changes: Any) -> ab.AblationConfig:
    """A second planner grid (own run folders and results) whose config reuses the results in ``source``."""
    (tmp_path / "b").mkdir(exist_ok=True)
    raw = _raw(tmp_path / "b", arms=["none", "cv", "oracle"], comparisons=[["cv", "none"]], reuse=[str(source)])
    raw["policies"] = {"planner": {"kind": "planner"}}
    del raw["policy_comparisons"]
    raw.update(changes)
    return ab.config_from_mapping(raw)


def test_a_cell_done_in_a_reused_grids_results_is_done_here_and_read_from_there(tmp_path: Path, fakes: Fakes) -> None:
    first, _ = _planner_grid(tmp_path)
    ab.summarize(first, out=lambda s: None, plots=False)
    cfg = _other_grid(tmp_path, first.out_path())
    for cell in ab.expand(cfg):  # not part of any cell's spec
        assert ab.cell_spec(cfg, cell) == ab.cell_spec(dataclasses.replace(cfg, reuse=()), cell)
    states = {st.cell.name: st for st in ab.plan(cfg)}
    assert {n: (st.state, st.source) for n, st in states.items()} == {
        "eval/zara1/planner/none": ("done", str(first.out_path())),
        "eval/zara1/planner/cv": ("done", str(first.out_path())),
        "eval/zara1/planner/oracle": ("todo", ""),
    }
    lines: list[str] = []
    ab.dry_run(cfg, ab.expand(cfg), workers=1, out=lines.append)
    assert any(line.startswith("done") and f"planner/cv  (from {first.out_path()})" in line for line in lines)
    assert f"todo 1; done from committed results: 2 in {first.out_path()}" in "\n".join(lines)
    # running the grid runs only the cell no results hold; the summary reads the others' episodes from there
    assert ab.run_grid(cfg, workers=1, summarize_after=False, out=lines.append)["ran"] == ["eval/zara1/planner/oracle"]
    assert fakes.eval_calls == ["eval/zara1/planner/oracle"]
    ab.summarize(cfg, out=lines.append, plots=False)
    theirs = {r["cell"]: r for r in json.loads((first.out_path() / "cells.json").read_text())}
    ours = {r["cell"]: r for r in json.loads((cfg.out_path() / "cells.json").read_text())}
    for name in ("eval/zara1/planner/none", "eval/zara1/planner/cv"):
        assert ours[name] == {**theirs[name], "from": str(first.out_path())}
        assert (
            ab.episodes.archive_rows(ab.archive.read_rows(cfg.out_path()))[name]
            == ab.episodes.archive_rows(ab.archive.read_rows(first.out_path()))[name]
        )
    assert "from" not in ours["eval/zara1/planner/oracle"]
    summary = json.loads((cfg.out_path() / "summary.json").read_text())
    assert summary["complete"] and summary["policies"]["planner"]["arms"]["cv"]["episodes"] == 4
    # its own results come first from then on: a fresh clone renders them again, byte for byte
    shipped = _results(cfg)
    import shutil

    shutil.rmtree(cfg.runs_path())
    assert all(st.source == str(cfg.out_path()) for st in ab.plan(cfg))
    ab.summarize(cfg, out=lambda s: None, plots=False)
    assert _results(cfg) == shipped


@pytest.mark.parametrize(
    "key",
    [
        "kind",
        "split",
        "policy",
        "policy_kind",
        "arm",
        "predictor",
        "noisy_oracle_ade_m",
        "seed",
        "env",
        "env_revision",
        "episodes",
        "eval_seed",
        "added",
        "removed",
        "no spec",
        "weights",
    ],
)
def test_a_cell_whose_spec_or_weights_differ_in_the_reused_results_runs(tmp_path: Path, fakes: Fakes, key: str) -> None:
    first, _ = _planner_grid(tmp_path)
    ab.summarize(first, out=lambda s: None, plots=False)
    records = json.loads((first.out_path() / "cells.json").read_text())
    rec = next(r for r in records if r["cell"] == "eval/zara1/planner/cv")
    if key == "added":
        rec["spec"]["options"] = {"candidates": "dense"}
    elif key == "removed":
        del rec["spec"]["env_revision"]
    elif key == "no spec":  # a record from before specs were recorded
        del rec["spec"]
    elif key == "weights":
        rec["weights_sha256"] = {"cv.pt": "0123456789ab"}
    else:
        assert key in rec["spec"]
        rec["spec"][key] = "something else"
    (first.out_path() / "cells.json").write_text(json.dumps(records))
    cfg = _other_grid(tmp_path, first.out_path())
    states = {st.cell.name: st.state for st in ab.plan(cfg)}
    assert states == {
        "eval/zara1/planner/none": "done",
        "eval/zara1/planner/cv": "todo",
        "eval/zara1/planner/oracle": "todo",
    }
    assert ab.run_grid(cfg, workers=1, summarize_after=False, out=lambda s: None)["ran"] == [
        "eval/zara1/planner/cv",
        "eval/zara1/planner/oracle",
    ]


def test_reused_results_are_tried_in_order_and_a_cell_without_episodes_there_is_stale(
    tmp_path: Path, fakes: Fakes
) -> None:
    for name in ("first", "second"):
        (tmp_path / name).mkdir()
    first, _ = _planner_grid(tmp_path / "first")
    second, _ = _planner_grid(tmp_path / "second", arms=("none", "cv", "oracle"))
    for grid in (first, second):
        ab.summarize(grid, out=lambda s: None, plots=False)
    cfg = _other_grid(tmp_path, first.out_path(), reuse=[str(first.out_path()), str(second.out_path())])
    assert {st.cell.name: st.source for st in ab.plan(cfg)} == {
        "eval/zara1/planner/none": str(first.out_path()),
        "eval/zara1/planner/cv": str(first.out_path()),  # the first listed
        "eval/zara1/planner/oracle": str(second.out_path()),
    }
    # the first results lose cv's episodes: cv comes from the second; without them there too it is stale, not done
    for grid in (first, second):
        path = grid.out_path() / "episodes" / "planner.csv.gz"
        with gzip.open(path, "rt") as fh:
            rows = [r for r in csv.DictReader(fh) if r["arm"] != "cv"]
        with gzip.open(path, "wt", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        if grid is first:
            assert {st.cell.name: st.source for st in ab.plan(cfg)}["eval/zara1/planner/cv"] == str(second.out_path())
    assert {st.cell.name: st.state for st in ab.plan(cfg)}["eval/zara1/planner/cv"] == "todo"
    records = {r["cell"]: r for r in ab.results.gather(cfg)[0]}
    assert records["eval/zara1/planner/cv"]["state"] == "stale"
    assert records["eval/zara1/planner/cv"]["from"] == str(first.out_path())


def test_replicate_runs_a_reused_cell_afresh(tmp_path: Path, fakes: Fakes) -> None:
    first, _ = _planner_grid(tmp_path)
    ab.summarize(first, out=lambda s: None, plots=False)
    cfg = _other_grid(tmp_path, first.out_path())
    lines: list[str] = []
    assert ab.replicate(cfg, "eval/zara1/planner/cv", tmp_path / "replica", workers=1, out=lines.append) == 1
    assert fakes.eval_calls == ["eval/zara1/planner/cv"]
    assert f"not compared: the grid's cell has no run folder (it is done from {first.out_path()})" in "\n".join(lines)


@pytest.mark.parametrize(
    ("reuse", "words"),
    [
        ("results/ablation/planners", ["'reuse'", "'results/ablation/planners'", "a list of other grids'"]),
        ([3], ["'reuse'", "[3]", "a list of other grids'"]),
        (["nowhere"], ["'reuse'", "'nowhere'", "there is no folder 'nowhere'"]),
        (["empty"], ["'reuse'", "'empty'", "cells.json is missing"]),
        (["no_archive"], ["'reuse'", "no_archive/episodes/ is missing"]),
        (["no_archive", "no_archive"], ["'reuse'", "without repeats"]),
        (["results"], ["'reuse'", "own out_dir"]),
    ],
)
def test_bad_reuse_names_key_value_and_allowed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reuse: Any, words: list[str]
) -> None:
    monkeypatch.chdir(tmp_path)  # folders are relative to the working directory
    for folder in ("empty", "no_archive", "results"):
        (tmp_path / folder).mkdir()
    (tmp_path / "no_archive" / "cells.json").write_text("[]")
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(_raw(tmp_path, out_dir="results", reuse=reuse))
    for word in words:
        assert word in str(err.value), (word, str(err.value))
    (tmp_path / "no_archive" / "episodes").mkdir()
    assert ab.config_from_mapping(_raw(tmp_path, reuse=["no_archive"])).reuse == ("no_archive",)
    (tmp_path / "no_archive" / "episodes").rmdir()  # the older single file counts too
    (tmp_path / "no_archive" / "episodes.csv.gz").write_bytes(gzip.compress(b""))
    assert ab.config_from_mapping(_raw(tmp_path, reuse=["no_archive"])).reuse == ("no_archive",)
