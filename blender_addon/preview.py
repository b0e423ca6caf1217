"""Viewport preview: the volume layer drawn over the 3D viewport in camera view.

`PreviewController` holds the logic, which runs without a window and is tested headless:
- any change (depsgraph update, frame change, setting) calls `mark_dirty`;
- `step` runs on the main thread (from a timer): once the scene has been quiet for
  `debounce` seconds, it exports the frame (bpy is only touched here) and starts the core on
  a worker thread, at 1/2, 1/4 or 1/8 of the render size. The core releases the GIL, so
  Blender stays responsive;
- a newer request cancels the running one: its progress callback raises `Superseded`;
- the finished volume is converted to display sRGB once, for drawing.
Drawing (a POST_PIXEL callback of the 3D view) is the only part that needs a GPU.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import bpy
import numpy as np

import crepuscular

from . import export

#: Seconds between timer ticks.
TICK = 0.1


class Superseded(Exception):
    """Raised in the worker's progress callback when a newer request replaced it."""


@dataclass
class PreviewResult:
    generation: int
    #: (H, W, 4) premultiplied scene-linear volume layer at preview size.
    volume: np.ndarray
    #: The same, as straight-alpha display sRGB floats ready for a texture (rows bottom up).
    display: np.ndarray
    seconds: float


def to_display(volume: np.ndarray) -> np.ndarray:
    """Premultiplied linear RGBA (rows top down) to premultiplied sRGB rows bottom up."""
    rgb = np.clip(volume[..., :3], 0.0, None)
    alpha = np.clip(volume[..., 3:4], 0.0, 1.0)
    encoded = np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * np.power(rgb, 1 / 2.4) - 0.055)
    return np.ascontiguousarray(
        np.concatenate([np.clip(encoded, 0.0, 1.0), alpha], axis=-1)[::-1], dtype=np.float32
    )


class PreviewController:
    def __init__(self, debounce: float = 0.25) -> None:
        self.debounce = debounce
        self.dirty = False
        self.last_change = 0.0
        self.generation = 0
        self.cache = export.GeometryCache()
        self.result: PreviewResult | None = None
        self.error = ""
        self.cancelled = 0
        #: The running update's fraction done, as the core reports it.
        self.progress = 0.0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def mark_dirty(self) -> None:
        self.dirty = True
        self.last_change = time.monotonic()

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def cancel(self) -> None:
        """Supersedes the running work and waits for its thread to end."""
        with self._lock:
            self.generation += 1
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def step(
        self, scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph, now: float | None = None
    ) -> bool:
        """Starts an update when one is due; returns whether it started one."""
        if not scene.crepuscular.preview or not self.dirty:
            return False
        now = time.monotonic() if now is None else now
        if now - self.last_change < self.debounce:
            return False
        self.dirty = False
        with self._lock:
            self.generation += 1
            generation = self.generation
        try:
            inputs = export.all_frame_inputs(
                scene,
                depsgraph,
                cache=self.cache,
                divisor=int(scene.crepuscular.preview_scale),
                preview=True,
            )
        except (export.ExportError, ValueError, crepuscular.CrepuscularError) as error:
            self.error = str(error)
            return False
        self.error = ""
        thread = threading.Thread(
            target=self._work,
            args=(generation, inputs),
            name="crepuscular-preview",
            daemon=True,
        )
        self._thread = thread
        self.progress = 0.0
        thread.start()
        return True

    def _work(self, generation: int, inputs: list[export.FrameInputs]) -> None:
        def progress(fraction: float) -> None:
            if self.generation != generation:
                raise Superseded
            self.progress = fraction

        start = time.perf_counter()
        try:
            volume, _, _ = export.render_suns(inputs, progress)
        except Superseded:
            with self._lock:
                self.cancelled += 1
            return
        except crepuscular.CrepuscularError as error:
            with self._lock:
                if generation == self.generation:
                    self.error = str(error)
            return
        result = PreviewResult(generation, volume, to_display(volume), time.perf_counter() - start)
        with self._lock:
            if generation == self.generation:
                self.result = result

    def wait(self, timeout: float = 60.0) -> None:
        """Blocks until the running update ends (for scripts and tests)."""
        if self._thread is not None:
            self._thread.join(timeout)


CONTROLLER = PreviewController()
_DRAW_HANDLE: list[Any] = []
_shown_generation = [0]


def _tick() -> float:
    context = bpy.context
    scene = context.scene
    if scene is not None and scene.crepuscular.preview:
        CONTROLLER.step(scene, context.evaluated_depsgraph_get())
        result = CONTROLLER.result
        if result is not None and result.generation != _shown_generation[0]:
            _shown_generation[0] = result.generation
            for window in context.window_manager.windows:
                for area in window.screen.areas:
                    if area.type == "VIEW_3D":
                        area.tag_redraw()
    return TICK


def _draw() -> None:
    """Draws the latest preview inside the camera frame (needs a GPU context)."""
    import gpu
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    from gpu_extras.batch import batch_for_shader

    context = bpy.context
    scene, region, view = context.scene, context.region, context.region_data
    result = CONTROLLER.result
    if (
        result is None
        or not scene.crepuscular.preview
        or view is None
        or view.view_perspective != "CAMERA"
        or scene.camera is None
    ):
        return
    camera = scene.camera
    frame = [camera.matrix_world @ v for v in camera.data.view_frame(scene=scene)]
    corners = [location_3d_to_region_2d(region, view, p) for p in frame]
    if any(c is None for c in corners):
        return
    height, width = result.display.shape[:2]
    buffer = gpu.types.Buffer("FLOAT", width * height * 4, result.display.ravel())
    texture = gpu.types.GPUTexture((width, height), format="RGBA32F", data=buffer)
    shader = gpu.shader.from_builtin("IMAGE")
    # view_frame: top right, bottom right, bottom left, top left.
    positions = [tuple(corners[i]) for i in (2, 1, 0, 3)]
    batch = batch_for_shader(
        shader, "TRI_FAN", {"pos": positions, "texCoord": ((0, 0), (1, 0), (1, 1), (0, 1))}
    )
    gpu.state.blend_set("ALPHA_PREMULT")
    shader.bind()
    shader.uniform_sampler("image", texture)
    batch.draw(shader)
    gpu.state.blend_set("NONE")


def register() -> None:
    bpy.app.timers.register(_tick, first_interval=TICK, persistent=True)
    if not bpy.app.background:
        _DRAW_HANDLE.append(
            bpy.types.SpaceView3D.draw_handler_add(_draw, (), "WINDOW", "POST_PIXEL")
        )


def unregister() -> None:
    while _DRAW_HANDLE:
        bpy.types.SpaceView3D.draw_handler_remove(_DRAW_HANDLE.pop(), "WINDOW")
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    CONTROLLER.cancel()
    CONTROLLER.result = None
    CONTROLLER.cache.invalidate()
    # Nothing renders once the add-on is off: the core's kept frame buffers can go.
    crepuscular.release_kept_buffers()
