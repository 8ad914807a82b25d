"""Gymnasium's default async vector env forks its workers: forecasts computed there (a cold forecast cache) must not
deadlock in torch's OpenMP pool inherited from the parent. Run in a subprocess with a timeout, so a hang fails."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

SCRIPT = """
import sys
import gymnasium, numpy as np, torch
import crowdnav_mesrnn
torch.ones(4096, 64) @ torch.ones(64, 64)  # the parent has used torch's thread pool before the fork
envs = gymnasium.make_vec(
    "CrowdNav-MESRNN-v0", num_envs=2, vectorization_mode="async", split="zara1", part="test", predictor=sys.argv[1]
)
obs, info = envs.reset(seed=0)
for _ in range(2):
    obs, *_ = envs.step(np.zeros((2, 2), dtype=np.float32))
assert obs["forecasts"].shape[0] == 2
envs.close()
print("stepped")
"""


@pytest.mark.slow
@pytest.mark.parametrize("predictor", ["mesrnn", "srnn", "vlstm"])
def test_async_make_vec_with_a_cold_forecast_cache_steps(predictor: str, data_dir: Path, tmp_path: Path) -> None:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        "CROWDNAV_MESRNN_DATA": str(data_dir),
        "CROWDNAV_MESRNN_CACHE": str(tmp_path / "cold-cache"),  # nothing cached: the workers compute forecasts
    }
    env.pop("OMP_NUM_THREADS", None)
    # a session of its own, so that a hang is ended with every worker (not only the main process)
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, predictor],
        env=env,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("async make_vec hung (a forked worker deadlocked computing forecasts)")
    assert proc.returncode == 0, err[-3000:]
    assert out.strip().endswith("stepped")
