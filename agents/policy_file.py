"""The project's policy format: a trained policy as data, loaded without unpickling anything.

A policy is two files side by side: ``NAME.policy.yaml`` (plain YAML, read with ``yaml.safe_load``) and
``NAME.pt`` (the policy network's tensors, read with ``torch.load(weights_only=True)``, which refuses anything
but tensors and plain containers). The YAML says everything needed to rebuild the policy with this project's own
code:

- ``format``/``format_version``: :data:`FORMAT`, :data:`FORMAT_VERSION`;
- ``algo``: ``ppo`` or ``sac``;
- ``policy``: the policy class, a name of the allow-list :data:`POLICY_CLASSES` (never an import path: a name
  not in the list is refused, nothing is imported because a file says so);
- ``policy_kwargs``: the constructor's keyword arguments as plain data (``net_arch``, ``activation_fn`` by name
  from :data:`agents.extractors.ACTIVATIONS`, ``features_extractor_class`` by name from :data:`EXTRACTORS` with its
  ``features_extractor_kwargs``, the scoring policy's ``head_kwargs``, ...), only the keys of :data:`POLICY_KWARGS`;
- ``observation_space``/``action_space``: descriptions (type, shape, dtype, bounds); at loading both are rebuilt
  from the training config's environment settings by :mod:`envs.observation` and must equal the description;
- ``normalization``: ``null``, or the ``VecNormalize`` observation statistics as numbers (``keys``, ``clip_obs``,
  ``epsilon``, ``gamma``, and per key ``mean``, ``var``, ``count``), applied by :class:`ObservationNormalizer`;
- ``weights``: ``file`` (``NAME.pt``, a bare file name beside the YAML) and its ``sha256``;
- ``training_config``: the run's resolved training config (``config.yaml`` of :mod:`agents.training.run`, whose
  ``crowdnav_mesrnn`` section gives the environment settings, the forecast arm and the action set);
- ``code_version`` (of the code that wrote the file), ``source`` (where the policy came from: run folder, model,
  steps) and ``library_versions`` (informational).

:func:`read_policy_file` validates every field (a :class:`PolicyFileError` names the file and the key), checks the
weights' sha256, loads them and rebuilds the policy; :meth:`PolicyDocument.policy` gives an inference-only
:class:`agents.rollout.SB3Policy` (the SB3 policy network with SB3's ``predict``). :func:`write_policy_file` writes
the format from a live SB3 policy; training writes it beside every model (:mod:`agents.training.callbacks`), and
``crowdnav-mesrnn agent export`` copies it (:func:`agents.runs.export_policy`).
"""

from __future__ import annotations

import hashlib
import inspect
import io
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
import yaml
from gymnasium import spaces

from crowdnav_mesrnn.config import ConfigError, check_keys

#: The ``format`` value of a policy file.
FORMAT: Final[str] = "crowdnav-mesrnn-policy"
#: The version this code writes and reads.
FORMAT_VERSION: Final[int] = 1
#: How a policy file's name ends; its weights are ``NAME.pt`` beside ``NAME.policy.yaml``.
POLICY_SUFFIX: Final[str] = ".policy.yaml"
#: How the weights file's name ends.
WEIGHTS_SUFFIX: Final[str] = ".pt"
#: Top-level keys: required, then optional.
REQUIRED_KEYS: Final[tuple[str, ...]] = (
    "format",
    "format_version",
    "algo",
    "policy",
    "policy_kwargs",
    "observation_space",
    "action_space",
    "normalization",
    "weights",
    "training_config",
    "code_version",
)
OPTIONAL_KEYS: Final[tuple[str, ...]] = ("source", "library_versions")
#: Top-level key of the project's settings inside ``training_config`` (:data:`agents.runs.PROJECT_KEY`).
_PROJECT_KEY: Final[str] = "crowdnav_mesrnn"
#: dtypes a space description may name.
DTYPES: Final[tuple[str, ...]] = ("float32", "float64", "int8", "int16", "int32", "int64", "uint8")


def _ppo_policies() -> dict[str, Any]:
    from stable_baselines3.common.policies import ActorCriticPolicy, MultiInputActorCriticPolicy

    from agents.extractors import CrowdActorCriticPolicy
    from agents.scoring import ActionScoringPolicy

    return {
        "MlpPolicy": ActorCriticPolicy,
        "MultiInputPolicy": MultiInputActorCriticPolicy,
        "agents.extractors.CrowdActorCriticPolicy": CrowdActorCriticPolicy,
        "agents.scoring.ActionScoringPolicy": ActionScoringPolicy,
    }


def _sac_policies() -> dict[str, Any]:
    from stable_baselines3.sac.policies import MultiInputPolicy, SACPolicy

    from agents.extractors import CrowdSACPolicy

    return {
        "MlpPolicy": SACPolicy,
        "MultiInputPolicy": MultiInputPolicy,
        "agents.extractors.CrowdSACPolicy": CrowdSACPolicy,
    }


def _extractors() -> dict[str, Any]:
    from stable_baselines3.common.torch_layers import CombinedExtractor, FlattenExtractor

    from agents.extractors import CrowdFeaturesExtractor
    from agents.scoring import ActionRolloutExtractor

    return {
        "CombinedExtractor": CombinedExtractor,
        "FlattenExtractor": FlattenExtractor,
        "agents.extractors.CrowdFeaturesExtractor": CrowdFeaturesExtractor,
        "agents.scoring.ActionRolloutExtractor": ActionRolloutExtractor,
    }


#: The allow-list of policy classes per algorithm, by name (SB3's aliases and the project's classes as its training
#: configs name them); the classes are looked up in this table, never imported by a name a file gives.
POLICY_CLASSES: Final[dict[str, Callable[[], dict[str, Any]]]] = {"ppo": _ppo_policies, "sac": _sac_policies}
#: The allow-list of features extractor classes, by name.
EXTRACTORS: Final[Callable[[], dict[str, Any]]] = _extractors
#: ``policy_kwargs`` keys a policy file may hold, per algorithm (``head_kwargs``: the action-scoring policy only).
POLICY_KWARGS: Final[dict[str, tuple[str, ...]]] = {
    "ppo": (
        "net_arch",
        "activation_fn",
        "ortho_init",
        "use_sde",
        "log_std_init",
        "full_std",
        "use_expln",
        "squash_output",
        "features_extractor_class",
        "features_extractor_kwargs",
        "share_features_extractor",
        "normalize_images",
        "head_kwargs",
    ),
    "sac": (
        "net_arch",
        "activation_fn",
        "use_sde",
        "log_std_init",
        "use_expln",
        "clip_mean",
        "n_critics",
        "features_extractor_class",
        "features_extractor_kwargs",
        "share_features_extractor",
        "normalize_images",
    ),
}
_BOOL_KWARGS: Final[tuple[str, ...]] = ("ortho_init", "use_sde", "share_features_extractor", "normalize_images")
#: PPO's are None unless ``use_sde`` (as SB3 itself saves them).
_OPTIONAL_BOOL_KWARGS: Final[tuple[str, ...]] = ("full_std", "squash_output", "use_expln")
_FLOAT_KWARGS: Final[tuple[str, ...]] = ("log_std_init", "clip_mean")


class PolicyFileError(ConfigError):
    """A policy file is malformed or cannot be written; the message names the file and the key."""

    def __init__(self, path: str | Path, key: str, message: str) -> None:
        super().__init__(f"{path}: {key}: {message}")
        self.path = str(path)
        self.key = key


def policy_file_path(path: str | Path) -> Path:
    """``NAME.policy.yaml`` for a model file ``NAME.zip`` (or any ``NAME.<ext>``); a policy file's path unchanged."""
    path = Path(path)
    if path.name.endswith(POLICY_SUFFIX):
        return path
    return path.with_name(path.stem + POLICY_SUFFIX)


def is_policy_file(path: str | Path) -> bool:
    """Whether ``path`` names a file of this format (by its name; the content is checked when it is read)."""
    return Path(path).name.endswith(POLICY_SUFFIX)


def weights_file_name(path: str | Path) -> str:
    """``NAME.pt`` for ``NAME.policy.yaml``."""
    name = Path(path).name
    if not name.endswith(POLICY_SUFFIX) or name == POLICY_SUFFIX:
        raise ValueError(f"a policy file is named NAME{POLICY_SUFFIX}, got {path}")
    return name[: -len(POLICY_SUFFIX)] + WEIGHTS_SUFFIX


# ---------------------------------------------------------------------------------------------------------- spaces


def describe_space(space: spaces.Space[Any]) -> dict[str, Any]:
    """A plain-data description of a ``Box``, ``Discrete`` or ``MultiBinary`` space (bounds as one number when
    uniform, else nested lists; float32 values are written exactly)."""
    if isinstance(space, spaces.Box):
        return {
            "type": "Box",
            "shape": [int(n) for n in space.shape],
            "dtype": str(space.dtype),
            "low": _bound(space.low),
            "high": _bound(space.high),
        }
    if isinstance(space, spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, spaces.MultiBinary):
        n = space.n
        return {"type": "MultiBinary", "n": int(n) if np.ndim(n) == 0 else [int(x) for x in np.ravel(n)]}
    raise TypeError(f"cannot describe a {type(space).__name__} space")


def _bound(values: np.ndarray) -> Any:
    flat = np.ravel(values)
    if flat.size and np.all(flat == flat[0]):
        return float(flat[0])
    return np.asarray(values, dtype=np.float64).tolist()


def describe_observation_space(space: spaces.Space[Any]) -> dict[str, Any]:
    """``{key: description}`` of a ``Dict`` observation space (the only kind the environment gives)."""
    if not isinstance(space, spaces.Dict):
        raise TypeError(f"the project's policies observe a Dict space, got {type(space).__name__}")
    return {str(key): describe_space(sub) for key, sub in space.spaces.items()}


def space_from_description(desc: Any, path: str | Path, key: str) -> spaces.Space[Any]:
    """The space a description gives; :class:`PolicyFileError` naming ``key`` when it is malformed."""
    if not isinstance(desc, Mapping):
        raise PolicyFileError(path, key, f"a space description must be a mapping, got {desc!r}")
    kind = desc.get("type")
    fields = {
        "Box": ("type", "shape", "dtype", "low", "high"),
        "Discrete": ("type", "n", "start"),
        "MultiBinary": ("type", "n"),
    }
    if kind not in fields:
        raise PolicyFileError(path, f"{key}.type", f"unknown space type {kind!r}; valid: {', '.join(fields)}")
    _check_keys(desc, fields[kind], fields[kind], path, key)
    if kind == "Discrete":
        n, start = _integer(desc["n"], path, f"{key}.n", 1), _integer(desc["start"], path, f"{key}.start")
        return spaces.Discrete(n, start=start)
    if kind == "MultiBinary":
        n = desc["n"]
        if isinstance(n, list):
            return spaces.MultiBinary([_integer(x, path, f"{key}.n", 1) for x in n])
        return spaces.MultiBinary(_integer(n, path, f"{key}.n", 1))
    shape = desc["shape"]
    if not isinstance(shape, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape):
        raise PolicyFileError(path, f"{key}.shape", f"must be a list of positive integers, got {shape!r}")
    if desc["dtype"] not in DTYPES:
        raise PolicyFileError(path, f"{key}.dtype", f"must be one of {', '.join(DTYPES)}, got {desc['dtype']!r}")
    bounds = []
    dtype = np.dtype(desc["dtype"])
    for side in ("low", "high"):
        value = _numbers(desc[side], path, f"{key}.{side}", allow_inf=True)
        try:
            bounds.append(np.broadcast_to(value, tuple(shape)).astype(dtype))
        except ValueError:
            raise PolicyFileError(
                path, f"{key}.{side}", f"shape {value.shape} does not fit the space's shape {tuple(shape)}"
            ) from None
    if np.any(bounds[0] > bounds[1]):
        raise PolicyFileError(path, f"{key}.low", "exceeds high")
    return spaces.Box(bounds[0], bounds[1], shape=tuple(shape), dtype=dtype)


def expected_spaces(training_config: Mapping[str, Any], path: str | Path) -> tuple[spaces.Dict, spaces.Space[Any]]:
    """The observation and action spaces of the environment a training config describes, built by the project's own
    code (:func:`envs.observation.observation_space`, :func:`agents.actions.action_set`)."""
    from agents.actions import action_set
    from envs.config import config_from
    from envs.observation import observation_space

    project = _project_section(training_config, path)
    env = {**dict(project.get("env") or {}), **dict(project.get("train_env") or {})}
    predictor = project["run"]["predictor"]
    try:
        cfg = config_from(env, {})
        actions = action_set(project.get("action"), cfg)
    except ValueError as exc:
        raise PolicyFileError(path, f"training_config.{_PROJECT_KEY}.env", str(exc)) from None
    obs = observation_space(cfg, with_forecasts=predictor != "none")
    act = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32) if actions is None else spaces.Discrete(actions.n)
    return obs, act  # the continuous action: CrowdNavEnv's velocity box


def _check_spaces(
    doc: Mapping[str, Any], training_config: Mapping[str, Any], path: str | Path
) -> tuple[spaces.Dict, spaces.Space[Any]]:
    stored_obs = doc["observation_space"]
    if not isinstance(stored_obs, Mapping) or not stored_obs:
        raise PolicyFileError(path, "observation_space", "must be a mapping of observation keys to space descriptions")
    stored = {
        str(k): describe_space(space_from_description(v, path, f"observation_space.{k}")) for k, v in stored_obs.items()
    }
    stored_act = describe_space(space_from_description(doc["action_space"], path, "action_space"))
    obs, act = expected_spaces(training_config, path)
    rebuilt = describe_observation_space(obs)
    for key in sorted(set(stored) | set(rebuilt)):
        if stored.get(key) != rebuilt.get(key):
            raise PolicyFileError(
                path,
                f"observation_space.{key}",
                f"the file describes {stored.get(key)!r} but the training config's environment settings give "
                f"{rebuilt.get(key)!r}",
            )
    if stored_act != describe_space(act):
        raise PolicyFileError(
            path,
            "action_space",
            f"the file describes {stored_act!r} but the training config gives {describe_space(act)!r}",
        )
    return obs, act


# --------------------------------------------------------------------------------------------------- normalisation


@dataclass(frozen=True)
class ObservationNormalizer:
    """SB3 ``VecNormalize``'s observation normalisation from its statistics as plain numbers:
    ``clip((obs - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)`` as float32, for each key of ``keys`` (the
    others unchanged) — the same operations as ``VecNormalize.normalize_obs``, so the results are identical."""

    keys: tuple[str, ...]
    mean: Mapping[str, np.ndarray]
    var: Mapping[str, np.ndarray]
    count: Mapping[str, float]
    clip_obs: float
    epsilon: float
    gamma: float

    def normalize_obs(self, obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = {k: np.array(v, copy=True) for k, v in obs.items()}
        for key in self.keys:
            scaled = (obs[key] - self.mean[key]) / np.sqrt(self.var[key] + self.epsilon)
            out[key] = np.clip(scaled, -self.clip_obs, self.clip_obs).astype(np.float32)
        return out

    @classmethod
    def from_vecnormalize(cls, vn: Any) -> ObservationNormalizer | None:
        """The statistics of a live ``VecNormalize`` (None when it does not normalise observations)."""
        if not getattr(vn, "norm_obs", False):
            return None
        if not isinstance(vn.obs_rms, dict):
            raise TypeError("the project's policies observe a Dict space; VecNormalize holds one statistic")
        keys = tuple(vn.norm_obs_keys)
        return cls(
            keys=keys,
            mean={k: np.asarray(vn.obs_rms[k].mean, dtype=np.float64) for k in keys},
            var={k: np.asarray(vn.obs_rms[k].var, dtype=np.float64) for k in keys},
            count={k: float(vn.obs_rms[k].count) for k in keys},
            clip_obs=float(vn.clip_obs),
            epsilon=float(vn.epsilon),
            gamma=float(vn.gamma),
        )

    def describe(self) -> dict[str, Any]:
        """The ``normalization`` section of a policy file."""
        return {
            "keys": list(self.keys),
            "clip_obs": self.clip_obs,
            "epsilon": self.epsilon,
            "gamma": self.gamma,
            "statistics": {
                k: {"mean": self.mean[k].tolist(), "var": self.var[k].tolist(), "count": self.count[k]}
                for k in self.keys
            },
        }


def _normalizer(desc: Any, obs_space: spaces.Dict, path: str | Path) -> ObservationNormalizer | None:
    if desc is None:
        return None
    key = "normalization"
    if not isinstance(desc, Mapping):
        raise PolicyFileError(path, key, f"must be null or a mapping, got {desc!r}")
    fields = ("keys", "clip_obs", "epsilon", "gamma", "statistics")
    _check_keys(desc, fields, fields, path, key)
    keys = desc["keys"]
    if (
        not isinstance(keys, list)
        or not keys
        or not all(isinstance(k, str) for k in keys)
        or len(set(keys)) < len(keys)
    ):
        raise PolicyFileError(
            path, f"{key}.keys", f"must be a non-empty list of distinct observation keys, got {keys!r}"
        )
    for k in keys:
        if not isinstance(obs_space.spaces.get(k), spaces.Box):
            raise PolicyFileError(path, f"{key}.keys", f"{k!r} is not a Box key of the observation space")
    clip_obs = _number(desc["clip_obs"], path, f"{key}.clip_obs", positive=True)
    epsilon = _number(desc["epsilon"], path, f"{key}.epsilon", positive=True)
    gamma = _number(desc["gamma"], path, f"{key}.gamma")
    if not 0.0 <= gamma <= 1.0:
        raise PolicyFileError(path, f"{key}.gamma", f"must lie in [0, 1], got {gamma!r}")
    stats = desc["statistics"]
    if not isinstance(stats, Mapping):
        raise PolicyFileError(path, f"{key}.statistics", "must be a mapping of the keys to their statistics")
    _check_keys(stats, keys, keys, path, f"{key}.statistics")
    mean, var, count = {}, {}, {}
    for k in keys:
        where = f"{key}.statistics.{k}"
        if not isinstance(stats[k], Mapping):
            raise PolicyFileError(path, where, "must be a mapping with mean, var and count")
        _check_keys(stats[k], ("mean", "var", "count"), ("mean", "var", "count"), path, where)
        shape = obs_space.spaces[k].shape
        for name, out in (("mean", mean), ("var", var)):
            value = _numbers(stats[k][name], path, f"{where}.{name}")
            if value.shape != shape:
                raise PolicyFileError(
                    path, f"{where}.{name}", f"shape {value.shape} differs from the observation's {shape}"
                )
            out[k] = value
        if np.any(var[k] < 0):
            raise PolicyFileError(path, f"{where}.var", "variances must be >= 0")
        count[k] = _number(stats[k]["count"], path, f"{where}.count", positive=True)
    return ObservationNormalizer(tuple(keys), mean, var, count, clip_obs, epsilon, gamma)


# ---------------------------------------------------------------------------------------------- policy arguments


def _class_name(cls: Any, table: Mapping[str, Any], path: str | Path, key: str) -> str:
    for name, known in table.items():
        if cls is known:
            return name
    raise PolicyFileError(
        path, key, f"{getattr(cls, '__qualname__', cls)!r} is not in the allow-list ({', '.join(table)})"
    )


def describe_policy_kwargs(policy: Any, algo: str, path: str | Path) -> dict[str, Any]:
    """The ``policy_kwargs`` of a policy file from a live SB3 policy (SB3's own constructor parameters, classes by
    allow-listed name; the optimizer and the learning-rate schedule are left out: they do not act)."""
    from agents.extractors import ACTIVATIONS

    params = dict(policy._get_constructor_parameters())
    params["share_features_extractor"] = bool(getattr(policy, "share_features_extractor", False))
    if hasattr(policy, "head_kwargs"):  # the action-scoring policy
        params["head_kwargs"] = dict(policy.head_kwargs)
    out: dict[str, Any] = {}
    for key in POLICY_KWARGS[algo]:
        if key not in params:
            continue
        value = params[key]
        if key == "activation_fn":
            value = _class_name(value, ACTIVATIONS, path, f"policy_kwargs.{key}")
        elif key == "features_extractor_class":
            value = _class_name(value, EXTRACTORS(), path, f"policy_kwargs.{key}")
        out[key] = _plain(value, path, f"policy_kwargs.{key}")
    return out


def _policy_kwargs(kwargs: Any, algo: str, policy_name: str, path: str | Path) -> dict[str, Any]:
    """Validated ``policy_kwargs`` with classes resolved from the allow-lists."""
    from agents.extractors import ACTIVATIONS
    from agents.scoring import ActionScoringHead

    key = "policy_kwargs"
    if not isinstance(kwargs, Mapping):
        raise PolicyFileError(path, key, f"must be a mapping, got {kwargs!r}")
    valid = [
        k for k in POLICY_KWARGS[algo] if k != "head_kwargs" or policy_name == "agents.scoring.ActionScoringPolicy"
    ]
    _check_keys(kwargs, valid, (), path, key)
    out: dict[str, Any] = {}
    for name, value in kwargs.items():
        where = f"{key}.{name}"
        if name in _BOOL_KWARGS or (name in _OPTIONAL_BOOL_KWARGS and value is not None):
            if not isinstance(value, bool):
                raise PolicyFileError(path, where, f"must be true or false, got {value!r}")
        elif name in _FLOAT_KWARGS:
            value = _number(value, path, where)
        elif name == "n_critics":
            value = _integer(value, path, where, 1)
        elif name == "net_arch":
            value = _net_arch(value, algo, path, where)
        elif name == "activation_fn":
            if value not in ACTIVATIONS:
                raise PolicyFileError(path, where, f"unknown activation {value!r}; valid: {', '.join(ACTIVATIONS)}")
            value = ACTIVATIONS[value]
        elif name == "features_extractor_class":
            table = EXTRACTORS()
            if value not in table:
                raise PolicyFileError(path, where, f"{value!r} is not in the allow-list ({', '.join(table)})")
            value = table[value]
        elif name in ("features_extractor_kwargs", "head_kwargs"):
            if not isinstance(value, Mapping):
                raise PolicyFileError(path, where, f"must be a mapping, got {value!r}")
            value = _plain(dict(value), path, where)
        out[name] = value
    extractor = out.get("features_extractor_class") or _default_extractor(policy_name)
    _check_signature(
        out.get("features_extractor_kwargs") or {},
        extractor,
        ("self", "observation_space"),
        path,
        f"{key}.features_extractor_kwargs",
    )
    _check_signature(
        out.get("head_kwargs") or {},
        ActionScoringHead,
        ("self", "num_actions", "num_features", "context_dim"),
        path,
        f"{key}.head_kwargs",
    )
    return out


def _default_extractor(policy_name: str) -> Any:
    table = EXTRACTORS()
    if policy_name.startswith("agents.scoring."):
        return table["agents.scoring.ActionRolloutExtractor"]
    if policy_name.startswith("agents.extractors."):
        return table["agents.extractors.CrowdFeaturesExtractor"]
    return table["CombinedExtractor"] if policy_name == "MultiInputPolicy" else table["FlattenExtractor"]


def _check_signature(kwargs: Mapping[str, Any], cls: Any, fixed: tuple[str, ...], path: str | Path, key: str) -> None:
    params = [p for p in inspect.signature(cls.__init__).parameters if p not in fixed]
    _check_keys(kwargs, params, (), path, key)


def _net_arch(value: Any, algo: str, path: str | Path, key: str) -> Any:
    def layers(v: Any, where: str) -> list[int]:
        if not isinstance(v, list):
            raise PolicyFileError(path, where, f"must be a list of layer widths, got {v!r}")
        return [_integer(n, path, where, 1) for n in v]

    if value is None or isinstance(value, list):
        return None if value is None else layers(value, key)
    if isinstance(value, Mapping):
        heads = ("pi", "vf") if algo == "ppo" else ("pi", "qf")
        _check_keys(value, heads, (), path, key)
        return {k: layers(v, f"{key}.{k}") for k, v in value.items()}
    raise PolicyFileError(path, key, f"must be a list of widths or a mapping of them, got {value!r}")


# -------------------------------------------------------------------------------------------------- the document


@dataclass
class PolicyDocument:
    """A validated policy file: the rebuilt SB3 policy network and what goes with it."""

    path: Path
    """The ``.policy.yaml``."""
    algo: str
    policy_name: str
    network: Any
    """The SB3 policy (``torch.nn.Module`` with SB3's ``predict``), weights loaded, in evaluation mode."""
    normalizer: ObservationNormalizer | None
    training_config: dict[str, Any]
    weights_path: Path
    raw: dict[str, Any]
    """The YAML document as read."""

    def policy(self) -> Any:
        """The inference-only policy: :class:`agents.rollout.SB3Policy` around the network and its normaliser."""
        from agents.rollout import SB3Policy

        return SB3Policy(self.network, self.normalizer, str(self.path))

    @property
    def settings(self) -> dict[str, Any]:
        """The ``crowdnav_mesrnn`` section of the training config (``algo``, ``env``, ``action``, ``run``, ...)."""
        return dict(self.training_config[_PROJECT_KEY])


def read_training_config(path: str | Path) -> dict[str, Any]:
    """The training config held by a policy file, its project section checked (no weights are read): what
    :func:`agents.runs.run_settings` needs before a policy is loaded."""
    doc = _read_yaml(path)
    if "training_config" not in doc:
        raise PolicyFileError(path, "training_config", "missing")
    config = doc["training_config"]
    _project_section(config, path)
    return dict(config)


def read_policy_file(path: str | Path) -> PolicyDocument:
    """Read, validate and rebuild a policy file (nothing is unpickled).

    Raises:
        PolicyFileError: naming the file and the key: an unknown or missing key, a class name outside the
            allow-lists, a space that differs from the one the training config's environment gives, statistics of
            the wrong shape or not finite, a weights file that is missing, not a bare name beside the YAML, of
            another sha256, not a mapping of tensors, or whose tensors differ in names, shapes or dtypes from the
            rebuilt policy's, or are not finite.
    """
    import torch

    path = Path(path)
    doc = _read_yaml(path)
    _check_keys(doc, (*REQUIRED_KEYS, *OPTIONAL_KEYS), REQUIRED_KEYS, path, "top level")
    if doc["format"] != FORMAT:
        raise PolicyFileError(path, "format", f"must be {FORMAT!r}, got {doc['format']!r}")
    if doc["format_version"] != FORMAT_VERSION:
        raise PolicyFileError(
            path, "format_version", f"this code reads version {FORMAT_VERSION}, got {doc['format_version']!r}"
        )
    algo = doc["algo"]
    if algo not in POLICY_CLASSES:
        raise PolicyFileError(path, "algo", f"must be one of {', '.join(POLICY_CLASSES)}, got {algo!r}")
    classes = POLICY_CLASSES[algo]()
    name = doc["policy"]
    if not isinstance(name, str) or name not in classes:
        raise PolicyFileError(
            path, "policy", f"{name!r} is not in the allow-list of {algo} policies ({', '.join(classes)})"
        )
    for key in ("code_version",):
        if not isinstance(doc[key], str):
            raise PolicyFileError(path, key, f"must be a string, got {doc[key]!r}")
    for key in OPTIONAL_KEYS:
        if key in doc:
            _plain(doc[key], path, key)
    training_config = doc["training_config"]
    project = _project_section(training_config, path)
    if project.get("algo") != algo:
        raise PolicyFileError(
            path, f"training_config.{_PROJECT_KEY}.algo", f"{project.get('algo')!r} differs from algo {algo!r}"
        )
    kwargs = _policy_kwargs(doc["policy_kwargs"], algo, name, path)
    obs_space, act_space = _check_spaces(doc, training_config, path)
    normalizer = _normalizer(doc["normalization"], obs_space, path)
    weights_path, state = _read_weights(doc["weights"], path)
    try:
        network = classes[name](obs_space, act_space, lr_schedule=lambda _: 0.0, **kwargs)
    except (TypeError, ValueError, AssertionError) as exc:
        raise PolicyFileError(path, "policy_kwargs", f"{name} cannot be built from them: {exc}") from None
    expected = network.state_dict()
    for key in sorted(set(expected) | set(state)):
        where = f"weights[{key!r}] ({weights_path.name})"
        if key not in state:
            raise PolicyFileError(path, where, "missing: the rebuilt policy has this tensor")
        if key not in expected:
            raise PolicyFileError(path, where, "unexpected: the rebuilt policy has no such tensor")
        got, want = state[key], expected[key]
        if tuple(got.shape) != tuple(want.shape) or got.dtype != want.dtype:
            raise PolicyFileError(
                path, where, f"{got.dtype} {tuple(got.shape)} but the policy needs {want.dtype} {tuple(want.shape)}"
            )
        if got.is_floating_point() and not bool(torch.isfinite(got).all()):
            raise PolicyFileError(path, where, "holds values that are not finite")
    network.load_state_dict(state, strict=True)
    network.set_training_mode(False)
    return PolicyDocument(path, algo, name, network, normalizer, dict(training_config), weights_path, doc)


def _read_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no policy file {path}")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise PolicyFileError(path, "top level", f"not valid YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise PolicyFileError(path, "top level", f"must be a mapping, got {type(doc).__name__}")
    return doc


def _project_section(config: Any, path: str | Path) -> Mapping[str, Any]:
    if not isinstance(config, Mapping):
        raise PolicyFileError(path, "training_config", "must be the run's training config (a mapping)")
    project = config.get(_PROJECT_KEY)
    where = f"training_config.{_PROJECT_KEY}"
    if not isinstance(project, Mapping):
        raise PolicyFileError(path, where, "missing: not a config written by agents.train")
    for key in ("env", "train_env", "action"):
        if project.get(key) is not None and not isinstance(project[key], Mapping):
            raise PolicyFileError(path, f"{where}.{key}", "must be a mapping")
    run = project.get("run")
    if not isinstance(run, Mapping) or not isinstance(run.get("predictor"), str):
        raise PolicyFileError(path, f"{where}.run.predictor", "missing: the forecast arm the policy was trained with")
    return project


def _read_weights(desc: Any, path: Path) -> tuple[Path, dict[str, Any]]:
    import torch

    key = "weights"
    if not isinstance(desc, Mapping):
        raise PolicyFileError(path, key, f"must be a mapping with file and sha256, got {desc!r}")
    _check_keys(desc, ("file", "sha256"), ("file", "sha256"), path, key)
    name, digest = desc["file"], desc["sha256"]
    if (
        not isinstance(name, str)
        or not name.endswith(WEIGHTS_SUFFIX)
        or name.startswith(".")
        or Path(name).name != name
        or "\\" in name
    ):
        raise PolicyFileError(path, f"{key}.file", f"must be a bare NAME{WEIGHTS_SUFFIX} beside the file, got {name!r}")
    if not isinstance(digest, str) or len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise PolicyFileError(path, f"{key}.sha256", f"must be 64 lowercase hex digits, got {digest!r}")
    weights = path.parent / name
    if not weights.is_file():
        raise PolicyFileError(path, f"{key}.file", f"{weights} does not exist")
    data = weights.read_bytes()
    actual = hashlib.sha256(data).hexdigest()
    if actual != digest:
        raise PolicyFileError(path, f"{key}.sha256", f"{weights} has sha256 {actual}, the file says {digest}")
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch's restricted unpickler refuses anything but tensors and plain containers
        raise PolicyFileError(path, f"{key}.file", f"{weights} is not a tensor file: {exc}") from None
    if not isinstance(state, Mapping) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise PolicyFileError(path, f"{key}.file", f"{weights} must hold a mapping of tensor names to tensors")
    return weights, dict(state)


def write_policy_file(
    dest: str | Path,
    policy: Any,
    algo: str,
    training_config: Mapping[str, Any],
    vecnormalize: Any = None,
    source: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``dest`` (``NAME.policy.yaml``) and ``NAME.pt`` from a live SB3 policy (``model.policy``).

    Args:
        dest: the policy file.
        policy: the SB3 policy network (its class in :data:`POLICY_CLASSES`).
        algo: ``ppo`` or ``sac``.
        training_config: the run's resolved training config (its ``config.yaml`` as data).
        vecnormalize: the ``VecNormalize`` the policy was trained behind, or None.
        source: where the policy comes from (plain data, informational).

    Returns:
        ``dest``. The weights are written first, so a reader never sees a YAML without its weights.

    Raises:
        PolicyFileError: the policy cannot be described (a class outside the allow-lists, arguments that are not
            plain data).
    """
    import stable_baselines3
    import torch

    from crowdnav_mesrnn.utils import atomic_write, atomic_write_text, code_version

    dest = Path(dest)
    weights_name = weights_file_name(dest)
    if algo not in POLICY_CLASSES:
        raise PolicyFileError(dest, "algo", f"must be one of {', '.join(POLICY_CLASSES)}, got {algo!r}")
    name = _class_name(type(policy), POLICY_CLASSES[algo](), dest, "policy")
    normalizer = None if vecnormalize is None else ObservationNormalizer.from_vecnormalize(vecnormalize)
    doc = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "algo": algo,
        "policy": name,
        "policy_kwargs": describe_policy_kwargs(policy, algo, dest),
        "observation_space": describe_observation_space(policy.observation_space),
        "action_space": describe_space(policy.action_space),
        "normalization": None if normalizer is None else normalizer.describe(),
        "weights": {"file": weights_name, "sha256": ""},
        "training_config": _plain(dict(training_config), dest, "training_config"),
        "code_version": code_version(),
        "source": _plain(dict(source or {}), dest, "source"),
        "library_versions": {"stable_baselines3": str(stable_baselines3.__version__), "torch": str(torch.__version__)},
    }
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu() for k, v in policy.state_dict().items()}, buf)
    data = buf.getvalue()
    doc["weights"]["sha256"] = hashlib.sha256(data).hexdigest()
    atomic_write(dest.with_name(weights_name), lambda fh: fh.write(data))
    atomic_write_text(dest, policy_yaml(doc))
    return dest


def policy_yaml(doc: Mapping[str, Any]) -> str:
    """The text of a policy file: a header saying what it is, then the document."""
    header = (
        f"# A crowdnav-mesrnn policy file (format {FORMAT_VERSION}): plain data. The weights are in "
        f"{doc['weights']['file']} beside it, read with torch.load(weights_only=True); the policy is rebuilt by the "
        "project's code (agents/policy_file.py).\n"
    )
    return header + yaml.safe_dump(dict(doc), sort_keys=False, default_flow_style=None, width=120)


# ------------------------------------------------------------------------------------------------------- helpers


def _check_keys(
    given: Mapping[str, Any],
    valid: tuple[str, ...] | list[str],
    required: tuple[str, ...] | list[str],
    path: str | Path,
    where: str,
) -> None:
    try:
        check_keys(given, list(valid), f"{where}")
    except ConfigError as exc:
        raise PolicyFileError(path, where, str(exc)) from None
    for key in required:
        if key not in given:
            raise PolicyFileError(path, f"{key}" if where == "top level" else f"{where}.{key}", "missing")


def _plain(value: Any, path: str | Path, key: str) -> Any:
    """``value`` as plain YAML data (numpy scalars and tuples converted); floats must be finite."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        if not math.isfinite(float(value)):
            raise PolicyFileError(path, key, f"must be finite, got {value!r}")
        return float(value)
    if isinstance(value, list | tuple):
        return [_plain(v, path, f"{key}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        if not all(isinstance(k, str) for k in value):
            raise PolicyFileError(path, key, "mapping keys must be strings")
        return {k: _plain(v, path, f"{key}.{k}") for k, v in value.items()}
    raise PolicyFileError(path, key, f"{type(value).__name__} is not plain data")


def _number(value: Any, path: str | Path, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PolicyFileError(path, key, f"must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise PolicyFileError(path, key, f"must be > 0, got {value!r}")
    return float(value)


def _integer(value: Any, path: str | Path, key: str, minimum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
        raise PolicyFileError(
            path, key, f"must be an integer{f' >= {minimum}' if minimum is not None else ''}, got {value!r}"
        )
    return value


def _numbers(value: Any, path: str | Path, key: str, allow_inf: bool = False) -> np.ndarray:
    """A number or (nested) list of numbers as a float64 array: rectangular, no NaN, infinities only if allowed."""

    def ok(x: Any) -> bool:
        if isinstance(x, list):
            return all(ok(v) for v in x)
        return isinstance(x, int | float) and not isinstance(x, bool)

    if not ok(value):
        raise PolicyFileError(path, key, "must be a number or a (nested) list of numbers")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except ValueError:
        raise PolicyFileError(path, key, "nested lists of unequal lengths") from None
    if np.isnan(arr).any() or (not allow_inf and not np.isfinite(arr).all()):
        raise PolicyFileError(path, key, "holds values that are not finite")
    return arr
