"""The import paths the re-layout replaced keep working for one release: they import, warn, and hand out the very
objects of the new modules; ``python -m agents.train``/``agents.evaluate`` stay the commands (without a warning);
pickles naming an old path (SB3 models with a ``lin_<x>`` schedule) still load."""

from __future__ import annotations

import importlib
import pickle
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: Old module -> {new module: names it moved there}.
MOVED: dict[str, dict[str, tuple[str, ...]]] = {
    "agents.train": {
        "agents.actions": ("action_set",),
        "agents.runs": ("PROJECT_KEY",),
        "agents.training.config": (
            "PROJECT_KEYS",
            "ENV_ID_OF",
            "ALGOS",
            "ZOO_KEYS",
            "UNSUPPORTED_ZOO_KEYS",
            "RUN_ENV_KEYS",
            "VEC_ENVS",
            "DEFAULT_CONFIG",
            "EvalConfig",
            "TrainConfig",
            "env_id_for",
            "load_train_config",
            "LinearSchedule",
            "algorithm_kwargs",
            "policy_class",
        ),
        "agents.training.logger": ("ProgressCSV", "make_logger"),
        "agents.training.callbacks": ("Validation", "Checkpoint", "Progress", "save_checkpoint", "latest_checkpoint"),
        "agents.training.run": (
            "make_env",
            "make_vec_env",
            "prepare_training_forecasts",
            "predictor_weights",
            "rollout_steps",
            "steps_trained",
            "default_run_dir",
            "resolved_yaml",
            "train",
        ),
        "agents.training.cli": ("add_train_arguments", "config_from_args", "run_from_args", "main"),
    },
    "agents.evaluate": {
        "agents.rollout": (
            "METRICS",
            "EPISODE_COLUMNS",
            "SB3Policy",
            "evaluation_seeds",
            "prepare_forecasts",
            "episode_row",
            "StepHook",
            "run_episodes",
        ),
        "agents.runs": (
            "RUN_MODELS",
            "algo_of_model",
            "load_sb3",
            "config_of",
            "run_settings",
            "export_policy",
            "without_optimizer_state",
            "model_path",
            "load_policy",
            "check_spaces",
        ),
        "agents.evaluation.summary": (
            "OUTCOMES",
            "SUCCESS_ONLY_METRICS",
            "summarise",
            "read_episodes",
            "ceiling_fraction",
            "episodes_csv",
            "format_summary",
        ),
        "agents.evaluation.run": ("evaluation_env_kwargs", "evaluate", "default_eval_dir"),
        "agents.evaluation.cli": ("add_evaluate_arguments", "run_from_args", "main"),
        "agents.entry": ("parse_set",),
    },
    "agents.pretrain": {
        "agents.training.pretrain": (
            "ACTION_LOSSES",
            "PretrainConfig",
            "teacher_class",
            "make_teacher",
            "teacher_seeds",
            "discounted_returns",
            "TeacherData",
            "collect_teacher",
            "concatenate",
            "student_policy",
            "fit_policy",
            "pretrain",
        ),
    },
    "agents.privileged": {"agents.planners.privileged": ("Plan", "PlannerStats", "PrivilegedPlanner")},
}


@pytest.fixture
def fresh() -> Iterator[None]:
    """The old modules unloaded before and after (a module warns once, when it is first imported)."""
    saved = {name: sys.modules.pop(name) for name in list(MOVED) if name in sys.modules}
    yield
    for name in MOVED:
        sys.modules.pop(name, None)
    sys.modules.update(saved)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_imports_warns_and_exposes_the_same_objects(old: str, fresh: None) -> None:
    with pytest.warns(DeprecationWarning, match=rf"{old} is deprecated") as caught:
        __import__(old)  # as an ``import`` statement does (importlib.import_module would be the importer)
    module = sys.modules[old]
    assert any(Path(w.filename).name == Path(__file__).name for w in caught), "the warning names the importer"
    listed = set()
    for new, names in MOVED[old].items():
        target = importlib.import_module(new)
        for name in names:
            assert getattr(module, name) is getattr(target, name), f"{old}.{name} is not {new}.{name}"
        listed.update(names)
    assert set(module.__all__) == listed


def test_the_planners_package_keeps_every_name_of_the_old_module() -> None:
    """``agents.planners`` was a module and is the package now: the same import path, so it does not warn."""
    import agents.planners as planners
    from agents.planners import base, privileged, sampling, search

    old = {
        "DEFAULT_HEADINGS_DEG": sampling,
        "DEFAULT_SPEED_FRACTIONS": sampling,
        "DENSE_HEADINGS_DEG": sampling,
        "DENSE_SPEED_FRACTIONS": sampling,
        "CANDIDATE_SETS": sampling,
        "SamplingPlanner": sampling,
        "as_env_config": base,
        "velocities_to_actions": base,
        "velocity_to_action": base,
        "go_to_goal": base,
        "region_radii": base,
        "StraightToGoal": base,
        "motion_candidates": search,
        "lattice_select": search,
        "SEARCH_HEADINGS_DEG": search,
        "SEARCH_SPEED_FRACTIONS": search,
        "SearchPlanner": search,
        "PrivilegedPlanner": privileged,
    }
    for name, module in old.items():
        assert getattr(planners, name) is getattr(module, name), name
    since = {"PLANNERS", "make_planner", "Plan", "PlannerStats"}
    # the privileged reactive ceiling (issue 28), added after the layout
    since |= {"ReactivePrivilegedPlanner", "ReactivePlan", "ReactivePlannerStats", "REACTIVE_OPTIONS"}
    since |= {"command_velocities", "env_velocities"}
    assert set(old) | since == set(planners.__all__)


def test_a_pickle_naming_an_old_path_loads() -> None:
    """An SB3 model trained with a ``lin_<x>`` learning rate pickles the schedule's class by its module path."""
    from agents.training.config import LinearSchedule

    new = pickle.dumps(LinearSchedule(5e-4), protocol=0)
    old = new.replace(b"agents.training.config\n", b"agents.train\n")
    assert old != new
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        schedule = pickle.loads(old)
    assert type(schedule) is LinearSchedule and schedule(0.5) == 2.5e-4


@pytest.mark.parametrize("command", ["agents.train", "agents.evaluate"])
def test_python_dash_m_of_an_old_path_is_still_the_command(command: str) -> None:
    result = subprocess.run(
        [sys.executable, "-W", "error::DeprecationWarning", "-m", command, "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"usage: python -m {command} ")


def test_a_name_that_left_a_live_module_warns_from_there() -> None:
    """``agents.ablation.backends`` stays (the local backends); the cell runner moved to ``agents.ablation.execute``."""
    from agents.ablation import backends, execute

    assert backends.execute_cell is execute.execute_cell and backends.CellTask is execute.CellTask
    with pytest.warns(DeprecationWarning, match="backends.train_overrides is deprecated"):
        assert backends.train_overrides is execute.train_overrides
    with pytest.raises(AttributeError):
        backends.no_such_name  # noqa: B018
