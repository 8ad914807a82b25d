"""What a viewer of a frame needs: a legend, a scale bar of the right length, a title and the outcome at the end."""

from __future__ import annotations

import numpy as np
import pytest

from envs.rendering import OUTCOME_COLOURS, SCALE_BAR, Renderer, Scene, scale_bar_m


def scene(**kw: object) -> Scene:
    base: dict[str, object] = {
        "robot": np.zeros(2),
        "robot_radius_m": 0.3,
        "heading": 0.0,
        "goal": np.array([4.0, 0.0]),
        "goal_tolerance_m": 0.3,
        "pedestrians": np.zeros((0, 2)),
        "visible": np.zeros(0, dtype=bool),
        "ped_radius_m": 0.3,
        "trails": [],
        "forecasts": None,
        "sensor_range_m": 6.0,
        "center": np.zeros(2),
        "text": "scene test   t = 0.0 s   forecasts: cv",
    }
    base.update(kw)
    return Scene(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize(("px_per_m", "metres"), [(40.0, 2.0), (60.0, 1.0), (10.0, 5.0), (300.0, 0.2)])
def test_scale_bar_is_the_shortest_round_length_of_at_least_50_px(px_per_m: float, metres: float) -> None:
    assert scale_bar_m(px_per_m) == metres


def test_scale_bar_is_drawn_at_the_frame_scale() -> None:
    frame = Renderer((400, 300), 40.0, "rgb_array", 10.0).draw(scene())
    row = frame[300 - 14]  # the bar's row, bottom right
    dark = np.flatnonzero(np.all(row == SCALE_BAR, axis=-1))
    assert dark.max() - dark.min() == pytest.approx(scale_bar_m(40.0) * 40.0, abs=2)  # 2 m = 80 px


def test_legend_lists_the_forecast_source_and_the_outcome_banner_appears_at_the_end() -> None:
    r = Renderer((400, 400), 40.0, "rgb_array", 10.0)
    running = r.draw(scene(forecast_source="mesrnn"))
    without = r.draw(scene())
    assert not np.array_equal(running, without)  # the legend's forecast entry
    colour = np.array(OUTCOME_COLOURS["collision"])
    assert not np.all(running == colour, axis=-1).any()
    ended = r.draw(scene(forecast_source="mesrnn", outcome="collision"))
    assert np.all(ended == colour, axis=-1).sum() > 500  # a banner, not a stray pixel
