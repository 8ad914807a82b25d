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
SENSOR = (225, 225, 240)
TEXT = (30, 30, 30)
#: Pixel coordinates and radii are clipped to this (Pillow overflows on huge ones, and slows down from ~1e5).
FAR_PX = 1 << 16
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
        text: a status line.
        collided: draw the robot as collided.
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


class Renderer:
    """Draws scenes at a fixed scale (``px_per_m``) onto a ``size_px`` image with Pillow.

    Args:
        size_px: ``(width, height)`` pixels.
        px_per_m: pixels per metre.
        mode: ``"rgb_array"`` (returns ``(height, width, 3)`` uint8 frames) or ``"human"`` (a pygame window).
        fps: frames per second of the human window.

    Raises:
        gymnasium.error.DependencyNotInstalled: ``human`` mode without pygame (the ``render`` extra).
    """

    def __init__(self, size_px: tuple[int, int], px_per_m: float, mode: str, fps: float) -> None:
        from PIL import ImageFont

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
        try:
            self.font: Any = ImageFont.load_default()
        except OSError:  # fonts are optional decoration
            self.font = None

    def to_px(self, p: np.ndarray, center: np.ndarray) -> tuple[int, int]:
        """Pixel of a world point, clipped to :data:`FAR_PX` around the frame (Pillow overflows far beyond it)."""
        x = self.size[0] / 2 + (p[0] - center[0]) * self.scale
        y = self.size[1] / 2 - (p[1] - center[1]) * self.scale
        return round(min(max(float(x), -FAR_PX), FAR_PX)), round(min(max(float(y), -FAR_PX), FAR_PX))

    def draw(self, scene: Scene) -> np.ndarray | None:
        """Draw a frame: ``(H, W, 3)`` uint8 in ``rgb_array`` mode, None in ``human`` mode."""
        from PIL import Image, ImageDraw

        image = Image.new("RGB", self.size, BACKGROUND)
        pen = ImageDraw.Draw(image)
        c = scene.center
        width, height = self.size

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
        if self.font is not None and scene.text:
            pen.text((8, 8), scene.text, fill=TEXT, font=self.font)
        frame = np.asarray(image, dtype=np.uint8)
        if self.mode == "human":
            pg = self.pygame
            pg.event.pump()
            self.window.blit(pg.image.frombuffer(image.tobytes(), self.size, "RGB"), (0, 0))
            pg.display.flip()
            self.clock.tick(self.fps)
            return None
        return frame.copy()

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
