"""What a viewer of a frame needs: a legend, a scale bar of the right length, a title and the outcome at the end."""

from __future__ import annotations

import numpy as np
import pytest

from envs.rendering import OUTCOME_COLOURS, PEDESTRIAN, SCALE_BAR, Renderer, Scene, scale_bar_m


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


def _inside(box: tuple[int, int, int, int], x: int, y: int) -> bool:
    return box[0] <= x < box[2] and box[1] <= y < box[3]


def _disjoint(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]


@pytest.mark.parametrize("size", [(640, 640), (400, 300), (900, 500)])
def test_the_legend_is_drawn_beside_the_scene_never_over_it(size: tuple[int, int]) -> None:
    """The legend's pixels lie in a strip outside the scene's box, and a pedestrian in any corner of the scene (the
    old legend's bottom-left one included) is drawn in full."""
    r = Renderer(size, 40.0, "rgb_array", 10.0)
    layout = r.layout
    assert layout.legend is not None and layout.title is not None and layout.legend_columns >= 1
    for strip in (layout.legend, layout.title):
        assert _disjoint(strip, layout.scene)
    # what the legend's content changes (its forecast entry) is inside its strip, never in the scene's box
    with_entry, without = r.draw(scene(forecast_source="mesrnn")), r.draw(scene())
    ys, xs = np.nonzero(np.any(with_entry != without, axis=-1))
    assert len(xs) > 20 and all(_inside(layout.legend, x, y) for x, y in zip(xs, ys, strict=True))
    # pedestrians centred 0.3 m inside each corner of the scene's box: every pixel of each disk is pedestrian blue
    width, height = layout.scene_size
    half = np.array([width, height]) / 2 / 40.0 - 0.3
    corners = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * half
    frame = r.draw(scene(pedestrians=corners, visible=np.ones(4, dtype=bool), ped_radius_m=0.25))
    for corner in corners:
        x, y = r.to_px(corner, np.zeros(2))
        x, y = x + layout.scene[0], y + layout.scene[1]
        patch = frame[y - 7 : y + 8, x - 7 : x + 8]  # inside the 10 px disk
        assert np.all(patch == np.array(PEDESTRIAN, dtype=np.uint8)), corner


@pytest.mark.parametrize("size", [(64, 48), (160, 120), (200, 100)])
def test_small_frames_have_no_legend_and_the_scene_fills_what_the_strips_leave(size: tuple[int, int]) -> None:
    r = Renderer(size, 40.0, "rgb_array", 10.0)
    frame = r.draw(scene(forecast_source="mesrnn", outcome="success"))
    assert frame.shape == (size[1], size[0], 3)
    assert r.layout.legend_columns == 0
    width, height = r.layout.scene_size
    assert width == size[0] and height >= size[1] / 2


def test_the_outcome_banner_is_in_the_title_strip_with_the_title() -> None:
    r = Renderer((640, 640), 40.0, "rgb_array", 10.0)
    ended = r.draw(scene(outcome="success"))
    colour = np.all(ended == np.array(OUTCOME_COLOURS["success"]), axis=-1)
    ys, _ = np.nonzero(colour)
    assert r.layout.title is not None and ys.max() < r.layout.title[3]  # the banner stays in the strip
    running = r.draw(scene())
    top = r.layout.scene[1]
    assert np.array_equal(ended[top:], running[top:])  # the scene and the legend are untouched by the banner
