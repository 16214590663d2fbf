"""Top-down pictures of pusher-reach: MuJoCo's renderer where OpenGL works, numpy where not.

``render_top_down(env)`` returns an (H, W, 3) uint8 image from the model's ``top``
camera. The GL path tries, in order, the backend ``import mujoco`` picked (the
``MUJOCO_GL`` variable; glfw when unset; ``MUJOCO_GL=disable`` means numpy only),
then EGL, then OSMesa, each through an
explicit context so that a headless machine needs no variable set before import.
Without any of them it draws the same view with numpy: the floor, the capsule links,
the target sphere and the fingertip site, projected through the same camera, so
the fallback's pixels line up with MuJoCo's.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import mujoco
import numpy as np

CAMERA = "top"
BACKENDS = ("auto", "gl", "numpy")


def _gl_context_classes():
    """(name, GLContext class) candidates, the one ``import mujoco`` chose first."""
    chosen = os.environ.get("MUJOCO_GL", "").lower().strip()
    if chosen in ("disable", "disabled", "off", "false", "0"):
        return  # the user turned OpenGL off: numpy only
    default = getattr(mujoco, "GLContext", None)
    # Unset MUJOCO_GL means glfw, which needs a display: skip it on a headless box.
    if default is not None and (chosen or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        yield chosen or "glfw", default
    for name in ("egl", "osmesa"):
        try:
            module = __import__(f"mujoco.{name}", fromlist=["GLContext"])
            yield name, module.GLContext
        except Exception:  # noqa: BLE001 - a missing library, or PyOpenGL bound to another platform
            continue


class _GLRenderer:
    """MuJoCo's own renderer on an offscreen buffer of one GL context."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int, context_cls):
        limit = (model.vis.global_.offwidth, model.vis.global_.offheight)
        if width > limit[0] or height > limit[1]:
            raise ValueError(f"{width}x{height} exceeds the model's offscreen buffer {limit[0]}x{limit[1]}")
        self.model, self.width, self.height = model, width, height
        self._ctx = context_cls(width, height)
        try:
            self._ctx.make_current()
            self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        except BaseException:
            self._ctx.free()
            raise
        self._scene = mujoco.MjvScene(model, maxgeom=100)
        self._opt = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = model.camera(CAMERA).id
        self._rect = mujoco.MjrRect(0, 0, width, height)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        self._ctx.make_current()
        mujoco.mjv_updateScene(self.model, data, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        mujoco.mjr_render(self._rect, self._scene, self._con)
        image = np.empty((self.height, self.width, 3), np.uint8)
        mujoco.mjr_readPixels(image, None, self._rect, self._con)
        return np.ascontiguousarray(image[::-1])  # GL rows run bottom-up

    def close(self) -> None:
        if self._ctx is not None:
            self._con.free()
            self._ctx.free()
            self._ctx = None


def camera_pixels(model: mujoco.MjModel, data: mujoco.MjData, points, width: int, height: int) -> np.ndarray:
    """Pixel (column, row) of world points (N, 3) in the ``top`` camera's image.

    A pinhole with MuJoCo's conventions: the camera looks along its -z axis, image
    x along its x axis, ``fovy`` spans the image height.
    """
    cam = model.camera(CAMERA).id
    rel = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - data.cam_xpos[cam]) @ data.cam_xmat[cam].reshape(3, 3)
    focal = 0.5 * height / np.tan(np.deg2rad(model.cam_fovy[cam]) / 2.0)
    depth = -rel[:, 2]
    return np.stack([width / 2.0 + focal * rel[:, 0] / depth, height / 2.0 - focal * rel[:, 1] / depth], axis=1)


class _NumpyRenderer:
    """The top view drawn with numpy: flat-shaded discs and capsules, floor colour behind."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int):
        self.model, self.width, self.height = model, width, height
        self._cols, self._rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)

    def _scale(self, data, z: float) -> float:
        """Pixels per metre at height z."""
        a, b = camera_pixels(self.model, data, [[0.0, 0.0, z], [1e-3, 0.0, z]], self.width, self.height)
        return float(np.hypot(*(b - a)) / 1e-3)

    def _paint(self, image, mask, rgba) -> None:
        alpha = float(rgba[3])
        image[mask] = (1.0 - alpha) * image[mask] + alpha * 255.0 * np.asarray(rgba[:3])

    def _capsule_mask(self, p0, p1, radius_px):
        seg = p1 - p0
        length2 = float(seg @ seg)
        u = self._cols - p0[0]
        v = self._rows - p0[1]
        t = np.clip((u * seg[0] + v * seg[1]) / length2, 0.0, 1.0) if length2 > 0 else 0.0
        return (u - t * seg[0]) ** 2 + (v - t * seg[1]) ** 2 <= radius_px**2

    def render(self, data: mujoco.MjData) -> np.ndarray:
        m = self.model
        image = np.empty((self.height, self.width, 3), np.float64)
        floor = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
        image[:] = 255.0 * (m.geom_rgba[floor[0], :3] if floor else np.array([0.9, 0.9, 0.9]))
        for g in range(m.ngeom):
            kind = m.geom_type[g]
            centre = data.geom_xpos[g]
            if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                axis = data.geom_xmat[g].reshape(3, 3)[:, 2] * m.geom_size[g, 1]
                ends = camera_pixels(m, data, [centre - axis, centre + axis], self.width, self.height)
                mask = self._capsule_mask(ends[0], ends[1], m.geom_size[g, 0] * self._scale(data, centre[2]))
            elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
                c = camera_pixels(m, data, [centre], self.width, self.height)[0]
                mask = self._capsule_mask(c, c, m.geom_size[g, 0] * self._scale(data, centre[2]))
            else:
                continue
            self._paint(image, mask, m.geom_rgba[g])
        for s in range(m.nsite):
            c = camera_pixels(m, data, [data.site_xpos[s]], self.width, self.height)[0]
            self._paint(image, self._capsule_mask(c, c, m.site_size[s, 0] * self._scale(data, data.site_xpos[s, 2])), m.site_rgba[s])
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)

    def close(self) -> None:
        pass


class TopDownRenderer:
    """A reusable top-down renderer for one model; ``backend`` is 'auto', 'gl' or 'numpy'.

    'auto' uses the first GL backend that renders and falls back to numpy; 'gl'
    raises when none does. ``self.backend`` says which one is in use
    ('glfw', 'egl', 'osmesa' or 'numpy').
    """

    def __init__(self, model: mujoco.MjModel, width: int = 480, height: int = 480, backend: str = "auto"):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.width, self.height = int(width), int(height)
        self._impl = None
        self.backend = "numpy"
        errors = []
        if backend != "numpy":
            for name, context_cls in _gl_context_classes():
                try:
                    self._impl = _GLRenderer(model, self.width, self.height, context_cls)
                    self.backend = name
                    break
                except Exception as exc:  # noqa: BLE001 - try the next backend
                    errors.append(f"{name}: {exc}")
            if self._impl is None and backend == "gl":
                raise RuntimeError("no OpenGL backend could render: " + ("; ".join(errors) or "none available"))
        if self._impl is None:
            self._impl = _NumpyRenderer(model, self.width, self.height)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        return self._impl.render(data)

    def close(self) -> None:
        self._impl.close()


def render_top_down(env, width: int = 480, height: int = 480, backend: str = "auto") -> np.ndarray:
    """One (height, width, 3) uint8 picture of ``env`` (anything with ``model`` and ``data``,
    e.g. ``PusherReachEnv`` or the Gymnasium env) seen from the ``top`` camera."""
    env = getattr(env, "unwrapped", env)
    renderer = TopDownRenderer(env.model, width, height, backend)
    try:
        return renderer.render(env.data)
    finally:
        renderer.close()


def save_png(image: np.ndarray, path) -> Path:
    """Write an (H, W, 3) uint8 image as an 8-bit RGB PNG, with zlib alone."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {image.dtype} {image.shape}")
    height, width, _ = image.shape
    raw = np.concatenate([np.zeros((height, 1), np.uint8), image.reshape(height, width * 3)], axis=1).tobytes()

    def chunk(tag: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + tag + body + zlib.crc32(tag + body).to_bytes(4, "big")

    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return path
