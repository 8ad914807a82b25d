"""The committed results as a source, and the rule that a summary never replaces one that holds more.

``results/ablation/<name>/`` is committed; the run folders (``runs/``) are not. Its ``cells.json`` (one record
per cell: state, timings with every attempt's start and end, the cell's spec) and ``episodes/`` (every evaluated
episode, values as the evaluations wrote them, one file per policy; :mod:`agents.ablation.archive`, which also reads
the single ``episodes.csv.gz`` of older results) hold everything :func:`agents.ablation.summarize` reads, so:

- a cell without a run folder is done, taken from the committed results, when they hold it as done and its spec
  and predictor weights are still the grid's (:func:`from_results`): the grid's own results first, then the other
  grids' results its config lists under ``reuse`` (a cell with the same name and an identical spec there is the same
  cell), in order. Running the grid skips it, so a fresh clone re-runs no committed cell, and its summary takes the
  cell's record and episodes from there (a record from another grid's results says so: ``"from": <folder>``);
- new result files are rendered completely before any file is replaced, each replaced atomically; an older
  ``episodes.csv.gz`` beside them is removed only when its rows are exactly the new archive's
  (:func:`agents.ablation.archive.settle_legacy`), else left with a warning;
- nothing is replaced by a summary that holds less: a cell done in the results but not now, or a complete
  summary replaced by an incomplete one, is refused (:class:`ResultsKept`, naming the missing cells) unless
  ``force``; a summary drawn from the grid's own archive alone that differs from the one it would replace (an archive
  written before it held start times and exact values) is refused the same way, saying what differs;
- when nothing but the stamps (code version, time) would change, the files are left untouched; when only the
  archive's layout would (the older single file, the same rows), only the archive is written.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from agents.ablation.archive import ARCHIVE_DIR, LEGACY_ARCHIVE, has_archive, read_rows
from agents.ablation.cells import (
    Cell,
    CellStatus,
    _file_sha256,
    cell_dir,
    cell_spec,
    plan_on_disk,
    trained_model,
    weights_fingerprint,
)
from agents.ablation.config import RESULTS_CELLS, AblationConfig
from agents.ablation.episodes import archive_rows, cell_record, read_episodes
from crowdnav_mesrnn.config import ConfigError

#: Keys of ``summary.json`` that name the checkout and the clock rather than the data.
STAMPS: Final[tuple[str, ...]] = ("code_version", "generated")

CELLS: Final[str] = RESULTS_CELLS
#: The older single archive's name, kept for imports written before ``episodes/`` (see ``config.RESULTS_ARCHIVE``).
ARCHIVE: Final[str] = LEGACY_ARCHIVE


class ResultsKept(Exception):
    """Result files were left as they are: the new summary would hold less, or differ from a re-render of the
    committed archive; the message says what and how to go on (``--force``)."""


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@dataclass
class Committed:
    """One committed results folder as a source of cells: its records, read when made, and its episodes, read once
    and only when asked for (an archive holds up to about 11 MB gzipped)."""

    folder: str
    """The folder as the config names it (``out_dir``, or an entry of ``reuse``)."""
    own: bool
    """The grid's own results (``out_dir``), not another grid's (``reuse``)."""
    records: dict[str, dict[str, Any]]
    """``cells.json``'s records by cell name."""
    _rows: dict[str, list[dict[str, str]]] | None = field(default=None, repr=False)

    def rows(self) -> dict[str, list[dict[str, str]]]:
        """The archive's rows (:func:`agents.ablation.archive.read_rows`) per evaluation cell name
        (:func:`agents.ablation.episodes.archive_rows`)."""
        if self._rows is None:
            self._rows = archive_rows(read_rows(self.folder))
        return self._rows


def committed(cfg: AblationConfig) -> list[Committed]:
    """The grid's own committed results (empty when ``out_dir`` holds no ``cells.json`` and episode archive), then
    each folder of its ``reuse``, in order. Raises :class:`ConfigError` naming ``reuse`` for a folder whose files are
    missing or whose ``cells.json`` is not a list of records."""
    own = str(cfg.out_path())
    records = _load_json(Path(own) / CELLS)
    if not isinstance(records, list) or not has_archive(own):
        records = []
    out = [Committed(own, True, _by_cell(records))]
    for folder in cfg.reuse:
        if not (Path(folder) / CELLS).is_file():
            raise ConfigError(f"ablation config key 'reuse': {Path(folder) / CELLS} is missing")
        if not has_archive(folder):
            raise ConfigError(f"ablation config key 'reuse': {Path(folder) / ARCHIVE_DIR}/ is missing")
        records = _load_json(Path(folder) / CELLS)
        if not isinstance(records, list):
            raise ConfigError(f"ablation config key 'reuse': {Path(folder) / CELLS} is not a list of cell records")
        out.append(Committed(folder, False, _by_cell(records)))
    return out


def _by_cell(records: Sequence[Any]) -> dict[str, dict[str, Any]]:
    return {r["cell"]: r for r in records if isinstance(r, dict) and "cell" in r}


def _still_valid(cfg: AblationConfig, cell: Cell, rec: Mapping[str, Any]) -> str:
    """Why an archived done cell no longer counts as done ("" if it does): its spec or weights changed."""
    if rec.get("spec") is not None and rec["spec"] != cell_spec(cfg, cell):
        return "spec changed"
    weights = {k: v[:12] for k, v in weights_fingerprint(cell.arm.predictor).items()}
    if rec.get("weights_sha256", weights) != weights:
        return "predictor weights changed"
    return ""


def _same_cell(cfg: AblationConfig, cell: Cell, source: Committed) -> bool:
    """``source`` records ``cell`` as done with this grid's spec (in another grid's results: the very same spec,
    ``==``; the grid's own records predating specs count, as ever) and predictor weights (:func:`_still_valid`)."""
    rec = source.records.get(cell.name)
    if rec is None or rec.get("state") != "done":
        return False
    if not source.own and rec.get("spec") != cell_spec(cfg, cell):
        return False
    return not _still_valid(cfg, cell, rec)


def _holds(cfg: AblationConfig, cell: Cell, source: Committed) -> bool:
    """``source`` holds ``cell`` as done (:func:`_same_cell`) and, for an evaluation, its episodes."""
    return _same_cell(cfg, cell, source) and (cell.kind != "eval" or bool(source.rows().get(cell.name)))


def _source_of(
    cfg: AblationConfig, cell: Cell, train: CellStatus | None, sources: Sequence[Committed]
) -> Committed | None:
    """The first of ``sources`` an evaluation cell without a run folder is taken from (``None``: it runs).

    An evaluation of a learned policy is taken only with its training (``train``, the training cell's state on disk):
    without a run folder, that training's record must be done there too (the pair is that results' answer; the model
    is not committed, so the training is not run for nothing); with a finished one, the record must name its model
    (``model_sha256``); a training that runs here (partial, stale) is evaluated here."""
    for source in sources:
        if not _holds(cfg, cell, source):
            continue
        if cell.needs is not None and train is not None:
            if train.state == "todo":
                if not _holds(cfg, dataclasses.replace(cell, kind="train"), source):
                    continue
            elif train.state == "done":
                model = trained_model(cell_dir(cfg, cell.needs), cell.policy.model)
                if model is None or source.records[cell.name].get("model_sha256") != _file_sha256(model)[:12]:
                    continue
            else:
                continue
        return source
    return None


def plan(
    cfg: AblationConfig, cells: Sequence[Cell] | None = None, committed: Sequence[Committed] | None = None
) -> list[CellStatus]:
    """States of ``cells`` (default: the whole grid), training cells resolved before their evaluations.

    A cell without a run folder (``todo``) is ``done`` when the committed results hold it: the grid's own, else its
    ``reuse`` folders in order (:func:`from_results`; its :attr:`~agents.ablation.cells.CellStatus.source` says
    which). ``committed``: those results read already (:func:`committed`), else read here.
    """
    statuses, train_states = plan_on_disk(cfg, cells)
    return from_results(cfg, statuses, train_states, committed)


def from_results(
    cfg: AblationConfig,
    statuses: Sequence[CellStatus],
    train_states: Mapping[str, CellStatus],
    sources: Sequence[Committed] | None = None,
) -> list[CellStatus]:
    """``statuses`` (states on disk, :func:`agents.ablation.cells.plan_on_disk`) with every cell without a run folder that the
    committed results hold (:func:`_source_of`) made ``done`` from there: ``source`` the folder, ``record`` its record,
    ``reason`` "from <folder>". ``sources``: :func:`committed` (read here if ``None``).

    A training cell, whose model is not committed, is taken only together with its evaluation: when that evaluation
    has no run folder and is taken from the same results. An evaluation that has to run thus never lacks its model
    (``--replicate`` runs both afresh)."""
    if not any(st.state == "todo" for st in statuses):
        return list(statuses)
    sources = committed(cfg) if sources is None else sources
    out: list[CellStatus] = []
    for st in statuses:
        cell = st.cell
        source = None
        if st.state == "todo" and cell.kind == "eval":
            source = _source_of(cfg, cell, train_states.get(cell.needs or ""), sources)
        elif st.state == "todo":
            evaluation = dataclasses.replace(cell, kind="eval")
            if not cell_dir(cfg, evaluation).exists():
                source = _source_of(cfg, evaluation, st, sources)
        if source is None:
            out.append(st)
            continue
        why = f"from {source.folder}" + (", with its evaluation; its model is not here" if cell.kind == "train" else "")
        out.append(
            dataclasses.replace(st, state="done", reason=why, source=source.folder, record=source.records[cell.name])
        )
    return out


def _not_held(cfg: AblationConfig, cell: Cell, sources: Sequence[Committed]) -> tuple[dict[str, Any], str] | None:
    """The record of a cell without a run folder that no committed results hold (:func:`from_results`), and where it is
    from (``archive``, ``reused``): the grid's own, ``stale`` if it says ``done`` (its spec, weights or training
    changed, or its episodes are missing); else the first other grid's that records this very cell as done but lacks its
    episodes or its training, ``stale`` with ``"from"``; ``None`` if neither."""
    own, *others = sources
    if cell.name in own.records:
        rec = dict(own.records[cell.name])
        if rec.get("state") == "done":
            rec["state"] = "stale"
        return rec, "archive"
    for source in others:
        if _same_cell(cfg, cell, source):
            return {**source.records[cell.name], "state": "stale", "from": source.folder}, "reused"
    return None


def gather(
    cfg: AblationConfig,
) -> tuple[list[dict[str, Any]], list[tuple[str, str, str, int | None, list[Mapping[str, str]]]], dict[str, int]]:
    """Every cell's record and the episodes of the done evaluation cells, from the run folders, or for a cell that has
    no folder from the committed results that hold it (:func:`from_results`): its record as committed there (another
    grid's with ``"from": <folder>`` added), its episodes from that archive. A cell without a folder that they record
    but do not hold keeps its record there, ``stale`` if it says ``done`` (:func:`_not_held`).

    Returns the records (grid order), ``(policy, arm, split, seed, rows)`` per done evaluation cell, and how
    many cells came from ``runs``, from the grid's own ``archive`` and from other grids' results (``reused``).
    """
    sources = committed(cfg)
    records: list[dict[str, Any]] = []
    episodes: list[tuple[str, str, str, int | None, list[Mapping[str, str]]]] = []
    counts = {"runs": 0, "archive": 0, "reused": 0}
    by_folder = {s.folder: s for s in sources}
    for st in plan(cfg, committed=sources):
        cell = st.cell
        rec, rows = cell_record(st), None
        if st.source:
            source = by_folder[st.source]
            rec = dict(st.record or {}) if source.own else {**(st.record or {}), "from": source.folder}
            rows = source.rows()[cell.name] if cell.kind == "eval" else None
            counts["archive" if source.own else "reused"] += 1
        elif st.state != "todo":
            counts["runs"] += 1
            if st.state == "done" and cell.kind == "eval":
                rows = read_episodes(cell_dir(cfg, cell) / "episodes.csv")
        elif (kept := _not_held(cfg, cell, sources)) is not None:
            rec, where = kept
            counts[where] += 1
        records.append(rec)
        if rows is not None:
            episodes.append((cell.policy.name, cell.arm.label, cell.split, cell.seed, rows))
    return records, episodes, counts


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
    lists the missing cells); a summary drawn only from the grid's own committed archive (``sources``: no cell from run
    folders or other grids' results) that differs from the one there (the message lists what differs, and why when the
    archive's records lack start times).
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
    if sources.get("runs", 0) == 0 and sources.get("reused", 0) == 0 and sources.get("archive", 0) > 0:
        diffs = _differences(_strip(old), json.loads(json.dumps(_strip(summary))))
        legacy = any("attempts" not in r for r in old_cells or [] if isinstance(r, dict))
        why = (
            f" Its {CELLS} predates complete records: no attempt start times (and the {LEGACY_ARCHIVE} of that version "
            "rounds every metric to 4 decimals), so the summary it was written with cannot be recomputed from it."
            if legacy
            else ""
        )
        raise ResultsKept(
            f"kept {dest}/ as it is: no run folders here, and the summary re-rendered from the committed archive "
            f"and {CELLS} differs from the one there in {len(diffs) or 'its text, not its data'}"
            + (f" value(s): {'; '.join(diffs[:6])}{' ...' if len(diffs) > 6 else ''}." if diffs else ".")
            + why
            + " Pass --force to replace the results with the re-render, or summarise from the run folders."
        )
