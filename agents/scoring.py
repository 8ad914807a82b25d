"""An action-conditioned scoring policy: every discrete action is scored by features of the robot's rollout
under it against every pedestrian's forecast in the observation, with weights shared across actions.

The pooled-set extractor (:mod:`agents.extractors`) must learn to compute, for 57 actions, how close a
12-step rollout passes to 10 forecasts — the geometry a planner does explicitly. Here that geometry is
computed, not learned (as SARL values each action by a lookahead, Chen et al. 2019):

1. :func:`action_rollout_features` (no parameters): for every action ``a`` of the discrete set
   (:class:`agents.actions.GoalRelativeActions`), the robot holding that velocity for ``h = 1..H`` steps is
   compared with every present pedestrian's future position at the same times — the observation's forecast,
   or, in the ``none`` arm (no forecasts in the observation), the constant-velocity extrapolation of the
   observed velocity (as the sampling planner does). Per action it gives the clearance profile (smallest gap
   to any pedestrian at each step, and its running minimum), the time of closest approach, the first step of
   a conflict, how many pedestrians pass within 0 / 0.3 / 1 m, a soft minimum of the gaps, progress towards
   the goal after one step and over the horizon, and the action's own speed and heading. Absent pedestrians
   (mask 0) never enter; every per-action feature is a minimum, count or soft minimum over pedestrians, so it
   does not depend on the order of the rows.
2. :class:`ActionRolloutExtractor`: those features ``(B, A, F)`` plus a context code of the whole observation
   (:class:`agents.extractors.CrowdFeaturesExtractor`, small), flattened for SB3.
3. :class:`ActionScoringHead` (SB3's ``mlp_extractor``): one MLP, the same for every action, maps an action's
   features (plus a projection of the context, computed once) to a score; the scores are the actor's logits
   (SB3's ``action_net`` is the identity). The value reads the context and the mean and max over actions of the
   actions' last hidden codes.
4. :class:`ActionScoringPolicy` (PPO) and :class:`ActionScoringQPolicy` (DQN: the scores are Q-values).

The policy uses only the observation: the forecast arms differ in what the ``forecasts`` key holds (and in the
``none`` arm the futures are extrapolated from the observed velocities, which every arm observes).

The action geometry (headings, speed fractions, preferred speed, step, radii) must be the environment's and the
action set's: :func:`action_geometry_kwargs` builds it, and :mod:`agents.training.config` fills it in for these
policies.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import DictRolloutBuffer
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.dqn.policies import MultiInputPolicy as DQNMultiInputPolicy
from stable_baselines3.dqn.policies import QNetwork
from torch import nn

from agents.extractors import PED_ROW, CrowdFeaturesExtractor, activation_class

#: Gap thresholds (m) of the per-action counts of pedestrians passing within them over the horizon.
COUNT_GAPS_M: Final[tuple[float, ...]] = (0.0, 0.3, 1.0)
#: Gap thresholds (m) of the per-action "first step of a conflict" features.
CONFLICT_GAPS_M: Final[tuple[float, ...]] = (0.0, 0.3)
#: Gaps are clipped to this (m) before scaling: beyond it a pedestrian is simply far.
GAP_CLIP_M: Final[float] = 4.0
#: Temperature (m) of the soft minimum of the pedestrians' smallest gaps.
SOFTMIN_M: Final[float] = 0.5
#: Where the robot's future positions come from without forecasts: the observed velocities held
#: (``constant_velocity``, the sampling planner's fallback) or the pedestrians standing still (``static``).
NO_FORECAST_FUTURES: Final[tuple[str, ...]] = ("constant_velocity", "static")
#: Key under which a batch of observations may carry its precomputed geometry (:class:`GeometryCachingBuffer`).
GEOMETRY_KEY: Final[str] = "_rollout_geometry"
#: Largest geometry (bytes) :meth:`ActionScoringPolicy.with_geometry` keeps for a whole data set.
MAX_CACHED_GEOMETRY_BYTES: Final[int] = 1 << 30
#: Observations per chunk of the (chunk, K, H, A) squared-distance tensor (sized to stay in a CPU cache).
_CHUNK: Final[int] = 16


def num_rollout_features(horizon: int) -> int:
    """Width ``F`` of :func:`action_rollout_features` for a horizon of ``horizon`` steps."""
    # profile, running minimum, closest approach, conflicts, counts, soft minimum, progress (2), action (5)
    return 2 * horizon + 1 + len(CONFLICT_GAPS_M) + len(COUNT_GAPS_M) + 1 + 2 + 5


def action_geometry_kwargs(actions: Any) -> dict[str, Any]:
    """Keyword arguments of :class:`ActionRolloutExtractor` describing a discrete action set
    (:class:`agents.actions.GoalRelativeActions`) and its environment: plain data (saved with the model)."""
    cfg = actions.cfg
    if cfg.kinematics != "holonomic":
        raise ValueError(f"the scoring policy needs holonomic kinematics, got {cfg.kinematics!r}")
    return {
        "action_angles_rad": [float(x) for x in actions.angles],
        "action_fractions": [float(x) for x in actions.fractions],
        "pref_speed_mps": float(cfg.robot_pref_speed_mps),
        "dt_s": float(cfg.dt_s),
        "radius_sum_m": float(cfg.robot_radius_m + cfg.pedestrian_radius_m),
        "horizon_steps": int(cfg.horizon_steps),
    }


def pedestrian_futures(
    robot: torch.Tensor,
    pedestrians: torch.Tensor,
    forecasts: torch.Tensor | None,
    times_s: torch.Tensor,
    no_forecast: str = "constant_velocity",
) -> torch.Tensor:
    """Future positions of the observation's pedestrian rows relative to the robot's current position.

    Args:
        robot: ``(B, R)`` (goal offset m, velocity m/s, ...).
        pedestrians: ``(B, K, 4)`` position relative to the robot (m), velocity relative to the robot's (m/s).
        forecasts: ``(B, K, H, 2)`` forecast positions relative to the robot (m), or None (the ``none`` arm).
        times_s: ``(H,)`` seconds ahead, ``h * dt_s``.
        no_forecast: without forecasts, ``constant_velocity`` (observed world velocity held) or ``static``.

    Returns:
        ``(B, K, H, 2)`` metres.
    """
    if forecasts is not None:
        return forecasts
    pos = pedestrians[..., None, 0:2]  # (B, K, 1, 2)
    if no_forecast == "static":
        return pos.expand(-1, -1, times_s.shape[0], -1)
    world_vel = pedestrians[..., 2:4] + robot[:, None, 2:4]  # (B, K, 2)
    return pos + world_vel[..., None, :] * times_s[:, None]


def action_rollout_features(
    robot: torch.Tensor,
    futures: torch.Tensor,
    mask: torch.Tensor,
    angles_rad: torch.Tensor,
    fractions: torch.Tensor,
    pref_speed_mps: float,
    dt_s: float,
    radius_sum_m: float,
) -> torch.Tensor:
    """Features of every action's rollout against every present pedestrian's future (no parameters).

    The robot holds action ``a``'s velocity (heading ``angles_rad[a]`` from the goal direction, speed
    ``fractions[a]`` times the cap ``min(pref_speed, goal distance / dt)``) for ``h = 1..H`` steps of ``dt_s``.

    Args:
        robot: ``(B, R)``: goal offset (m), velocity (m/s), the rest unused.
        futures: ``(B, K, H, 2)`` pedestrians' positions at ``h * dt_s`` relative to the robot now, metres.
        mask: ``(B, K)`` bool: the row holds a pedestrian.
        angles_rad: ``(A,)``; fractions: ``(A,)`` in [0, 1].
        pref_speed_mps: the robot's preferred speed; dt_s: the step, s; radius_sum_m: robot + pedestrian radius.

    Returns:
        ``(B, A, F)`` with ``F = num_rollout_features(H)``, in this order (gaps are centre distance minus
        ``radius_sum_m``, clipped to ``[-radius_sum_m, GAP_CLIP_M]``, in metres; times are fractions of H):
        ``[0:H]`` the smallest gap to any pedestrian at each step; ``[H:2H]`` its running minimum (the smallest
        within the first h steps); the step of closest approach / H; per :data:`CONFLICT_GAPS_M` the first step
        whose gap is below it / H (``(H + 1) / H`` if none); per :data:`COUNT_GAPS_M` the number of pedestrians
        whose smallest gap is below it / K; the soft minimum over pedestrians of their smallest gaps
        (temperature :data:`SOFTMIN_M`); progress towards the goal after one step and after H steps, over the
        preferred speed's progress; the speed fraction, the cap over the preferred speed, cos and sin of the
        heading, and whether the action stands still. With no pedestrian present every gap is ``GAP_CLIP_M``.
    """
    b, k, h, _ = futures.shape
    dtype = futures.dtype
    goal = robot[:, 0:2]
    dist = torch.linalg.vector_norm(goal, dim=1)  # (B,)
    at_goal = dist < 1e-6
    ux = torch.where(at_goal, 1.0, goal[:, 0] / dist.clamp_min(1e-6))
    uy = torch.where(at_goal, 0.0, goal[:, 1] / dist.clamp_min(1e-6))
    cap = torch.minimum(torch.full_like(dist, pref_speed_mps), dist / dt_s)  # (B,)
    ca, sa = torch.cos(angles_rad).to(dtype), torch.sin(angles_rad).to(dtype)  # (A,)
    frac = fractions.to(dtype)
    n_act = len(frac)
    t = dt_s * torch.arange(1, h + 1, dtype=dtype, device=futures.device)  # (H,)
    # futures in the goal frame (x along the goal direction); absent rows at 0 and "far" through their norm
    fx, fy = futures[..., 0], futures[..., 1]
    p = torch.where(mask[..., None], ux[:, None, None] * fx + uy[:, None, None] * fy, 0.0)  # (B, K, H)
    q = torch.where(mask[..., None], ux[:, None, None] * fy - uy[:, None, None] * fx, 0.0)
    far = (GAP_CLIP_M + radius_sum_m + 1.0) ** 2
    f2 = torch.where(mask[..., None], p * p + q * q, far)  # (B, K, H)
    # squared distance of the robot at r (ca, sa) (r = speed * t) to (p, q): r^2 - 2 r (ca p + sa q) + |f|^2, laid
    # out (B, K, H, A) and reduced to the minima over pedestrians and over steps before the square root; in chunks
    # of observations that stay in cache (a whole minibatch's (B, K, H, A) is megabytes, written and read twice)
    cs = torch.stack([ca, sa])  # (2, A)
    pq = torch.stack([p, q], dim=-1).reshape(b, k * h, 2)
    r = (frac[None, :] * cap[:, None])[:, None, :] * t[None, :, None]  # (B, H, A)
    minus_2r, r2 = -2.0 * r, r * r
    min_over_peds = torch.empty(b, h, n_act, dtype=dtype, device=futures.device)
    min_over_steps = torch.empty(b, k, n_act, dtype=dtype, device=futures.device)
    for lo in range(0, b, _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        d2 = torch.matmul(pq[sl], cs).reshape(-1, k, h, n_act)
        d2.mul_(minus_2r[sl, None]).add_(r2[sl, None]).add_(f2[sl, :, :, None])
        torch.amin(d2, dim=1, out=min_over_peds[sl])
        torch.amin(d2, dim=2, out=min_over_steps[sl])

    def gaps(sq: torch.Tensor) -> torch.Tensor:
        return (torch.sqrt(sq.clamp_min(0.0)) - radius_sum_m).clamp(-radius_sum_m, GAP_CLIP_M)

    profile = gaps(min_over_peds).transpose(1, 2).contiguous()  # (B, A, H): smallest gap at each step
    per_ped = gaps(min_over_steps).transpose(1, 2).contiguous()  # (B, A, K): each pedestrian's smallest gap
    running = torch.cummin(profile, dim=2).values
    step = torch.arange(h, dtype=dtype, device=futures.device)

    def first_step(hit: torch.Tensor) -> torch.Tensor:  # (B, A): first step index where hit, else h
        return torch.where(hit, step, float(h)).amin(dim=2)

    closest = first_step(profile <= running[..., -1:])[..., None] / h  # (B, A, 1); ties: the first
    conflicts = [(first_step(profile < threshold) + 1.0) / h for threshold in CONFLICT_GAPS_M]
    counts = [(per_ped < threshold).to(dtype).sum(dim=2) / k for threshold in COUNT_GAPS_M]
    softmin = -SOFTMIN_M * torch.logsumexp(-per_ped / SOFTMIN_M, dim=2)
    # progress along the goal direction after one step and after H steps (capped at the goal distance)
    speed = frac[None, :] * cap[:, None]  # (B, A)
    along = speed * ca[None, :]  # (B, A) m/s towards the goal
    full = max(pref_speed_mps, 1e-9)
    progress_1 = along / full
    progress_h = torch.minimum(along * t[-1], dist[:, None]) / (full * float(t[-1]))
    action = [
        frac[None, :].expand(b, -1),
        (cap / full)[:, None].expand(-1, n_act),
        ca[None, :].expand(b, -1),
        sa[None, :].expand(b, -1),
        (frac == 0).to(dtype)[None, :].expand(b, -1),
    ]
    scalars = torch.stack([*conflicts, *counts, softmin, progress_1, progress_h, *action], dim=2)
    return torch.cat([profile, running, closest, scalars], dim=2)


class ActionRolloutExtractor(BaseFeaturesExtractor):
    """Per-action rollout features and a context code of the observation, flattened: ``(B, A * F + C)``.

    Args:
        observation_space: the environment's ``Dict`` space (``robot``, ``pedestrians``, ``mask``, and
            ``forecasts`` except in the ``none`` arm).
        action_angles_rad: the discrete actions' headings relative to the goal direction (``A``).
        action_fractions: their speeds as fractions of the speed cap (0 = standing still).
        pref_speed_mps: the robot's preferred speed, m/s; dt_s: the control step, s.
        radius_sum_m: robot radius plus pedestrian radius, metres.
        horizon_steps: H, steps of the rollouts (the forecasts' horizon when the observation has them).
        context_dim: width of the context encoder (:class:`agents.extractors.CrowdFeaturesExtractor`, goal frame,
            robot context; its output has ``3 * context_dim + 1`` features).
        no_forecast: futures without forecasts (:data:`NO_FORECAST_FUTURES`).
        gap_scale_m: gaps are divided by this.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_angles_rad: Sequence[float],
        action_fractions: Sequence[float],
        pref_speed_mps: float,
        dt_s: float,
        radius_sum_m: float,
        horizon_steps: int = 12,
        context_dim: int = 32,
        no_forecast: str = "constant_velocity",
        gap_scale_m: float = 1.0,
    ) -> None:
        if len(action_angles_rad) != len(action_fractions) or not len(action_angles_rad):
            raise ValueError(
                f"action_angles_rad and action_fractions must be non-empty and of one length, got "
                f"{len(action_angles_rad)} and {len(action_fractions)}"
            )
        if no_forecast not in NO_FORECAST_FUTURES:
            raise ValueError(f"unknown no_forecast {no_forecast!r}; valid: {', '.join(NO_FORECAST_FUTURES)}")
        if not (pref_speed_mps > 0 and dt_s > 0 and radius_sum_m >= 0 and gap_scale_m > 0):
            raise ValueError("pref_speed_mps, dt_s and gap_scale_m must be positive, radius_sum_m >= 0")
        if context_dim < 1 or horizon_steps < 1:
            raise ValueError(f"context_dim and horizon_steps must be >= 1, got {context_dim!r}, {horizon_steps!r}")
        keys = set(observation_space.spaces)
        if not {"robot", "pedestrians", "mask"} <= keys:
            raise ValueError(f"observation space must have robot, pedestrians and mask keys, got {sorted(keys)}")
        k = int(observation_space["mask"].n)  # type: ignore[attr-defined]
        with_forecasts = "forecasts" in keys
        horizon = int(horizon_steps)
        if with_forecasts and int(math.prod(observation_space["forecasts"].shape)) != k * horizon * 2:  # type: ignore[arg-type]
            raise ValueError(
                f"horizon_steps {horizon} does not match the observation's forecasts {observation_space['forecasts']}"
            )
        context = CrowdFeaturesExtractor(observation_space, hidden_dim=context_dim, frame="goal", robot_context=True)
        c_dim = context.features_dim
        n_actions = len(action_angles_rad)
        f = num_rollout_features(horizon)
        super().__init__(observation_space, features_dim=n_actions * f + c_dim)
        self.context = context
        self.num_actions = n_actions
        self.num_features = f
        self.context_dim = c_dim
        self.num_pedestrians = k
        self.horizon = horizon
        self.with_forecasts = with_forecasts
        self.no_forecast = no_forecast
        self.pref_speed_mps, self.dt_s, self.radius_sum_m = float(pref_speed_mps), float(dt_s), float(radius_sum_m)
        self.register_buffer("angles", torch.tensor(list(action_angles_rad), dtype=torch.float32), persistent=False)
        self.register_buffer("fractions", torch.tensor(list(action_fractions), dtype=torch.float32), persistent=False)
        self.register_buffer("times_s", dt_s * torch.arange(1, horizon + 1, dtype=torch.float32), persistent=False)
        # gap features (profile, running minimum, soft minimum) in gap_scale_m; the rest already O(1)
        scale = torch.ones(f)
        scale[: 2 * horizon] = 1.0 / gap_scale_m
        scale[2 * horizon + 1 + len(CONFLICT_GAPS_M) + len(COUNT_GAPS_M)] = 1.0 / gap_scale_m
        self.register_buffer("feature_scale", scale, persistent=False)

    def rollout_features(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(B, A, F)`` unscaled (see :func:`action_rollout_features`)."""
        mask = observations["mask"] > 0.5
        b, k = mask.shape
        robot = observations["robot"]
        peds = observations["pedestrians"].reshape(b, k, PED_ROW)
        fc = observations["forecasts"].reshape(b, k, self.horizon, 2) if self.with_forecasts else None
        fut = pedestrian_futures(robot, peds, fc, self.times_s, self.no_forecast)
        return action_rollout_features(
            robot, fut, mask, self.angles, self.fractions, self.pref_speed_mps, self.dt_s, self.radius_sum_m
        )

    def geometry(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(B, A * F)``: the scaled, flattened rollout features (no gradient: no parameters involved)."""
        with torch.no_grad():
            return (self.rollout_features(observations) * self.feature_scale).flatten(1)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:  # type: ignore[override]
        """Features of a batch; with :data:`GEOMETRY_KEY` among the observations (precomputed by :meth:`geometry`,
        see :class:`GeometryCachingBuffer`) the geometry is not computed again."""
        feats = observations.get(GEOMETRY_KEY)
        if feats is None:
            feats = self.geometry(observations)
        return torch.cat([feats, self.context(observations)], dim=1)


class ActionScoringHead(nn.Module):
    """SB3's ``mlp_extractor`` for :class:`ActionRolloutExtractor` features: per-action scores (actor latent,
    ``(B, A)``, used as logits) and a value latent ``(B, hidden_dim)``.

    Score of action ``a``: ``w . act(W2 act(W1 x_a + U c + b1) + b2) + b3`` with ``x_a`` its features and ``c``
    the context (``U c`` computed once per observation); the same weights for every action. Value latent:
    ``act(V [c, mean_a h_a, max_a h_a])`` with ``h_a`` the last hidden code of action ``a``.

    The per-action features are the extractor's parameter-free geometry, so no gradient is taken with respect to
    them (it would cost a ``(B * A, hidden) x (hidden, F)`` product and a zero-filled copy of the whole feature
    tensor per update step, and be thrown away). The maximum over actions is ``max(...).values``, whose backward
    passes the gradient to the largest code alone (``amax`` shares it among exact ties, which distinct actions
    practically never have). The outputs are the same bits as the plain formula's and the gradients the same up
    to float rounding (``tests/agents/test_scoring.py``); a PPO update of the shipped recipe is about 13 % cheaper.
    """

    def __init__(
        self, num_actions: int, num_features: int, context_dim: int, hidden_dim: int = 32, activation: str = "relu"
    ) -> None:
        super().__init__()
        act = activation_class(activation)
        self.num_actions, self.num_features, self.context_dim = num_actions, num_features, context_dim
        self.action_in = nn.Linear(num_features, hidden_dim)
        self.context_in = nn.Linear(context_dim, hidden_dim, bias=False)
        self.hidden = nn.Linear(hidden_dim, hidden_dim)
        self.score = nn.Linear(hidden_dim, 1)
        self.value_in = nn.Linear(context_dim + 2 * hidden_dim, hidden_dim)
        self.act = act()
        self.latent_dim_pi = num_actions
        self.latent_dim_vf = hidden_dim

    def codes(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(per-action codes (B, A, hidden), context (B, C))`` of flattened extractor features."""
        b = features.shape[0]
        split = self.num_actions * self.num_features
        x = features[:, :split].detach().reshape(b, self.num_actions, self.num_features)  # geometry: no gradient
        ctx = features[:, split:]
        z = self.action_in(x)
        z.add_(self.context_in(ctx)[:, None, :])  # in place: one (B, A, hidden) tensor fewer per call
        return self.act(self.hidden(self.act(z))), ctx

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        h, _ = self.codes(features)
        return self.score(h).squeeze(-1)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        h, ctx = self.codes(features)
        return self._value(h, ctx)

    def _value(self, h: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
        return self.act(self.value_in(torch.cat([ctx, h.mean(dim=1), h.max(dim=1).values], dim=1)))

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, ctx = self.codes(features)  # once for both heads
        return self.score(h).squeeze(-1), self._value(h, ctx)


def _check_discrete(action_space: spaces.Space[Any], extractor: ActionRolloutExtractor) -> None:
    if not isinstance(action_space, spaces.Discrete) or int(action_space.n) != extractor.num_actions:
        raise ValueError(
            f"the scoring policy scores {extractor.num_actions} actions but the action space is {action_space}: "
            "use action kind 'discrete' with the same action set (agents.scoring.action_geometry_kwargs)"
        )


class _HeadKwargs:
    """Constructor plumbing shared by the PPO and DQN scoring policies: ``head_kwargs`` kept (and saved with the
    model), :class:`ActionRolloutExtractor` as the default extractor, ``net_arch`` ignored (the head replaces it)."""

    def __init__(self, *args: Any, head_kwargs: dict[str, Any] | None = None, **kwargs: Any) -> None:
        self.head_kwargs = dict(head_kwargs or {})
        kwargs.setdefault("features_extractor_class", ActionRolloutExtractor)
        kwargs.pop("net_arch", None)
        super().__init__(*args, **kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        data["head_kwargs"] = self.head_kwargs
        return data


class ActionScoringPolicy(_HeadKwargs, MultiInputActorCriticPolicy):
    """PPO/A2C policy: :class:`ActionRolloutExtractor` + :class:`ActionScoringHead`; the logits are the scores.

    ``net_arch`` is not used; ``head_kwargs`` (``hidden_dim``, ``activation``) configure the head and
    ``features_extractor_kwargs`` the extractor (the action geometry is required there).
    """

    def _build_mlp_extractor(self) -> None:
        ext = self.features_extractor
        assert isinstance(ext, ActionRolloutExtractor), "ActionScoringPolicy needs ActionRolloutExtractor"
        _check_discrete(self.action_space, ext)
        self.mlp_extractor = ActionScoringHead(ext.num_actions, ext.num_features, ext.context_dim, **self.head_kwargs)

    def extract_features(  # type: ignore[override]
        self, obs: Any, features_extractor: BaseFeaturesExtractor | None = None
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """SB3's, passing a precomputed geometry (:data:`GEOMETRY_KEY`, not part of the observation space) past the
        observation preprocessing to the extractor."""
        if not (isinstance(obs, dict) and GEOMETRY_KEY in obs):
            return super().extract_features(obs, features_extractor)
        rest = {k: v for k, v in obs.items() if k != GEOMETRY_KEY}
        pre = preprocess_obs(rest, self.observation_space, normalize_images=self.normalize_images)
        pre[GEOMETRY_KEY] = obs[GEOMETRY_KEY]  # type: ignore[index]
        if features_extractor is not None:
            return features_extractor(pre)
        if self.share_features_extractor:
            return self.features_extractor(pre)
        return self.pi_features_extractor(pre), self.vf_features_extractor(pre)

    #: Whether :meth:`forward` keeps the geometry it computes (:meth:`take_rollout_geometry`); set by
    #: :func:`attach_geometry_cache`.
    keep_rollout_geometry: bool = False
    _kept: tuple[dict[str, torch.Tensor], torch.Tensor] | None = None

    def forward(self, obs: Any, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SB3's (a rollout step's actions, values and log-probabilities). With :attr:`keep_rollout_geometry` the
        geometry is computed first, passed on under :data:`GEOMETRY_KEY` (the same features) and kept with a copy
        of the observations, so that the rollout buffer stores it instead of computing it again."""
        if not (self.keep_rollout_geometry and isinstance(obs, dict)) or GEOMETRY_KEY in obs:
            return super().forward(obs, deterministic)
        extractor = self.pi_features_extractor  # shared or not, the geometry is the same (no parameters)
        assert isinstance(extractor, ActionRolloutExtractor)
        pre = preprocess_obs(obs, self.observation_space, normalize_images=self.normalize_images)
        geometry = extractor.geometry(pre)  # type: ignore[arg-type]
        self._kept = ({k: v.clone() for k, v in obs.items()}, geometry)
        return super().forward({**obs, GEOMETRY_KEY: geometry}, deterministic)

    def take_rollout_geometry(self, observations: dict[str, np.ndarray]) -> torch.Tensor | None:
        """The geometry ``(B, A * F)`` the last :meth:`forward` computed, if it was given exactly ``observations``
        (as SB3's rollout buffer holds them: float32), else None; either way it is not kept any longer."""
        kept, self._kept = self._kept, None
        if kept is None:
            return None
        seen, geometry = kept
        if set(seen) != set(observations):
            return None
        for key, value in observations.items():
            given = torch.as_tensor(np.asarray(value, dtype=np.float32))
            if given.shape != seen[key].shape or not torch.equal(given, seen[key].to(torch.float32)):
                return None
        return geometry

    def get_distribution(self, obs: Any) -> Any:
        """SB3's, through :meth:`extract_features` (SB3 calls the base class's, which rejects the geometry key)."""
        features = self.extract_features(obs, self.pi_features_extractor)
        return self._get_action_dist_from_latent(self.mlp_extractor.forward_actor(features))

    def predict_values(self, obs: Any) -> torch.Tensor:
        """SB3's, through :meth:`extract_features` (as :meth:`get_distribution`)."""
        features = self.extract_features(obs, self.vf_features_extractor)
        return self.value_net(self.mlp_extractor.forward_critic(features))

    def with_geometry(self, observations: dict[str, torch.Tensor], chunk: int = 1024) -> dict[str, torch.Tensor]:
        """``observations`` (a whole data set of tensors) plus their geometry under :data:`GEOMETRY_KEY`, computed
        once, so that fitting over many epochs (the warm start) does not recompute it per minibatch; unchanged
        when that would take more than :data:`MAX_CACHED_GEOMETRY_BYTES`."""
        ext = self.features_extractor
        assert isinstance(ext, ActionRolloutExtractor)
        n = len(observations["mask"])
        if n * ext.num_actions * ext.num_features * 4 > MAX_CACHED_GEOMETRY_BYTES:
            return observations
        geometry = torch.cat([ext.geometry({k: v[i : i + chunk] for k, v in observations.items()})
                              for i in range(0, n, chunk)])  # fmt: skip
        return {**observations, GEOMETRY_KEY: geometry}

    def _build(self, lr_schedule: Any) -> None:
        super()._build(lr_schedule)
        self.action_net = nn.Identity()  # the head's scores are the logits (weights shared across actions)
        head = self.mlp_extractor
        assert isinstance(head, ActionScoringHead)
        nn.init.orthogonal_(head.score.weight, gain=0.01)  # SB3's small initial logits
        nn.init.zeros_(head.score.bias)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)


class ActionScoringQNetwork(QNetwork):
    """DQN's Q-network with the scoring head: ``Q(s, a)`` is the score of action ``a``."""

    def __init__(self, *args: Any, head_kwargs: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        ext = self.features_extractor
        assert isinstance(ext, ActionRolloutExtractor), "ActionScoringQNetwork needs ActionRolloutExtractor"
        _check_discrete(self.action_space, ext)
        self.head = ActionScoringHead(ext.num_actions, ext.num_features, ext.context_dim, **dict(head_kwargs or {}))
        self.q_net = nn.Identity()  # unused: forward below

    def forward(self, obs: Any) -> torch.Tensor:  # type: ignore[override]
        return self.head.forward_actor(self.extract_features(obs, self.features_extractor))


class ActionScoringQPolicy(_HeadKwargs, DQNMultiInputPolicy):
    """SB3 DQN policy whose Q-network is :class:`ActionScoringQNetwork` (``head_kwargs`` as for PPO)."""

    def make_q_net(self) -> QNetwork:
        args = self._update_features_extractor(self.net_args, features_extractor=None)
        return ActionScoringQNetwork(**args, head_kwargs=self.head_kwargs).to(self.device)


class GeometryCachingBuffer(DictRolloutBuffer):
    """PPO's rollout buffer, adding to every minibatch the observations' rollout geometry (:data:`GEOMETRY_KEY`),
    computed once per rollout instead of once per epoch and minibatch (the geometry depends on the observation
    alone). With a policy attached (:func:`attach_geometry_cache`), the geometry its forward pass computed for the
    rollout's steps is stored as they are added and not computed at all for the update; a step added without it is
    computed at the first minibatch, as is everything without a policy. Without :meth:`attach` it is SB3's buffer.
    Results equal recomputation up to float rounding."""

    geometry_fn: Any = None
    policy: Any = None
    _geometry: torch.Tensor | None = None
    _rows: torch.Tensor | None = None
    _have: np.ndarray | None = None
    _CHUNK_ROWS: Final[int] = 512

    def attach(self, geometry_fn: Any, policy: Any = None) -> None:
        """Use ``geometry_fn`` (:meth:`ActionRolloutExtractor.geometry`: batch of observation tensors ->
        ``(B, A * F)``), and take what ``policy`` (:class:`ActionScoringPolicy`, or None) computed in the rollout
        (:meth:`ActionScoringPolicy.take_rollout_geometry`)."""
        self.geometry_fn = geometry_fn
        self.policy = policy
        self._geometry = None
        self._rows, self._have = None, np.zeros(self.buffer_size, dtype=bool)

    def reset(self) -> None:
        super().reset()
        self._geometry = None
        if self._have is not None:
            self._have[:] = False

    def add(self, obs: dict[str, np.ndarray], *args: Any, **kwargs: Any) -> None:  # type: ignore[override]
        pos = self.pos
        super().add(obs, *args, **kwargs)
        if self.policy is None or self._have is None:
            return
        geometry = self.policy.take_rollout_geometry(obs)
        if geometry is None or geometry.shape[0] != self.n_envs:
            return
        if self._rows is None or self._rows.shape[2] != geometry.shape[1]:
            self._rows = torch.empty(self.buffer_size, self.n_envs, geometry.shape[1], dtype=geometry.dtype)
        self._rows[pos] = geometry
        self._have[pos] = True

    def _get_samples(self, batch_inds: Any, env: Any = None) -> Any:  # type: ignore[override]
        samples = super()._get_samples(batch_inds, env)
        if self.geometry_fn is None:
            return samples
        if self._geometry is None:  # first minibatch of this rollout: observations are flattened by now
            if self._rows is not None and self._have is not None and self._have.all():
                # kept in the rollout, (step, env) -> SB3's flattened order (env, step)
                self._geometry = self._rows.transpose(0, 1).reshape(self.buffer_size * self.n_envs, -1)
            else:
                n = self.buffer_size * self.n_envs
                parts = []
                for lo in range(0, n, self._CHUNK_ROWS):
                    chunk = {k: self.to_torch(v[lo : lo + self._CHUNK_ROWS]) for k, v in self.observations.items()}
                    parts.append(self.geometry_fn(chunk))
                self._geometry = torch.cat(parts)
        obs = dict(samples.observations)
        rows = torch.as_tensor(batch_inds, device=self._geometry.device)
        obs[GEOMETRY_KEY] = torch.index_select(self._geometry, 0, rows)  # the same rows, 6x faster than [rows]
        return samples._replace(observations=obs)


def attach_geometry_cache(model: Any) -> bool:
    """Let ``model``'s rollout buffer cache the scoring policy's geometry (:class:`GeometryCachingBuffer`), keeping
    what the policy computes in the rollouts; returns whether it applies (a PPO model with that buffer and
    :class:`ActionScoringPolicy`)."""
    buffer = getattr(model, "rollout_buffer", None)
    policy = getattr(model, "policy", None)
    if isinstance(buffer, GeometryCachingBuffer) and isinstance(policy, ActionScoringPolicy):
        extractor = policy.features_extractor
        assert isinstance(extractor, ActionRolloutExtractor)
        policy.keep_rollout_geometry = True
        buffer.attach(extractor.geometry, policy)
        return True
    return False


def is_scoring_policy(policy: Any) -> bool:
    """Whether a policy class (or an SB3 alias string) needs the action geometry in its extractor kwargs."""
    return isinstance(policy, type) and issubclass(policy, ActionScoringPolicy | ActionScoringQPolicy)
