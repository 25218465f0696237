"""`aimbench render` and the offscreen renderer under it (twin/sim/render.py): real MuJoCo
rendering through EGL/OSMesa on a machine without a display, checked against MuJoCo's own
segmentation of the same view."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import mujoco
import numpy as np
import pytest

import models
from twin.sim.render import FreeCamera, OffscreenRenderer, RenderError, camera_names

REPO = Path(__file__).resolve().parents[1]


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("DISPLAY", None)  # headless, as on a server
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def _board_mask(width: int, height: int, camera: str | FreeCamera) -> np.ndarray:
    model = mujoco.MjModel.from_xml_path(str(models.SCENE))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    board = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "board")
    with OffscreenRenderer(model, width, height) as r:
        return r.segmentation(data, camera) == board


def test_render_the_bench_scene_to_png_headless(tmp_path: Path) -> None:
    res = aimbench("render", str(models.SCENE), "--out", "bench.png", "--width", "640",
                   "--height", "360", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "camera overview" in res.stderr and "bench.png" in res.stderr
    # seconds of work, each step shown as it ends
    assert re.search(r"^render: 2/4 steps \| OpenGL context \(\w+\)$", res.stderr, re.M)
    assert "render: 4/4 steps | written to" in res.stderr
    img = matplotlib.image.imread(tmp_path / "bench.png")
    assert img.shape[:2] == (360, 640)
    rgb = (img[..., :3] * 255).astype(int)
    # The board's pixels (MuJoCo's segmentation of the same view) are there, bright.
    board = _board_mask(640, 360, "overview")
    assert board.sum() > 2000
    assert rgb[board].mean() > 200 and rgb[~board].mean() < 150


def test_render_default_model_and_free_camera(tmp_path: Path) -> None:
    res = aimbench("render", "--out", "free.png", "--camera", "free", "--azimuth-deg", "60",
                   "--elevation-deg", "-30", "--width", "320", "--height", "240", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "the free camera" in res.stderr
    img = matplotlib.image.imread(tmp_path / "free.png")
    assert img.shape[:2] == (240, 320) and img[..., :3].std() > 0.05
    # a model without a camera gets the free camera framing it
    (tmp_path / "ball.xml").write_text(
        "<mujoco><worldbody><light pos='0 0 3'/>"
        "<geom type='sphere' size='0.3' rgba='1 0 0 1'/></worldbody></mujoco>")
    res = aimbench("render", "ball.xml", "--out", "ball.png", "--width", "200", "--height",
                   "200", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    ball = (matplotlib.image.imread(tmp_path / "ball.png")[..., :3] * 255).astype(int)
    r, g, b = ball[..., 0], ball[..., 1], ball[..., 2]
    red = (r > 150) & (r - g > 100) & (g == b)  # red, lit by a white headlight
    assert red[90:110, 90:110].all()  # the ball in the middle of the picture


@pytest.mark.parametrize(("args", "message"), [
    (("--out", "x.png", "--camera", "nope"), "no camera 'nope' in the model; it has overview"),
    (("nope.xml", "--out", "x.png"), "no model file nope.xml"),
    (("bad.xml", "--out", "x.png"), "bad.xml does not compile as MJCF"),
    (("--out", "x.jpg"), "written as PNG"),
    (("--out", "x.png", "--camera", "overview", "--distance", "3"), "move the free camera"),
    (("--out", "x.png", "--keyframe", "away"), "no keyframe 'away' in the model; it has home"),
    (("--out", "x.png", "--camera", "free", "--lookat", "1,2"), "give 3 comma-separated"),
])
def test_bad_render_input_is_one_clear_line(tmp_path: Path, args, message) -> None:
    (tmp_path / "bad.xml").write_text("<mujoco><worldbody><geom type='bogus'/></worldbody>"
                                      "</mujoco>")
    res = aimbench("render", *args, cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], res.stderr


def test_renderer_cameras_and_sizes() -> None:
    model = mujoco.MjModel.from_xml_path(str(models.SCENE))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert camera_names(model) == ["overview"]
    # larger than the model's offscreen buffer (1280 x 720): the buffer grows
    with OffscreenRenderer(model, 1600, 900) as r:
        assert r.render(data, "overview").shape == (900, 1600, 3)
        with pytest.raises(RenderError, match="no camera 'side'"):
            r.render(data, "side")
    with pytest.raises(RenderError, match="at least 1 pixel"):
        OffscreenRenderer(model, 0, 10)
