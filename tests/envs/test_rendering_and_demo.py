"""Rendering (rgb_array, human with a dummy display), GIF export and the ``demo`` command."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from crowdnav_mesrnn.cli import main
from envs.crowd_nav import CrowdNavEnv
from envs.rendering import FORECAST, ROBOT, save_gif

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


def _has_colour(frame: np.ndarray, colour: tuple[int, int, int]) -> bool:
    return bool(np.any(np.all(frame == np.array(colour, dtype=np.uint8), axis=-1)))


def test_rgb_array_frames_show_robot_and_forecasts(tmp_path: Path) -> None:
    env = CrowdNavEnv(predictor="cv", crowd="synthetic", render_mode="rgb_array", render_size_px=(320, 240))
    env.reset(seed=0)
    frames = [env.render()]
    for _ in range(6):
        env.step(np.zeros(2, dtype=np.float32))
        frames.append(env.render())
    for frame in frames:
        assert isinstance(frame, np.ndarray) and frame.shape == (240, 320, 3) and frame.dtype == np.uint8
        assert _has_colour(frame, ROBOT)
    assert any(_has_colour(f, FORECAST) for f in frames)
    path = save_gif(frames, tmp_path / "episode.gif", fps=env.metadata["render_fps"])
    with Image.open(path) as gif:
        assert gif.n_frames == len(frames) and gif.size == (320, 240)
    env.close()


def test_pygame_is_imported_only_for_rendering() -> None:
    import subprocess

    code = (
        "import numpy as np, sys\n"
        "from envs.crowd_nav import CrowdNavEnv\n"
        "env = CrowdNavEnv(predictor='none', crowd='empty')\n"
        "env.reset(seed=0); env.step(np.zeros(2))\n"
        "print('pygame' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"


def test_human_mode_with_a_dummy_display() -> None:
    env = CrowdNavEnv(predictor="none", crowd="synthetic", render_mode="human", render_size_px=(64, 64), dt_s=0.05)
    env.reset(seed=0)
    env.step(np.zeros(2, dtype=np.float32))
    assert env.render() is None
    env.close()
    env.close()


def test_demo_on_the_synthetic_crowd(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo.gif"
    assert main(["demo", "--synthetic", "--predictor", "cv", "--seed", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "synthetic" in text and "outcome" in text and f"wrote {out}" in text
    assert "forecast error, average over the horizon (ADE), m" in text  # metric lines named in full
    with Image.open(out) as gif:
        assert gif.n_frames > 5


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_demo_on_a_held_out_scene(data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo.gif"
    assert main(["demo", "--split", "zara1", "--data-dir", str(data_dir), "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    assert "crowds_zara01" in captured.out and out.is_file()
    # MESRNN forecasts, or constant velocity with a warning when the pretrained weights are missing
    assert "mesrnn" in captured.out or ("falling back" in captured.err and '"predictor": "cv"' in captured.out)


def test_demo_with_an_explicit_missing_predictor_is_an_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from crowdnav_mesrnn import predictors
    from envs.forecasting import factory

    def missing(name: str, split: str | None = None) -> None:
        raise FileNotFoundError("no weights here")

    monkeypatch.setattr(predictors, "load", missing)
    monkeypatch.setattr(factory, "_LOADED", {})
    assert main(["demo", "--synthetic", "--predictor", "srnn", "--no-gif"]) == 2
    assert "no weights here" in capsys.readouterr().err
