"""Dataclass configurations merged from YAML/mappings, rejecting unknown keys with the valid ones."""

from __future__ import annotations

import dataclasses
import difflib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Final, TypeVar

import yaml

T = TypeVar("T")

#: The checkout's ``configs/`` folder: the experiment YAMLs by kind (``agent``, ``ablation``, ``predictor``, ``env``).
CONFIGS_DIR: Final[Path] = Path(__file__).resolve().parent.parent / "configs"


class ConfigError(ValueError):
    """A configuration key or value is invalid; the message names it and lists what is valid."""


class UnknownKeyError(ConfigError, TypeError):
    """A key (a configuration entry, a keyword argument) that is not accepted at all.

    It is a :class:`ConfigError` (so a ``ValueError``) like every configuration error, and also a ``TypeError``: the
    error Python raises for an unexpected keyword argument. Libraries that probe a constructor with optional keywords
    (TorchRL's ``GymEnv`` passes ``frameskip=`` to ``gymnasium.make``, among others) take only a ``TypeError`` as
    "not supported" and retry without it. A wrong *value* of a known key stays a plain :class:`ConfigError`.

    Attributes:
        keys: the unknown keys, sorted.
    """

    def __init__(self, message: str, keys: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.keys = keys


def close_matches(word: str, valid: Iterable[str], n: int = 1) -> list[str]:
    """The ``n`` entries of ``valid`` closest to ``word`` (:func:`difflib.get_close_matches`, cutoff 0.6); empty when
    none is close."""
    return difflib.get_close_matches(str(word), [str(v) for v in valid], n=n)


def did_you_mean(word: str, valid: Iterable[str]) -> str:
    """``"did you mean 'x'?"`` naming the entry of ``valid`` closest to ``word``, or ``""`` when none is close."""
    match = close_matches(word, valid)
    return f"did you mean {match[0]!r}?" if match else ""


def check_keys(
    given: Mapping[str, Any], valid: list[str] | tuple[str, ...], where: str, *, keywords: bool = False
) -> None:
    """Raise :class:`UnknownKeyError` (a :class:`ConfigError` and a ``TypeError``) for any key of ``given`` not in
    ``valid``: the message leads with the closest valid key of each unknown one (``unknown env config key
    'num_pedestrian'; did you mean 'num_pedestrians'?``) and ends with every valid key.

    With ``keywords=True`` (the keys are a function's keyword arguments, as in ``gymnasium.make(id, **kwargs)``) the
    message then adds Python's own wording, ``unexpected keyword argument 'frameskip'``, which libraries probing a
    constructor look for in a ``TypeError``."""
    unknown = sorted(set(given) - set(valid), key=str)
    if not unknown:
        return
    valid_list = f"(valid keys: {', '.join(sorted(valid))})"
    if len(unknown) == 1:
        hint = did_you_mean(unknown[0], valid)
        message = f"unknown {where} key {unknown[0]!r}{'; ' + hint if hint else ''} {valid_list}"
    else:
        named = ", ".join(f"{key!r}" + (f" ({hint})" if (hint := did_you_mean(key, valid)) else "") for key in unknown)
        message = f"unknown {where} keys {named} {valid_list}"
    if keywords:
        message += "; " + ", ".join(f"unexpected keyword argument {key!r}" for key in unknown)
    raise UnknownKeyError(message, tuple(unknown))


def replace_checked(cfg: T, overrides: Mapping[str, Any] | None, where: str = "config") -> T:
    """``dataclasses.replace`` that rejects unknown keys and coerces simple types (tuples, floats)."""
    if not overrides:
        return cfg
    fields = {f.name: f for f in dataclasses.fields(cfg)}  # type: ignore[arg-type]
    check_keys(overrides, list(fields), where)
    clean: dict[str, Any] = {}
    for key, value in overrides.items():
        current = getattr(cfg, key)
        if isinstance(current, tuple) and isinstance(value, list | tuple):
            value = tuple(value)
        elif isinstance(current, bool) and not isinstance(value, bool):
            raise ConfigError(f"{where} key {key!r} must be true or false, got {value!r}")
        elif isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif (
            isinstance(current, int)
            and not isinstance(current, bool)
            and isinstance(value, float)
            and value.is_integer()
        ):
            value = int(value)
        clean[key] = value
    return dataclasses.replace(cfg, **clean)  # type: ignore[type-var]


def load_yaml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a YAML mapping with ``yaml.safe_load``; an empty file is an empty mapping."""
    path = Path(path)
    with open(path, encoding="utf-8") as fh:
        data = yaml.safe_load(fh)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it, else as it is."""
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def existing_config(path: str | os.PathLike[str], kind: str) -> Path:
    """``path`` when it is a file; else :class:`FileNotFoundError` naming it, with the closest file name and every YAML
    under ``configs/<kind>/`` (:data:`CONFIGS_DIR`), so a mistyped ``--config`` is answered before anything heavy is
    imported: ``no agent config configs/agent/ppo_scorin.yaml; did you mean configs/agent/ppo_scoring.yaml? (configs
    in configs/agent: ppo.yaml, ppo_scoring.yaml, ...)``."""
    given = Path(path)
    if given.is_file():
        return given
    folder = CONFIGS_DIR / kind
    shipped = sorted(folder.glob("*.yaml")) if folder.is_dir() else []
    message = f"no {kind} config {path}" + (" (a folder)" if given.is_dir() else "")
    if shipped:
        close = close_matches(given.stem, [s.stem for s in shipped])  # stems: every name ends in .yaml
        if close:
            message += f"; did you mean {_shown(folder / (close[0] + '.yaml'))}?"
        message += f" (configs in {_shown(folder)}: {', '.join(s.name for s in shipped)})"
    raise FileNotFoundError(message)
