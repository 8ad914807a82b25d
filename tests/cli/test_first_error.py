"""A mistyped option, name or config key, or a missing file, is refused before torch or SB3 is imported (so the first
error comes in about a second, not after the 5-20 s those imports take on a busy machine).

Every case runs in one fresh interpreter, in order; after each the interpreter's modules are checked, so the first
case that imports torch or SB3 is the one named. No wall time is asserted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: Runs each case (``["cli"|"module", argv]``) and prints one JSON line per case: exit status, what was imported.
RUNNER = r"""
import contextlib, io, json, runpy, sys

HEAVY = ("torch", "stable_baselines3")
for kind, argv in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            if kind == "cli":
                from crowdnav_mesrnn.cli import main
                rc = main(argv)
            else:
                sys.argv = [argv[0], *argv[1:]]
                runpy.run_module(argv[0], run_name="__main__", alter_sys=True)
                rc = 0
        except SystemExit as exc:
            rc = exc.code
    print(json.dumps({"argv": argv, "rc": rc, "heavy": [m for m in HEAVY if m in sys.modules], "stderr": err.getvalue()}))
"""


def _typo_config(tmp_path: Path) -> Path:
    text = (REPO / "configs/agent/ppo_smoke.yaml").read_text(encoding="utf-8")
    assert "  n_timesteps: " in text
    path = tmp_path / "typo.yaml"
    path.write_text(text.replace("  n_timesteps: ", "  n_timestep: ", 1), encoding="utf-8")
    return path


def _cases(tmp_path: Path) -> list[tuple[str, list[str], list[str]]]:
    """``(kind, argv, what stderr must say)``."""
    typo = str(_typo_config(tmp_path))
    return [
        ("cli", ["agent", "train", "--config", "missing.yaml"], ["no agent config missing.yaml", "ppo_scoring.yaml"]),
        ("cli", ["agent", "train", "--config", "configs/agent/ppo_scorin.yaml"], ["did you mean configs/agent/ppo_"]),
        ("cli", ["agent", "train", "--config", typo], ["'n_timestep'", "did you mean 'n_timesteps'?"]),
        (
            "cli",
            ["agent", "train", "--config", "configs/agent/ppo_smoke.yaml", "--set", "_init_setup_model=false"],
            ["unknown ppo entry", "'_init_setup_model'"],
        ),
        ("cli", ["agent", "train", "--config", "configs/agent/ppo_smoke.yaml", "--bogus"], ["--bogus"]),
        ("cli", ["agent", "train", "--predictor", "nope"], ["unknown predictor 'nope'"]),
        ("cli", ["agent", "evaluate", "missing.zip"], ["'missing.zip'"]),
        ("cli", ["agent", "evaluate", "planner", "--predictor", "nope"], ["unknown predictor 'nope'"]),
        ("cli", ["agent", "evaluate", "planner", "--split", "nope"], ["invalid choice: 'nope'"]),
        ("cli", ["demo", "--policy", "missing"], ["'missing'"]),
        ("cli", ["predictor", "evaluate", "--model", "nope"], ["invalid choice: 'nope'"]),
        (
            "cli",
            ["predictor", "evaluate", "--model", "mesrnn", "--split", "zara1", "--checkpoint", "missing.pt"],
            ["no predictor checkpoint at missing.pt"],
        ),
        (
            "cli",
            ["predictor", "train", "--model", "mesrnn", "--split", "zara1", "--config", "missing.yaml"],
            ["no predictor config missing.yaml", "mesrnn.yaml"],
        ),
        ("cli", ["predictor", "plan", "missing.yaml"], ["no predictor config missing.yaml"]),
        ("cli", ["bench", "nope"], ["unknown predictor 'nope'"]),
        ("cli", ["ablation", "missing.yaml"], ["no ablation config missing.yaml", "learned.yaml"]),
        ("cli", ["forecasts", "build", "--predictor", "nope"], ["unknown predictor 'nope'"]),
        ("module", ["agents.train", "--config", "missing.yaml"], ["no agent config missing.yaml"]),
        ("module", ["agents.evaluate", "missing.zip"], ["'missing.zip'"]),
    ]


def test_a_first_error_comes_before_torch_and_sb3_are_imported(tmp_path: Path) -> None:
    cases = _cases(tmp_path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, json.dumps([[kind, argv] for kind, argv, _ in cases])],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    results = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert len(results) == len(cases), done.stdout[-3000:] + done.stderr[-3000:]
    for (_, argv, says), result in zip(cases, results, strict=True):
        assert result["rc"] not in (0, None), (argv, result)
        assert result["heavy"] == [], f"{' '.join(argv)} imported {result['heavy']} before refusing it"
        for text in says:
            assert text in result["stderr"], (argv, result["stderr"])


def test_the_private_init_setup_model_is_never_offered(tmp_path: Path) -> None:
    from agents.training.config import ALGO_KEYS, load_train_config
    from crowdnav_mesrnn.config import ConfigError

    with pytest.raises(ConfigError) as info:
        load_train_config(REPO / "configs/agent/ppo_smoke.yaml", overrides={"_init_setup_model": False})
    valid = str(info.value).split("(valid keys:")[1]
    assert "_init_setup_model" not in valid and "n_timesteps" in valid and "batch_size" in valid
    assert not [k for keys in ALGO_KEYS.values() for k in keys if k.startswith("_")]
    with pytest.raises(ConfigError, match=r"did you mean 'n_timesteps'\?"):
        load_train_config(_typo_config(tmp_path))


def test_the_written_out_algorithm_keys_are_sb3s() -> None:
    """:data:`agents.training.config.ALGO_KEYS` (checked without importing SB3) are the installed SB3's PPO and SAC
    keyword arguments, without those a run sets itself and the private ones."""
    import inspect

    from stable_baselines3 import PPO, SAC

    from agents.training.config import ALGO_KEYS, ZOO_KEYS

    run_sets = {"self", "policy", "env", "seed", "verbose", "device", "tensorboard_log"}
    for algo, cls in (("ppo", PPO), ("sac", SAC)):
        params = [p for p in inspect.signature(cls.__init__).parameters if p not in run_sets]
        public = {p for p in params if not p.startswith("_")} - set(ZOO_KEYS)
        assert set(ALGO_KEYS[algo]) == public, algo


def test_a_missing_config_lists_the_shipped_ones(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from crowdnav_mesrnn.config import existing_config

    assert existing_config(REPO / "configs/agent/ppo.yaml", "agent") == REPO / "configs/agent/ppo.yaml"
    monkeypatch.chdir(REPO)
    with pytest.raises(FileNotFoundError) as info:
        existing_config("configs/agent/pp_scoring.yaml", "agent")
    msg = str(info.value)
    assert msg.startswith("no agent config configs/agent/pp_scoring.yaml; did you mean configs/agent/ppo_scoring.yaml?")
    shipped = ", ".join(sorted(p.name for p in (REPO / "configs/agent").glob("*.yaml")))
    assert "ppo_smoke.yaml" in shipped
    assert f"(configs in configs/agent: {shipped})" in msg
    with pytest.raises(FileNotFoundError, match="did you mean") as info:
        existing_config("configs/ablation/learnd.yaml", "ablation")
    with pytest.raises(FileNotFoundError) as info:
        existing_config(tmp_path / "x.yaml", "nothing-of-this-kind")
    assert str(info.value) == f"no nothing-of-this-kind config {tmp_path / 'x.yaml'}"
