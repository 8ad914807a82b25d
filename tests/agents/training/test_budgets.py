"""The shipped agent configs train exactly their budget (whole rollouts), so no run of them warns about itself; the
committed grids' training cells keep their specs when an agent YAML's budget is written as whole rollouts."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

from agents.training.config import ENV_ID_OF, load_train_config
from agents.training.run import rollout_steps, steps_trained
from crowdnav_mesrnn.config import load_yaml

REPO = Path(__file__).resolve().parents[3]
SHIPPED = sorted((REPO / "configs" / "agent").glob("*.yaml"))


def test_the_scan_sees_the_shipped_configs() -> None:
    assert {"ppo.yaml", "ppo_scoring.yaml", "ppo_smoke.yaml", "sac.yaml"} <= {p.name for p in SHIPPED}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_config_trains_exactly_its_budget(path: Path) -> None:
    """``train`` warns ``n_timesteps N trains M steps`` exactly when ``steps_trained`` differs from the budget; for
    every entry (forecast arm) of every shipped config it does not, and loading the config warns about nothing."""
    entries = [k for k in load_yaml(path) if k != "crowdnav_mesrnn"]
    arms = [arm for arm, env_id in ENV_ID_OF.items() if env_id in entries]
    assert arms
    for arm in arms:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            cfg = load_train_config(path, None, {"predictor": arm})
        unit = rollout_steps(cfg)
        assert unit is not None and cfg.n_timesteps % unit[0] == 0, (path.name, arm, cfg.n_timesteps, unit)
        assert steps_trained(cfg) == cfg.n_timesteps


def test_the_committed_learned_grids_cells_keep_their_specs() -> None:
    """``results/ablation/learned/cells.json`` records each cell's spec, with the sha256 of its agent YAML: writing the
    recipe's budget as the whole rollouts it always trained (``100352`` for ``!!float 1e5``) leaves every recorded
    spec as the code gives it now, so a fresh clone still summarises the shipped grid instead of retraining it."""
    import agents.ablation as ab

    cfg = ab.load_config(REPO / "configs/ablation/learned.yaml")
    records = json.loads((REPO / "results/ablation/learned/cells.json").read_text(encoding="utf-8"))
    cells = {c.name: c for c in ab.expand(cfg)}
    trained = [r for r in records if r["spec"]["kind"] == "train"]
    assert trained and len(records) == len(cells)
    for rec in records:
        want = {k: v for k, v in ab.cell_spec(cfg, cells[rec["cell"]]).items() if k != "env_revision"}
        assert {k: v for k, v in rec["spec"].items() if k != "env_revision"} == want, rec["cell"]
