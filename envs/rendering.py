"""Rendering with Pillow (``rgb_array``: no pygame needed), a pygame window for ``human`` mode (the ``render``
extra, imported only then), and GIF export with Pillow.

Save an episode as a GIF::

    env = gymnasium.make("CrowdNav-CV-v0", render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    frames = [env.render()]
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        frames.append(env.render())
        done = terminated or truncated
    save_gif(frames, "episode.gif", fps=env.metadata["render_fps"])

(``gymnasium.wrappers.RecordVideo`` also works with ``render_mode="rgb_array"`` if moviepy is installed.)
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from crowdnav_mesrnn.utils import atomic_write

BACKGROUND = (250, 250, 250)
GRID = (230, 230, 230)
ROBOT = (220, 60, 40)
GOAL = (40, 170, 70)
PEDESTRIAN = (40, 90, 200)
UNSEEN = (160, 170, 190)
TRAIL = (150, 175, 225)
FORECAST = (240, 140, 20)
TRUTH = (120, 120, 120)
SENSOR = (200, 200, 225)
TEXT = (30, 30, 30)
SCALE_BAR = (20, 20, 20)
PANEL = (255, 255, 255)
PANEL_EDGE = (200, 200, 200)
#: Banner colour of each episode outcome.
OUTCOME_COLOURS = {"success": (40, 150, 60), "collision": (200, 40, 30), "timeout": (200, 130, 20)}
#: Banner text of each episode outcome.
OUTCOME_TEXT = {
    "success": "SUCCESS: reached the goal",
    "collision": "COLLISION",
    "timeout": "TIMEOUT: time limit reached",
}
#: Scale-bar lengths tried, metres (the shortest at least :data:`SCALE_BAR_MIN_PX` long is drawn).
SCALE_BAR_STEPS_M = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
SCALE_BAR_MIN_PX = 50
#: Pixel coordinates and radii are clipped to this (Pillow overflows on huge ones, and slows down from ~1e5).
FAR_PX = 1 << 16
#: Height of the title strip above the scene (title; the outcome banner on the last frame), pixels.
TITLE_PX = 28
#: Height of a legend row and the padding around the legend's entries, pixels.
LEGEND_ROW_PX = 16
LEGEND_PAD_PX = 6
#: Labels the legend's columns are made wide enough for (a longer label is cut to its column): the longest fixed
#: label and a long forecast source's.
LEGEND_WIDEST = ("unobserved pedestrian", "forecast (noisy_oracle)")
#: Most entries the legend can have (robot, goal, observed and unobserved pedestrian, path, forecast, sensor range).
LEGEND_MAX_ENTRIES = 7
HUMAN_NEEDS_PYGAME = (
    'render_mode="human" needs pygame: pip install "crowdnav-mesrnn[render]" (render_mode="rgb_array" works without it)'
)


@dataclass
class Scene:
    """What to draw for one frame (world coordinates, metres).

    Attributes:
        robot: ``(2,)`` robot centre.
        robot_radius_m: robot radius.
        heading: robot heading, radians.
        goal: ``(2,)`` goal.
        goal_tolerance_m: radius of the goal marker.
        pedestrians: ``(n, 2)`` present pedestrians.
        visible: ``(n,)`` bool: observed by the robot.
        ped_radius_m: pedestrian radius.
        trails: list of ``(T_i, 2)`` recent positions of the present pedestrians.
        forecasts: ``(m, H, 2)`` forecasts of the observed pedestrians (or None).
        sensor_range_m: sensor range.
        center: ``(2,)`` centre of the view.
        text: the title line (scene, time, forecast source).
        collided: draw the robot as collided.
        outcome: the episode's outcome once it has ended (``success``, ``collision``, ``timeout``), drawn as a
            banner; None while it runs.
        forecast_source: name of the forecast source, for the legend (None: a legend entry only on frames with
            forecasts).
    """

    robot: np.ndarray
    robot_radius_m: float
    heading: float
    goal: np.ndarray
    goal_tolerance_m: float
    pedestrians: np.ndarray
    visible: np.ndarray
    ped_radius_m: float
    trails: list[np.ndarray]
    forecasts: np.ndarray | None
    sensor_range_m: float
    center: np.ndarray
    text: str
    collided: bool = False
    outcome: str | None = None
    forecast_source: str | None = None


Box = tuple[int, int, int, int]
"""A pixel rectangle ``(left, top, right, bottom)``, right and bottom exclusive."""


@dataclass(frozen=True)
class Layout:
    """Where the parts of a frame go. The scene (grid, sensor range, goal, pedestrians, trails, forecasts, robot) is
    drawn in its own box and nothing else is drawn there: the title, legend and scale bar sit in strips above and
    below it, so they never hide a pedestrian, the robot, a forecast or the goal.

    Attributes:
        scene: the scene's box; the whole frame when the frame is too small for strips.
        title: the strip above the scene (title line; the outcome banner on the last frame), or None (no font, or a
            frame under ``4 * TITLE_PX`` high).
        legend: the strip below the scene (legend entries at its left, scale bar at its right), or None.
        legend_columns: legend entries per row; 0 when the bottom strip holds the scale bar alone (a frame too narrow
            for the legend) or there is no bottom strip.
        legend_cell_px: width of a legend column, pixels.
    """

    scene: Box
    title: Box | None
    legend: Box | None
    legend_columns: int
    legend_cell_px: int

    @property
    def scene_size(self) -> tuple[int, int]:
        """``(width, height)`` of the scene's box, pixels."""
        return self.scene[2] - self.scene[0], self.scene[3] - self.scene[1]


def frame_layout(
    size_px: tuple[int, int], px_per_m: float, title_font: Any, legend_font: Any, measure: Any = None
) -> Layout:
    """The :class:`Layout` of ``size_px`` frames: a title strip of :data:`TITLE_PX` on top (with a font and a frame at
    least four times as high), a bottom strip for the legend and the scale bar, the scene in between.

    The legend's :data:`LEGEND_MAX_ENTRIES` entries fill rows of columns wide enough for :data:`LEGEND_WIDEST`; the
    scale bar sits at the right of the last row (a row of its own when the entries leave no room there). The strip is
    kept when the title and it leave the scene at least half the frame's height; else a strip of one row holds the
    scale bar alone when that leaves half; else there is no bottom strip (no legend, no scale bar). The layout does
    not depend on a frame's content, so the scene keeps its place in every frame of an episode.

    Args:
        size_px: ``(width, height)`` of the frame.
        px_per_m: the scale (for the scale bar's room).
        title_font: Pillow font of the title, or None (then no title strip).
        legend_font: Pillow font of the legend, or None (then no legend).
        measure: ``textlength(text, font)`` (default: Pillow's).
    """
    width, height = int(size_px[0]), int(size_px[1])
    if measure is None:
        from PIL import Image, ImageDraw

        measure = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength
    pad, row = LEGEND_PAD_PX, LEGEND_ROW_PX
    top = TITLE_PX if title_font is not None and height >= 4 * TITLE_PX else 0
    bar = _scale_bar_px(px_per_m, width)
    bar_room = 0
    if bar:
        label = round(measure(f"{scale_bar_m(px_per_m):g} m", font=legend_font)) if legend_font is not None else 0
        bar_room = bar + label + 32  # gap to the entries, label, gap, bar, right margin
    cell = columns = 0
    if legend_font is not None:
        cell = 24 + max(round(measure(label, font=legend_font)) for label in LEGEND_WIDEST) + 2 * pad
        columns = min(LEGEND_MAX_ENTRIES, max(0, (width - 2 * pad) // cell))
    bottom = 0
    if columns:
        rows = -(-LEGEND_MAX_ENTRIES // columns)
        last = LEGEND_MAX_ENTRIES - columns * (rows - 1)
        if bar_room and pad + last * cell + bar_room > width:
            rows += 1
        bottom = row * rows + 2 * pad
        if top + bottom > height / 2:
            bottom = columns = 0
    if not bottom and bar and top + row + 2 * pad <= height / 2:
        bottom = row + 2 * pad
    return Layout(
        scene=(0, top, width, height - bottom),
        title=(0, 0, width, top) if top else None,
        legend=(0, height - bottom, width, height) if bottom else None,
        legend_columns=columns,
        legend_cell_px=cell,
    )


def _scale_bar_px(px_per_m: float, width: int) -> int:
    """Pixel length of the scale bar in a ``width`` px frame, or 0 when no round length fits (extreme scales)."""
    px = scale_bar_m(px_per_m) * px_per_m
    return round(px) if 2 <= px <= width / 2 else 0


def _fit(pen: Any, text: str, font: Any, width: float) -> str:
    """``text``, cut and ended with ``...`` when it is wider than ``width`` pixels."""
    if font is None or pen.textlength(text, font=font) <= width:
        return text
    while text and pen.textlength(text + "...", font=font) > width:
        text = text[:-1]
    return text + "..." if text else ""


def scale_bar_m(px_per_m: float) -> float:
    """Length of the scale bar, metres: the shortest of :data:`SCALE_BAR_STEPS_M` drawn at least
    :data:`SCALE_BAR_MIN_PX` pixels long (the longest when none is)."""
    for length in SCALE_BAR_STEPS_M:
        if length * px_per_m >= SCALE_BAR_MIN_PX:
            return length
    return SCALE_BAR_STEPS_M[-1]


def _font(size: int) -> Any:
    """Pillow's default font at ``size`` px (a scalable one when Pillow has FreeType), or None."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()
    except OSError:  # fonts are optional decoration
        return None


class Renderer:
    """Draws scenes at a fixed scale (``px_per_m``) onto a ``size_px`` image with Pillow.

    The frame is ``size_px``; the scene takes the part of it the title and legend strips leave (:attr:`layout`,
    :func:`frame_layout`).

    Args:
        size_px: ``(width, height)`` pixels of the frame.
        px_per_m: pixels per metre.
        mode: ``"rgb_array"`` (returns ``(height, width, 3)`` uint8 frames) or ``"human"`` (a pygame window).
        fps: frames per second of the human window.

    Raises:
        gymnasium.error.DependencyNotInstalled: ``human`` mode without pygame (the ``render`` extra).
    """

    def __init__(self, size_px: tuple[int, int], px_per_m: float, mode: str, fps: float) -> None:
        self.size = (int(size_px[0]), int(size_px[1]))
        self.scale = float(px_per_m)
        self.mode = mode
        self.fps = fps
        self.window: Any = None
        self.clock: Any = None
        self.pygame: Any = None
        if mode == "human":
            try:
                import pygame
            except ImportError as exc:
                from gymnasium.error import DependencyNotInstalled

                raise DependencyNotInstalled(HUMAN_NEEDS_PYGAME) from exc
            self.pygame = pygame
            pygame.display.init()
            self.window = pygame.display.set_mode(self.size)
            pygame.display.set_caption("CrowdNav-MESRNN")
            self.clock = pygame.time.Clock()
        self.font: Any = _font(14)
        self.small: Any = _font(12)
        self.big: Any = _font(20)
        self.layout = frame_layout(self.size, self.scale, self.font, self.small)

    def to_px(self, p: np.ndarray, center: np.ndarray) -> tuple[int, int]:
        """Pixel of a world point in the scene's box (``center`` at the box's centre; add the box's left and top for
        frame coordinates), clipped to :data:`FAR_PX` around it (Pillow overflows far beyond it)."""
        width, height = self.layout.scene_size
        x = width / 2 + (p[0] - center[0]) * self.scale
        y = height / 2 - (p[1] - center[1]) * self.scale
        return round(min(max(float(x), -FAR_PX), FAR_PX)), round(min(max(float(y), -FAR_PX), FAR_PX))

    def draw(self, scene: Scene) -> np.ndarray | None:
        """Draw a frame: ``(H, W, 3)`` uint8 in ``rgb_array`` mode, None in ``human`` mode."""
        from PIL import Image, ImageDraw

        image = Image.new("RGB", self.size, PANEL)
        image.paste(self._scene_image(scene), self.layout.scene[:2])
        pen = ImageDraw.Draw(image)
        self._title(pen, scene)
        self._legend(pen, scene)
        self._scale_bar(pen)
        frame = np.asarray(image, dtype=np.uint8)
        if self.mode == "human":
            pg = self.pygame
            pg.event.pump()
            self.window.blit(pg.image.frombuffer(image.tobytes(), self.size, "RGB"), (0, 0))
            pg.display.flip()
            self.clock.tick(self.fps)
            return None
        return frame.copy()

    def _scene_image(self, scene: Scene) -> Any:
        """The scene alone, an image of the scene box's size (nothing drawn past its edges)."""
        from PIL import Image, ImageDraw

        width, height = self.layout.scene_size
        image = Image.new("RGB", (width, height), BACKGROUND)
        pen = ImageDraw.Draw(image)
        c = scene.center

        def disk(p: np.ndarray, radius_m: float, colour: tuple[int, int, int], outline: int = 0) -> None:
            x, y = self.to_px(p, c)
            r = max(1, round(min(radius_m * self.scale, FAR_PX)))
            if outline:
                pen.ellipse((x - r, y - r, x + r, y + r), outline=colour, width=outline)
            else:
                pen.ellipse((x - r, y - r, x + r, y + r), fill=colour)

        # 1 m grid (10 m, 100 m, ... when lines would be closer than 4 px; none when even 1 m is under a pixel)
        step = 10.0 ** max(0, math.ceil(math.log10(4.0 / self.scale))) if self.scale < 4.0 else 1.0
        half_w, half_h = width / 2 / self.scale, height / 2 / self.scale
        if width / 2 / step * self.scale >= 1.0 and math.isfinite(half_w + half_h + c[0] + c[1]):
            for k in range(math.floor((c[0] - half_w) / step), math.ceil((c[0] + half_w) / step) + 1):
                x = self.to_px(np.array([k * step, c[1]]), c)[0]
                pen.line((x, 0, x, height), fill=GRID)
            for k in range(math.floor((c[1] - half_h) / step), math.ceil((c[1] + half_h) / step) + 1):
                y = self.to_px(np.array([c[0], k * step]), c)[1]
                pen.line((0, y, width, y), fill=GRID)
        disk(scene.robot, scene.sensor_range_m, SENSOR, outline=1)
        disk(scene.goal, scene.goal_tolerance_m, GOAL, outline=2)
        gx, gy = self.to_px(scene.goal, c)
        pen.line((gx - 6, gy - 6, gx + 6, gy + 6), fill=GOAL, width=2)
        pen.line((gx - 6, gy + 6, gx + 6, gy - 6), fill=GOAL, width=2)
        for trail in scene.trails:
            if len(trail) >= 2:
                pen.line([self.to_px(p, c) for p in trail], fill=TRAIL, width=2)
        if scene.forecasts is not None:
            for fc in scene.forecasts:
                pts = [self.to_px(p, c) for p in fc]
                for a, b in itertools.pairwise(pts):
                    # dotted polyline: a dot every 4 px along each segment
                    n = max(1, min(int(np.hypot(b[0] - a[0], b[1] - a[1]) // 4), (width + height) // 2))
                    for i in range(n):
                        t = i / n
                        x, y = round(a[0] + t * (b[0] - a[0])), round(a[1] + t * (b[1] - a[1]))
                        pen.point((x, y), fill=FORECAST)
                for x, y in pts:
                    pen.ellipse((x - 2, y - 2, x + 2, y + 2), fill=FORECAST)
        for p, seen in zip(scene.pedestrians, scene.visible, strict=True):
            disk(p, scene.ped_radius_m, PEDESTRIAN if seen else UNSEEN)
        disk(scene.robot, scene.robot_radius_m, (0, 0, 0) if scene.collided else ROBOT)
        tip = scene.robot + scene.robot_radius_m * np.array([np.cos(scene.heading), np.sin(scene.heading)])
        pen.line((*self.to_px(scene.robot, c), *self.to_px(tip, c)), fill=(255, 255, 255), width=2)
        if scene.outcome is not None and self.layout.title is None:  # no title strip (a small frame): over the scene
            self._banner(pen, scene.outcome, (0, 32, width, 64), "")
        return image

    def _title(self, pen: Any, scene: Scene) -> None:
        """The title strip: the title line, or on the episode's last frame the outcome banner followed by it."""
        box = self.layout.title
        if box is None:
            return
        x0, y0, x1, y1 = box
        if scene.outcome is not None:
            self._banner(pen, scene.outcome, box, scene.text)
            return
        pen.line((x0, y1 - 1, x1, y1 - 1), fill=PANEL_EDGE)
        if scene.text:
            pen.text((x0 + 8, y0 + 6), _fit(pen, scene.text, self.font, x1 - x0 - 16), fill=TEXT, font=self.font)

    def _banner(self, pen: Any, outcome: str, box: Box, title: str) -> None:
        """The episode's outcome across ``box`` (the title strip), in the outcome's colour, then the title line."""
        colour = OUTCOME_COLOURS.get(outcome, TEXT)
        text = OUTCOME_TEXT.get(outcome, outcome.upper())
        font = self.big or self.font
        x0, y0, x1, y1 = box
        pen.rectangle((x0, y0, x1 - 1, y1 - 1), fill=colour)
        pen.text((x0 + 8, y0 + 3), text, fill=(255, 255, 255), font=font)
        if title and self.font is not None:
            left = x0 + 8 + (pen.textlength(text, font=font) if font is not None else 8 * len(text)) + 16
            pen.text((left, y0 + 6), _fit(pen, title, self.font, x1 - 8 - left), fill=(255, 255, 255), font=self.font)

    def _legend(self, pen: Any, scene: Scene) -> None:
        """Key of the symbols in the bottom strip: robot, goal, observed and unobserved pedestrians, trail, forecast
        (when drawn), sensor range; in :attr:`Layout.legend_columns` columns, row by row."""
        box, columns, cell = self.layout.legend, self.layout.legend_columns, self.layout.legend_cell_px
        if box is None:
            return
        pen.line((box[0], box[1], box[2], box[1]), fill=PANEL_EDGE)
        if not columns:
            return
        items: list[tuple[str, str, tuple[int, int, int]]] = [
            ("disk", "robot", ROBOT),
            ("goal", "goal", GOAL),
            ("disk", "observed pedestrian", PEDESTRIAN),
            ("disk", "unobserved pedestrian", UNSEEN),
            ("line", "observed path", TRAIL),
        ]
        if scene.forecast_source is not None:
            items.append(("dots", f"forecast ({scene.forecast_source})", FORECAST))
        elif scene.forecasts is not None:
            items.append(("dots", "forecast", FORECAST))
        items.append(("ring", f"sensor range ({scene.sensor_range_m:g} m)", SENSOR))
        row, pad = LEGEND_ROW_PX, LEGEND_PAD_PX
        for k, (kind, label, colour) in enumerate(items):
            cx = box[0] + pad + 8 + cell * (k % columns)
            cy = box[1] + pad + row * (k // columns) + row // 2
            if kind == "disk":
                pen.ellipse((cx - 5, cy - 5, cx + 5, cy + 5), fill=colour)
            elif kind == "goal":
                pen.ellipse((cx - 6, cy - 6, cx + 6, cy + 6), outline=colour, width=2)
                pen.line((cx - 4, cy - 4, cx + 4, cy + 4), fill=colour, width=2)
                pen.line((cx - 4, cy + 4, cx + 4, cy - 4), fill=colour, width=2)
            elif kind == "line":
                pen.line((cx - 8, cy, cx + 8, cy), fill=colour, width=2)
            elif kind == "dots":
                for dx in (-8, -2, 4):
                    pen.ellipse((cx + dx - 2, cy - 2, cx + dx + 2, cy + 2), fill=colour)
            else:
                pen.ellipse((cx - 6, cy - 6, cx + 6, cy + 6), outline=colour, width=1)
            text = _fit(pen, label, self.small, cell - 24 - pad)
            pen.text((cx + 14, cy - 7), text, fill=TEXT, font=self.small)

    def _scale_bar(self, pen: Any) -> None:
        """A bar of :func:`scale_bar_m` metres with its length written to its left, at the right of the bottom strip's
        last row."""
        px = _scale_bar_px(self.scale, self.size[0])
        if not px or self.layout.legend is None:  # no round length fits, or no strip to hold it
            return
        x1, y = self.size[0] - 12, self.size[1] - LEGEND_PAD_PX - LEGEND_ROW_PX // 2
        x0 = x1 - px
        pen.line((x0, y, x1, y), fill=SCALE_BAR, width=3)
        pen.line((x0, y - 5, x0, y + 4), fill=SCALE_BAR, width=2)
        pen.line((x1, y - 5, x1, y + 4), fill=SCALE_BAR, width=2)
        if self.small is not None:
            label = f"{scale_bar_m(self.scale):g} m"
            tw = pen.textlength(label, font=self.small)
            pen.text((x0 - 8 - tw, y - 7), label, fill=TEXT, font=self.small)

    def close(self) -> None:
        if self.window is not None:
            self.pygame.display.quit()
            self.window = None


def save_gif(frames: Sequence[np.ndarray], path: str | os.PathLike[str], fps: float = 2.5) -> str:
    """Write ``rgb_array`` frames (``(H, W, 3)`` uint8 each) as a looping GIF with Pillow (atomically).

    Returns:
        the path written.
    """
    from PIL import Image

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    duration_ms = max(20, round(1000.0 / fps))

    def write(fh: Any) -> None:
        images[0].save(fh, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0)

    atomic_write(path, write)
    return str(path)
