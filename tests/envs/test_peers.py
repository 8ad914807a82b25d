"""The environment in other RL libraries, built by id as their users would (optional peers: ``pip install -e
'.[peers]'``; CI installs them)."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest


@pytest.mark.slow
def test_torchrl_builds_the_env_by_id_checks_its_specs_and_rolls_out(data_dir: Path) -> None:
    """TorchRL's ``GymEnv`` passes ``frameskip=`` and retries without it only on a ``TypeError`` naming it."""
    if importlib.util.find_spec("torchrl") is None:
        why = "TorchRL is not installed (pip install -e '.[peers]')"
        pytest.fail(f"CI installs the peers extra: {why}") if os.environ.get("CI") else pytest.skip(why)
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    import crowdnav_mesrnn  # noqa: F401 (registers the ids)

    env = GymEnv("CrowdNav-MESRNN-v0")
    try:
        check_env_specs(env, seed=0)
        rollout = env.rollout(5)
        assert rollout["forecasts"].shape == (len(rollout), 240)  # K=10 pedestrians x H=12 steps x 2
        assert rollout["next", "reward"].isfinite().all()
    finally:
        env.close()
