"""Carried forecasts of a recurrent predictor: hidden states kept per pedestrian from its first appearance
(``forecast_memory="carried"``).

An online forecaster (the predictor's ``online(num_slots)``) is fed every annotation frame of the recording in
order; its forecast at a frame is used, as window forecasts are, at every env time whose latest annotation is that
frame. Cached (one pass over the recording) and online forecasts are identical.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import PRED_LEN
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.predictors import check_forecast, label_of
from envs.forecasting.cache import ForecastStore, FrameTable, chunk_frames, num_chunks
from envs.forecasting.sources import ForecastModel
from envs.forecasting.window import PredictorForecast


class _CarriedWalk:
    """One online forecaster walking a recording's annotation frames in order (slot = recording column).

    :meth:`at` observes frames up to ``i`` (restarting from the first frame when asked for an earlier
    one) and returns the forecast at frame ``i`` of the pedestrians present there.
    """

    def __init__(self, model: Any, recording: Recording, label: str) -> None:
        self.model = model
        self.label = label
        self.recording = recording
        self.num_slots = int(recording.present.shape[1])
        self.pred_len = int(getattr(model, "pred_len", PRED_LEN))
        self.forecaster: Any = None
        self.observed = 0  # frames 0 .. observed - 1 have been fed
        self.last: tuple[int, np.ndarray, np.ndarray] | None = None
        self.calls = 0

    def at(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, pred_len, 2) float32 metres)`` at annotation frame ``i``."""
        if self.last is not None and self.last[0] == i:
            return self.last[1], self.last[2]
        rec = self.recording
        if self.forecaster is None or i < self.observed - 1:
            self.forecaster = self.model.online(self.num_slots)
            self.observed = 0
        while self.observed <= i:
            self.forecaster.observe(rec.positions[self.observed], rec.present[self.observed])
            self.observed += 1
        cols = np.flatnonzero(rec.present[i])
        pred = self.forecaster.forecast()
        self.calls += 1
        pred = check_forecast(
            pred,
            name=f"{self.label} (online forecaster)",
            expected_shape=(self.num_slots, self.pred_len, 2),
            recording=rec.name,
            frame=i,
            time_s=rec.times_s()[i],
            rows=cols,
        )
        out = np.ascontiguousarray(pred[cols], dtype=np.float32)
        self.last = (i, cols, out)
        return cols, out


class CarriedPredictorForecast(PredictorForecast):
    """Forecasts of a recurrent predictor carrying hidden states per pedestrian (``forecast_memory="carried"``).

    The predictor's ``online(num_slots)`` forecaster (:class:`crowdnav_mesrnn.models.learned.OnlineForecaster`)
    gets one slot per pedestrian id of the recording and observes every annotation frame of the whole
    recording in time order from its first frame (the file's positions and presence, frames as in the file:
    the predictor's training windows also step over annotation gaps frame by frame), so each pedestrian's
    hidden states run from its first appearance. Its forecast at frame ``i`` covers ``tau + j * step_s``
    (j = 1..pred_len, ``tau`` = the frame's time) and is used, as in :class:`PredictorForecast`, at every env
    time whose latest annotation is frame ``i``. The forecaster only ever sees frames up to ``tau``.

    With ``cache=True`` a recording's forecasts at all its frames are computed in one pass on first use
    (replayed pedestrians ignore the robot), and shared through the disk cache like window forecasts.
    With ``cache=False`` (online) a forecaster per recording
    advances frame by frame as the env's time does, restarting from the first frame when an episode goes
    back in time. Both feed the same frames in the same order, so they give identical forecasts. Each step
    of the forecaster computes only the pedestrians present at that frame or the one before.

    Args: as :class:`PredictorForecast`; every predictor must have an ``online(num_slots)`` method.
    """

    def __init__(
        self,
        name: str,
        predictors: dict[str, ForecastModel],
        default: ForecastModel | None,
        dt_s: float,
        horizon: int,
        cache: bool = True,
        store: ForecastStore | None = None,
    ) -> None:
        super().__init__(name, predictors, default, dt_s, horizon, cache, store)
        self.memory = "carried"
        self.whole_recording = True
        for model in [*predictors.values(), *([default] if default is not None else [])]:
            if not callable(getattr(model, "online", None)):
                raise ConfigError(
                    f"forecast_memory 'carried' needs a predictor with an online(num_slots) method (hidden states "
                    f"carried between steps); {getattr(model, 'name', model)!r} has none. Use forecast_memory 'window'."
                )
        self._walks: dict[str, _CarriedWalk] = {}

    def clear_cache(self) -> None:
        super().clear_cache()
        self._walks.clear()

    def compute_frame(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        walk = self._walks.get(recording.name)
        if walk is None or walk.recording is not recording:
            model = self.predictor_for(recording.name)
            walk = _CarriedWalk(model, recording, label_of(model))
            self._walks[recording.name] = walk
        before = walk.calls
        out = walk.at(i)
        self.calls += walk.calls - before
        return out

    def compute_chunks(self, recording: Recording, chunk: int) -> dict[int, FrameTable]:
        """Every chunk of the recording, in one pass of an online forecaster from its first frame (hidden states
        cannot start in the middle)."""
        model = self.predictor_for(recording.name)
        walk = _CarriedWalk(model, recording, label_of(model))
        frames = range(len(recording.frames))
        forecasts = [walk.at(k) for k in self._progress(frames, recording, frames)]
        out = {
            c: FrameTable.from_frames([forecasts[k] for k in chunk_frames(recording, c)], walk.pred_len)
            for c in range(num_chunks(recording))
        }
        self.calls += walk.calls
        return out
