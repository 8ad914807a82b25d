"""The shipped planners and the privileged ceiling on the episodes a user's policy ran: from the committed planner
grid when it holds exactly those episodes, else run here.

The planner grid (``configs/ablation/planners.yaml``, results in ``results/ablation/planners/``) evaluated the
sampling planner (arms none, cv, mesrnn, oracle), the search planner (cv, mesrnn, oracle: in the none arm it
extrapolates the observed velocities, i.e. its cv arm) and the privileged ceiling (one arm: it reads the true
future, so its forecast input is unused) on the first 500 episodes of every held-out scene's fixed list
(:func:`agents.rollout.evaluation_seeds`, list 0). The first ``n`` of a list are the list of ``n``, so the
grid's episodes ``0 .. n-1`` are a bench of ``n`` episodes -- when:

- the grid's cell is still valid (:func:`agents.ablation.results.gather`: its spec, which holds the environment
  revision and settings, and its predictor weights are the current ones);
- the bench runs the grid's list (``seed``) with the grid's environment settings (none: ``env: {}``) and
  ``n`` is at most the grid's 500;
- the episodes are the same, checked episode by episode on the policy-independent ``crowd_density``.

Otherwise the reference runs here (:func:`agents.evaluation.evaluate`, the very evaluation a grid cell runs), its
files under ``<out>/references/`` (reused by the next bench with the same episodes and environment revision).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

#: Reference name -> (policy name in the planner grid, planner kind for agents.evaluate).
REFERENCES: Final[dict[str, tuple[str, str]]] = {
    "sampling": ("planner", "planner"),
    "search": ("search", "search"),
    "privileged": ("privileged", "privileged"),
}
#: Readable names of the references.
REFERENCE_LABELS: Final[dict[str, str]] = {
    "sampling": "sampling planner",
    "search": "search planner",
    "privileged": "privileged ceiling (PRIVILEGED: reads the true future)",
}
#: Arms a reference does not run (as in the planner grid): the search planner's none arm is its cv arm.
SKIPPED_ARMS: Final[dict[str, tuple[str, ...]]] = {"search": ("none",)}
#: The arm the privileged ceiling runs in, whatever the bench's arm (its forecast input is unused).
CEILING_ARM: Final[str] = "oracle"
#: The committed planner grid, relative to the repository.
GRID_CONFIG: Final[str] = "configs/ablation/planners.yaml"


def reference_arms(reference: str, arms: Sequence[str]) -> list[str]:
    """The arms ``reference`` runs for a bench of ``arms``: the ceiling one, the search planner all but none."""
    if reference == "privileged":
        return [CEILING_ARM]
    return [a for a in arms if a not in SKIPPED_ARMS.get(reference, ())]


def _repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def committed_grid(root: Path | None = None) -> tuple[Any, dict[tuple[str, str, str], list[Mapping[str, str]]]]:
    """The planner grid's config and its valid evaluated episodes per ``(grid policy, arm, split)`` (rows sorted
    by episode); ``(None, {})`` when the checkout holds no grid (an installed package)."""
    from agents.ablation.archive import has_archive
    from agents.ablation.config import load_config
    from agents.ablation.results import gather

    root = root or _repo_root()
    path = root / GRID_CONFIG
    if not path.is_file():
        return None, {}
    cfg = load_config(path)
    cfg = dataclasses.replace(
        cfg,
        out_dir=str(root / cfg.out_path()),
        runs_dir=str(root / cfg.runs_path()),
        reuse=tuple(str(root / r) for r in cfg.reuse),
        source=str(path),
    )
    if not has_archive(cfg.out_path()):
        return cfg, {}
    _records, episodes, _sources = gather(cfg)
    cells = {
        (policy, arm, split): sorted(rows, key=lambda r: int(float(r["episode"])))
        for policy, arm, split, seed, rows in episodes
        if seed is None
    }
    return cfg, cells


def _density(row: Mapping[str, Any]) -> float:
    try:
        return float(row.get("crowd_density"))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def same_episodes(ours: Sequence[Mapping[str, Any]], theirs: Sequence[Mapping[str, Any]]) -> bool:
    """The two lists hold the same episodes in order: one per index, equal crowd densities (a property of the
    episode -- recording, start time, start and goal -- not of the policy)."""
    if len(ours) != len(theirs):
        return False
    for a, b in zip(ours, theirs, strict=True):
        if int(float(a["episode"])) != int(float(b["episode"])):
            return False
        da, db = _density(a), _density(b)
        if not (math.isfinite(da) and math.isfinite(db) and abs(da - db) <= 1e-9 * max(1.0, abs(da))):
            return False
    return True


def reference_rows(
    reference: str,
    arm: str,
    split: str,
    episodes: int,
    seed: int,
    env_overrides: Mapping[str, Any],
    policy_rows: Sequence[Mapping[str, Any]],
    out_dir: Path,
    grid: tuple[Any, Mapping[tuple[str, str, str], list[Mapping[str, str]]]],
    rerun: bool = False,
    progress: bool = False,
    log: Callable[[str], None] = lambda _m: None,
) -> tuple[list[Mapping[str, Any]], str]:
    """A reference's episodes on the bench's list and where they came from (``"committed"``: the planner grid,
    ``"cached"``: an earlier bench into ``out_dir``, ``"run"``: evaluated now).

    Args:
        reference: ``sampling``, ``search`` or ``privileged``.
        arm: the reference's arm (:func:`reference_arms`).
        policy_rows: the user's policy's episodes of this scene (to check the episodes are the same).
        out_dir: the bench's ``references/`` folder.
        grid: :func:`committed_grid`.
        rerun: never take the committed grid's episodes.
    """
    from agents.evaluation import evaluate, read_episodes
    from envs.crowd_nav import ENV_REVISION
    from envs.reaction import revision_rules

    grid_name, kind = REFERENCES[reference]
    cfg, cells = grid
    rows = cells.get((grid_name, arm, split))
    if (
        not rerun
        and rows is not None
        and cfg is not None
        and cfg.eval_seed == seed
        and not dict(cfg.env)
        and not dict(env_overrides)
        and episodes <= len(rows)
    ):
        first = rows[:episodes]
        if same_episodes(policy_rows, first):
            return list(first), "committed"
        log(f"  {reference}/{arm} on {split}: the committed episodes differ from these; running it here")
    folder = out_dir / split / reference / arm
    summary_path = folder / "summary.json"
    try:
        done = json.loads(summary_path.read_text())
    except (OSError, ValueError):
        done = None
    if (
        isinstance(done, dict)
        and done.get("episodes") == episodes
        and done.get("seed") == seed
        and done.get("env_revision") == ENV_REVISION
        and done.get("reaction_revision")
        == revision_rules(env_overrides.get("reaction", "none")).get("reaction_revision")
        and dict(done.get("env_overrides") or {}) == dict(env_overrides)
    ):
        cached = read_episodes(folder)
        if same_episodes(policy_rows, cached):
            return cached, "cached"
    log(f"  {reference}/{arm} on {split}: {episodes} episodes")
    summary = evaluate(
        kind,
        arm,
        split,
        episodes,
        seed=seed,
        out_dir=folder,
        env_overrides=dict(env_overrides) or None,
        progress=progress,
    )
    summary["env_overrides"] = dict(env_overrides)
    from crowdnav_mesrnn.utils import atomic_write_json

    atomic_write_json(summary_path, summary)
    return read_episodes(folder), "run"
