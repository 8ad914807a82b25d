"""``crowdnav-mesrnn bench-policy``: the policy contract, the argument checks, the references on the same episodes
and the report, end to end with the example package and a tiny budget."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.ablation.archive import has_archive
from agents.policy_bench.policy import UserPolicy, check_import_path
from agents.policy_bench.references import reference_arms, same_episodes
from agents.policy_bench.run import env_kwargs
from crowdnav_mesrnn.cli import main

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "my_policy"

POLICIES = '''
import numpy as np

class Sb3Like:
    """predict returns (action, state), like SB3."""
    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        return np.array([0.5, -0.5], np.float32), None

def plain(obs):
    return [0.25, 0.0]

class WithConfig:
    """A factory taking the environment's config."""
    def __init__(self, config=None):
        self.speed = config.robot_pref_speed_mps
    def __call__(self, obs):
        return np.array([self.speed / 2, 0.0])

def make(scale=1.0):
    return lambda obs: np.array([scale, 0.0])

sb3_instance = Sb3Like()
not_a_policy = 42

def bad_shape(obs):
    return np.zeros(3)

def nan_action(obs):
    return [np.nan, 0.0]
'''


@pytest.fixture
def user_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "user_policies.py").write_text(textwrap.dedent(POLICIES))
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("user_policies", None)
    return "user_policies"


OBS = {"robot": np.zeros(4, np.float32), "pedestrians": np.zeros(40, np.float32), "mask": np.zeros(10, np.float32)}


def test_every_form_of_policy_the_contract_names(user_module: str) -> None:
    from envs.config import config_from

    config = config_from({"robot_pref_speed_mps": 0.8}, {})
    cases = {
        "Sb3Like": ("predict", True, [0.5, -0.5]),  # a class: a factory
        "sb3_instance": ("predict", False, [0.5, -0.5]),
        "plain": ("callable", False, [0.25, 0.0]),
        "WithConfig": ("callable", True, [0.4, 0.0]),  # given config=
        "make": ("callable", True, [1.0, 0.0]),  # a function whose parameters all have defaults
    }
    for attr, (kind, factory, action) in cases.items():
        policy = UserPolicy(f"{user_module}:{attr}", config)
        assert (policy.kind, policy.factory) == (kind, factory), attr
        np.testing.assert_allclose(policy.act(OBS), action, err_msg=attr)
    # a batch (what run_episodes passes): one call per row
    batch = {k: np.stack([v, v, v]) for k, v in OBS.items()}
    actions, state = UserPolicy(f"{user_module}:plain").predict(batch)
    assert actions.shape == (3, 2) and state is None


def test_what_is_not_a_policy_is_refused_naming_it(user_module: str) -> None:
    with pytest.raises(ValueError, match="is a int"):
        UserPolicy(f"{user_module}:not_a_policy")
    for attr in ("bad_shape", "nan_action"):
        with pytest.raises(ValueError, match=f"policy '{user_module}:{attr}' returned .* 2 finite numbers"):
            UserPolicy(f"{user_module}:{attr}").act(OBS)
    with pytest.raises(ValueError, match="has no attribute 'missing'"):
        UserPolicy(f"{user_module}:missing")
    with pytest.raises(ValueError, match="not an import path"):
        check_import_path("user_policies.plain")
    with pytest.raises(ValueError, match="no module named 'surely_not_installed'"):
        check_import_path("surely_not_installed.mod:policy")


def test_bad_arguments_are_refused_before_anything_heavy_is_imported(tmp_path: Path) -> None:
    """Each mistake gets its message and exit status 2, with neither the environment, torch nor SB3 imported."""
    code = textwrap.dedent(
        """
        import sys
        from crowdnav_mesrnn.cli import main
        cases = [
            ["bench-policy", "not a path"],
            ["bench-policy", "surely_not_installed:policy"],
            ["bench-policy", "json:dumps", "--arms", "none,kalmn"],
            ["bench-policy", "json:dumps", "--splits", "zara3"],
            ["bench-policy", "json:dumps", "--episodes", "0"],
            ["bench-policy", "json:dumps", "--set", "sensor_rnage_m=3"],
        ]
        for argv in cases:
            assert main(argv) == 2, argv
        heavy = [m for m in ("torch", "stable_baselines3", "pymunk", "envs.crowd_nav") if m in sys.modules]
        assert not heavy, heavy
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    err = done.stderr
    for words in ("not an import path", "no module named 'surely_not_installed'", "unknown predictor 'kalmn'",
                  "unknown split(s) zara3", "--episodes and --n-envs must be >= 1", "sensor_rnage_m"):  # fmt: skip
        assert words in err, (words, err)


def test_the_policy_runs_the_environment_a_planner_evaluation_runs() -> None:
    from agents.evaluation import evaluation_env_kwargs

    for arm, split in (("none", "zara1"), ("mesrnn", "eth")):
        assert env_kwargs(arm, split, {}) == evaluation_env_kwargs("planner", arm, split)
        assert env_kwargs(arm, split, {"time_penalty": -0.1}) == evaluation_env_kwargs(
            "planner", arm, split, {"time_penalty": -0.1}
        )


def test_references_follow_the_planner_grid_and_episodes_are_matched_one_by_one() -> None:
    assert reference_arms("sampling", ["none", "cv"]) == ["none", "cv"]
    assert reference_arms("search", ["none", "cv"]) == ["cv"]
    assert reference_arms("privileged", ["none", "cv"]) == ["oracle"]
    ours = [{"episode": i, "crowd_density": 1.5 * i} for i in range(3)]
    theirs = [{"episode": str(i), "crowd_density": repr(1.5 * i)} for i in range(3)]
    assert same_episodes(ours, theirs)
    assert not same_episodes(ours, theirs[:2])
    assert not same_episodes(ours, [*theirs[:2], {"episode": "2", "crowd_density": "3.5"}])


def _report(out: Path) -> dict[str, Any]:
    assert {"report.md", "report.json", "success_by_scene.png"} <= {p.name for p in out.iterdir()}
    return json.loads((out / "report.json").read_text())


def test_bench_policy_end_to_end_on_the_example_package(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The example package with a tiny budget: the references come from the committed planner grid (the same
    episodes, checked one by one), the tests pair them, the page and the plot are written."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    out = tmp_path / "bench"
    argv = ["bench-policy", "my_policy:RepulsivePolicy", "--episodes", "3", "--splits", "zara1", "--arms", "none"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    report = _report(out)
    zara1 = report["scenes"]["zara1"]
    assert zara1["policy"]["none"]["episodes"] == 3 and "spl_mean" in zara1["policy"]["none"]
    refs = zara1["references"]
    assert set(refs["sampling"]) == {"none"} and refs["search"] == {} and set(refs["privileged"]) == {"oracle"}
    if has_archive(ROOT / "results" / "ablation" / "planners"):
        assert (
            refs["sampling"]["none"]["source"] == "committed" and refs["privileged"]["oracle"]["source"] == "committed"
        )
    assert [(t["reference"], t["reference_arm"]) for t in report["tests"]] == [
        ("sampling", "none"),
        ("privileged", "oracle"),
    ]
    for t in report["tests"]:
        lo, hi = t["difference_exact_ci"]
        assert (lo > 0 or hi < 0) == (t["p_value"] < 0.05) and t["verdict"] in (
            "better",
            "worse",
            "no difference shown",
        )
    page = (out / "report.md").read_text()
    assert "| zara1 | none | **my_policy:RepulsivePolicy** |" in page and "privileged ceiling" in page
    assert (out / "policy" / "zara1" / "none" / "episodes.csv").is_file()
    # another policy into the same folder is refused (the report kept)
    assert main(["bench-policy", "my_policy:go_to_goal", "--episodes", "3", "--splits", "zara1", "--arms", "none",
                 "--out", str(out), "--no-progress"]) == 2  # fmt: skip
    assert _report(out)["policy"] == "my_policy:RepulsivePolicy"


@pytest.mark.slow
def test_references_run_here_equal_the_committed_ones(data_dir: Path, tmp_path: Path) -> None:
    """The references' committed episodes are what an evaluation gives now: run here, their outcomes and crowd
    densities equal the grid's first episodes."""
    from agents.policy_bench.references import committed_grid

    _cfg, cells = committed_grid()
    if not cells:
        pytest.skip("no committed planner grid in this checkout")
    out = tmp_path / "bench"
    sys.path.insert(0, str(EXAMPLE))
    try:
        argv = ["bench-policy", "my_policy:go_to_goal", "--episodes", "2", "--splits", "zara1", "--arms", "cv"]
        assert main([*argv, "--out", str(out), "--rerun-references", "--no-progress"]) == 0
    finally:
        sys.path.remove(str(EXAMPLE))
    report = _report(out)
    from agents.evaluation import read_episodes

    for name, grid_name, arm in (("sampling", "planner", "cv"), ("search", "search", "cv"), ("privileged", "privileged", "oracle")):  # fmt: skip
        assert report["scenes"]["zara1"]["references"][name][arm]["source"] == "run"
        here = read_episodes(out / "references" / "zara1" / name / arm)
        committed = cells[(grid_name, arm, "zara1")][:2]
        assert [r["outcome"] for r in here] == [r["outcome"] for r in committed]
        assert same_episodes(here, committed)


def test_a_cached_reference_of_another_reaction_revision_is_run_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An earlier bench's reference under ``social_force`` is reused only if it ran at the model's current revision
    (``reaction_revision`` in its summary): one from revision 1 is evaluated again, not served as cached."""
    import json

    import agents.evaluation
    from agents.policy_bench.references import reference_rows
    from envs.crowd_nav import ENV_REVISION
    from envs.reaction import MODEL_REVISIONS

    rows = [{"episode": str(i), "crowd_density": str(0.5 + i)} for i in range(2)]
    folder = tmp_path / "zara1" / "sampling" / "cv"
    folder.mkdir(parents=True)
    (folder / "episodes.csv").write_text("episode,seed,crowd_density,outcome\n0,7,0.5,success\n1,8,1.5,collision\n")
    overrides = {"reaction": "social_force"}
    base = {"episodes": 2, "seed": 0, "env_revision": ENV_REVISION, "env_overrides": overrides}

    class Ran(Exception):
        pass

    def evaluate(*args, **kwargs):
        raise Ran

    monkeypatch.setattr(agents.evaluation, "evaluate", evaluate)
    current = {**base, "reaction_revision": MODEL_REVISIONS["social_force"]}
    (folder / "summary.json").write_text(json.dumps(current))
    got = reference_rows("sampling", "cv", "zara1", 2, 0, overrides, rows, tmp_path, (None, {}))
    assert got[1] == "cached" and len(got[0]) == 2
    (folder / "summary.json").write_text(json.dumps(base))  # written before revision 2 named itself
    with pytest.raises(Ran):
        reference_rows("sampling", "cv", "zara1", 2, 0, overrides, rows, tmp_path, (None, {}))
