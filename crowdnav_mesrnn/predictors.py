"""The one registry of forecast source names and the one loader of predictors.

Every name the project accepts where a forecast source is chosen (``predictor=`` of the environment, an ablation
arm, ``forecasts build --predictor``, ``bench``) is known here and nowhere else; other modules ask:

- :func:`names` lists them (in the order shown to users: ``none``, ``cv``, ``cv_gaussian``, ``mesrnn``, ``srnn``,
  ``vlstm``, ``oracle``, ``noisy_oracle``, then the installed plug-ins);
- :func:`kind` says what a name is (:data:`KINDS`): no forecast, the replay's true future (with or without
  noise), a weightless shipped baseline, a shipped baseline with parameters fitted per leave-one-out split, shipped
  weights per leave-one-out split, or a plug-in;
- :func:`check` accepts a name or raises :class:`PluginError` listing the valid ones;
- :func:`load` returns a ready predictor, ``factory(split=SPLIT)`` of a registered name or an import path;
- :func:`check_forecast` accepts a forecast (numbers, the promised shape, finite where read) or raises
  :class:`ForecastError` naming the predictor, the recording and the frame: every forecast passes it where it enters
  the environment, the disk cache and ``bench``.

A name goes from here to its user and does not come back: the environment asks :func:`kind` which forecast source
to build and :func:`load` for the predictor of each split.

**The protocol** (:class:`crowdnav_mesrnn.models.Predictor`). A predictor is any object with

- ``name: str`` — shown in results;
- ``obs_len: int`` and ``pred_len: int`` — observed and predicted annotation steps (8 and 12 on ETH/UCY);
- ``forecast(history, mask) -> future``:

  - ``history``: ``(obs_len, N, 2)`` float32, metres, world frame, the last ``obs_len`` annotation steps of the
    ``N`` pedestrians seen in them, oldest first (values where ``mask`` is False are 0 and must be ignored);
  - ``mask``: ``(obs_len, N)`` bool, pedestrian ``n`` annotated at step ``t``;
  - returns ``(N, pred_len, 2)`` float metres at the next ``pred_len`` annotation steps. Rows of pedestrians
    absent at the last observed step are ignored (by convention they hold the last observed position).

  One step is one annotation of the recording (0.4 s; 0.667 s on ``biwi_eth``); the environment resamples
  forecasts onto its own time grid. Every pedestrian present in the window is passed together, so a social
  model can use the others as context.

Optional parts, looked up with ``getattr`` (a plug-in without them works):

- ``forecast_distribution(history, mask) -> (mean, cov)``: a Gaussian per pedestrian and step, ``mean``
  ``(N, pred_len, 2)`` metres and ``cov`` ``(N, pred_len, 2, 2)`` square metres
  (:class:`DistributionPredictor`); ``forecast`` should return ``mean``.
- ``online(num_slots)``: an incremental forecaster (``observe(positions (S, 2), present (S,))`` per annotation
  step, ``forecast() -> (S, pred_len, 2)``) for ``forecast_memory="carried"``.
- ``cache_fingerprint() -> str``: a digest of whatever determines the forecasts that the plug-in's files do not
  hold (weights downloaded to a user folder, a service's model version). The forecast cache keys a registered
  plug-in's forecasts on its identity (:meth:`PredictorSpec.identity`: name, import target, distribution name and
  version, and a digest of every file of the plug-in, :mod:`crowdnav_mesrnn.plugin_files`) plus this digest, or
  the hash of a torch ``net`` and ``norm`` when the predictor has them.

**Registration.** A package declares a factory under the entry-point group :data:`ENTRY_POINT_GROUP`::

    [project.entry-points."crowdnav_mesrnn.predictors"]
    kalman = "kalman_predictor:KalmanPredictor"

or any user passes an import path ``package.module:Factory`` where a predictor name is accepted. The factory is
called as ``factory(split=SPLIT)``: ``SPLIT`` is the leave-one-out split whose held-out scene will be forecast
(a learned plug-in returns weights trained without that scene; others ignore it), or None. The shipped models
register the same way (``pyproject.toml``); :data:`SHIPPED` is used for them when the package runs from a source
tree without installed metadata. The names in :data:`RESERVED` (``none``, ``oracle``, ``noisy_oracle``) are forecast
sources of the environment, not predictors: they cannot be registered and :func:`load` refuses them. An entry point
that breaks these rules (a reserved or shipped name, a name two distributions register) is skipped with a
:class:`PluginWarning` naming its distribution, and every other plug-in keeps working.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.metadata
import importlib.util
import json
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Protocol, runtime_checkable

import numpy as np

from crowdnav_mesrnn.config import ConfigError

if TYPE_CHECKING:
    from crowdnav_mesrnn.models.base import Predictor

#: Entry-point group predictors register under.
ENTRY_POINT_GROUP: Final[str] = "crowdnav_mesrnn.predictors"

# ---------------------------------------------------------------------------- names and kinds

#: Kind of ``none``: no forecasts in the observation.
NO_FORECAST: Final[str] = "none"
#: Kind of ``oracle``: the replay's true future (not a predictor).
TRUTH: Final[str] = "truth"
#: Kind of ``noisy_oracle``: the true future plus noise of a set expected ADE (not a predictor).
NOISY_TRUTH: Final[str] = "noisy_truth"
#: Kind of ``cv``: a shipped predictor without weights, the same for every split (loaded with ``split=None``).
BASELINE: Final[str] = "baseline"
#: Kind of ``cv_gaussian``: a shipped baseline without a network whose few parameters are fitted per leave-one-out
#: split (a small file per split); loaded per split like the pretrained, with a distribution.
FITTED_BASELINE: Final[str] = "fitted_baseline"
#: Kind of ``mesrnn``, ``srnn``, ``vlstm``: shipped weights per leave-one-out split.
PRETRAINED: Final[str] = "pretrained"
#: Kind of an installed plug-in or an import path ``package.module:Factory``: loaded per split like the pretrained.
PLUGIN: Final[str] = "plugin"
#: Every kind, in the order above.
KINDS: Final[tuple[str, ...]] = (NO_FORECAST, TRUTH, NOISY_TRUTH, BASELINE, FITTED_BASELINE, PRETRAINED, PLUGIN)
#: Kinds loaded per leave-one-out split (a recording is forecast by the predictor of the split holding it out); their
#: forecasts are what the shared disk cache keeps.
SPLIT_KINDS: Final[tuple[str, ...]] = (FITTED_BASELINE, PRETRAINED, PLUGIN)

#: The project's own names in the order shown to users: name -> (kind, factory or None for the non-predictors).
_BUILTIN: Final[dict[str, tuple[str, str | None]]] = {
    "none": (NO_FORECAST, None),
    "cv": (BASELINE, "crowdnav_mesrnn.predictors:constant_velocity"),
    "cv_gaussian": (FITTED_BASELINE, "crowdnav_mesrnn.predictors:cv_gaussian"),
    "mesrnn": (PRETRAINED, "crowdnav_mesrnn.predictors:mesrnn"),
    "srnn": (PRETRAINED, "crowdnav_mesrnn.predictors:srnn"),
    "vlstm": (PRETRAINED, "crowdnav_mesrnn.predictors:vlstm"),
    "oracle": (TRUTH, None),
    "noisy_oracle": (NOISY_TRUTH, None),
}

#: The shipped predictors: name -> factory (the same entries as in pyproject.toml).
SHIPPED: Final[dict[str, str]] = {name: target for name, (_, target) in _BUILTIN.items() if target is not None}

#: Forecast sources of the environment that are not predictors (never registrable names).
RESERVED: Final[tuple[str, ...]] = tuple(name for name, (_, target) in _BUILTIN.items() if target is None)


@runtime_checkable
class DistributionPredictor(Protocol):
    """The optional distribution part of the protocol: a Gaussian forecast per pedestrian and step."""

    def forecast_distribution(self, history: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(obs_len, N, 2)`` metres + ``(obs_len, N)`` mask -> ``mean (N, pred_len, 2)`` metres,
        ``cov (N, pred_len, 2, 2)`` square metres."""
        ...


class PluginError(ConfigError):
    """A predictor name or import path that cannot be resolved or loaded, or a plug-in breaking the protocol."""


class ForecastError(PluginError):
    """A predictor returned forecasts that cannot be used: not numbers, of the wrong shape, or not finite where they
    are read (:func:`check_forecast`)."""


def check_forecast(
    out: Any,
    *,
    name: str,
    expected_shape: tuple[int, ...],
    recording: str,
    frame: int | str | np.ndarray,
    time_s: float | np.ndarray | None = None,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """``out`` as an array once it is what the protocol promises: numbers of ``expected_shape`` (``(N, pred_len, 2)``
    for :meth:`forecast`), finite in every row that is read. The one check every forecast passes where it enters the
    project: the environment's sources (window and carried), the disk cache (no chunk is written otherwise) and
    ``bench``.

    Args:
        out: what the predictor returned.
        name: the predictor as the user chose it (a plug-in's registered name, a shipped name, an object's ``name``).
        expected_shape: the shape ``out`` must have.
        recording: what was forecast (a recording's name).
        frame: where in it: an annotation frame, a label (``"1230 (the window's first observed step)"``), or
            ``(N,)`` the frame of each row of a batch over several frames (the first bad row's frame is named).
        time_s: the time of ``frame`` in the recording, seconds (a scalar, or ``(N,)`` per row), if known.
        rows: the rows that are read, a boolean mask ``(N,)`` or indices (default: all). Only they must be finite:
            the protocol leaves the rows of pedestrians absent at the last observed step unread.

    Raises:
        ForecastError: naming the predictor, the recording, the frame (and time) and what was wrong.
    """

    def where(row: int | None) -> str:
        at = frame if not isinstance(frame, np.ndarray) else frame[row if row is not None else 0]
        t = time_s if not isinstance(time_s, np.ndarray) else time_s[row if row is not None else 0]
        return f"recording {recording!r} at frame {at}" + (f" (t = {float(t):.2f} s)" if t is not None else "")

    try:
        arr = np.asarray(out)
    except (TypeError, ValueError) as exc:  # ragged sequences and the like
        raise ForecastError(
            f"predictor {name!r} returned {type(out).__name__}, not an array, for {where(None)}: {exc}"
        ) from exc
    if arr.dtype.kind not in "fiu":
        raise ForecastError(
            f"predictor {name!r} returned an array of {arr.dtype} for {where(None)}, expected float metres"
        )
    if arr.shape != tuple(expected_shape):
        raise ForecastError(
            f"predictor {name!r} returned shape {arr.shape} for {where(None)}, expected {tuple(expected_shape)}"
        )
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr).all(axis=tuple(range(1, arr.ndim)))  # (N,): a row with any non-finite value
        read = np.ones(len(bad), bool)
        if rows is not None:
            read[:] = False
            read[rows] = True
            bad &= read
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            values = arr[bad]
            kinds = " and ".join(
                k for k, hit in (("NaN", np.isnan(values).any()), ("inf", np.isinf(values).any())) if hit
            )
            raise ForecastError(
                f"predictor {name!r} returned non-finite forecasts ({kinds}) for {where(first)}: {int(bad.sum())} of "
                f"{int(read.sum())} pedestrians read (first: row {first}); forecasts must be finite positions in metres"
            )
    return arr


# ---------------------------------------------------------------------------- shipped factories


def constant_velocity(split: str | None = None) -> Predictor:
    """The constant-velocity baseline (no weights; ``split`` is ignored)."""
    from crowdnav_mesrnn.models.base import ConstantVelocity

    return ConstantVelocity()


def cv_gaussian(split: str | None = None) -> Predictor:
    """Constant velocity with an isotropic Gaussian of scale ``a + b·h`` (:mod:`crowdnav_mesrnn.models.cv_gaussian`),
    its parameters fitted on ``split``'s training windows (the shipped ``cv_gaussian_<split>.json``)."""
    if split is None:
        raise PluginError("predictor 'cv_gaussian' needs the split whose held-out scene it will forecast")
    from crowdnav_mesrnn.models.cv_gaussian import load_cv_gaussian

    return load_cv_gaussian(split)


def _learned(model: str, split: str | None) -> Predictor:
    if split is None:
        raise PluginError(f"predictor {model!r} needs the split whose held-out scene it will forecast")
    from crowdnav_mesrnn.models.pretrained import load_pretrained

    return load_pretrained(model, split)


def mesrnn(split: str | None = None) -> Predictor:
    """The shipped MESRNN trained without ``split``'s held-out scene."""
    return _learned("mesrnn", split)


def srnn(split: str | None = None) -> Predictor:
    """The shipped SRNN trained without ``split``'s held-out scene."""
    return _learned("srnn", split)


def vlstm(split: str | None = None) -> Predictor:
    """The shipped Vanilla LSTM trained without ``split``'s held-out scene."""
    return _learned("vlstm", split)


# ---------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class PredictorSpec:
    """A resolvable predictor: a registered name or an import path."""

    name: str
    """The name it is chosen by (``predictor="kalman"``), or the import path itself."""
    target: str
    """``package.module:Factory``."""
    distribution: str | None = None
    """The installed distribution declaring it (None for a bare import path)."""
    version: str | None = None
    """That distribution's version."""

    @property
    def shipped(self) -> bool:
        """One of the project's own predictors."""
        return self.name in SHIPPED and self.target == SHIPPED[self.name]

    def factory(self) -> Callable[..., Any]:
        """The imported factory; raises :class:`PluginError` naming the target when it cannot be imported."""
        module, sep, attr = self.target.partition(":")
        if not sep or not module or not attr:
            raise PluginError(f"predictor {self.name!r}: target {self.target!r} is not 'package.module:Factory'")
        try:
            obj: Any = importlib.import_module(module)
            for part in attr.split("."):
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as exc:
            raise PluginError(f"predictor {self.name!r}: cannot import {self.target!r} ({exc})") from exc
        if not callable(obj):
            raise PluginError(f"predictor {self.name!r}: {self.target!r} is not callable")
        return obj

    def identity(self) -> str:
        """SHA-256 of what the forecast cache keys a plug-in on, besides its weights (or its own
        ``cache_fingerprint()``): name, target, distribution name and version, and a digest of every file of the
        plug-in (:func:`crowdnav_mesrnn.plugin_files.files_digest`: its installed distribution's ``RECORD``, or
        every file of its package for an editable install or an import path), so that changing any of them — another
        module, a parameter file — recomputes its forecasts.

        A shipped predictor keeps the identity it always had (its factory module's source in place of the files
        digest), so results keyed on it stay valid."""
        module = self.target.partition(":")[0]
        if not self.shipped:
            from crowdnav_mesrnn.plugin_files import files_digest

            head = [
                self.name,
                self.target,
                self.distribution,
                self.version,
                "files",
                files_digest(module, self.distribution),
            ]
            return hashlib.sha256(json.dumps(head).encode()).hexdigest()
        source = ""
        try:
            found = importlib.util.find_spec(module)
            if found is not None and found.origin and found.origin.endswith(".py"):
                with open(found.origin, "rb") as fh:
                    source = hashlib.sha256(fh.read()).hexdigest()
        except (ImportError, ValueError, OSError):
            pass
        head = [self.name, self.target, self.distribution, self.version, source]
        return hashlib.sha256(json.dumps(head).encode()).hexdigest()


@functools.cache
def _entry_points() -> tuple[importlib.metadata.EntryPoint, ...]:
    return tuple(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))


def refresh() -> None:
    """Forget the entry points read so far (call after installing a plug-in into a running interpreter), and which
    :class:`PluginWarning` were given."""
    _entry_points.cache_clear()
    _WARNED.clear()


class PluginWarning(UserWarning):
    """An installed entry point of :data:`ENTRY_POINT_GROUP` was skipped; the message names its distribution, its name
    and why. The other plug-ins keep working."""


#: The messages of :class:`PluginWarning` already given in this process (each is given once; :func:`refresh` forgets).
_WARNED: set[str] = set()


def _skip(message: str) -> None:
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, PluginWarning, stacklevel=4)


def _scan() -> tuple[dict[str, PredictorSpec], dict[str, tuple[PredictorSpec, ...]]]:
    """``(usable specs by name, names registered by several targets -> their specs)`` from the installed entry points;
    every entry point that cannot be used is skipped with a :class:`PluginWarning` naming its distribution."""
    out: dict[str, PredictorSpec] = {}
    twice: dict[str, tuple[PredictorSpec, ...]] = {}
    for ep in _entry_points():
        dist = getattr(ep, "dist", None)
        spec = PredictorSpec(
            ep.name, ep.value, getattr(dist, "name", None) if dist else None, getattr(dist, "version", None)
        )
        entry = f"the predictor plug-in {ep.name!r} = {ep.value!r} of the distribution {spec.distribution!r}"
        if ep.name in RESERVED or ":" in ep.name:
            why = "contains ':'" if ":" in ep.name else f"is reserved ({', '.join(RESERVED)} are not predictors)"
            _skip(f"skipped {entry}: its name {why}; the other plug-ins work. Ask its authors to rename it.")
            continue
        if ep.name in SHIPPED and ep.value != SHIPPED[ep.name]:
            _skip(
                f"skipped {entry}: it would replace the shipped predictor {ep.name!r}, which keeps its place; the other "
                "plug-ins work. Ask its authors to rename it."
            )
            continue
        if ep.name in twice:
            twice[ep.name] = (*twice[ep.name], spec)
            continue
        held = out.get(ep.name)
        if held is not None and held.target != spec.target:
            twice[ep.name] = (out.pop(ep.name), spec)
            continue
        out.setdefault(ep.name, spec)
    for name, specs in twice.items():
        _skip(f"skipped the predictor name {name!r}: {_registered_by(specs)}; the other plug-ins work")
    for name, target in SHIPPED.items():
        out.setdefault(name, PredictorSpec(name, target, "crowdnav-mesrnn", _own_version()))
    return out, twice


def _registered_by(specs: tuple[PredictorSpec, ...]) -> str:
    both = " and ".join(f"{s.target!r} ({s.distribution})" for s in specs)
    return f"it is registered by several plug-ins, {both}; uninstall all but one"


def registered() -> dict[str, PredictorSpec]:
    """Every registered predictor by name: installed entry points, plus :data:`SHIPPED` when the project's own
    metadata is not installed.

    An entry point that cannot be used — a reserved name (:data:`RESERVED`) or one containing ``:``, a shipped name
    for another factory, a name that several distributions register — is left out with a :class:`PluginWarning`
    naming its distribution (once per process); every other plug-in stays usable. Asking for a name registered
    twice is an error naming both (:func:`resolve`).
    """
    return _scan()[0]


def _own_version() -> str:
    from crowdnav_mesrnn._version import __version__

    return __version__


def plugin_names() -> tuple[str, ...]:
    """Registered names that are not shipped (installed plug-ins), sorted."""
    return tuple(sorted(n for n, s in registered().items() if not s.shipped))


def is_import_path(name: str) -> bool:
    """``package.module:Factory``."""
    module, sep, attr = name.partition(":")
    return bool(sep and module and attr) and all(p.isidentifier() for p in [*module.split("."), *attr.split(".")])


def resolve(name: str) -> PredictorSpec:
    """The spec of a registered name or an import path.

    Raises:
        PluginError: unknown name (listing the registered ones and the import-path form), or a name several
            distributions register (naming them).
    """
    if not isinstance(name, str):
        raise PluginError(f"a predictor name must be a string, got {name!r}")
    specs, twice = _scan()
    if name in specs:
        return specs[name]
    if name in twice:
        raise PluginError(f"predictor name {name!r} is ambiguous: {_registered_by(twice[name])}")
    if is_import_path(name):
        return PredictorSpec(name, name)
    raise PluginError(
        f"unknown predictor {name!r}; valid: {', '.join([*SHIPPED, *plugin_names()])} (registered under the "
        f"entry-point group {ENTRY_POINT_GROUP!r}), or an import path 'package.module:Factory'"
    )


def is_known(name: str) -> bool:
    """True for a registered name or a well-formed import path (not imported here)."""
    try:
        resolve(name)
    except PluginError:
        return False
    return True


def names(*kinds: str, plugins: bool = True) -> tuple[str, ...]:
    """Every forecast source name of the given kinds (all kinds when none is given), in the order shown to users:
    the project's own names (``none``, ``cv``, ``cv_gaussian``, ``mesrnn``, ``srnn``, ``vlstm``, ``oracle``,
    ``noisy_oracle``), then the installed plug-ins sorted (with ``plugins=True`` and when :data:`PLUGIN` is asked for).

    Raises:
        PluginError: an unknown kind.
    """
    for k in kinds:
        if k not in KINDS:
            raise PluginError(f"unknown predictor kind {k!r}; valid: {', '.join(KINDS)}")
    own = tuple(name for name, (k, _) in _BUILTIN.items() if not kinds or k in kinds)
    if plugins and (not kinds or PLUGIN in kinds):
        return (*own, *plugin_names())
    return own


def _unknown(name: Any) -> PluginError:
    return PluginError(
        f"unknown predictor {name!r}; valid: {', '.join(names())}, or an import path 'package.module:Factory' (see "
        "crowdnav_mesrnn.predictors)"
    )


def kind(name: str) -> str:
    """What the forecast source ``name`` is: one of :data:`KINDS`.

    Raises:
        PluginError: an unknown name (listing the valid ones: :func:`check`).
    """
    held = _BUILTIN.get(name) if isinstance(name, str) else None
    if held is not None:
        return held[0]
    if not is_known(name):
        raise _unknown(name)
    return PLUGIN


def check(name: Any) -> str:
    """``name`` when it is a forecast source (:func:`names`) or an import path ``package.module:Factory`` (not
    imported here); else :class:`PluginError` (a :class:`~crowdnav_mesrnn.config.ConfigError`) listing the valid
    names."""
    kind(name)
    return name


def is_plugin(name: Any) -> bool:
    """True for an installed plug-in's name or an import path (False for the project's own names and unknown ones)."""
    return isinstance(name, str) and name not in _BUILTIN and is_known(name)


def per_split(name: Any) -> bool:
    """True when ``name`` is loaded per leave-one-out split (:data:`SPLIT_KINDS`: the pretrained and the plug-ins),
    so its forecasts go to the shared disk cache; False for the others and for unknown names."""
    held = _BUILTIN.get(name) if isinstance(name, str) else None
    return held[0] in SPLIT_KINDS if held is not None else is_plugin(name)


_IDENTITIES: dict[int, tuple[Any, str]] = {}
_CHOSEN: dict[int, tuple[Any, str]] = {}


def label_of(model: Any) -> str:
    """How messages name a predictor: the name :func:`load` was given for it, followed by the object's own ``name``
    in brackets when that differs (``"nanny (broken-nan)"``); an object not loaded by name goes by its ``name``."""
    own = str(getattr(model, "name", "") or type(model).__name__)
    held = _CHOSEN.get(id(model))
    chosen = held[1] if held is not None and held[0] is model else own
    return chosen if chosen == own else f"{chosen} ({own})"


def check_protocol(model: Any, label: str) -> None:
    """Raise :class:`PluginError` unless ``model`` has ``forecast`` and integer ``obs_len``/``pred_len`` >= 1."""
    if not callable(getattr(model, "forecast", None)):
        raise PluginError(f"predictor {label!r} returned {model!r}, which has no forecast(history, mask) method")
    for attr in ("obs_len", "pred_len"):
        value = getattr(model, attr, None)
        if not (isinstance(value, int | np.integer) and value >= 1):
            raise PluginError(f"predictor {label!r}: {attr} must be an integer >= 1, got {value!r}")


def load(name: str, split: str | None = None) -> Predictor:
    """A ready predictor: ``factory(split=split)`` of the registered name or import path.

    A plug-in's object is remembered with its identity (:func:`identity_of`), which keys its forecasts in the
    shared cache.

    Raises:
        PluginError: unknown name, import failure, or an object breaking the protocol.
    """
    spec = resolve(name)
    factory = spec.factory()
    try:
        model = factory(split=split)
    except TypeError as exc:
        if "split" not in str(exc):
            raise
        raise PluginError(
            f"predictor {name!r}: its factory {spec.target!r} must accept a keyword argument split= (the "
            f"leave-one-out split whose held-out scene it will forecast; ignore it if the model has none): {exc}"
        ) from exc
    check_protocol(model, name)
    _CHOSEN[id(model)] = (model, name)
    if not spec.shipped:
        _IDENTITIES[id(model)] = (model, spec.identity())
        if not getattr(model, "name", None):
            try:
                model.name = spec.name
            except AttributeError:
                pass
    return model


def identity_of(model: Any) -> str | None:
    """The identity of a plug-in loaded by :func:`load` (None for shipped predictors and other objects)."""
    held = _IDENTITIES.get(id(model))
    return held[1] if held is not None and held[0] is model else None
