"""The features extractor for the environment's ``Dict`` observation, and SB3 policies that use it.

:class:`CrowdFeaturesExtractor` encodes the robot state with one MLP and every pedestrian row with one
shared MLP (the row's position and velocity, plus its flattened forecast when the observation has
one), then pools the pedestrian codes over the mask. The architecture is the same in every forecast
arm: only the input width of the pedestrian encoder's first layer differs (4 without forecasts,
4 + 2H with them). A row whose mask is 0 is replaced by zeros before encoding and excluded from the
pooling, so whatever it holds cannot change the output.

:class:`CrowdActorCriticPolicy` (PPO) and :class:`CrowdSACPolicy` (SAC) are SB3's multi-input policies
with this extractor as default and ``activation_fn`` accepted as a name (``"relu"``, ``"tanh"``, ...), so
every hyperparameter can be written as plain YAML data (RL Zoo's ``policy: agents.extractors.CrowdActorCriticPolicy``).
"""

from __future__ import annotations

import math
from typing import Any, Final

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.sac.policies import MultiInputPolicy as SACMultiInputPolicy
from torch import nn

#: Activation names accepted in YAML (``activation`` of the extractor, ``activation_fn`` of the policies).
ACTIVATIONS: Final[dict[str, type[nn.Module]]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
    "leaky_relu": nn.LeakyReLU,
    "silu": nn.SiLU,
}
#: Pooling of the pedestrian codes over the mask.
POOLINGS: Final[tuple[str, ...]] = ("meanmax", "attention")
#: Frames the extractor may work in: the observation's (world axes) or one whose x axis points at the goal.
FRAMES: Final[tuple[str, ...]] = ("world", "goal")
#: Width of one pedestrian row of the observation (position x, y, velocity x, y).
PED_ROW: Final[int] = 4


def activation_class(name: str | type[nn.Module]) -> type[nn.Module]:
    """The activation class for a name (or the class itself); ``ValueError`` listing the valid names."""
    if isinstance(name, type) and issubclass(name, nn.Module):
        return name
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; valid: {', '.join(ACTIVATIONS)}")
    return ACTIVATIONS[name]


def _mlp(in_dim: int, hidden_dim: int, act: type[nn.Module]) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), act(), nn.Linear(hidden_dim, hidden_dim), act())


class CrowdFeaturesExtractor(BaseFeaturesExtractor):
    """Robot encoder + one shared pedestrian encoder pooled over the mask.

    Inputs (SB3 passes a batch ``B`` of each key, the mask as float):
        ``robot`` ``(B, R)``: goal offset (m), velocity (m/s), then any further features (heading,
        time left) as they are. ``pedestrians`` ``(B, K*4)`` or ``(B, K, 4)``: position (m) and
        velocity (m/s) relative to the robot. ``mask`` ``(B, K)``. ``forecasts`` (optional)
        ``(B, K*H*2)`` or ``(B, K, H, 2)``: forecast positions relative to the robot (m).

    Positions are divided by ``position_scale_m`` and velocities by ``velocity_scale_mps`` (fixed
    scales, no running statistics); the robot input also gets the goal distance and direction.

    Output ``(B, features_dim)``: the robot code ``(hidden_dim)``, the pooled pedestrian code
    (``meanmax``: masked mean and max, ``2 * hidden_dim``; ``attention``: one attention head with
    the robot code as query, ``hidden_dim``) and the fraction of rows present ``(1)``. With no
    pedestrian the pooled code is 0.

    Args:
        observation_space: the environment's ``Dict`` space.
        hidden_dim: width of both encoders' two layers.
        pooling: ``meanmax`` or ``attention``.
        activation: activation name (``relu``, ``tanh``, ``elu``, ``leaky_relu``, ``silu``).
        position_scale_m: positions are divided by this, metres.
        velocity_scale_mps: velocities are divided by this, m/s.
        distances: also give the pedestrian encoder each row's distance to the robot, and (with forecasts) the
            distance of every forecast position (widths 5 and 5 + 3H instead of 4 and 4 + 2H).
        frame: ``world`` (the observation's axes) or ``goal``: every 2-D vector (goal offset, robot velocity,
            pedestrian positions, velocities and forecasts) is first rotated into the frame whose x axis points
            from the robot to the goal, as in SARL (Chen et al. 2019). With actions relative to the goal direction
            (:mod:`agents.actions`) the policy is then the same function whatever the goal's bearing, instead of
            having to learn every rotation. (The unicycle's heading, ``robot[4:6]``, stays in world axes.)
        robot_context: append the robot's scaled features (``R + 3``) to every pedestrian row, so the shared
            encoder judges each pedestrian against the robot's goal and velocity before pooling (the same in
            every arm; absent rows stay zero).
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        hidden_dim: int = 64,
        pooling: str = "meanmax",
        activation: str = "relu",
        position_scale_m: float = 5.0,
        velocity_scale_mps: float = 1.0,
        distances: bool = False,
        frame: str = "world",
        robot_context: bool = False,
    ) -> None:
        if frame not in FRAMES:
            raise ValueError(f"unknown frame {frame!r}; valid: {', '.join(FRAMES)}")
        if pooling not in POOLINGS:
            raise ValueError(f"unknown pooling {pooling!r}; valid: {', '.join(POOLINGS)}")
        if hidden_dim < 1:
            raise ValueError(f"hidden_dim must be >= 1, got {hidden_dim!r}")
        if not (position_scale_m > 0 and velocity_scale_mps > 0):
            raise ValueError("position_scale_m and velocity_scale_mps must be positive")
        keys = set(observation_space.spaces)
        if not {"robot", "pedestrians", "mask"} <= keys:
            raise ValueError(f"observation space must have robot, pedestrians and mask keys, got {sorted(keys)}")
        k = int(observation_space["mask"].n)  # type: ignore[attr-defined]
        robot_dim = int(math.prod(observation_space["robot"].shape))  # type: ignore[arg-type]
        forecast_dim = 0
        if "forecasts" in keys:
            forecast_dim = int(math.prod(observation_space["forecasts"].shape)) // k  # type: ignore[arg-type]
        horizon = forecast_dim // 2
        pooled = 2 * hidden_dim if pooling == "meanmax" else hidden_dim
        super().__init__(observation_space, features_dim=hidden_dim + pooled + 1)
        act = activation_class(activation)
        self.num_pedestrians = k
        self.forecast_dim = forecast_dim
        self.horizon = horizon
        self.distances = bool(distances)
        self.frame = frame
        self.robot_context = bool(robot_context)
        self.pooling = pooling
        inv_pos, inv_vel = 1.0 / float(position_scale_m), 1.0 / float(velocity_scale_mps)
        # robot: goal offset, velocity, the rest (heading, time left) as is, then goal distance and direction
        robot_scale = [inv_pos] * 2 + [inv_vel] * 2 + [1.0] * (robot_dim - 4) + [inv_pos, 1.0, 1.0]
        # row: position, velocity, [distance], forecast positions, [forecast distances]
        n_dist = (1 + horizon) if self.distances else 0
        row_scale = [inv_pos] * 2 + [inv_vel] * 2 + [inv_pos] * (forecast_dim + n_dist)
        self.register_buffer("robot_scale", torch.tensor(robot_scale, dtype=torch.float32), persistent=False)
        self.register_buffer("row_scale", torch.tensor(row_scale, dtype=torch.float32), persistent=False)
        self.nonnegative = act in (nn.ReLU,)
        self.robot_encoder = _mlp(robot_dim + 3, hidden_dim, act)
        n_context = robot_dim + 3 if self.robot_context else 0
        self.pedestrian_encoder = _mlp(PED_ROW + forecast_dim + n_dist + n_context, hidden_dim, act)
        if pooling == "attention":
            self.query = nn.Linear(hidden_dim, hidden_dim, bias=False)
            self.key = nn.Linear(hidden_dim, hidden_dim, bias=False)
            self.attn_scale = 1.0 / math.sqrt(hidden_dim)

    @property
    def pedestrian_input_layer(self) -> nn.Linear:
        """The only layer whose size depends on the forecast arm."""
        return self.pedestrian_encoder[0]  # type: ignore[return-value]

    def robot_features(self, robot: torch.Tensor) -> torch.Tensor:
        """``(B, R + 3)``: scaled goal offset and velocity, the rest as is, scaled goal distance and direction."""
        goal = robot[:, :2]
        dist = torch.linalg.vector_norm(goal, dim=1, keepdim=True)
        return torch.cat([robot, dist, goal / dist.clamp_min(1e-6)], dim=1) * self.robot_scale

    def to_goal_frame(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The observation with every 2-D vector rotated into the frame whose x axis points at the goal."""
        robot = obs["robot"]
        goal = robot[:, :2]
        dist = torch.linalg.vector_norm(goal, dim=1)
        at_goal = dist < 1e-6
        c = torch.where(at_goal, 1.0, goal[:, 0] / dist.clamp_min(1e-6))  # (B,)
        s = torch.where(at_goal, 0.0, goal[:, 1] / dist.clamp_min(1e-6))
        b, k = obs["mask"].shape
        out = dict(obs)
        out["robot"] = torch.cat([_rotate(robot[:, 0:2], c, s), _rotate(robot[:, 2:4], c, s), robot[:, 4:]], dim=1)
        peds = obs["pedestrians"].reshape(b, k, PED_ROW)
        ck, sk = c[:, None], s[:, None]
        out["pedestrians"] = torch.cat([_rotate(peds[..., 0:2], ck, sk), _rotate(peds[..., 2:4], ck, sk)], dim=-1)
        if self.forecast_dim:
            fc = obs["forecasts"].reshape(b, k, self.horizon, 2)
            out["forecasts"] = _rotate(fc, ck[..., None], sk[..., None])
        return out

    def pedestrian_features(self, obs: dict[str, torch.Tensor], present: torch.Tensor) -> torch.Tensor:
        """``(B, K, 4 [+ 1] [+ 2H [+ H]])`` scaled rows (with ``distances``: the distance to the robot now and of
        every forecast position), zero where absent."""
        b, k = present.shape
        parts = [obs["pedestrians"].reshape(b, k, PED_ROW)]
        if self.distances:
            parts.append(torch.linalg.vector_norm(parts[0][..., :2], dim=-1, keepdim=True))
        if self.forecast_dim:
            fc = obs["forecasts"].reshape(b, k, self.horizon, 2)
            parts.append(fc.reshape(b, k, self.forecast_dim))
            if self.distances:
                parts.append(torch.linalg.vector_norm(fc, dim=-1))
        rows = parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)
        rows = rows * self.row_scale
        if self.robot_context:
            context = self.robot_features(obs["robot"])
            rows = torch.cat([rows, context.unsqueeze(1).expand(b, k, context.shape[1])], dim=-1)
        return torch.where(present.unsqueeze(-1), rows, 0.0)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:  # type: ignore[override]
        mask = observations["mask"]  # (B, K) float 0/1
        present = mask > 0.5
        if self.frame == "goal":
            observations = self.to_goal_frame(observations)
        robot_h = self.robot_encoder(self.robot_features(observations["robot"]))  # (B, d)
        ped_h = self.pedestrian_encoder(self.pedestrian_features(observations, present))  # (B, K, d)
        count = present.sum(dim=1, keepdim=True, dtype=ped_h.dtype)  # (B, 1)
        m = present.unsqueeze(-1)
        masked = torch.where(m, ped_h, 0.0)
        if self.pooling == "meanmax":
            mean = masked.sum(dim=1) / count.clamp_min(1.0)
            if self.nonnegative:  # codes >= 0: filling absent rows with 0 leaves the max of the present ones
                peak = masked.amax(dim=1)
            else:
                peak = torch.where(count > 0, torch.where(m, ped_h, -math.inf).amax(dim=1), 0.0)
            pooled = torch.cat([mean, peak], dim=1)
        else:
            scores = torch.matmul(self.key(ped_h), self.query(robot_h).unsqueeze(-1)).squeeze(-1) * self.attn_scale
            # absent rows get -inf; with nobody present every score is 0 (a finite softmax) and the sum below is 0
            scores = torch.where(present, scores, torch.where(count > 0, -math.inf, 0.0))
            pooled = torch.matmul(torch.softmax(scores, dim=1).unsqueeze(1), masked).squeeze(1)
        return torch.cat([robot_h, pooled, count * (1.0 / self.num_pedestrians)], dim=1)


def _rotate(v: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """2-D vectors ``v`` ``(..., 2)`` rotated by minus the angle whose cosine and sine are ``c``, ``s`` (broadcast
    against ``v[..., 0]``): world axes -> a frame whose x axis has direction ``(c, s)``."""
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x + s * y, c * y - s * x], dim=-1)


def _policy_kwargs(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Defaults of the project's policies: this extractor, and activation names resolved to classes."""
    out = dict(kwargs)
    out.setdefault("features_extractor_class", CrowdFeaturesExtractor)
    if "activation_fn" in out:
        out["activation_fn"] = activation_class(out["activation_fn"])
    return out


class CrowdActorCriticPolicy(MultiInputActorCriticPolicy):
    """SB3's ``MultiInputPolicy`` for PPO/A2C with :class:`CrowdFeaturesExtractor` by default and
    ``activation_fn`` accepted as a name."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **_policy_kwargs(kwargs))


class CrowdSACPolicy(SACMultiInputPolicy):
    """SB3's SAC ``MultiInputPolicy`` with :class:`CrowdFeaturesExtractor` by default and ``activation_fn``
    accepted as a name."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **_policy_kwargs(kwargs))
