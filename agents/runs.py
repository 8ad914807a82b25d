"""Run folders and policy files: find a run's model and config, load any policy by spec, export a run's model.

A *policy spec* is a planner name (:data:`agents.planners.PLANNERS`), a policy file of the project's format
(``NAME.policy.yaml`` with ``NAME.pt`` beside it, :mod:`agents.policy_file`), a run folder of :mod:`agents.training`
(its best or final model, :func:`model_path`: the policy file training writes beside each SB3 zip), or an SB3 ``.zip``.

Policy files are data: loading one unpickles nothing. SB3 zips (SB3 serialises some entries with cloudpickle) and
the ``<stem>_vecnormalize.pkl`` beside them are code: loading them can run anything their author wrote, so they load
only with ``trust_pickle=True`` (``--trust-pickle`` on the command line); otherwise :class:`UntrustedPolicyError`
says why and how to convert them (:func:`export_policy`, from a source you trust).

A run folder's ``config.yaml``, an SB3 model's ``<stem>.yaml`` or the ``training_config`` inside a policy file holds
the training config with the project's own settings under :data:`PROJECT_KEY`; :func:`run_settings` reads that
section.
"""

from __future__ import annotations

import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from agents.actions import DiscretePolicy, action_set
from agents.planners import PLANNERS, as_env_config, make_planner
from agents.policy_file import (
    POLICY_SUFFIX,
    is_policy_file,
    policy_yaml,
    read_policy_file,
    read_training_config,
    weights_file_name,
    write_policy_file,
)
from agents.rollout import SB3Policy
from crowdnav_mesrnn.config import ConfigError, load_yaml
from crowdnav_mesrnn.utils import atomic_write, atomic_write_text
from envs.config import CrowdNavConfig

#: Top-level key of the project's own settings in a training config file (RL Zoo ignores it).
PROJECT_KEY: Final[str] = "crowdnav_mesrnn"
#: Names of the models a run folder holds, for ``which=``.
RUN_MODELS: Final[tuple[str, ...]] = ("best", "final")
#: What to do with an SB3 zip or a pickle, said by every refusal to load one.
CONVERT_HINT: Final[str] = (
    "SB3 zips and pickle files can run arbitrary code when they are loaded. If you trust the file (you trained it, or "
    "you know where it comes from), convert it once to the project's policy format, which is data only: "
    "crowdnav-mesrnn agent export {source} NAME.policy.yaml --trust-pickle; or pass --trust-pickle "
    "(trust_pickle=True in Python) to load it as it is"
)


class UntrustedPolicyError(ValueError):
    """A policy spec names an SB3 zip or a pickle and ``trust_pickle`` was not given: nothing was loaded."""


def is_pickle_based(path: str | Path) -> bool:
    """Whether loading ``path`` would unpickle it: any model file that is not a policy file of the project's format
    (SB3 zips, ``.pkl``)."""
    return not is_policy_file(path)


def require_trust(path: str | Path, trust_pickle: bool, what: str = "load") -> None:
    """Raise :class:`UntrustedPolicyError` if ``path`` is pickle-based and ``trust_pickle`` is False (before anything
    reads it)."""
    if trust_pickle or not is_pickle_based(path):
        return
    raise UntrustedPolicyError(
        f"refusing to {what} {path} without --trust-pickle: it is not a policy file of the project's format "
        f"(NAME{POLICY_SUFFIX}), so it would be unpickled as an SB3 zip (with the _vecnormalize.pkl beside it). "
        + CONVERT_HINT.format(source=path)
    )


def check_trust(spec: str | Path, which: str = "best", trust_pickle: bool = False) -> None:
    """Refuse a policy spec that would unpickle a file without ``trust_pickle`` (planners and policy files pass); run
    by the command lines before any environment is built."""
    if str(spec) in PLANNERS:
        return
    require_trust(model_path(spec, which), trust_pickle)


def algo_of_model(path: str | Path, *, trust_pickle: bool = False) -> str:
    """``"ppo"`` or ``"sac"``: which SB3 algorithm saved the ``.zip`` (from its policy class). Reading it unpickles
    the zip's data, so only with ``trust_pickle=True`` (:class:`UntrustedPolicyError` otherwise)."""
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.save_util import load_from_zip_file
    from stable_baselines3.sac.policies import SACPolicy

    require_trust(path, trust_pickle)
    data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    policy_class = (data or {}).get("policy_class")
    if isinstance(policy_class, type) and issubclass(policy_class, SACPolicy):
        return "sac"
    if isinstance(policy_class, type) and issubclass(policy_class, ActorCriticPolicy):
        return "ppo"
    raise ValueError(f"{path}: not a PPO or SAC model saved by Stable-Baselines3 (policy class {policy_class!r})")


def load_sb3(path: str | Path, algo: str | None = None, *, trust_pickle: bool = False) -> SB3Policy:
    """Load an SB3 ``.zip`` (PPO or SAC, detected unless given) on the CPU, with ``<stem>_vecnormalize.pkl``
    beside it if present: both are unpickled, so only with ``trust_pickle=True`` (:class:`UntrustedPolicyError`
    otherwise, before either file is read)."""
    from stable_baselines3 import PPO, SAC

    path = Path(path)
    require_trust(path, trust_pickle)
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path}")
    algo = algo or algo_of_model(path, trust_pickle=True)
    cls = {"ppo": PPO, "sac": SAC}[algo]
    model = cls.load(path, device="cpu")
    vecnormalize = None
    stats = vecnormalize_path(path)
    if stats.is_file():
        with open(stats, "rb") as fh:
            vecnormalize = pickle.load(fh)
        vecnormalize.training = False
        vecnormalize.norm_reward = False
    return SB3Policy(model, vecnormalize, str(path))


def vecnormalize_path(model_file: str | Path) -> Path:
    """``<stem>_vecnormalize.pkl`` beside an SB3 model file."""
    model_file = Path(model_file)
    return model_file.with_name(f"{model_file.stem}_vecnormalize.pkl")


def config_of(spec: str | Path) -> Path | None:
    """The training config that goes with a policy spec: a run folder's ``config.yaml``, the policy file itself (it
    holds its training config), for an SB3 model file ``<stem>.yaml`` beside it (as older exports wrote) or its
    folder's ``config.yaml``; None for planners and bare models."""
    p = Path(spec)
    if str(spec) in PLANNERS:
        return None
    if is_policy_file(p):
        return p if p.is_file() else None
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
    if is_policy_file(path):
        return dict(read_training_config(path)[PROJECT_KEY])
    section = load_yaml(path).get(PROJECT_KEY)
    if not isinstance(section, dict):
        raise ConfigError(f"{path} has no {PROJECT_KEY!r} section: not a config written by agents.train")
    return section


def export_policy(run_dir: str | Path, dest: str | Path, which: str = "best", trust_pickle: bool = False) -> Path:
    """Write a run's model (or a model file) as a policy file of the project's format: ``dest`` (``NAME.policy.yaml``)
    and ``NAME.pt`` beside it, to evaluate or ship alone.

    A run folder written by ``agent train`` holds the policy file beside each SB3 zip: it is validated and copied
    (nothing is unpickled). An SB3 zip (a run folder from before the format, or a model file with its training config
    as ``<stem>.yaml`` beside it) is converted: it and its ``<stem>_vecnormalize.pkl`` are unpickled, so only with
    ``trust_pickle=True``.

    Raises:
        UntrustedPolicyError: the source is an SB3 zip and ``trust_pickle`` is False (nothing was read).
        ValueError: ``dest`` is not named ``NAME.policy.yaml``.
    """
    src = model_path(run_dir, which)
    dest = Path(dest)
    weights_name = weights_file_name(dest)  # ValueError naming the expected form
    if is_policy_file(src):
        doc = read_policy_file(src)  # every field validated, the weights' sha256 checked
        if src.resolve() != dest.resolve():
            data = doc.weights_path.read_bytes()
            atomic_write(dest.with_name(weights_name), lambda fh: fh.write(data))
            atomic_write_text(dest, policy_yaml({**doc.raw, "weights": {**doc.raw["weights"], "file": weights_name}}))
        return dest
    require_trust(src, trust_pickle, what="convert")
    config = config_of(src)
    if config is None:
        raise FileNotFoundError(f"{run_dir} holds no config.yaml (nor {src.stem}.yaml): not a model of agents.train")
    settings = load_yaml(config)
    algo = (settings.get(PROJECT_KEY) or {}).get("algo") or algo_of_model(src, trust_pickle=True)
    policy = load_sb3(src, algo, trust_pickle=True)
    source = {"model": str(src), "model_sha256": _sha256(src), "training_config": str(config)}
    write_policy_file(dest, policy.model.policy, algo, settings, policy.vecnormalize, source)
    read_policy_file(dest)  # what was written loads
    return dest


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


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


def run_model(run_dir: str | Path, which: str = "best") -> Path | None:
    """The model file of a run folder: ``<which>_model.policy.yaml`` (the project's format, written by training
    beside the SB3 zip), else ``<which>_model.zip`` (a run from before the format); ``best`` falls back to ``final``
    when no validation ran. None when there is neither."""
    run = Path(run_dir)
    for name in dict.fromkeys((which, "final")):
        for candidate in (run / f"{name}_model{POLICY_SUFFIX}", run / f"{name}_model.zip"):
            if candidate.is_file():
                return candidate
    return None


def model_path(spec: str | Path, which: str = "best") -> Path:
    """The model file a spec names: the spec itself, or a run folder's (:func:`run_model`)."""
    if which not in RUN_MODELS:
        raise ValueError(f"unknown model {which!r}; valid: {', '.join(RUN_MODELS)}")
    p = Path(spec)
    if p.is_file():
        return p
    if p.is_dir():
        found = run_model(p, which)
        if found is None:
            raise FileNotFoundError(f"{p} holds neither {which}_model nor final_model (is the run finished?)")
        return found
    raise FileNotFoundError(
        f"no run folder, model file or planner named {str(spec)!r} (planners: {', '.join(PLANNERS)})"
    )


def load_policy(
    spec: str | Path,
    env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
    which: str = "best",
    planner_kwargs: Mapping[str, Any] | None = None,
    trust_pickle: bool = False,
) -> Any:
    """A policy with SB3's ``predict``: ``"planner"``/``"straight"`` (built for ``env_config``, with
    ``planner_kwargs``), a policy file (``NAME.policy.yaml``), a run folder (its best model, see :func:`model_path`),
    or an SB3 ``.zip``, which is unpickled and so needs ``trust_pickle=True``.

    Raises:
        UntrustedPolicyError: the spec is (or the run folder holds only) an SB3 zip and ``trust_pickle`` is False;
            nothing was read.
        agents.policy_file.PolicyFileError: a malformed policy file (naming the file and the key).
    """
    if str(spec) in PLANNERS:
        return make_planner(str(spec), env_config, **dict(planner_kwargs or {}))  # type: ignore[return-value]
    path = model_path(spec, which)
    require_trust(path, trust_pickle)
    settings = run_settings(path)
    if is_policy_file(path):
        policy: Any = read_policy_file(path).policy()
    else:
        policy = load_sb3(path, settings.get("algo"), trust_pickle=True)
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
