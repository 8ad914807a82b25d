"""Policy files are data, SB3 zips and pickles are code (issue 27, item 1).

- A crafted SB3 zip (a cloudpickled entry of its ``data``) and a crafted ``<stem>_vecnormalize.pkl`` that write a
  marker file when unpickled are refused by ``demo``, ``agent evaluate``, ``agent export``, ``load_policy`` and the
  ablation's evaluation cell without the trust flag, and the marker never appears; with the flag they load and the
  marker appears (the payload is live).
- The project's format gives the same actions (bit-identical logits) as the SB3 model it was written from: a trained
  run's zip, live PPO (action scoring, ``VecNormalize``) and SAC models, and the shipped policy against the zip it was
  converted from (read from the git history), on observations of real ETH/UCY episodes.
- A malformed policy file is refused naming the file and the key.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import operator
import os
import pickle
import shutil
import subprocess
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest
import torch
import yaml

import agents.ablation as ab
from agents.evaluation.run import evaluate, evaluation_env_kwargs
from agents.policy_file import PolicyFileError, read_policy_file, write_policy_file
from agents.rollout import SB3Policy, evaluation_seeds
from agents.runs import PROJECT_KEY, UntrustedPolicyError, export_policy, load_policy, load_sb3
from crowdnav_mesrnn.cli import main

REPO = Path(__file__).resolve().parents[2]
#: The SB3 zip the shipped policy was converted from, by its git blob id and sha256 (agents/pretrained/README.md).
SHIPPED_ZIP_BLOB = "77ff50b9c8bbb63729031cc153b7a3ffe81cc977"
SHIPPED_ZIP_SHA256 = "aa0681f191fd52f938df3fdff85a7ae487addbe52cd417439af317a022241613"


# ------------------------------------------------------------------------------------------------ crafted files


class _Run:
    """Unpickling this runs ``code``: what a malicious pickle does."""

    def __init__(self, code: str) -> None:
        self.code = code

    def __reduce__(self) -> Any:
        return (exec, (self.code,))


class _Laced:
    """Unpickles as ``obj`` after writing ``marker`` (so a laced file still loads: the payload is silent)."""

    def __init__(self, obj: Any, marker: Path) -> None:
        self.obj, self.marker = obj, marker

    def __reduce__(self) -> Any:
        code = f"open({str(self.marker)!r}, 'w').write('the payload ran')"
        return (operator.getitem, ((_Run(code), self.obj), 1))


def _laced_zip(src: Path, dest: Path, marker: Path) -> None:
    """``src`` (an SB3 zip) with its ``policy_class`` entry re-serialised with the payload (SB3 cloudpickles it)."""
    with zipfile.ZipFile(src) as zin:
        entries = {name: zin.read(name) for name in zin.namelist()}
    data = json.loads(entries["data"])
    policy_class = cloudpickle.loads(base64.b64decode(data["policy_class"][":serialized:"]))
    payload = cloudpickle.dumps(_Laced(policy_class, marker))
    data["policy_class"][":serialized:"] = base64.b64encode(payload).decode()
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(dest, "w") as zout:
        for name, content in entries.items():
            zout.writestr(name, content)


def _laced_vecnormalize(dest: Path, marker: Path) -> None:
    """A real ``VecNormalize`` (statistics for the tiny run's observation) pickled with the payload."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from envs.crowd_nav import CrowdNavEnv

    venv = DummyVecEnv([lambda: CrowdNavEnv(crowd="synthetic", predictor="none", observe_time_left=True)])
    vn = VecNormalize(venv, norm_obs_keys=["robot", "pedestrians"])
    vn.venv = None
    dest.write_bytes(pickle.dumps(_Laced(vn, marker)))
    venv.close()


@pytest.fixture
def crafted(tiny_ppo_run: Path, tmp_path: Path) -> dict[str, Path]:
    """``evil.zip`` + ``evil.yaml`` (its training config) + ``evil_vecnormalize.pkl``, and a run folder holding only
    such files; unpickling the zip writes ``zip_ran``, the pickle ``pkl_ran``."""
    markers = {"zip": tmp_path / "zip_ran", "pkl": tmp_path / "pkl_ran"}
    zip_path = tmp_path / "evil.zip"
    _laced_zip(tiny_ppo_run / "final_model.zip", zip_path, markers["zip"])
    shutil.copyfile(tiny_ppo_run / "config.yaml", tmp_path / "evil.yaml")
    _laced_vecnormalize(tmp_path / "evil_vecnormalize.pkl", markers["pkl"])
    run = tmp_path / "old_run"
    run.mkdir()
    shutil.copyfile(zip_path, run / "best_model.zip")
    shutil.copyfile(tmp_path / "evil_vecnormalize.pkl", run / "best_model_vecnormalize.pkl")
    shutil.copyfile(tiny_ppo_run / "config.yaml", run / "config.yaml")
    return {"zip": zip_path, "run": run, **{f"{k}_marker": v for k, v in markers.items()}}


def _ran(crafted: Mapping[str, Path]) -> list[str]:
    return [k for k in ("zip_marker", "pkl_marker") if crafted[k].exists()]


def test_crafted_zip_and_pickle_are_refused_everywhere_and_nothing_they_carry_runs(
    crafted: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for spec in (crafted["zip"], crafted["run"]):  # a model file, and an old run folder holding only zips
        assert main(["demo", "--policy", str(spec), "--synthetic", "--no-gif"]) == 2
        err = capsys.readouterr().err
        assert "--trust-pickle" in err and "can run arbitrary code" in err and "agent export" in err
        args = ["agent", "evaluate", str(spec), "--predictor", "none", "--episodes", "1", "--set", "crowd=synthetic"]
        assert main([*args, "--out", str(tmp_path / "eval")]) == 2
        assert "--trust-pickle" in capsys.readouterr().err
        assert main(["agent", "export", str(spec), str(tmp_path / "x.policy.yaml")]) == 2
        assert "refusing to convert" in capsys.readouterr().err
        with pytest.raises(UntrustedPolicyError, match="arbitrary code"):
            load_policy(spec)
        with pytest.raises(UntrustedPolicyError):
            evaluate(spec, "none", "zara1", 1, env_overrides={"crowd": "synthetic"})
    with pytest.raises(UntrustedPolicyError):
        load_sb3(crafted["zip"])
    assert not (tmp_path / "x.policy.yaml").exists() and not (tmp_path / "eval").exists()
    assert _ran(crafted) == [], "a crafted file was unpickled without the trust flag"


def test_the_ablation_refuses_to_unpickle_a_training_cells_zip(crafted: dict[str, Path], tmp_path: Path) -> None:
    """An evaluation cell whose training run holds only SB3 zips (a grid trained before the policy format) fails with
    the refusal, recorded in its cell.json; nothing is unpickled."""
    raw = {
        "name": "crafted",
        "runs_dir": str(tmp_path / "grid" / "runs"),
        "out_dir": str(tmp_path / "grid" / "results"),
        "splits": ["zara1"],
        "arms": ["none"],
        "seeds": [0],
        "policies": {"ppo": {"kind": "ppo", "config": str(REPO / "configs" / "agent" / "ppo.yaml"), "timesteps": 64}},
        "evaluation": {"episodes": 1, "seed": 0},
        "env": {"crowd": "synthetic"},
    }
    cfg = ab.config_from_mapping(raw)
    cell = next(c for c in ab.expand(cfg) if c.kind == "eval")
    shutil.copytree(crafted["run"], ab.cell_dir(cfg, cell.needs) / ab.TRAIN_RUN)
    task = ab.backends._task(cfg, cell)
    assert task.model is not None and task.model.endswith("best_model.zip")
    result = ab.execute_cell(task)
    assert not result["ok"] and "--trust-pickle" in result["error"]
    assert "--trust-pickle" in json.loads((ab.cell_dir(cfg, cell) / ab.CELL_JSON).read_text())["error"]
    assert _ran(crafted) == []


def test_with_the_trust_flag_the_crafted_files_load_and_their_payload_runs(
    crafted: dict[str, Path], tmp_path: Path
) -> None:
    """The payload is live: trusting the files runs it (which is why the flag exists)."""
    policy = load_policy(crafted["zip"], trust_pickle=True)
    assert _ran(crafted) == ["zip_marker", "pkl_marker"]
    assert policy.model.vecnormalize is not None  # the pickled statistics, behind the discrete-action adapter
    for marker in ("zip_marker", "pkl_marker"):
        crafted[marker].unlink()
    assert main(["demo", "--policy", str(crafted["zip"]), "--synthetic", "--no-gif", "--trust-pickle"]) == 0
    assert _ran(crafted) == ["zip_marker", "pkl_marker"]
    for marker in ("zip_marker", "pkl_marker"):
        crafted[marker].unlink()
    dest = tmp_path / "converted.policy.yaml"
    assert main(["agent", "export", str(crafted["zip"]), str(dest), "--trust-pickle"]) == 0
    assert _ran(crafted) == ["zip_marker", "pkl_marker"]
    # the conversion is data: loading it runs nothing, and it keeps the statistics as numbers
    for marker in ("zip_marker", "pkl_marker"):
        crafted[marker].unlink()
    assert read_policy_file(dest).normalizer is not None and _ran(crafted) == []


def test_a_tensor_file_carrying_a_pickle_payload_is_refused_without_running_it(
    tiny_ppo_run: Path, tmp_path: Path
) -> None:
    """The weights go through ``torch.load(weights_only=True)``: a ``.pt`` carrying objects is refused unread."""
    policy, marker = _copy(tiny_ppo_run / "final_model.policy.yaml", tmp_path), tmp_path / "pt_ran"
    buf = io.BytesIO()
    torch.save({"weights": _Laced(torch.zeros(1), marker)}, buf)
    _set_weights(policy, buf.getvalue())
    with pytest.raises(PolicyFileError, match=r"weights\.file.*not a tensor file"):
        read_policy_file(policy)
    assert not marker.exists()


# -------------------------------------------------------------------------------------------- identical actions


def _observations(env_kwargs: Mapping[str, Any], policy: Any, n: int, split: str = "zara1") -> dict[str, np.ndarray]:
    """``n`` observations of real episodes (the split's evaluation seeds), ``policy`` driving; batched."""
    from envs.crowd_nav import CrowdNavEnv

    env = CrowdNavEnv(**dict(env_kwargs))
    seen: list[dict[str, np.ndarray]] = []
    try:
        for seed in evaluation_seeds(split, 100):
            obs, info = env.reset(seed=seed)
            assert info["crowd"] == "replay"
            done = False
            while not done and len(seen) < n:
                seen.append(obs)
                action, _ = policy.predict(obs, deterministic=True)
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
            if len(seen) >= n:
                break
    finally:
        env.close()
    return {key: np.stack([o[key] for o in seen]) for key in seen[0]}


def _sb3_policy(policy: Any) -> SB3Policy:
    """The :class:`SB3Policy` behind an adapter (discrete actions)."""
    while not isinstance(policy, SB3Policy):
        policy = policy.model
    return policy


def _network(policy: SB3Policy) -> Any:
    """The SB3 policy network of an :class:`SB3Policy` (holding an SB3 algorithm or, from a policy file, the network)."""
    return policy.model if isinstance(policy.model, torch.nn.Module) else policy.model.policy


def _assert_same_actions(a: Any, b: Any, obs: Mapping[str, np.ndarray]) -> None:
    """Same deterministic actions on the batch, identically normalised observations, and bit-identical action
    distributions and values."""
    np.testing.assert_array_equal(a.predict(dict(obs))[0], b.predict(dict(obs))[0])
    sa, sb = _sb3_policy(a), _sb3_policy(b)
    norm_a = obs if sa.vecnormalize is None else sa.vecnormalize.normalize_obs(dict(obs))
    norm_b = obs if sb.vecnormalize is None else sb.vecnormalize.normalize_obs(dict(obs))
    for key in obs:
        np.testing.assert_array_equal(norm_a[key], norm_b[key])
    net_a, net_b = _network(sa), _network(sb)
    with torch.no_grad():
        ta, _ = net_a.obs_to_tensor(dict(norm_a))
        if hasattr(net_a, "get_distribution"):  # PPO: logits (discrete actions) or mean and std, and the value
            da, db = net_a.get_distribution(ta).distribution, net_b.get_distribution(ta).distribution
            if isinstance(da, torch.distributions.Categorical):
                assert torch.equal(da.logits, db.logits)
            else:
                assert torch.equal(da.mean, db.mean) and torch.equal(da.stddev, db.stddev)
            assert torch.equal(net_a.predict_values(ta), net_b.predict_values(ta))
        else:  # SAC: the actor's mean and log-std, the critics' values
            mean_a, log_std_a, _ = net_a.actor.get_action_dist_params(ta)
            mean_b, log_std_b, _ = net_b.actor.get_action_dist_params(ta)
            assert torch.equal(mean_a, mean_b) and torch.equal(log_std_a, log_std_b)
            action = net_a.actor(ta, deterministic=True)
            for qa, qb in zip(net_a.critic(ta, action), net_b.critic(ta, action), strict=True):
                assert torch.equal(qa, qb)


def test_a_trained_runs_policy_file_acts_as_its_zip(tiny_ppo_run: Path, data_dir: Path) -> None:
    """The policy file training wrote beside the zip, on 300 observations of real ZARA1 episodes."""
    kwargs = evaluation_env_kwargs(tiny_ppo_run, "none", "zara1", {"crowd": "replay", "data_dir": str(data_dir)})
    safe = load_policy(tiny_ppo_run / "final_model.policy.yaml")
    pickled = load_policy(tiny_ppo_run / "final_model.zip", trust_pickle=True)
    obs = _observations(kwargs, safe, 300)
    assert len(obs["mask"]) == 300 and obs["mask"].any()
    _assert_same_actions(safe, pickled, obs)


def _live_model(algo: str, tiny: Any, **extra: Any) -> tuple[Any, dict[str, Any]]:
    """A model built as training builds it (random weights; PPO: the action-scoring recipe), and its training config
    as data."""
    from stable_baselines3 import PPO, SAC

    from agents.training.config import algorithm_kwargs, load_train_config, policy_class
    from agents.training.run import make_vec_env

    over = tiny(algo, "cv", vec_env="dummy", **extra)
    if algo == "ppo":  # the action-scoring extractor is sized by context_dim
        del over["policy_kwargs.features_extractor_kwargs.hidden_dim"]
        over["policy_kwargs.features_extractor_kwargs.context_dim"] = 8
    recipe = REPO / "configs" / "agent" / ("ppo_scoring.yaml" if algo == "ppo" else "sac.yaml")
    cfg = load_train_config(recipe, None, over)
    cls = {"ppo": PPO, "sac": SAC}[algo]
    model = cls(policy_class(cfg.policy), make_vec_env(cfg), seed=3, device="cpu", **algorithm_kwargs(cfg))
    doc = cfg.to_yaml()
    doc[PROJECT_KEY]["run"] = {"predictor": cfg.predictor, "split": cfg.split}
    return model, doc


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_a_live_model_written_and_read_back_acts_identically(
    algo: str, tiny: Any, data_dir: Path, tmp_path: Path
) -> None:
    """PPO with the action-scoring policy behind ``VecNormalize`` (statistics from real observations), and SAC: the
    policy file written from the live model, and the conversion of the same model's SB3 zip and pickled statistics,
    act as the live model does on 300 observations of real ZARA1 episodes (constant-velocity forecasts)."""
    from agents.actions import DiscretePolicy, action_set
    from agents.training.callbacks import save_model, save_vecnormalize
    from envs.config import config_from

    model, config = _live_model(algo, tiny, **({"normalize": True} if algo == "ppo" else {}))
    vn = model.get_vec_normalize_env()
    assert (vn is not None) == (algo == "ppo")
    env_kwargs = {**config[PROJECT_KEY]["env"], "predictor": "cv", "split": "zara1", "part": "test"}
    env_kwargs.update(episode_time="all", crowd="replay", data_dir=str(data_dir))
    env_config = config_from(env_kwargs, {})
    live: Any = SB3Policy(model, vn)
    if algo == "ppo":
        live = DiscretePolicy(live, action_set(config[PROJECT_KEY]["action"], env_config))
    obs = _observations(env_kwargs, live, 300)
    if vn is not None:  # statistics that are not the identity
        for key in vn.norm_obs_keys:
            vn.obs_rms[key].update(obs[key])
    dest = write_policy_file(tmp_path / "live.policy.yaml", model.policy, algo, config, vn)
    _assert_same_actions(load_policy(dest, env_config), live, obs)
    save_model(model, tmp_path / "m.zip")
    save_vecnormalize(model, tmp_path / "m.zip")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(config))
    converted = export_policy(tmp_path / "m.zip", tmp_path / "converted.policy.yaml", trust_pickle=True)
    _assert_same_actions(load_policy(converted, env_config), live, obs)
    if vn is not None:
        normalizer = read_policy_file(converted).normalizer
        assert normalizer is not None and normalizer.keys == tuple(vn.norm_obs_keys)
    model.get_env().close()


def _shipped_zip() -> bytes:
    try:
        data = subprocess.run(
            ["git", "-C", str(REPO), "cat-file", "blob", SHIPPED_ZIP_BLOB], capture_output=True, check=True, timeout=30
        ).stdout
    except (OSError, subprocess.SubprocessError):
        pytest.skip(f"the shipped policy's original zip (git blob {SHIPPED_ZIP_BLOB[:8]}) is not in this checkout")
    assert hashlib.sha256(data).hexdigest() == SHIPPED_ZIP_SHA256
    return data


@pytest.mark.slow
def test_the_shipped_policy_acts_as_the_zip_it_was_converted_from(data_dir: Path, tmp_path: Path) -> None:
    """400 observations of real ZARA1 test episodes with MESRNN forecasts: the same actions, logits and values."""
    import agents.cli
    from envs.config import config_from

    shipped = agents.cli.SHIPPED_POLICY
    doc = read_policy_file(shipped)
    assert doc.raw["source"]["model_sha256"] == SHIPPED_ZIP_SHA256
    original = tmp_path / "ppo_mesrnn_zara1.zip"
    original.write_bytes(_shipped_zip())
    (tmp_path / "ppo_mesrnn_zara1.yaml").write_text(yaml.safe_dump(doc.training_config))
    kwargs = evaluation_env_kwargs(shipped, "mesrnn", "zara1", {"data_dir": str(data_dir)})
    env_config = config_from(kwargs, {})
    safe = load_policy(shipped, env_config)
    pickled = load_policy(original, env_config, trust_pickle=True)
    obs = _observations(kwargs, safe, 400)
    _assert_same_actions(safe, pickled, obs)
    assert len(np.unique(safe.model.predict(obs)[0])) > 3  # the policy does more than one thing on these


# --------------------------------------------------------------------------------------------- malformed files


def _copy(policy: Path, folder: Path) -> Path:
    """A policy file and its weights copied into ``folder``."""
    doc = yaml.safe_load(policy.read_text())
    shutil.copyfile(policy.with_name(doc["weights"]["file"]), folder / doc["weights"]["file"])
    shutil.copyfile(policy, folder / policy.name)
    return folder / policy.name


def _edit(path: Path, change: Any) -> None:
    doc = yaml.safe_load(path.read_text())
    change(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def _set_weights(path: Path, data: bytes) -> None:
    doc = yaml.safe_load(path.read_text())
    path.with_name(doc["weights"]["file"]).write_bytes(data)
    _edit(path, lambda d: d["weights"].update(sha256=hashlib.sha256(data).hexdigest()))


def _set(keys: str, value: Any) -> Any:
    def change(doc: dict[str, Any]) -> None:
        *parents, last = keys.split(".")
        for key in parents:
            doc = doc[key]
        doc[last] = value

    return change


def _robot_statistics(mean: Any) -> dict[str, Any]:
    return {
        "keys": ["robot"],
        "clip_obs": 10.0,
        "epsilon": 1e-8,
        "gamma": 0.99,
        "statistics": {"robot": {"mean": mean, "var": [1.0] * 5, "count": 4.0}},
    }


@pytest.mark.parametrize(
    ("change", "key", "message"),
    [
        (_set("extra", 1), "top level", "unknown top level key 'extra'"),
        (lambda d: d.pop("weights"), "weights", "missing"),
        (_set("format_version", 2), "format_version", "reads version 1"),
        (_set("algo", "dqn"), "algo", "must be one of ppo, sac"),
        (_set("policy", "os.system"), "policy", "not in the allow-list"),
        (_set("policy_kwargs.features_extractor_class", "builtins.eval"), "features_extractor_class", "allow-list"),
        (_set("policy_kwargs.activation_fn", "torch.nn.GELU"), "policy_kwargs.activation_fn", "unknown activation"),
        (_set("policy_kwargs.optimizer_class", "Adam"), "policy_kwargs", "unknown policy_kwargs key 'optimizer_class'"),
        (_set("policy_kwargs.net_arch", [16, -1]), "policy_kwargs.net_arch", "integer >= 1"),
        (_set("policy_kwargs.features_extractor_kwargs.hidden", 8), "features_extractor_kwargs", "'hidden'"),
        (_set("observation_space.robot.shape", [6]), "observation_space.robot.low", "shape (5,) does not fit"),
        (_set("observation_space.robot.high", 1.0), "observation_space.robot", "training config"),
        (_set("observation_space.mask", {"type": "Text"}), "observation_space.mask.type", "unknown space type"),
        (_set("action_space.n", 56), "action_space", "training config gives"),
        (_set("normalization", _robot_statistics([0.0] * 4)), "normalization.statistics.robot.mean", "shape (4,)"),
        (_set("normalization", _robot_statistics([0.0, 0.0, float("nan"), 0.0, 0.0])), "robot.mean", "not finite"),
        (_set("normalization", _robot_statistics([0.0, 0.0, float("inf"), 0.0, 0.0])), "robot.mean", "not finite"),
        (_set("normalization", {**_robot_statistics([0.0] * 5), "clip_obs": -1}), "normalization.clip_obs", "> 0"),
        (_set("weights.file", "../best_model.pt"), "weights.file", "bare NAME.pt"),
        (_set("weights.sha256", "0" * 64), "weights.sha256", "has sha256"),
        (_set("training_config.crowdnav_mesrnn.algo", "sac"), "training_config.crowdnav_mesrnn.algo", "differs"),
        (_set("training_config.crowdnav_mesrnn.env.num_pedestrians", 4), "observation_space.", "training config"),
    ],
)
def test_a_malformed_policy_file_is_refused_naming_the_file_and_key(
    tiny_ppo_run: Path, tmp_path: Path, change: Any, key: str, message: str
) -> None:
    path = _copy(tiny_ppo_run / "final_model.policy.yaml", tmp_path)
    _edit(path, change)
    with pytest.raises(PolicyFileError) as err:
        read_policy_file(path)
    assert str(path) in str(err.value) and key in str(err.value) and message in str(err.value), str(err.value)


@pytest.mark.parametrize("defect", ["shape", "name", "nan", "not a mapping"])
def test_weights_that_do_not_fit_the_rebuilt_policy_are_refused_naming_the_tensor(
    tiny_ppo_run: Path, tmp_path: Path, defect: str
) -> None:
    path = _copy(tiny_ppo_run / "final_model.policy.yaml", tmp_path)
    state = torch.load(path.with_name("final_model.pt"), weights_only=True)
    name = next(k for k, v in state.items() if v.ndim == 2)
    if defect == "shape":
        state[name] = state[name][:, :-1].clone()
    elif defect == "name":
        state["extra.weight"] = state.pop(name)
    elif defect == "nan":
        state[name] = state[name].clone()
        state[name][0, 0] = float("nan")
    buf = io.BytesIO()
    torch.save(list(state.values()) if defect == "not a mapping" else state, buf)
    _set_weights(path, buf.getvalue())
    with pytest.raises(PolicyFileError) as err:
        read_policy_file(path)
    text = str(err.value)
    assert str(path) in text and "weights" in text
    if defect == "name":  # the first of the two in sorted order is named
        assert "extra.weight" in text or name in text, text
    else:
        assert {"shape": name, "nan": "not finite", "not a mapping": "mapping"}[defect] in text, text


def test_policy_files_load_without_the_flag_and_a_run_prefers_them(tiny_ppo_run: Path, tmp_path: Path) -> None:
    from agents.runs import model_path

    assert model_path(tiny_ppo_run).name == "best_model.policy.yaml"
    assert model_path(tiny_ppo_run, "final").name == "final_model.policy.yaml"
    assert ab.trained_model(tiny_ppo_run.parent, "best") is None  # not a cell folder: no run/ inside
    cell = tmp_path / "cell"
    shutil.copytree(tiny_ppo_run, cell / ab.TRAIN_RUN)
    assert ab.trained_model(cell, "best") == cell / ab.TRAIN_RUN / "best_model.policy.yaml"
    os.remove(cell / ab.TRAIN_RUN / "best_model.policy.yaml")
    assert ab.trained_model(cell, "best") == cell / ab.TRAIN_RUN / "best_model.zip"
