"""Run folders and policy files: find a run's model and config, load any policy by spec, export a run's model.

A *policy spec* is a planner name (:data:`agents.planners.PLANNERS`), an SB3 ``.zip``, or a run folder of
:mod:`agents.training` (its ``best_model.zip`` or ``final_model.zip``, :func:`model_path`). A run folder's
``config.yaml``, or an exported model's ``<stem>.yaml``, holds the training config with the project's own
settings under :data:`PROJECT_KEY`; :func:`run_settings` reads that section.
"""

from __future__ import annotations

import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from agents.actions import DiscretePolicy, action_set
from agents.planners import PLANNERS, as_env_config, make_planner
from agents.rollout import SB3Policy
from crowdnav_mesrnn.config import ConfigError, load_yaml
from crowdnav_mesrnn.utils import atomic_write, atomic_write_text
from envs.config import CrowdNavConfig

#: Top-level key of the project's own settings in a training config file (RL Zoo ignores it).
PROJECT_KEY: Final[str] = "crowdnav_mesrnn"
#: Names of the models a run folder holds, for ``which=``.
RUN_MODELS: Final[tuple[str, ...]] = ("best", "final")


def algo_of_model(path: str | Path) -> str:
    """``"ppo"`` or ``"sac"``: which SB3 algorithm saved the ``.zip`` (from its policy class)."""
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.save_util import load_from_zip_file
    from stable_baselines3.sac.policies import SACPolicy

    data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    policy_class = (data or {}).get("policy_class")
    if isinstance(policy_class, type) and issubclass(policy_class, SACPolicy):
        return "sac"
    if isinstance(policy_class, type) and issubclass(policy_class, ActorCriticPolicy):
        return "ppo"
    raise ValueError(f"{path}: not a PPO or SAC model saved by Stable-Baselines3 (policy class {policy_class!r})")


def load_sb3(path: str | Path, algo: str | None = None) -> SB3Policy:
    """Load an SB3 ``.zip`` (PPO or SAC, detected unless given) on the CPU, with ``<stem>_vecnormalize.pkl``
    beside it if present."""
    from stable_baselines3 import PPO, SAC

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path}")
    algo = algo or algo_of_model(path)
    cls = {"ppo": PPO, "sac": SAC}[algo]
    model = cls.load(path, device="cpu")
    vecnormalize = None
    stats = path.with_name(f"{path.stem}_vecnormalize.pkl")
    if stats.is_file():
        with open(stats, "rb") as fh:
            vecnormalize = pickle.load(fh)
        vecnormalize.training = False
        vecnormalize.norm_reward = False
    return SB3Policy(model, vecnormalize, str(path))


def config_of(spec: str | Path) -> Path | None:
    """The training config that goes with a policy spec: a run folder's ``config.yaml``, for a model file
    ``<stem>.yaml`` beside it (an exported policy, see :func:`export_policy`) or its folder's ``config.yaml``;
    None for planners and bare models."""
    p = Path(spec)
    if str(spec) in PLANNERS:
        return None
    if p.is_dir():
        return p / "config.yaml" if (p / "config.yaml").is_file() else None
    for candidate in (p.with_suffix(".yaml"), p.parent / "config.yaml"):
        if p.is_file() and candidate.is_file():
            return candidate
    return None


def run_settings(spec: str | Path) -> dict[str, Any]:
    """The project section (``algo``, ``env``, ``run``, ...) of the training config of a policy spec; empty when
    there is none (planners, bare models)."""
    path = config_of(spec)
    if path is None:
        return {}
    section = load_yaml(path).get(PROJECT_KEY)
    if not isinstance(section, dict):
        raise ConfigError(f"{path} has no {PROJECT_KEY!r} section: not a config written by agents.train")
    return section


def export_policy(run_dir: str | Path, dest: str | Path, which: str = "best") -> Path:
    """Copy a run's model to ``dest`` (``.zip``) with its config as ``<stem>.yaml`` (and normalisation statistics
    as ``<stem>_vecnormalize.pkl``), so the file alone can be evaluated or shipped."""
    import shutil

    src = model_path(run_dir, which)
    dest = Path(dest)
    if dest.suffix != ".zip":
        raise ValueError(f"the exported policy must be a .zip path, got {dest}")
    config = config_of(src)
    if config is None:
        raise FileNotFoundError(f"{run_dir} holds no config.yaml: not a run folder of agents.train")
    atomic_write(dest, lambda fh: fh.write(without_optimizer_state(src.read_bytes())))
    atomic_write_text(dest.with_suffix(".yaml"), config.read_text())
    stats = src.with_name(f"{src.stem}_vecnormalize.pkl")
    if stats.is_file():
        shutil.copyfile(stats, dest.with_name(f"{dest.stem}_vecnormalize.pkl"))
    return dest


def without_optimizer_state(model_zip: bytes) -> bytes:
    """An SB3 model archive whose optimizer keeps its settings but not its moment estimates (Adam's are twice the
    policy's size and serve only to continue training); the policy, and so every action, is unchanged."""
    import io
    import zipfile

    import torch

    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(model_zip)) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename.endswith("optimizer.pth"):
                state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
                buf = io.BytesIO()
                torch.save({**state, "state": {}}, buf)
                data = buf.getvalue()
            dst.writestr(item, data)
    return out.getvalue()


def model_path(spec: str | Path, which: str = "best") -> Path:
    """The ``.zip`` a spec names: the spec itself, or ``best_model.zip``/``final_model.zip`` of a run folder
    (``best`` falls back to ``final`` when no validation ran)."""
    if which not in RUN_MODELS:
        raise ValueError(f"unknown model {which!r}; valid: {', '.join(RUN_MODELS)}")
    p = Path(spec)
    if p.is_file():
        return p
    if p.is_dir():
        for name in (f"{which}_model.zip", "final_model.zip"):
            if (p / name).is_file():
                return p / name
        raise FileNotFoundError(f"{p} holds neither {which}_model.zip nor final_model.zip (is the run finished?)")
    raise FileNotFoundError(
        f"no run folder, model file or planner named {str(spec)!r} (planners: {', '.join(PLANNERS)})"
    )


def load_policy(
    spec: str | Path,
    env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
    which: str = "best",
    planner_kwargs: Mapping[str, Any] | None = None,
) -> Any:
    """A policy with SB3's ``predict``: ``"planner"``/``"straight"`` (built for ``env_config``, with
    ``planner_kwargs``), an SB3 ``.zip``, or a run folder (its best model, see :func:`model_path`)."""
    if str(spec) in PLANNERS:
        return make_planner(str(spec), env_config, **dict(planner_kwargs or {}))  # type: ignore[return-value]
    path = model_path(spec, which)
    settings = run_settings(path)
    policy: Any = load_sb3(path, settings.get("algo"))
    if (settings.get("action") or {}).get("kind", "continuous") != "continuous":
        policy = DiscretePolicy(policy, action_set(settings["action"], as_env_config(env_config)))
    return policy


def check_spaces(policy: Any, env: Any) -> None:
    """Raise ``ValueError`` if an SB3 policy was trained on another observation space than ``env`` gives."""
    space = getattr(policy, "observation_space", None)
    while space is None and hasattr(policy, "model"):  # adapters (e.g. discrete actions) around an SB3 policy
        policy = policy.model
        space = getattr(policy, "observation_space", None)
    if space is None:
        return
    want = {k: getattr(v, "shape", None) for k, v in space.spaces.items()}
    got = {k: getattr(v, "shape", None) for k, v in env.observation_space.spaces.items()}
    if want != got:
        raise ValueError(
            f"the policy was trained on observations {want} but the environment gives {got}: "
            "evaluate with the forecast arm and env settings it was trained with (forecasts vs none, "
            "observe_time_left, num_pedestrians, horizon_steps, kinematics)"
        )
