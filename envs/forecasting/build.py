"""Filling the shared forecast cache ahead of training (``crowdnav-mesrnn forecasts build``).

Vectorised environments and grid workers then load every chunk instead of computing it; chunks already on disk
are checked and kept.
"""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING, Any, Final, TextIO

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLIT_TEST_RECORDINGS
from envs.config import FORECAST_MEMORIES, CrowdNavConfig
from envs.forecasting.cache import ForecastStore, cache_root, chunk_frames, definition_key, num_chunks
from envs.forecasting.factory import make_forecast_source
from envs.forecasting.threads import FORECAST_THREADS, torch_threads
from envs.forecasting.window import PredictorForecast

if TYPE_CHECKING:
    from crowdnav_mesrnn.data.recordings import Recording

#: Parts accepted by :func:`build_forecast_cache`.
CACHE_PARTS: Final[tuple[str, ...]] = ("train", "test", "all")


def cache_recordings(split: str | None = None, part: str = "all") -> tuple[str, ...]:
    """Recordings whose forecasts an env of ``split``/``part`` may need: ``part="all"`` = train and test;
    ``split=None`` = every replayable recording (the five scenes' held-out recordings)."""
    from envs.config import episode_recordings

    if part not in CACHE_PARTS:
        raise ValueError(f"unknown part {part!r}; valid: {', '.join(CACHE_PARTS)}")
    if split is None:
        return tuple(r for recs in SPLIT_TEST_RECORDINGS.values() for r in recs)
    if split not in SPLIT_TEST_RECORDINGS:
        raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLIT_TEST_RECORDINGS)}")
    parts = ("train", "test") if part == "all" else (part,)
    return tuple(r for p in parts for r in episode_recordings(split, p))


def check_cacheable(predictor: str) -> None:
    """Raise ``ValueError`` unless ``predictor``'s forecasts go to the disk cache (a predictor loaded per split:
    :func:`crowdnav_mesrnn.predictors.per_split`), listing those that do."""
    if not predictors.per_split(predictor):
        weightless = predictors.names(*(k for k in predictors.KINDS if k not in predictors.SPLIT_KINDS), plugins=False)
        raise ValueError(
            f"unknown predictor {predictor!r} for the forecast cache; valid: "
            f"{', '.join(predictors.names(predictors.PRETRAINED, plugins=False))}, an installed predictor plug-in or an "
            f"import path 'package.module:Factory' ({', '.join(weightless[:-1])} and {weightless[-1]} need no cache)"
        )


def build_forecast_cache(
    predictor: str,
    split: str | None = None,
    part: str = "all",
    *,
    memory: str = "window",
    data_dir: str | None = None,
    cache_dir: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Fill the shared disk cache with a learned predictor's forecasts for the recordings an env of ``split``/``part``
    replays (every replayable recording when ``split`` is None), each by its out-of-sample predictor.

    Chunks already on disk are checked and kept; missing, unreadable or stale ones are computed and
    written. Call it before starting vectorised environments or grid workers, so none of them computes forecasts.
    Forecasts are computed on :data:`~envs.forecasting.threads.FORECAST_THREADS` torch threads whatever the caller
    has set (restored after): the files then hold the bits an environment computes itself.

    Args:
        predictor: a name loaded per split (:data:`crowdnav_mesrnn.predictors.SPLIT_KINDS`): ``mesrnn``, ``srnn``,
            ``vlstm``, an installed plug-in or an import path.
        split: leave-one-out split (None: all recordings).
        part: ``train``, ``test`` or ``all``.
        memory: ``window`` or ``carried`` (see ``forecast_memory``).
        data_dir: ETH/UCY folder (default: the usual search).
        cache_dir: cache folder (default: ``$CROWDNAV_MESRNN_CACHE`` or ``~/.cache/crowdnav-mesrnn/forecasts``).
        progress: show a progress bar (tqdm) over chunks.

    Returns:
        ``{"predictor", "memory", "cache_dir", "recordings", "chunks", "loaded", "computed", "seconds"}``.
    """
    from crowdnav_mesrnn.data.recordings import load_recording

    check_cacheable(predictor)
    if memory not in FORECAST_MEMORIES:
        raise ValueError(f"unknown forecast memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    started = time.perf_counter()
    names = cache_recordings(split, part)
    recordings = [load_recording(n, "all_data", data_dir) for n in names]
    root = cache_root(cache_dir)
    problem = ForecastStore(root).write_problem()
    if problem is not None:
        raise ValueError(f"the forecast cache folder {root} cannot be written ({problem}); choose another one")
    config = CrowdNavConfig(
        predictor=predictor,
        split=split if split is not None else "zara1",
        cache_forecasts=True,
        forecast_disk_cache=True,
        forecast_cache_dir=str(root),
        forecast_memory=memory,
    )
    source = make_forecast_source(config, names)
    assert isinstance(source, PredictorForecast) and source.store is not None
    store = source.store
    source.progress = False  # this function's own bar counts the chunks
    source.threads = FORECAST_THREADS  # the bits every environment computes, whatever the caller's torch threads
    total = sum(num_chunks(r) for r in recordings)
    announce_work(source, recordings, root)  # one line on stderr before minutes of work, with or without the bar
    bar: Any = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=f"{predictor} forecasts", unit="chunk")
    for rec in recordings:
        for c in range(num_chunks(rec)):
            source.chunk(rec, c)
            if bar is not None:
                bar.set_postfix_str(rec.name, refresh=False)
                bar.update(1)
    if bar is not None:
        bar.close()
    if store.unwritable is not None:
        raise ValueError(f"the forecast cache folder {root} could not be written ({store.unwritable})")
    return {
        "predictor": predictor,
        "memory": memory,
        "cache_dir": str(root),
        "recordings": list(names),
        "chunks": total,
        "loaded": source.chunks_loaded,
        "computed": source.chunks_computed,
        "seconds": round(time.perf_counter() - started, 2),
    }


def missing_chunks(source: PredictorForecast, recordings: list[Recording]) -> list[tuple[Recording, int]]:
    """``(recording, chunk)`` of every chunk whose file is not in ``source``'s disk cache yet (all of them without a
    disk cache or without weights to key on)."""
    out = []
    for rec in recordings:
        key = source.table_key(rec) if source.store is not None else None
        for c in range(num_chunks(rec)):
            if key is None or source.store is None or not source.store.path(key, c).is_file():
                out.append((rec, c))
    return out


def seconds_per_frame(source: PredictorForecast, frames: list[tuple[Recording, int]]) -> float | None:
    """What forecasting one annotation frame costs ``source`` here and now: the median over ``frames`` (``(recording,
    frame)``, e.g. three with few, typical and many pedestrians), timed after one untimed frame that loads and warms
    the predictor. None for a source that does not forecast frame by frame (constant velocity forecasts a recording
    in one call; carried memory walks it once)."""
    if not frames or source.memory != "window" or definition_key(source.predictor_for(frames[0][0].name)) is not None:
        return None
    calls = source.calls  # the probe is not counted: ``calls`` counts the frames forecast for the cache
    times = []
    try:
        with torch_threads(source.threads):  # timed as the build computes: on the source's threads
            source.compute_frame(*frames[0])
            for rec, i in frames:
                t = time.perf_counter()
                source.compute_frame(rec, i)
                times.append(time.perf_counter() - t)
    finally:
        source.calls = calls
    return sorted(times)[len(times) // 2]


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, round(seconds))} s"
    if seconds < 90 * 60:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"


def announce_work(
    source: PredictorForecast, recordings: list[Recording], root: Any, stream: TextIO | None = None
) -> str | None:
    """Before forecasts are computed, say on ``stream`` (default stderr) in one line what (predictor, recordings,
    chunks, frames, pedestrian forecasts), about how long on this machine (:func:`seconds_per_frame`, measured now)
    and where they are cached; None and nothing said when every chunk is on disk already.

    ``computing mesrnn forecasts for 1 recording (crowds_zara01: 14 of 14 chunks, 866 frames, 9,871 pedestrian
    forecasts), about 9 min on this machine now; cached afterwards in ~/.cache/crowdnav-mesrnn/forecasts``"""
    missing = missing_chunks(source, recordings)
    if not missing:
        return None
    per_rec: dict[str, list[int]] = {}
    for rec, c in missing:
        per_rec.setdefault(rec.name, []).append(c)
    by_name = {rec.name: rec for rec in recordings}
    counts = [(int(rec.present[i].sum()), rec, i) for rec, c in missing for i in chunk_frames(rec, c)]
    frames = len(counts)
    people = sum(n for n, _, _ in counts)
    busy = sorted((x for x in counts if x[0] > 0), key=lambda x: x[0])  # frames without anyone cost no call
    parts = [f"{name}: {len(cs)} of {num_chunks(by_name[name])} chunks" for name, cs in per_rec.items()]
    what = f"{len(per_rec)} recording{'s' if len(per_rec) != 1 else ''} ({'; '.join(parts)}; {frames:,} frames, "
    what += f"{people:,} pedestrian forecasts)"
    samples = [(rec, i) for _, rec, i in (busy[len(busy) * k // 4] for k in (1, 2, 3))] if busy else []
    per_frame = seconds_per_frame(source, samples)
    when = "" if per_frame is None else f", about {_duration(per_frame * len(busy))} on this machine now"
    line = f"computing {source.name} forecasts for {what}{when}; cached afterwards in {root}"
    print(line, file=stream or sys.stderr, flush=True)
    return line
