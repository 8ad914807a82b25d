"""The shared on-disk forecast cache: identical to online forecasts, keyed by weights and recording, corrupt or
stale files rebuilt, shared between processes, filled ahead by ``crowdnav-mesrnn forecasts build``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data import load_recording
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.models import ConstantVelocity
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.cache import CACHE_ENV_VAR, CacheWarning, clear_shared_tables, num_chunks
from envs.forecasting.window import PredictorForecast

REPO = Path(__file__).resolve().parents[3]
EPISODES = [{"t0_s": t0, "start": (1.0, 1.0), "goal": (7.0, 3.0), "time_limit_s": 6.0} for t0 in (14.0, 40.0)]


def prefix(data_dir: Path, name: str, frames: int) -> Recording:
    rec = load_recording(name, data_dir=data_dir)
    cols = np.flatnonzero(rec.present[:frames].any(axis=0))
    rows = slice(0, frames)
    return replace(
        rec, frames=rec.frames[rows], ped_ids=rec.ped_ids[cols], positions=rec.positions[rows][:, cols],
        present=rec.present[rows][:, cols],
    )  # fmt: skip


def source(env: CrowdNavEnv) -> PredictorForecast:
    assert isinstance(env.forecaster, PredictorForecast)
    return env.forecaster


def files(root: Path) -> list[Path]:
    return sorted(root.glob("*/*.npz"))


@pytest.mark.slow
@pytest.mark.parametrize("memory", ["window", "carried"])
def test_disk_cache_equals_online_forecasts_and_is_reused(
    data_dir: Path, tmp_path: Path, tiny_learned_predictor: Callable, lockstep: Callable, memory: str
) -> None:
    rec = prefix(data_dir, "students003", 150)  # 3 chunks of 64 frames
    common = {"crowd": rec, "forecast_memory": memory, "forecast_cache_dir": str(tmp_path)}
    cached = CrowdNavEnv(predictor=tiny_learned_predictor(), **common)
    online = CrowdNavEnv(predictor=tiny_learned_predictor(), cache_forecasts=False, **common)
    # batched (cached, frames grouped by width) and single (online) calls give the same bits
    assert lockstep(cached, online, EPISODES) > 20
    assert source(cached).chunks_computed > 0 and len(files(tmp_path)) == source(cached).chunks_computed
    assert not files(tmp_path / "none")
    # a new predictor object with the same weights (as in another process) loads everything, computes nothing
    fresh = CrowdNavEnv(predictor=tiny_learned_predictor(), **common)
    assert lockstep(fresh, cached, EPISODES) > 20  # bit for bit what was computed
    assert source(fresh).calls == 0 and source(fresh).chunks_loaded > 0 and source(fresh).chunks_computed == 0


@pytest.mark.slow
def test_weights_and_recording_are_part_of_the_key(
    data_dir: Path, tmp_path: Path, tiny_learned_predictor: Callable
) -> None:
    rec = prefix(data_dir, "students003", 150)
    first = CrowdNavEnv(predictor=tiny_learned_predictor(seed=0), crowd=rec, forecast_cache_dir=str(tmp_path))
    first.precompute_forecasts()
    assert source(first).chunks_computed == num_chunks(rec) == 3
    other_weights = CrowdNavEnv(predictor=tiny_learned_predictor(seed=1), crowd=rec, forecast_cache_dir=str(tmp_path))
    other_weights.precompute_forecasts()
    assert source(other_weights).chunks_computed == 3 and source(other_weights).chunks_loaded == 0
    a, b = source(first).chunk(rec, 1), source(other_weights).chunk(rec, 1)
    np.testing.assert_array_equal(a.columns, b.columns)
    assert np.abs(a.forecasts - b.forecasts).max() > 1e-3
    positions = rec.positions.copy()
    positions[100] += 0.1
    moved = replace(rec, positions=positions)
    env = CrowdNavEnv(predictor=tiny_learned_predictor(seed=0), crowd=moved, forecast_cache_dir=str(tmp_path))
    env.precompute_forecasts()
    assert source(env).chunks_computed == 3
    assert len(files(tmp_path)) == 9


@pytest.mark.slow
def test_corrupt_and_stale_files_are_rebuilt_with_a_warning(
    data_dir: Path, tmp_path: Path, tiny_learned_predictor: Callable
) -> None:
    rec = prefix(data_dir, "students003", 150)

    def make() -> CrowdNavEnv:
        return CrowdNavEnv(predictor=tiny_learned_predictor(), crowd=rec, forecast_cache_dir=str(tmp_path))

    built = make()
    built.precompute_forecasts()
    good = {c: source(built).chunk(rec, c) for c in range(3)}
    paths = files(tmp_path)
    assert len(paths) == 3
    paths[2].write_bytes(b"not an npz file")  # corrupt
    store, key = source(built).store, source(built).table_key(rec)
    assert store is not None and key is not None
    stale_key = replace(key, obs_len=7)  # (a pred_len that the forecasts do not have cannot be written)
    store.save(stale_key, 1, good[1])  # stale: another key under this file's name...
    os.replace(store.path(stale_key, 1), paths[1])
    store.save(key, 0, good[1])  # ...and another chunk's forecasts: inconsistent with the recording
    fresh = make()
    with pytest.warns(CacheWarning) as caught:
        fresh.precompute_forecasts()
    text = " ".join(str(w.message) for w in caught)
    assert "unreadable" in text and "stale (stored key differs in obs_len)" in text and "inconsistent" in text
    assert source(fresh).chunks_computed == 3
    for c in range(3):
        np.testing.assert_array_equal(source(fresh).chunk(rec, c).forecasts, good[c].forecasts)
    again = make()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again.precompute_forecasts()
    assert source(again).chunks_loaded == 3 and source(again).calls == 0


SHARED = """
import json, numpy as np, torch
torch.set_num_threads(1)
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording
rng = np.random.default_rng(0)
paths = [np.cumsum(rng.normal(0.0, 0.3, (200, 2)), axis=0) + 3.0 * k for k in range(6)]
env = CrowdNavEnv(predictor="mesrnn", crowd=scripted_recording(paths, name="shared"))
env.precompute_forecasts()
f = env.forecaster
print(json.dumps({"calls": f.calls, "computed": f.chunks_computed, "loaded": f.chunks_loaded}))
"""


@pytest.mark.slow
def test_processes_share_the_cache(tmp_path: Path) -> None:
    env = {**os.environ, CACHE_ENV_VAR: str(tmp_path)}

    def start() -> subprocess.Popen[str]:
        cmd = [sys.executable, "-c", SHARED]
        return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    procs = [start(), start()]  # started together: the per-chunk lock lets one compute and the other load
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    assert sum(r["computed"] for r in results) == 4 and sum(r["loaded"] for r in results) == 4
    third = start()
    out, err = third.communicate(timeout=300)
    assert third.returncode == 0, err
    assert json.loads(out.strip().splitlines()[-1]) == {"calls": 0, "computed": 0, "loaded": 4}


CARRIED = """
import json, sys, time, numpy as np
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording

class Slow:  # a carried-memory predictor whose pass over the recording takes ~2 s (sleeping, not computing)
    name, obs_len, pred_len = "slow", 8, 12
    def cache_fingerprint(self):
        return "slow-v1"
    def forecast(self, history, mask):
        return np.repeat(history[-1][:, None], 12, axis=1)
    def online(self, num_slots):
        return Walk(num_slots)

class Walk:
    def __init__(self, n):
        self.last = np.zeros((n, 2), np.float32)
    def observe(self, positions, present):
        self.last = np.where(present[:, None], positions, self.last).astype(np.float32)
    def forecast(self):
        time.sleep(0.01)
        return np.repeat(self.last[:, None], 12, axis=1)

rng = np.random.default_rng(0)
paths = [np.cumsum(rng.normal(0.0, 0.3, (200, 2)), axis=0) + 3.0 * k for k in range(3)]
env = CrowdNavEnv(predictor=Slow(), crowd=scripted_recording(paths, name="carried"), forecast_memory="carried")
env.forecaster.chunk(env.recordings[0], int(sys.argv[1]))
f = env.forecaster
print(json.dumps({"computed": f.chunks_computed, "loaded": f.chunks_loaded}))
"""


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_carried_forecasts_are_computed_once_by_processes_started_together(tmp_path: Path) -> None:
    """A carried-memory pass computes every chunk of a recording at once: a process needing another chunk must
    wait for it rather than run the whole pass again (each SubprocVecEnv worker did)."""
    env = {**os.environ, CACHE_ENV_VAR: str(tmp_path)}
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    procs = [subprocess.Popen([sys.executable, "-c", CARRIED, c], cwd=REPO, env=env, **pipes) for c in ("0", "3")]
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    assert sum(r["computed"] for r in results) == 4 and sum(r["loaded"] for r in results) == 1, results


@pytest.mark.slow
def test_build_command_fills_the_cache_for_envs(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["forecasts", "build", "--predictor", "vlstm", "--split", "eth", "--part", "test"]
    assert main([*args, "--cache-dir", str(tmp_path), "--no-progress", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    chunks = num_chunks(load_recording("biwi_eth", data_dir=data_dir))
    assert summary["recordings"] == ["biwi_eth"] and summary["computed"] == summary["chunks"] == chunks
    assert main(["forecasts", "info", "--cache-dir", str(tmp_path), "--json"]) == 0
    [entry] = json.loads(capsys.readouterr().out)["entries"]
    assert entry["source"] == "vlstm-window" and entry["recording"] == "biwi_eth" and entry["chunks"] == chunks
    env = CrowdNavEnv(
        predictor="vlstm", split="eth", part="test", data_dir=str(data_dir), forecast_cache_dir=str(tmp_path)
    )
    env.reset(seed=0)
    for _ in range(20):
        env.step(np.zeros(2, dtype=np.float32))
    assert source(env).calls == 0 and source(env).chunks_loaded > 0
    assert main([*args, "--cache-dir", str(tmp_path), "--no-progress", "--threads", "2"]) == 0
    out, err = capsys.readouterr()
    assert f"{chunks} already cached, 0 computed" in out
    assert "--threads 2 is ignored: forecasts are computed on 1 torch thread(s)" in err  # more would change bits


def test_disk_cache_can_be_switched_off(data_dir: Path, tmp_path: Path, tiny_learned_predictor: Callable) -> None:
    rec = prefix(data_dir, "students003", 70)
    env = CrowdNavEnv(
        predictor=tiny_learned_predictor(), crowd=rec, forecast_cache_dir=str(tmp_path), forecast_disk_cache=False
    )
    env.precompute_forecasts()
    assert source(env).chunks_computed == 2 and not files(tmp_path)
    # predictors without weights to hash (constant velocity) are never written either (kept in the process's memory)
    cv = CrowdNavEnv(predictor="cv", crowd=rec, forecast_cache_dir=str(tmp_path))
    cv.precompute_forecasts()
    assert source(cv).chunks_computed + source(cv).chunks_shared == 2 and not files(tmp_path)


@pytest.mark.parametrize("name", ["biwi_eth", "students003"])  # annotation steps of 0.667 s and 0.4 s
def test_constant_velocity_tables_equal_the_forecasts_of_each_frame_alone(
    data_dir: Path, name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = load_recording(name, data_dir=data_dir)
    clear_shared_tables()
    batched = PredictorForecast("cv", {}, ConstantVelocity(), 0.4, 12)
    alone = PredictorForecast("cv", {}, ConstantVelocity(), 0.4, 12, cache=False)  # one call per frame, as before
    calls = []
    forecast = ConstantVelocity.forecast
    monkeypatch.setattr(ConstantVelocity, "forecast", lambda self, h, m: calls.append(h.shape) or forecast(self, h, m))
    assert batched.table(rec) == len(rec.frames)
    assert len(calls) == batched.chunks_computed == num_chunks(rec)  # a whole recording, one call per chunk
    assert batched.calls == np.count_nonzero(rec.present.any(axis=1))
    entries = 0
    for i in range(len(rec.frames)):
        cols_a, fc_a = batched.frame_forecasts(rec, i)
        cols_b, fc_b = alone.frame_forecasts(rec, i)
        assert (cols_a.dtype, fc_a.dtype, fc_a.shape) == (cols_b.dtype, fc_b.dtype, fc_b.shape)
        np.testing.assert_array_equal(cols_a, cols_b)
        np.testing.assert_array_equal(fc_a, fc_b)  # bit for bit
        entries += len(cols_a)
    assert entries == rec.present.sum() > 1000
    assert len(calls) == num_chunks(rec) + alone.calls


def test_constant_velocity_forecasts_are_computed_once_per_process(
    data_dir: Path, tmp_path: Path, lockstep: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    clear_shared_tables()
    rec = prefix(data_dir, "students003", 150)
    envs = [CrowdNavEnv(predictor="cv", crowd=rec, forecast_cache_dir=str(tmp_path)) for _ in range(3)]
    envs[0].precompute_forecasts()
    assert source(envs[0]).chunks_computed == 3 and source(envs[0]).chunks_shared == 0
    for env in envs[1:]:  # the other environments of the process take the first one's tables
        env.precompute_forecasts()
        assert source(env).chunks_computed == 0 and source(env).chunks_shared == 3 and source(env).calls == 0
    assert source(envs[1]).chunk(rec, 2) is source(envs[0]).chunk(rec, 2)
    assert lockstep(envs[2], CrowdNavEnv(predictor="cv", crowd=rec, cache_forecasts=False), EPISODES) > 20
    assert not files(tmp_path)  # never written to disk
    # another recording under the same name is another table; beyond SHARED_RECORDINGS the oldest is forgotten
    monkeypatch.setattr("envs.forecasting.cache.SHARED_RECORDINGS", 1)
    positions = rec.positions.copy()
    positions[100] += 0.1
    moved = CrowdNavEnv(predictor="cv", crowd=replace(rec, positions=positions))
    moved.precompute_forecasts()
    assert source(moved).chunks_computed == 3
    again = CrowdNavEnv(predictor="cv", crowd=rec)
    again.precompute_forecasts()
    assert source(again).chunks_computed == 3 and source(again).chunks_shared == 0


def test_a_shared_constant_velocity_table_cannot_be_written_through_one_source(data_dir: Path) -> None:
    """The tables are shared by every source of the process: a caller writing into the arrays one source hands out
    (``frame_forecasts`` and ``chunk`` return views) would change every other environment's forecasts."""
    clear_shared_tables()
    rec = prefix(data_dir, "students003", 150)
    first = PredictorForecast("cv", {}, ConstantVelocity(), 0.4, 12)
    other = PredictorForecast("cv", {}, ConstantVelocity(), 0.4, 12)
    i = int(np.flatnonzero(rec.present.any(axis=1))[0])
    cols, fc = first.frame_forecasts(rec, i)
    kept = other.frame_forecasts(rec, i)[1].copy()
    assert len(cols) and other.chunks_shared
    for array in (fc, cols, first.chunk(rec, 0).offsets):
        with pytest.raises(ValueError, match="read-only"):
            array[...] = 0
    np.testing.assert_array_equal(other.frame_forecasts(rec, i)[1], kept)
    # what a source computes for itself alone (no sharing) stays writable, as before
    alone = PredictorForecast("cv", {}, ConstantVelocity(), 0.4, 12, cache=False).frame_forecasts(rec, i)[1]
    alone[...] = 0


@pytest.mark.slow
def test_a_cache_folder_that_cannot_be_written_falls_back_to_memory_with_a_warning(
    data_dir: Path, tmp_path: Path, tiny_learned_predictor: Callable, lockstep: Callable
) -> None:
    """A cache folder that cannot be created or written (here: a path through a regular file; also a read-only or
    full disk) must not stop the env: one CacheWarning naming the folder, forecasts computed in memory."""
    rec = prefix(data_dir, "students003", 70)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.warns(CacheWarning, match=r"cannot be written .*NotADirectoryError.* in memory only") as caught:
        env = CrowdNavEnv(predictor=tiny_learned_predictor(), crowd=rec, forecast_cache_dir=str(blocker / "cache"))
        env.precompute_forecasts()
    assert len([w for w in caught if issubclass(w.category, CacheWarning)]) == 1
    assert source(env).chunks_computed == 2 and blocker.read_text() == "not a folder"
    online = CrowdNavEnv(predictor=tiny_learned_predictor(), crowd=rec, cache_forecasts=False)
    assert lockstep(env, online, [{"t0_s": 4.0, "start": (1.0, 1.0), "goal": (7.0, 3.0), "time_limit_s": 6.0}]) > 5
    # filling the cache ahead into such a folder is an error (exit 2), not a silent in-memory computation
    args = ["forecasts", "build", "--predictor", "mesrnn", "--split", "eth", "--part", "test", "--no-progress"]
    assert main([*args, "--cache-dir", str(blocker / "cache")]) == 2


def test_info_skips_files_it_did_not_write(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``forecasts info`` failed with 'not enough values to unpack' on any other .npz file in the folder."""
    (tmp_path / "mesrnn-window").mkdir()
    (tmp_path / "mesrnn-window" / "notes.npz").write_bytes(b"x")
    assert main(["forecasts", "info", "--cache-dir", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["entries"] == []


def test_the_online_arithmetic_revision_keys_carried_tables_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """A change of the online forecast's arithmetic (CARRIED_REVISION) gives carried tables a new key, so tables
    computed by the old arithmetic are rebuilt, and leaves window tables' keys as they were."""
    from envs.forecasting import cache as forecast_cache

    def digests() -> dict[str, str]:
        keys = {
            m: forecast_cache.TableKey("mesrnn", "p" * 64, "rec", "r" * 64, m, 8, 12) for m in ("window", "carried")
        }
        return {m: k.digest() for m, k in keys.items()}

    before = digests()
    monkeypatch.setattr(forecast_cache, "CARRIED_REVISION", forecast_cache.CARRIED_REVISION + 1)
    after = digests()
    assert after["window"] == before["window"]
    assert after["carried"] != before["carried"]


@pytest.mark.parametrize("changes", [{}, {"head": "gaussian"}, {"head": "gaussian", "scale_detach": True}])
def test_the_model_config_enters_the_key_from_to_dict_as_it_always_read(changes: dict) -> None:
    """The key hashes :func:`config_text`, built from ``to_dict()``: the text earlier versions hashed (the repr of
    the config then), so caches written before stay valid, and independent of how the config prints now."""
    from crowdnav_mesrnn.models.architecture import ModelConfig
    from envs.forecasting.cache import config_text

    cfg = ModelConfig(model="srnn", **changes)
    assert config_text(cfg) == repr(cfg)
    fields = ", ".join(f"{k}={(tuple(v) if isinstance(v, list) else v)!r}" for k, v in cfg.to_dict().items())
    assert config_text(cfg) == f"ModelConfig({fields})"
    assert config_text(None) == "None"


def test_the_key_does_not_depend_on_how_a_config_prints(
    monkeypatch: pytest.MonkeyPatch, tiny_learned_predictor: Callable
) -> None:
    from crowdnav_mesrnn.models.architecture import ModelConfig
    from envs.forecasting.cache import predictor_fingerprint

    before = predictor_fingerprint(tiny_learned_predictor(seed=3))
    monkeypatch.setattr(ModelConfig, "__repr__", lambda self: "printed otherwise")
    assert predictor_fingerprint(tiny_learned_predictor(seed=3)) == before
    other = tiny_learned_predictor(seed=3)
    other.net.cfg = replace(other.net.cfg, dropout=0.5)  # same weights, another config
    assert predictor_fingerprint(other) != before


def test_the_shipped_predictors_keep_their_cache_keys() -> None:
    """SHA-256 of the shipped zara1 weights + config, as every version of the cache has computed it (so the files
    users have cached stay valid)."""
    from crowdnav_mesrnn import predictors
    from envs.forecasting.cache import predictor_fingerprint

    assert predictor_fingerprint(predictors.load("srnn", "zara1")) == (
        "6270c154e20e1ed2e053067c2b1b21e90fdd5d35d1552f1d551e32e80af70b0a"
    )
