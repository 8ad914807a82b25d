"""A tiny real ablation grid on both backends: a PPO training run of a few hundred steps, its evaluation and a
planner evaluation (three cells), on the synthetic crowd so that no ETH/UCY data is needed."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab

TINY_PPO = """\
CrowdNav-NoPred-v0:
  n_envs: 1
  n_timesteps: 128
  policy: MultiInputPolicy
  policy_kwargs: {net_arch: [16]}
  n_steps: 64
  batch_size: 32
  n_epochs: 1
crowdnav_mesrnn:
  algo: ppo
  eval: {freq_steps: 0, episodes: 2, n_envs: 1}
  checkpoint_freq_steps: 64
  pretrain: null
"""

CELLS = ["train/zara1/ppo/none/seed0", "eval/zara1/ppo/none/seed0", "eval/zara1/planner/none"]


def _config(tmp_path: Path, timesteps: int = 128) -> ab.AblationConfig:
    tmp_path.mkdir(parents=True, exist_ok=True)
    agent_yaml = tmp_path / "ppo_tiny.yaml"
    agent_yaml.write_text(TINY_PPO, encoding="utf-8")
    raw: dict[str, Any] = {
        "name": "e2e",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["zara1"],
        "arms": ["none"],
        "seeds": [0],
        "policies": {
            "ppo": {"kind": "ppo", "config": str(agent_yaml), "timesteps": timesteps, "n_envs": 1},
            "planner": {"kind": "planner"},
        },
        "evaluation": {"episodes": 3, "seed": 0},
        "env": {"crowd": "synthetic"},
        "policy_comparisons": [["ppo", "planner"]],
    }
    (tmp_path / "grid.yaml").write_text(json.dumps(raw), encoding="utf-8")  # JSON is YAML: for the command line
    return ab.config_from_mapping(raw)


def _check(cfg: ab.AblationConfig, result: dict[str, Any]) -> None:
    assert not result["failed"], result["failed"]
    assert sorted(result["ran"]) == sorted(CELLS)
    assert {st.cell.name: st.state for st in ab.plan(cfg)} == dict.fromkeys(CELLS, "done")
    run = ab.cell_dir(cfg, CELLS[0]) / ab.TRAIN_RUN
    assert (run / "DONE").is_file() and (run / "config.yaml").is_file()
    assert ab.trained_model(ab.cell_dir(cfg, CELLS[0]), "best") is not None
    for name in CELLS[1:]:
        assert len(ab.read_episodes(ab.cell_dir(cfg, name) / "episodes.csv")) == cfg.episodes
    meta = json.loads((ab.cell_dir(cfg, CELLS[1]) / ab.CELL_JSON).read_text())
    assert meta["model_sha256"] and Path(meta["model"]).is_file()
    assert meta["model"].endswith("best_model.policy.yaml")  # the policy file training wrote: nothing unpickled
    summary = json.loads((cfg.out_path() / "summary.json").read_text())
    assert summary["complete"] is True
    assert summary["policies"]["ppo"]["arms"]["none"]["episodes"] == cfg.episodes
    assert [t["n"] for t in summary["tests"] if t["endpoint"] == "success"] == [cfg.episodes]


@pytest.mark.slow
def test_local_pool_grid_and_rerun_skips_everything(tmp_path: Path) -> None:
    cfg = _config(tmp_path)
    _check(cfg, ab.run_grid(cfg, backend="local", workers=2, out=lambda s: None))
    assert ab.run_grid(cfg, backend="local", workers=2, summarize_after=False, out=lambda s: None)["ran"] == []


@pytest.mark.slow
def test_ray_grid_gathers_cells_through_return_values(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    cfg = _config(tmp_path)
    _check(cfg, ab.run_grid(cfg, backend="ray", workers=1, out=lambda s: None))


def _press_ctrl_c(times: int, when: Callable[[], bool]) -> threading.Thread:
    """Ctrl-C ``times`` times (SIGINT to this process, as the terminal sends it) once ``when()`` holds."""

    def press() -> None:
        deadline = time.monotonic() + 120
        while not when() and time.monotonic() < deadline:
            time.sleep(0.05)
        for _ in range(times):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)

    thread = threading.Thread(target=press, daemon=True)
    thread.start()
    return thread


#: Set in the fresh interpreter that runs the Ctrl-C scenario (see the test below).
_ISOLATED = "CROWDNAV_MESRNN_TEST_ISOLATED"


@pytest.mark.slow
def test_ctrl_c_on_the_local_pool_waits_then_stops_training_at_a_round_boundary(tmp_path: Path) -> None:
    if os.environ.get(_ISOLATED) != "1":
        # Signals are process-wide: after an earlier test of this process has run Ray (whose start-up and shutdown
        # touch signal handling), a press could land outside the grid's handler. The scenario runs in a fresh
        # interpreter, as a user's grid does.
        name = (
            f"{Path(__file__).resolve()}::test_ctrl_c_on_the_local_pool_waits_then_stops_training_at_a_round_boundary"
        )
        # -m: this test is marked slow, which the default addopts deselect
        args = ["-q", "-p", "no:cacheprovider", "-m", "slow or not slow", name, "--basetemp", str(tmp_path / "t")]
        done = subprocess.run(
            [sys.executable, "-m", "pytest", *args],
            cwd=Path(__file__).resolve().parents[3],
            env={**os.environ, _ISOLATED: "1"},
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
        return
    # once: the running cells (the training run and the planner's evaluation) finish, nothing else starts
    cfg = _config(tmp_path / "once", timesteps=256)
    train = ab.cell_dir(cfg, CELLS[0])
    lines: list[str] = []
    _press_ctrl_c(1, lambda: (train / ab.CELL_JSON).is_file())
    result = ab.run_grid(cfg, backend="local", workers=2, out=lines.append)
    assert "waiting for the 2 running cell(s) to finish: eval/zara1/planner/none, train/zara1/ppo/none/seed0" in (
        "\n".join(lines)
    )
    assert sorted(result["ran"]) == [CELLS[2], CELLS[0]] and result["interrupted"] == [CELLS[1]]
    assert json.loads((train / ab.TRAIN_RUN / "DONE").read_text())["steps"] == 256

    # twice: the training run stops now, at its last round boundary, and the next run ends at exactly its budget
    # (a budget the run cannot finish between the two presses, 0.5 s apart, on a fast idle machine)
    budget = 8192
    cfg = _config(tmp_path / "twice", timesteps=budget)
    train = ab.cell_dir(cfg, CELLS[0])
    _press_ctrl_c(2, lambda: (train / ab.TRAIN_RUN / "checkpoints" / "latest.json").is_file())
    with pytest.raises(KeyboardInterrupt):
        ab.run_grid(cfg, backend="local", workers=2, only=CELLS[0], out=lines.append)
    meta = json.loads((train / ab.CELL_JSON).read_text())
    assert meta["status"] == "interrupted"
    steps = json.loads((train / ab.TRAIN_RUN / "checkpoints" / "latest.json").read_text())["steps"]
    assert 0 < steps < budget and steps % 64 == 0  # a round boundary (rounds of n_steps = 64)
    assert not (train / ab.TRAIN_RUN / "DONE").exists()
    result = ab.run_grid(cfg, backend="local", workers=2, out=lambda s: None)
    assert not result["failed"]
    assert json.loads((train / ab.TRAIN_RUN / "DONE").read_text())["steps"] == budget
    assert f"# resumed from step_{steps:010d}" in (train / ab.TRAIN_RUN / "command.txt").read_text()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1):
            return True
    except OSError:
        return False


@pytest.mark.slow
def test_a_head_started_by_ray_start_with_a_token_is_joined(tmp_path: Path) -> None:
    """The documented set-up on loopback: ``ray start --head`` where a token exists (so the head requires it),
    then the grid with ``--address``."""
    pytest.importorskip("ray")
    cfg = _config(tmp_path)
    home = tmp_path / "home"
    (home / ".ray").mkdir(parents=True)
    (home / ".ray" / "auth_token").write_text("a" * 32)
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")}
    env["HOME"] = str(home)
    port = _free_port()
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths must fit in 107 bytes
    log = open(tmp_path / "head.log", "w")
    ray_start = [str(Path(sys.executable).parent / "ray"), "start", "--head", "--block", "--port", str(port)]
    ray_start += ["--num-cpus", "1", "--node-ip-address", "127.0.0.1", "--include-dashboard", "false"]
    head = subprocess.Popen(
        [*ray_start, "--disable-usage-stats", "--temp-dir", temp],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 120
        while not _accepts(port) and head.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        assert _accepts(port), (tmp_path / "head.log").read_text()
        assert "Token authentication is enabled" in (tmp_path / "head.log").read_text()
        grid = [sys.executable, "-m", "agents.ablation", str(tmp_path / "grid.yaml"), "--backend", "ray"]
        driver = subprocess.run(
            [*grid, "--address", f"127.0.0.1:{port}", "--only", CELLS[2]],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert driver.returncode == 0, driver.stdout + driver.stderr
        assert "Ray: token authentication on (token from" in driver.stdout
        assert {st.cell.name: st.state for st in ab.plan(cfg)}[CELLS[2]] == "done"
    finally:
        head.terminate()  # `ray start --block` stops the processes it started
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


@pytest.mark.slow
def test_a_killed_ray_training_task_resumes_from_its_shipped_checkpoint(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    cfg = _config(tmp_path, timesteps=2048)
    train = ab.cell_dir(cfg, CELLS[0])
    latest = train / ab.TRAIN_RUN / "checkpoints" / "latest.json"
    killed: dict[str, int] = {}

    def kill() -> None:  # once a checkpoint has reached the driver's folder, the task's worker is killed
        deadline = time.monotonic() + 300
        while not latest.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        killed["pid"] = json.loads((train / ab.CELL_JSON).read_text())["pid"]
        os.kill(killed["pid"], signal.SIGKILL)

    threading.Thread(target=kill, daemon=True).start()
    result = ab.run_grid(cfg, backend="ray", workers=1, only=CELLS[0], summarize_after=False, out=lambda s: None)
    assert list(result["failed"]) == [CELLS[0]]
    steps = json.loads(latest.read_text())["steps"]
    assert f"its last checkpoint (step {steps:,})" in result["failed"][CELLS[0]]
    leftovers = list(Path(tempfile.gettempdir()).glob(f"crowdnav-ablation-{killed['pid']}-*"))
    assert leftovers  # the killed task could not clean up after itself ...
    result = ab.run_grid(cfg, backend="ray", workers=1, summarize_after=False, out=lambda s: None)
    assert not result["failed"], result["failed"]
    assert not any(p.exists() for p in leftovers)  # ... the next task on the node did
    run = train / ab.TRAIN_RUN
    assert f"# resumed from step_{steps:010d}" in (run / "command.txt").read_text()
    assert json.loads((run / "DONE").read_text())["steps"] == 2048
