"""Registers the environment ids with Gymnasium using string entry points.

Nothing of ``envs`` is imported here: the entry point is resolved only when an env is made.
"""

from __future__ import annotations

import gymnasium

ENTRY_POINT = "envs.crowd_nav:CrowdNavEnv"
#: ``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")``: N episodes batched in one process
#: (single environments, with a warning, for what the batched one does not step).
VECTOR_ENTRY_POINT = "envs.vector:make_vector_env"

#: id -> the forecast source it uses; every other setting is the same.
ENV_IDS: dict[str, str] = {
    "CrowdNav-MESRNN-v0": "mesrnn",
    "CrowdNav-NoPred-v0": "none",
    "CrowdNav-CV-v0": "cv",
    "CrowdNav-Oracle-v0": "oracle",
}


def register_envs() -> None:
    """Register every id once (safe to call repeatedly)."""
    for env_id, predictor in ENV_IDS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point=ENTRY_POINT,
            vector_entry_point=VECTOR_ENTRY_POINT,
            kwargs={"predictor": predictor},
        )
