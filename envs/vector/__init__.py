"""The batched environment: N episodes of :class:`envs.crowd_nav.CrowdNavEnv` stepped at once in one process
(:class:`BatchedCrowdNavEnv`, the ``vector_entry_point`` of every environment id)."""

from envs.vector.batched import BatchedCrowdNavEnv

__all__ = ["BatchedCrowdNavEnv"]
