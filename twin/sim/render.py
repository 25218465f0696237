"""Offscreen rendering of a MuJoCo model to RGB arrays, on a machine without a display.

Why not `mujoco.Renderer`: it takes its OpenGL backend from ``MUJOCO_GL`` once, when ``mujoco`` is
first imported (GLFW unless told otherwise, which needs a display), and every aimbench process
has imported mujoco long before anyone asks for a picture. `OffscreenRenderer` opens its own
headless context instead, EGL first (Mesa renders on the CPU when there is no GPU), then OSMesa,
and draws with MuJoCo's own renderer (``mjr_render``) into the offscreen framebuffer. A backend
named by ``MUJOCO_GL`` (``egl``, ``osmesa``, ``glfw``) or by ``backend=`` is tried first.

Only one OpenGL platform can be loaded into a process (PyOpenGL fixes it at its first import):
the first backend that works is kept for every renderer after it.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from twin.core.errors import AimbenchError
from twin.sim.gl_backends import BACKENDS

#: The Debian packages each of the headless BACKENDS (in the order they are tried) needs.
DEBIAN_PACKAGES = {"egl": "libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0",
                   "osmesa": "libosmesa6",
                   "glfw": "a display (DISPLAY) and libglfw3"}
#: The backend that worked in this process (PyOpenGL keeps one platform per process).
_chosen: str | None = None


class RenderError(AimbenchError):
    """No OpenGL context could be made, or a camera is not the model's."""


@dataclass(frozen=True)
class FreeCamera:
    """A camera aimed at ``lookat`` (m, world frame) from ``distance`` (m), ``azimuth`` and
    ``elevation`` (rad, MuJoCo's convention: azimuth about +Z from +X, elevation negative when
    looking down). None: the model's default free camera (its statistics frame the model)."""

    lookat: tuple[float, float, float] | None = None
    distance: float | None = None
    azimuth: float | None = None
    elevation: float | None = None


Camera = str | int | FreeCamera
#: ``decorate(scene)``: adds geoms (`add_geom`, `add_arrow`) after the model's own are in.
Decorate = Callable[[mujoco.MjvScene], None]


def _context_class(backend: str) -> type:
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    elif backend == "glfw":
        from mujoco.glfw import GLContext
    else:
        raise RenderError(f"unknown OpenGL backend {backend!r}; use one of {', '.join(BACKENDS)}")
    return GLContext


def _order(backend: str | None) -> list[str]:
    if _chosen is not None:
        return [_chosen]
    wanted = backend or os.environ.get("MUJOCO_GL", "").strip().lower()
    first = [wanted] if wanted in BACKENDS else []
    return first + [b for b in BACKENDS if b not in first]


def open_context(width: int, height: int, backend: str | None = None) -> tuple[object, str]:
    """(an OpenGL context of at least width x height, made current; its backend's name)."""
    global _chosen
    tried = []
    for name in _order(backend):
        try:
            context = _context_class(name)(width, height)
            context.make_current()
        except RenderError:
            raise
        except Exception as exc:  # each backend fails its own way (ImportError, RuntimeError)
            tried.append(f"{name}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
            continue
        _chosen = name
        return context, name
    needs = "; ".join(f"{b} needs {DEBIAN_PACKAGES[b]}" for b in BACKENDS)
    raise RenderError(f"no OpenGL context for offscreen rendering ({'; '.join(tried)}); {needs} "
                      "(tools/setup.sh installs the EGL packages)")


class OffscreenRenderer:
    """Renders one compiled model's scenes to arrays of ``height`` x ``width`` pixels."""

    def __init__(self, model: mujoco.MjModel, width: int = 640, height: int = 480,
                 backend: str | None = None, max_geom: int = 10000) -> None:
        if width < 1 or height < 1:
            raise RenderError(f"image size {width} x {height}: both must be at least 1 pixel")
        self.model = model
        self.width, self.height = int(width), int(height)
        # The offscreen framebuffer is sized from the model; a larger picture needs a larger one.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        self._context, self.backend = open_context(self.width, self.height, backend)
        self._mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._mjr)
        self.scene = mujoco.MjvScene(model, maxgeom=max_geom)
        self.option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)

    def camera(self, camera: Camera = -1) -> mujoco.MjvCamera:
        """The `MjvCamera` of a model camera (name or id; -1: the free camera) or a free one."""
        cam = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(self.model, cam)
        if isinstance(camera, FreeCamera):
            for name in ("distance", "azimuth", "elevation"):
                value = getattr(camera, name)
                if value is not None:
                    setattr(cam, name, float(np.degrees(value)) if name != "distance" else value)
            if camera.lookat is not None:
                cam.lookat[:] = camera.lookat
            return cam
        cam_id = camera if isinstance(camera, int) else mujoco.mj_name2id(
            self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if not -1 <= cam_id < self.model.ncam or (isinstance(camera, str) and cam_id < 0):
            raise RenderError(f"no camera {camera!r} in the model; it has "
                              f"{', '.join(camera_names(self.model)) or 'none'}")
        if cam_id >= 0:
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cam_id
        return cam

    def render(self, data: mujoco.MjData, camera: Camera = -1,
               decorate: Decorate | None = None, text: Sequence[str] = ()) -> np.ndarray:
        """RGB image (height, width, 3) uint8 of ``data`` seen from ``camera``, with the geoms
        ``decorate`` adds and ``text`` in the top left corner."""
        self._draw(data, camera, decorate, text)
        rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(rgb, None, self._rect, self._mjr)
        return np.flipud(rgb).copy()  # OpenGL's rows run bottom-up

    def segmentation(self, data: mujoco.MjData, camera: Camera = -1) -> np.ndarray:
        """Geom id per pixel (height, width) int32, -1 where no model geom is seen."""
        flags = self.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        try:
            self._draw(data, camera, None, ())
            rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
            mujoco.mjr_readPixels(rgb, None, self._rect, self._mjr)
        finally:
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
        seg = np.flipud(rgb).astype(np.int64)
        segid = seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16)  # 0: background
        lookup = np.full(self.scene.ngeom + 1, -1, dtype=np.int32)
        for g in self.scene.geoms[: self.scene.ngeom]:
            if g.segid >= 0 and g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lookup[g.segid + 1] = g.objid
        return lookup[np.clip(segid, 0, len(lookup) - 1)]

    def _draw(self, data: mujoco.MjData, camera: Camera, decorate: Decorate | None,
              text: Sequence[str]) -> None:
        self._context.make_current()
        mujoco.mjv_updateScene(self.model, data, self.option, None, self.camera(camera),
                               mujoco.mjtCatBit.mjCAT_ALL, self.scene)
        if decorate is not None:
            decorate(self.scene)
        mujoco.mjr_render(self._rect, self.scene, self._mjr)
        if text:
            mujoco.mjr_overlay(mujoco.mjtFontScale.mjFONTSCALE_150,
                               mujoco.mjtGridPos.mjGRID_TOPLEFT, self._rect, "\n".join(text),
                               "", self._mjr)

    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        if self._mjr is not None:
            self._context.make_current()
            self._mjr.free()
            self._mjr = None
        free = getattr(self._context, "free", None)
        if free is not None:
            free()

    def __enter__(self) -> OffscreenRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def camera_names(model: mujoco.MjModel) -> list[str]:
    """Names of the model's cameras (unnamed ones as ``#id``)."""
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) or f"#{i}"
            for i in range(model.ncam)]


def add_geom(scene: mujoco.MjvScene, kind: mujoco.mjtGeom, size: Sequence[float],
             pos: Sequence[float], mat: np.ndarray | None = None,
             rgba: Sequence[float] = (1.0, 0.0, 0.0, 1.0)) -> None:
    """Append a decoration geom (world frame, m) to ``scene``; silently none once it is full."""
    if scene.ngeom >= scene.maxgeom:
        return
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, int(kind), np.asarray(size, float).reshape(3),
                        np.asarray(pos, float).reshape(3),
                        (np.eye(3) if mat is None else np.asarray(mat, float)).reshape(9),
                        np.asarray(rgba, np.float32).reshape(4))
    scene.ngeom += 1


def add_arrow(scene: mujoco.MjvScene, start: Sequence[float], end: Sequence[float],
              width: float = 0.01, rgba: Sequence[float] = (1.0, 0.0, 0.0, 1.0)) -> None:
    """Append an arrow from ``start`` to ``end`` (world frame, m) to ``scene``."""
    if scene.ngeom >= scene.maxgeom:
        return
    add_geom(scene, mujoco.mjtGeom.mjGEOM_ARROW, (width, width, width), start, None, rgba)
    mujoco.mjv_connector(scene.geoms[scene.ngeom - 1], int(mujoco.mjtGeom.mjGEOM_ARROW),
                         float(width), np.asarray(start, float), np.asarray(end, float))
