"""The planning-aid ablation: forecast arms x policies x seeds x held-out splits, run as resumable cells.

``python -m agents.ablation configs/ablation/planning_aid.yaml [--dry-run] [--workers N]
[--backend local|ray] [--address ADDR] [--only PATTERN] [--summarize-only] [--replicate DIR]`` (also
``crowdnav-mesrnn ablation ...``).

The grid
    A YAML config (see ``configs/ablation/planning_aid.yaml``) names forecast arms (``none``, ``cv``,
    ``mesrnn``, ``srnn``, ``vlstm``, ``oracle``, ``noisy_oracle`` expanded into one arm per target
    ADE, and uncertainty arms ``cv_unc``, ``mesrnn_unc``, ``srnn_unc``, ``vlstm_unc``: the source's forecasts plus
    their calibrated regions, which the ``planner``/``search`` policies keep clear of), policies (learned
    ``ppo``/``sac`` with an agent config and a training budget; non-learned ``planner``/``search``/``straight``/
    ``privileged``), training seeds, held-out splits and the fixed evaluation episode list. A planner policy may
    carry environment settings of its own on top of the grid's ``env`` (``policies.search@orca: {kind: search, env:
    {reaction: orca}}``): a policy that sets the pedestrians' ``reaction`` is keyed ``<planner>@<reaction>``, and the
    reaction's every parameter is resolved into its cells' specs (``configs/ablation/reactive.yaml``). A policy's
    ``priority`` orders the running of cells. ``reuse`` lists other grids' committed results folders whose cells this
    grid shares (below); it is not part of any cell's spec.
    It expands into *cells*:

    - ``train/<split>/<policy>/<arm>/seed<k>``: one training run (:func:`agents.training.run.train`) of a learned
      policy on the split's training scenes;
    - ``eval/<split>/<policy>/<arm>[/seed<k>]``: the trained model (its ``best`` or ``final`` model) or a
      planner evaluated with :func:`agents.evaluation.run.evaluate` on the split's held-out scene over the fixed
      episode list (``evaluation.episodes`` episodes from ``evaluation.seed``), identical in every cell. With
      ``evaluation.episodes_from: val`` every evaluation cell replays the split's training scenes in their validation
      period instead (a pilot: choices are made there, never on a held-out scene; the summary says so).

Cells and their state
    Every cell is a folder under ``runs_dir`` (default ``runs/ablation/<name>/``, gitignored) holding
    ``cell.json`` (what the cell is — its *spec* —, the predictor weights it used, timings) and, written
    last, ``DONE``. A cell is ``done`` (DONE present, spec and weights as now), ``stale`` (DONE present but its
    spec, the sha256 of the shipped predictor weights it used, or the model it evaluated changed: redone),
    ``partial`` (a folder without DONE: an interrupted run; a training cell resumes with
    ``train(..., resume=True)``, an evaluation cell is redone) or ``todo``. A cell without a folder is ``done``
    when committed results hold it (:func:`agents.ablation.results.from_results`): the grid's own (``out_dir``),
    else the folders of ``reuse`` in order, with a done record of the same cell name, an identical spec, the same
    predictor weights and its episodes (a training cell only with its evaluation: its model is not committed).
    Re-running the grid skips done cells, so a fresh clone re-runs no committed cell. ``--dry-run`` lists every
    cell with its state (and the results a cell done from them comes from) and an estimated time from the
    throughput of finished cells -- the grid's own (``cell.json``), else those the committed results record
    (``cells.json``) --, falling back to the config's ``estimates``; it says which it used.
    ``--replicate DIR --only PATTERN`` runs the selected cells afresh in the scratch folder ``DIR`` and
    compares each replicated evaluation with the grid's, episode by episode (:func:`replicate`): cells are
    seeded, so a difference means nondeterminism or a change of behaviour since the grid's cell ran (only grid
    cells that are ``done`` in a run folder are compared; the folder must be new or empty). It runs the cells even
    where committed results hold them: the way to run a committed cell again.

Backends
    ``local`` (default): a process pool (forkserver) of ``--workers`` processes (default: cores // the
    largest ``cpus`` of a cell), each with one torch thread; ``--workers 1`` runs cells one after the
    other in this process. ``ray``: the same cell function as Ray tasks (``ray.init(address=...)`` for an
    existing cluster, a local instance otherwise), ``num_cpus`` per task = the cell's ``cpus``; see
    :mod:`agents.ablation.ray_backend` for the supported Ray versions, the set-up, token authentication and
    how files and checkpoints travel without shared storage. On a cluster::

        CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --head --port=6379   # head node
        CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --address=HEAD:6379  # every other node
        python -m agents.ablation configs/ablation/planning_aid.yaml --backend ray --address HEAD:6379

    ``--address`` is probed (TCP, :data:`CONNECT_TIMEOUT_S` s) before any cell starts. Without ``--address`` a
    local Ray instance with ``--workers`` x the largest ``cpus`` is started (no dashboard) and shut down at
    the end. Ctrl-C: the first lets the running cells finish and starts no other (saying which it waits
    for), the second stops them now; an interrupted training run keeps its last checkpoint, taken at a
    round boundary, and the next run of the grid resumes it to exactly its budget, on either backend.

The answer
    :func:`summarize` reads the evaluation cells and writes ``summary.json``, ``summary.md`` and plots into
    ``out_dir`` (default ``results/ablation/<name>/``): rates with Wilson intervals and metric means with
    bootstrap intervals per policy and arm (pooled over splits and seeds, and per split), rates by crowd
    density bins, the pre-declared paired tests (exact McNemar on success, Wilcoxon signed-rank on the
    navigation time of episodes both arms finished, pairs = (training seed, episode)), Holm-corrected per
    endpoint with the family size stated, and the difference in success rate each McNemar design detects at
    the configured power. Where pedestrians react, it adds the disturbance metrics per arm (means with bootstrap
    percentile intervals), the declared change of each gain across reactions (``reaction_comparisons``: an exact
    sign-flip test of the per-episode difference of paired differences, Holm) and the declared disturbance comparisons
    (``disturbance_comparisons``: Wilcoxon, Holm per metric). It also writes ``cells.json`` (every cell's state,
    timings and spec) and ``episodes/`` (every evaluated episode, values as written, one file per policy:
    :mod:`agents.ablation.archive`); the statistics are computed from that archive, and a cell without a run folder is
    read from it (or from the ``reuse`` results that hold it: its record says ``"from": <folder>``), so the committed
    results alone render the same summary again. A summary never
    replaces one holding more (missing cells: refused, named; ``--force`` overrides), and files whose content would not
    change are left untouched (:mod:`agents.ablation.results`).
"""

from __future__ import annotations

from agents.ablation.backends import build_forecast_caches, replicate, run_grid
from agents.ablation.cells import (
    Cell,
    CellStatus,
    cell_dir,
    cell_spec,
    cell_status,
    check_environments,
    default_workers,
    estimate_seconds,
    expand,
    measured_rates,
    plan_on_disk,
    recorded_rates,
    select,
    trained_model,
    weights_fingerprint,
)
from agents.ablation.cli import add_arguments, main, run_from_args
from agents.ablation.config import (
    AGENT_CONFIG,
    ARM_SAMPLES,
    ARM_SOURCES,
    BACKENDS,
    CELL_JSON,
    CELL_STATES,
    DONE,
    EPISODES_FROM,
    GRID_ENV_KEYS,
    LEARNED_KINDS,
    LEARNED_SOURCES,
    MODEL_CHOICES,
    ONLINE_UNCERTAINTY_SUFFIX,
    OUTCOMES,
    POLICY_KINDS,
    REACTION_SEPARATOR,
    SAMPLES_KINDS,
    SAMPLES_SOURCES,
    SAMPLES_SUFFIX,
    TRAIN_RUN,
    UNCERTAINTY_KINDS,
    UNCERTAINTY_SOURCES,
    UNCERTAINTY_SUFFIX,
    AblationConfig,
    Arm,
    PolicySpec,
    config_from_mapping,
    load_config,
    resolve_env,
)
from agents.ablation.dryrun import dry_run
from agents.ablation.episodes import ARCHIVE_KEYS, aggregate, cell_record, episodes_archive, read_archive, read_episodes
from agents.ablation.execute import CellTask, execute_cell, train_overrides
from agents.ablation.plots import write_plots
from agents.ablation.ray_backend import CONNECT_TIMEOUT_S, RayBackend, check_address, execute_shipped
from agents.ablation.report import summary_markdown
from agents.ablation.results import ResultsKept, plan
from agents.ablation.stats import (
    by_density,
    density_edges,
    disturbance_summary,
    disturbance_tests,
    paired_tests,
    percentile_mean_ci,
    reaction_tests,
    sign_flip_exact,
)
from agents.ablation.summary import summarize

__all__ = [
    "AGENT_CONFIG",
    "ARCHIVE_KEYS",
    "ARM_SAMPLES",
    "ARM_SOURCES",
    "BACKENDS",
    "CELL_JSON",
    "CELL_STATES",
    "CONNECT_TIMEOUT_S",
    "DONE",
    "EPISODES_FROM",
    "GRID_ENV_KEYS",
    "LEARNED_KINDS",
    "LEARNED_SOURCES",
    "MODEL_CHOICES",
    "ONLINE_UNCERTAINTY_SUFFIX",
    "OUTCOMES",
    "POLICY_KINDS",
    "REACTION_SEPARATOR",
    "SAMPLES_KINDS",
    "SAMPLES_SOURCES",
    "SAMPLES_SUFFIX",
    "TRAIN_RUN",
    "UNCERTAINTY_KINDS",
    "UNCERTAINTY_SOURCES",
    "UNCERTAINTY_SUFFIX",
    "AblationConfig",
    "Arm",
    "Cell",
    "CellStatus",
    "CellTask",
    "PolicySpec",
    "RayBackend",
    "ResultsKept",
    "add_arguments",
    "aggregate",
    "build_forecast_caches",
    "by_density",
    "cell_dir",
    "cell_record",
    "cell_spec",
    "cell_status",
    "check_address",
    "check_environments",
    "config_from_mapping",
    "default_workers",
    "density_edges",
    "disturbance_summary",
    "disturbance_tests",
    "dry_run",
    "episodes_archive",
    "estimate_seconds",
    "execute_cell",
    "execute_shipped",
    "expand",
    "load_config",
    "main",
    "measured_rates",
    "paired_tests",
    "percentile_mean_ci",
    "plan",
    "plan_on_disk",
    "reaction_tests",
    "read_archive",
    "read_episodes",
    "recorded_rates",
    "replicate",
    "resolve_env",
    "run_from_args",
    "run_grid",
    "select",
    "sign_flip_exact",
    "summarize",
    "summary_markdown",
    "train_overrides",
    "trained_model",
    "weights_fingerprint",
    "write_plots",
]
