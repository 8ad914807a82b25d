"""The committed results as a source, and the rule that a summary never replaces one that holds more.

``results/ablation/<name>/`` is committed; the run folders (``runs/``) are not. Its ``cells.json`` (one record
per cell: state, timings with every attempt's start and end, the cell's spec) and ``episodes.csv.gz`` (every
evaluated episode, values as the evaluations wrote them) hold everything :func:`agents.ablation.summarize`
reads, so:

- a cell without a run folder is taken from the committed results when they hold it as done (and its spec
  and predictor weights are still the grid's): a fresh clone summarises the shipped grid again;
- new result files are rendered completely before any file is replaced, each replaced atomically;
- nothing is replaced by a summary that holds less: a cell done in the results but not now, or a complete
  summary replaced by an incomplete one, is refused (:class:`ResultsKept`, naming the missing cells) unless
  ``force``; a summary drawn from the archive alone that differs from the one it would replace (an archive
  written before it held start times and exact values) is refused the same way, saying what differs;
- when nothing but the stamps (code version, time) would change, the files are left untouched.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

from agents.ablation.cells import CellStatus, cell_dir, cell_spec, plan, weights_fingerprint
from agents.ablation.config import AblationConfig
from agents.ablation.episodes import archive_rows, cell_record, read_episodes

#: Keys of ``summary.json`` that name the checkout and the clock rather than the data.
STAMPS: Final[tuple[str, ...]] = ("code_version", "generated")

ARCHIVE: Final[str] = "episodes.csv.gz"
CELLS: Final[str] = "cells.json"


class ResultsKept(Exception):
    """Result files were left as they are: the new summary would hold less, or differ from a re-render of the
    committed archive; the message says what and how to go on (``--force``)."""


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _archived(cfg: AblationConfig) -> tuple[dict[str, dict[str, Any]], dict[str, list[dict[str, str]]]]:
    """The committed records (by cell name) and episodes (by evaluation cell name); empty without results."""
    dest = cfg.out_path()
    records = _load_json(dest / CELLS)
    if not isinstance(records, list) or not (dest / ARCHIVE).is_file():
        return {}, {}
    return {r["cell"]: r for r in records if isinstance(r, dict) and "cell" in r}, archive_rows(
        (dest / ARCHIVE).read_bytes()
    )


def _still_valid(cfg: AblationConfig, st: CellStatus, rec: Mapping[str, Any]) -> str:
    """Why an archived done cell no longer counts as done ("" if it does): its spec or weights changed."""
    if rec.get("spec") is not None and rec["spec"] != cell_spec(cfg, st.cell):
        return "spec changed"
    weights = {k: v[:12] for k, v in weights_fingerprint(st.cell.arm.predictor).items()}
    if rec.get("weights_sha256", weights) != weights:
        return "predictor weights changed"
    return ""


def gather(
    cfg: AblationConfig,
) -> tuple[list[dict[str, Any]], list[tuple[str, str, str, int | None, list[Mapping[str, str]]]], dict[str, int]]:
    """Every cell's record and the episodes of the done evaluation cells, from the run folders, or from the
    committed results for a cell that has no folder.

    Returns the records (grid order), ``(policy, arm, split, seed, rows)`` per done evaluation cell, and how
    many cells came from ``runs`` and from the ``archive``.
    """
    archived, archived_rows = _archived(cfg)
    records: list[dict[str, Any]] = []
    episodes: list[tuple[str, str, str, int | None, list[Mapping[str, str]]]] = []
    sources = {"runs": 0, "archive": 0}
    for st in plan(cfg):
        cell = st.cell
        rec, rows = cell_record(st), None
        if st.state != "todo":
            sources["runs"] += 1
            if st.state == "done" and cell.kind == "eval":
                rows = read_episodes(cell_dir(cfg, cell) / "episodes.csv")
        elif cell.name in archived:
            rec = dict(archived[cell.name])
            why = _still_valid(cfg, st, rec) if rec.get("state") == "done" else ""
            rows = archived_rows.get(cell.name) if rec.get("state") == "done" and cell.kind == "eval" else None
            if why or (cell.kind == "eval" and rec.get("state") == "done" and not rows):
                rec["state"] = "stale"
                rows = None
            sources["archive"] += 1
        records.append(rec)
        if rows is not None:
            episodes.append((cell.policy.name, cell.arm.label, cell.split, cell.seed, rows))
    return records, episodes, sources


def _strip(summary: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in summary.items() if k not in STAMPS}


def _differences(old: Any, new: Any, path: str = "") -> list[str]:
    """Paths (``a.b[2]``) where two JSON values differ, with both values."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for key in list(old) + [k for k in new if k not in old]:
            sub = f"{path}.{key}" if path else str(key)
            if key not in new or key not in old:
                out.append(
                    f"{sub}: {'absent' if key not in old else 'present'} -> {'absent' if key not in new else 'present'}"
                )
            else:
                out += _differences(old[key], new[key], sub)
        return out
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [d for i, (a, b) in enumerate(zip(old, new, strict=True)) for d in _differences(a, b, f"{path}[{i}]")]
    return [] if old == new else [f"{path}: {_short(old)} -> {_short(new)}"]


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _names(cells: Sequence[str], limit: int = 12) -> str:
    more = f" and {len(cells) - limit} more" if len(cells) > limit else ""
    return ", ".join(cells[:limit]) + more


def check_replace(
    cfg: AblationConfig,
    summary: Mapping[str, Any],
    records: Sequence[Mapping[str, Any]],
    sources: Mapping[str, int],
    force: bool,
) -> None:
    """Raise :class:`ResultsKept` (unless ``force``) when the new summary must not replace the results there.

    Refused: a cell done there but not here, or a complete summary replaced by an incomplete one (the message
    lists the missing cells); a summary drawn only from the committed archive that differs from the one there
    (the message lists what differs, and why when the archive's records lack start times).
    """
    dest = cfg.out_path()
    old = _load_json(dest / "summary.json")
    old_cells = _load_json(dest / CELLS)
    if force or not isinstance(old, dict):
        return
    old_done = [r["cell"] for r in old_cells or [] if isinstance(r, dict) and r.get("state") == "done"]
    new_done = {r["cell"] for r in records if r.get("state") == "done"}
    lost = [c for c in old_done if c not in new_done]
    incomplete = bool(old.get("complete")) and not summary["complete"]
    if lost or incomplete:
        missing = lost + [c for c in summary["missing_cells"] if c not in lost]
        raise ResultsKept(
            f"kept {dest}/ as it is: the new summary would hold less than the one there "
            f"({len(old_done)} cells done there, {len(new_done)} here); missing {len(missing)} cell(s): "
            f"{_names(missing)}. Finish them (python -m agents.ablation {cfg.source or 'CONFIG'}), or pass --force "
            "to replace the results with this summary."
        )
    if sources.get("runs", 0) == 0 and sources.get("archive", 0) > 0:
        diffs = _differences(_strip(old), json.loads(json.dumps(_strip(summary))))
        legacy = any("attempts" not in r for r in old_cells or [] if isinstance(r, dict))
        why = (
            f" Its {CELLS} predates complete records: no attempt start times (and the {ARCHIVE} of that version "
            "rounds every metric to 4 decimals), so the summary it was written with cannot be recomputed from it."
            if legacy
            else ""
        )
        raise ResultsKept(
            f"kept {dest}/ as it is: no run folders here, and the summary re-rendered from the committed {ARCHIVE} "
            f"and {CELLS} differs from the one there in {len(diffs) or 'its text, not its data'}"
            + (f" value(s): {'; '.join(diffs[:6])}{' ...' if len(diffs) > 6 else ''}." if diffs else ".")
            + why
            + " Pass --force to replace the results with the re-render, or summarise from the run folders."
        )
