# Stubs for the native module crepuscular._core (core/python/src/lib.rs). Keep them in step:
# tests/test_core_api.py checks that the names, parameters and exception bases match.
# The render functions return (width, height, volume, visibility, depth) with arrays shaped
# (H, W, 4), (H, W) and (H, W); `crepuscular.Layers(*raw)` wraps them.

import os
from collections.abc import Callable
from typing import Final, Literal, TypeAlias

import numpy as np
import numpy.typing as npt

__version__: Final[str]
SCENE_VERSION: Final[int]
EXR_COMPRESSIONS: Final[tuple[str, ...]]
STYLE_VERSION: Final[int]

_Float32Array: TypeAlias = npt.NDArray[np.float32]
_UInt32Array: TypeAlias = npt.NDArray[np.uint32]
_DepthKind: TypeAlias = Literal["planar", "ray_distance"]
_Progress: TypeAlias = Callable[[float], object]
#: (width, height, volume (H, W, 4), visibility (H, W), depth (H, W)).
_RawLayers: TypeAlias = tuple[int, int, _Float32Array, _Float32Array, _Float32Array, float]

class CrepuscularError(Exception): ...

class InvalidInputError(CrepuscularError, ValueError):
    field: str | None

class ExrError(CrepuscularError, OSError): ...
class CancelledError(CrepuscularError): ...

def release_kept_buffers() -> None: ...
def render_json(
    scene_json: str,
    /,
    *,
    base_dir: str | os.PathLike[str] | None = None,
    style_json: str | None = None,
    camera_depth: _Float32Array | None = None,
    depth_kind: _DepthKind = "planar",
    progress: _Progress | None = None,
) -> _RawLayers: ...
def render_arrays(
    positions: _Float32Array,
    triangles: _UInt32Array,
    object_ids: _UInt32Array,
    camera_json: str,
    sun_json: str,
    medium_json: str,
    settings_json: str,
    /,
    *,
    style_json: str | None = None,
    camera_depth: _Float32Array | None = None,
    depth_kind: _DepthKind = "planar",
    progress: _Progress | None = None,
    origin: tuple[float, float, float] | None = None,
    uvs: _Float32Array | None = None,
    triangle_masks: _UInt32Array | None = None,
    masks: list[tuple[_Float32Array, float, str, str, str, float]] | None = None,
    triangle_visibility: npt.NDArray[np.uint8] | None = None,
) -> _RawLayers: ...
def normalize_scene_json(
    scene_json: str, /, *, base_dir: str | os.PathLike[str] | None = None
) -> str: ...
def normalize_style_json(
    style_json: str, /, *, base_dir: str | os.PathLike[str] | None = None
) -> str: ...
def bake_tf(style_json: str, /, *, time: float = 0.0) -> _Float32Array: ...
def builtin_scene_json(name: str, /) -> str: ...
def builtin_scene_names() -> list[str]: ...
def read_exr(path: str | os.PathLike[str], /) -> tuple[int, int, dict[str, _Float32Array]]: ...
def read_exr_pixel_aspect(path: str | os.PathLike[str], /) -> float: ...
def write_layers_exr(
    path: str | os.PathLike[str],
    volume: _Float32Array,
    visibility: _Float32Array,
    depth: _Float32Array,
    /,
    *,
    half: bool = False,
    compression: str = "zip",
    pixel_aspect: float = 1.0,
) -> None: ...
def write_channels_exr(
    path: str | os.PathLike[str],
    channels: list[tuple[str, _Float32Array]],
    /,
    *,
    half: bool = False,
    compression: str = "zip",
    pixel_aspect: float = 1.0,
) -> None: ...
def composite(volume: _Float32Array, beauty: _Float32Array, /) -> _Float32Array: ...
def write_preview_png(
    path: str | os.PathLike[str],
    rgba: _Float32Array,
    /,
    *,
    exposure: float | None = None,
    tone_map: bool = True,
) -> None: ...
