"""The layout of ``crowdnav_mesrnn``: moved modules and names still import from their old paths (with a
``DeprecationWarning``, the same objects), nothing in the repository uses an old path, and the package's import
graph has no cycle."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

EVAL = "crowdnav_mesrnn.evaluation"
UNC = "crowdnav_mesrnn.uncertainty"
STUDIES = "crowdnav_mesrnn.studies"

#: Old module -> new module -> the old module's public names that now live there.
SHIMS: dict[str, dict[str, str]] = {
    "crowdnav_mesrnn.stats": {
        f"{EVAL}.statistics": "DEFAULT_BLOCK_LEN DEFAULT_RESAMPLES PairedErrors SeededDifference SeededErrors "
        "average_ci block_bootstrap_ci block_bootstrap_replicates block_totals_replicates combine_interval "
        "ratio_differences seeded_average_ci seeded_difference_ci verdict",
    },
    "crowdnav_mesrnn.calibration": {
        f"{UNC}.conformal": "CALIBRATION_FORMAT LEVELS SCORES SIGMA_FLOOR_M Calibration Coverage ErrorModel "
        "conformal_quantile conformal_thresholds gaussians_of level_key measure_coverage region_scores",
        f"{UNC}.calibration": "Forecaster average_fields calibrate_model calibration_from_scores calibration_scores "
        "coverage_fields fit_calibration forecaster_for format_calibration",
    },
    "crowdnav_mesrnn.online_conformal": {
        f"{UNC}.online_conformal": "EXPERT_INTERVAL GAMMA_GRID GAMMA_RULES GAMMA_TOLERANCE METHODS REVEAL_RULES "
        "Feedback OnlineResult Stream aggregate_thresholds choose_gamma expert_rates feedback_stream "
        "online_coverage online_for_split scene_streams track_thresholds unit_radius validation_deviation "
        "window_clock",
    },
    "crowdnav_mesrnn.head_fit": {
        "crowdnav_mesrnn.training.head_fit": "HEAD_KEYS SHORTCUT_NOTE HeadFitConfig HeadRows fit_head "
        "fit_head_on_rows gaussian_network head_rows metres_offset validation_nll_m",
    },
    "crowdnav_mesrnn.plan": {
        f"{STUDIES}.plan": "REPO_ROOT STAGES Candidate Plan Run candidate_runs execute export load_plan "
        "parse_shard read_done run_dir run_lock seed_runs selected_candidate shard_filter stage_runs status "
        "summary train_run yaml_scalar",
        f"{STUDIES}.plan_budget": "Rate dry_run epoch_rates measure_rate observed_rates",
        "crowdnav_mesrnn.cli.predictor": "main_plan",
    },
    "crowdnav_mesrnn.report": {
        f"{STUDIES}.report": "PAIRS WindowErrors add_claims build_plan_report build_report compare seed_results",
        f"{STUDIES}.report_render": "COLS FIGURES LABELS NAMES OPTIONS PLAN_FILE PUBLISHED_SGAN REPRODUCE SECTIONS "
        "candidate_confounds ordering render render_candidates_test render_comparisons render_plan "
        "render_seeds reproduce_rows",
    },
    "crowdnav_mesrnn.plotting": {f"{STUDIES}.plotting": "COLOURS plot_window"},
    "crowdnav_mesrnn.cli_predictor": {"crowdnav_mesrnn.cli.predictor": "add_parser"},
    "crowdnav_mesrnn.claims": {},
    "crowdnav_mesrnn.claims.compute": {
        f"{STUDIES}.claims.compute": "COMMAND LEARNED MODELS Measured POOLED check_headline claims_results "
        "compute_claims measure_all tables verdicts weights_for",
    },
    "crowdnav_mesrnn.claims.declared": {f"{STUDIES}.claims.declared": "DECLARED ClaimsConfig"},
    "crowdnav_mesrnn.claims.measure": {
        f"{STUDIES}.claims.measure": "FORECAST_KEYS MOTIONS bin_label colliding_pairs density_bin measure_batch "
        "measure_windows motion_types",
    },
    "crowdnav_mesrnn.claims.render": {f"{STUDIES}.claims.render": "MODEL_ORDER NAMES render_claims"},
}

#: Modules (and packages) that stayed, or became a package of the same name, and serve names that moved out of
#: them through ``__getattr__``: module -> new module -> names.
MOVED_ATTRIBUTES: dict[str, dict[str, str]] = {
    EVAL: {
        f"{EVAL}.metrics": "BatchPredictFn DISTRIBUTION_KEYS DistributionFn METRIC_KEYS SampleFn ScoredForecasts "
        "batches collect_forecasts cv_predict_batch distribution_metrics evaluate_windows predicted_batches "
        "summarise window_errors",
        f"{EVAL}.protocol": "PAIRED_KEYS SAMPLINGS evaluate_model evaluate_versus format_result paired_differences "
        "paired_sums resolve_splits split_norm",
    },
    "crowdnav_mesrnn.training": {
        "crowdnav_mesrnn.training.trainer": "CONFIG_DIR PRECISIONS SELECT_ON TrainConfig Trainer "
        "TrainingDivergedError clip_gradients gaussian_nll_loss keep_freed_memory load_configs make_optimizer "
        "masked_loss rotate_windows training_loss",
    },
    "crowdnav_mesrnn.models.structural_rnn": {
        "crowdnav_mesrnn.models.architecture": "HEADS MODEL_TYPES ModelConfig",
        "crowdnav_mesrnn.models.online": "lstm_pointwise_from_sigmoid",
    },
}

#: Names renamed on the way: (old module, old name) -> (new module, new name).
RENAMED = {("crowdnav_mesrnn.cli", "add_data"): ("crowdnav_mesrnn.cli.data", "add_parser")}


def _names(table: dict[str, str]) -> list[tuple[str, str]]:
    return [(new, name) for new, names in table.items() for name in names.split()]


@pytest.mark.parametrize("old", list(SHIMS))
def test_an_old_module_path_imports_warns_and_holds_the_same_objects(old: str) -> None:
    for new, _ in _names(SHIMS[old]):
        importlib.import_module(new)  # the new modules are loaded before, so only the shim's own warning is seen
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=rf"^{old} moved to "):
        shim = importlib.import_module(old)
    for new, name in _names(SHIMS[old]):
        assert getattr(shim, name) is getattr(importlib.import_module(new), name), f"{old}.{name} is not {new}.{name}"


@pytest.mark.parametrize("module", list(MOVED_ATTRIBUTES))
def test_a_moved_name_is_served_from_its_old_module_with_a_warning(module: str) -> None:
    mod = importlib.import_module(module)
    for new, name in _names(MOVED_ATTRIBUTES[module]):
        with pytest.warns(DeprecationWarning, match=rf"^{module}\.{name} moved to {new}\.{name}"):
            value = getattr(mod, name)
        assert value is getattr(importlib.import_module(new), name)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        mod.not_a_name  # noqa: B018


def test_renamed_names_are_served_from_their_old_path() -> None:
    for (module, name), (new, new_name) in RENAMED.items():
        with pytest.warns(DeprecationWarning, match=rf"^{module}\.{name} moved"):
            value = getattr(importlib.import_module(module), name)
        assert value is getattr(importlib.import_module(new), new_name)


@pytest.mark.slow
def test_the_warning_points_at_the_line_using_the_old_path() -> None:
    """``stacklevel`` reaches past the shim and importlib: the filter of ``pyproject.toml``
    (``error::DeprecationWarning:crowdnav_mesrnn.*``) then catches any old path used inside the package."""
    code = (
        "import warnings\n"
        "warnings.simplefilter('always')\n"
        "with warnings.catch_warnings(record=True) as seen:\n"
        "    import crowdnav_mesrnn.stats\n"
        "    from crowdnav_mesrnn.evaluation import evaluate_model\n"
        "print(sorted({(w.filename, w.lineno) for w in seen}))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert done.stdout.strip() == "[('<string>', 4), ('<string>', 5)]"


def _python_files() -> list[Path]:
    listed = subprocess.run(["git", "ls-files", "*.py"], capture_output=True, text=True, cwd=REPO, check=True)
    files = [REPO / line for line in listed.stdout.splitlines()]
    shims = {REPO / (old.replace(".", "/") + ("/__init__.py" if old.endswith("claims") else ".py")) for old in SHIMS}
    return [f for f in files if f.is_file() and f not in shims and f != Path(__file__).resolve()]


def _old_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """``(line, what)`` of every import of an old path in ``tree``."""
    moved = {(m, n) for m, table in MOVED_ATTRIBUTES.items() for _, n in _names(table)} | set(RENAMED)
    old_modules = set(SHIMS)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name in old_modules]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                full = f"{node.module}.{a.name}"
                if node.module in old_modules or full in old_modules or (node.module, a.name) in moved:
                    out.append((node.lineno, full))
    return out


def test_nothing_in_the_repository_imports_an_old_path() -> None:
    uses = [
        f"{path.relative_to(REPO)}:{line}: {what}"
        for path in _python_files()
        for line, what in _old_uses(ast.parse(path.read_text(), str(path)))
    ]
    assert not uses, "old import paths (use the new ones):\n" + "\n".join(uses)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(tree: ast.Module, modules: set[str]) -> set[str]:
    """Modules of ``modules`` imported anywhere in ``tree`` (in functions too), except under ``if TYPE_CHECKING:``."""
    out: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            test = child.test if isinstance(child, ast.If) else None
            if isinstance(test, ast.Name | ast.Attribute) and getattr(test, "id", getattr(test, "attr", "")) == (
                "TYPE_CHECKING"
            ):
                for stmt in child.orelse:  # type: ignore[attr-defined]
                    visit(stmt)
                continue
            if isinstance(child, ast.Import):
                out.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.module and child.level == 0:
                for a in child.names:
                    full = f"{child.module}.{a.name}"
                    out.add(full if full in modules else child.module)
            visit(child)

    visit(tree)
    return out & modules


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            connect(v)
    return found


def test_the_predictor_package_has_no_import_cycle() -> None:
    """Every import counts, lazy ones inside functions too (a cycle through a lazy import is still a cycle); a
    module importing its own package's ``__init__`` for a name is an edge to that ``__init__``."""
    files = {_module_name(p): p for p in (REPO / "crowdnav_mesrnn").rglob("*.py")}
    graph = {m: _imports(ast.parse(p.read_text()), set(files)) - {m} for m, p in files.items()}
    assert _cycles(graph) == []


def test_the_predictor_package_imports_neither_envs_nor_agents() -> None:
    """The predictor side is the bottom layer: environment ids and subcommands of the higher packages are named
    by ``"module:function"`` strings, never imported."""
    higher = {
        f"{path.relative_to(REPO)}: {name}"
        for path in (REPO / "crowdnav_mesrnn").rglob("*.py")
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Import | ast.ImportFrom)
        for name in ([a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""])
        if name.split(".")[0] in ("envs", "agents", "stable_baselines3", "pymunk")
    }
    assert not higher
