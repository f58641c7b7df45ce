"""Image observations: off-screen MuJoCo rendering of MetaWorld scenes.

``PixelRenderer(size)`` renders an environment's current scene from a fixed camera to a
``[3, size, size]`` uint8 array (channels first, the layout the conv encoders read), with shadows
off (about 4x cheaper than with shadows). The default camera is MetaWorld's
``corner2``, whose image comes out upside down: it is flipped upright.

MuJoCo chooses its OpenGL backend once, when it is imported, from the environment variable
``MUJOCO_GL``; without a display only ``egl`` (GPU or Mesa's llvmpipe on a CPU) or ``osmesa``
work. The processes that render here are always worker processes started after
:func:`headless_gl` has set ``MUJOCO_GL=egl`` (unless the user set it), so that they import
MuJoCo with a headless backend; a process that imported MuJoCo with another backend gets a clear
error from :class:`PixelRenderer` instead of a crash.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["CAMERA", "PixelRenderer", "RenderError", "headless_gl"]

CAMERA = "corner2"


class RenderError(RuntimeError):
    """Off-screen rendering is not available in this process."""


def headless_gl() -> str:
    """Set ``MUJOCO_GL=egl`` for processes started from now on, unless set already; returns the value."""
    return os.environ.setdefault("MUJOCO_GL", "egl")


class PixelRenderer:
    """Renders ``env``'s scene to ``[3, size, size]`` uint8 (module docstring).

    Args:
        size: image height and width in pixels (e.g. 64).
        camera: a camera of the MetaWorld model; ``corner2`` (default) is flipped upright.

    Raises:
        ValueError: a size below 8.
        RenderError: (on the first call) MuJoCo cannot render off-screen in this process.
    """

    def __init__(self, size: int, camera: str = CAMERA):
        if isinstance(size, bool) or not isinstance(size, int) or size < 8:
            raise ValueError(f"the image size must be an integer >= 8 pixels, got {size!r}")
        self.size, self.camera = size, camera
        self._renderers: dict[int, tuple] = {}  # id(model) -> (model, mujoco.Renderer): one GL context per model

    def __call__(self, env) -> np.ndarray:
        env = getattr(env, "unwrapped", env)
        entry = self._renderers.get(id(env.model))
        if entry is None or entry[0] is not env.model:
            entry = self._renderers[id(env.model)] = (env.model, self._new_renderer(env.model))
        renderer = entry[1]
        renderer.update_scene(env.data, camera=self.camera)
        image = renderer.render()  # [S, S, 3] uint8
        if self.camera == CAMERA:
            image = image[::-1, ::-1]
        return np.ascontiguousarray(image.transpose(2, 0, 1))

    def _new_renderer(self, model):
        import mujoco

        model.vis.quality.shadowsize = 0
        try:
            return mujoco.Renderer(model, self.size, self.size)
        except Exception as err:
            backend = os.environ.get("MUJOCO_GL", "")
            raise RenderError(
                f"MuJoCo cannot render off-screen here (MUJOCO_GL={backend!r} when MuJoCo was imported: "
                f"{type(err).__name__}: {err}). Image observations need MUJOCO_GL=egl (or osmesa) set before "
                "MuJoCo is imported, e.g. `MUJOCO_GL=egl tar-rl train ...`, and libEGL (Mesa on a CPU)."
            ) from err

    def close(self) -> None:
        for _, renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()

    def __getstate__(self):
        return {"size": self.size, "camera": self.camera, "_renderers": {}}
