"""Turns Python values into what `crepuscular._core` takes, copying only when it must.

Arrays that are already C-contiguous, aligned and of the native dtype the core reads
(float32 positions and depths, uint32 indices and ids) pass through as the same object and
the core reads them in place. Anything else is converted once with `np.ascontiguousarray`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from crepuscular import _core
from crepuscular._core import InvalidInputError

_U32_MAX = int(np.iinfo(np.uint32).max)
_Scalar = TypeVar("_Scalar", bound=np.generic)


def invalid(field: str, reason: str) -> InvalidInputError:
    """An `InvalidInputError` worded like the core's ("invalid FIELD: REASON")."""
    error = InvalidInputError(f"invalid {field}: {reason}")
    error.field = field
    return error


# --- JSON ---------------------------------------------------------------------------------


def scene_json(scene: Mapping[str, Any] | str | os.PathLike[str]) -> str:
    """JSON text for a scene given as a mapping, JSON text or a path to a .json file.

    A string whose first non-blank character is "{" is JSON text; any other string is a path.
    """
    if isinstance(scene, os.PathLike):
        return Path(scene).read_text(encoding="utf-8")
    if isinstance(scene, str):
        if scene.lstrip().startswith("{"):
            return scene
        return Path(scene).read_text(encoding="utf-8")
    if isinstance(scene, Mapping):
        return to_json(scene, "")
    raise TypeError(
        f"scene must be a mapping, JSON text or a path to a .json file, got {type(scene).__name__}"
    )


def base_dir(source: Mapping[str, Any] | str | os.PathLike[str]) -> Path | None:
    """The directory of a scene or preset given as a path, which its relative image paths
    are relative to; None for JSON text and mappings (the working directory's)."""
    if isinstance(source, os.PathLike) or (
        isinstance(source, str) and not source.lstrip().startswith("{")
    ):
        return Path(source).parent
    return None


def style_json(style: Mapping[str, Any] | str | os.PathLike[str]) -> str:
    """JSON text for a style preset, as `scene_json`; a file's relative image paths are
    joined to its directory, so that a preset finds its images from any working directory."""
    text = scene_json(style)
    folder = base_dir(style)
    return text if folder is None else _core.normalize_style_json(text, base_dir=folder)


def to_json(value: Any, path: str) -> str:
    """Strict JSON for `value`; `path` names it in errors ("camera", "" for a whole scene).

    numpy arrays and scalars are accepted. NaN and infinities cannot be written as JSON, so
    they raise `InvalidInputError` naming their path, e.g. "camera.world_from_camera[5]".
    """
    try:
        return json.dumps(value, allow_nan=False, default=_json_default, separators=(",", ":"))
    except (TypeError, ValueError) as error:
        found = _find_unencodable(value, path, set())
        if found is None:
            raise
        field, reason = found
        raise invalid(field, reason) from error


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Mapping):
        return dict(value)
    raise TypeError(f"a {type(value).__name__} cannot be written as JSON")


def _find_unencodable(value: Any, path: str, seen: set[int]) -> tuple[str, str] | None:
    """The path of the first value that strict JSON cannot hold, and why."""
    here = path or "scene"
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, float):
        if math.isfinite(value):
            return None
        return here, f"{value} is not finite (scene values must be finite numbers)"
    if value is None or isinstance(value, str | int):
        return None
    if isinstance(value, Mapping | list | tuple):
        if id(value) in seen:
            return here, "contains itself"
        seen.add(id(value))
        if isinstance(value, Mapping):
            for key, item in value.items():
                if not isinstance(key, str):
                    return here, f"has the key {key!r}; keys must be strings"
                found = _find_unencodable(item, f"{path}.{key}" if path else key, seen)
                if found is not None:
                    return found
        else:
            for index, item in enumerate(value):
                found = _find_unencodable(item, f"{here}[{index}]", seen)
                if found is not None:
                    return found
        seen.discard(id(value))
        return None
    return here, f"a {type(value).__name__} cannot be written as JSON"


# --- arrays -------------------------------------------------------------------------------


def float_rows(value: npt.ArrayLike, name: str) -> npt.NDArray[np.float32]:
    """An (N, 3) float32 array for `name`."""
    array = np.asarray(value)
    if array.ndim != 2 or array.shape[1] != 3:
        raise invalid(name, f"must have shape (N, 3), got {_shape(array)}")
    _require_real(array, name)
    return _contiguous(array, np.float32)


def index_rows(value: npt.ArrayLike, name: str) -> npt.NDArray[np.uint32]:
    """An (M, 3) uint32 array of vertex indices for `name`."""
    array = np.asarray(value)
    if array.ndim != 2 or array.shape[1] != 3:
        raise invalid(name, f"must have shape (M, 3), got {_shape(array)}")
    return _uint32(array, name)


def object_ids(value: npt.ArrayLike | None, triangle_count: int) -> npt.NDArray[np.uint32]:
    """One uint32 id per triangle; all 0 when `value` is None."""
    if value is None:
        return np.zeros(triangle_count, dtype=np.uint32)
    array = np.asarray(value)
    if array.shape != (triangle_count,):
        raise invalid(
            "object_ids",
            f"must have shape (M,) = ({triangle_count},), one id per triangle, got {_shape(array)}",
        )
    return _uint32(array, "object_ids")


def uv_rows(value: npt.ArrayLike, position_count: int) -> npt.NDArray[np.float32]:
    """(N, 2) float32 texture coordinates, one row per position."""
    array = np.asarray(value)
    if array.shape != (position_count, 2):
        raise invalid(
            "uvs",
            f"must have shape (N, 2) = ({position_count}, 2), one row per position, "
            f"got {_shape(array)}",
        )
    _require_real(array, "uvs")
    return _contiguous(array, np.float32)


def _integer_per_triangle(value: npt.ArrayLike, triangle_count: int, name: str) -> np.ndarray:
    """An (M,) integer array, one entry per triangle, or an error naming `name`."""
    array = np.asarray(value)
    if array.shape != (triangle_count,):
        raise invalid(
            name,
            f"must have shape (M,) = ({triangle_count},), one per triangle, got {_shape(array)}",
        )
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise invalid(name, f"must hold integers, got dtype {array.dtype}")
    return array


def triangle_masks(value: npt.ArrayLike, triangle_count: int) -> npt.NDArray[np.uint32]:
    """One mask index per triangle, -1 (no mask) as the core's 0xFFFFFFFF."""
    array = _integer_per_triangle(value, triangle_count, "triangle_masks")
    if array.size and array.dtype.kind == "i":
        if int(array.min()) < -1:
            row = int(np.argmin(array))
            raise invalid(f"triangle_masks[{row}]", f"{int(array[row])} is below -1 (no mask)")
        array = np.where(array < 0, _U32_MAX, array)
    return _uint32(array, "triangle_masks")


def triangle_visibility(value: npt.ArrayLike, triangle_count: int) -> npt.NDArray[np.uint8]:
    """One flag set per triangle: 1 blocks the sun, 2 is seen by the camera."""
    array = _integer_per_triangle(value, triangle_count, "triangle_visibility")
    if array.size and (int(array.min()) < 0 or int(array.max()) > 3):
        row = int(np.argmax((array < 0) | (array > 3)))
        raise invalid(
            f"triangle_visibility[{row}]",
            f"is {int(array[row])}; flags are 1 (blocks the sun) and 2 (seen by the camera)",
        )
    return _contiguous(array, np.uint8)


def alpha_mask(value: npt.ArrayLike, index: int) -> npt.NDArray[np.float32]:
    """A (height, width) float32 alpha texture."""
    array = np.asarray(value)
    if array.ndim != 2:
        raise invalid(f"masks[{index}]", f"must have shape (height, width), got {_shape(array)}")
    _require_real(array, f"masks[{index}]")
    return _contiguous(array, np.float32)


_MASK_WRAPS = ("repeat", "extend", "mirror", "clip")
_MASK_FILTERS = ("linear", "closest")


def mask_sampling(wrap: object, filter_: object, index: int) -> tuple[str, str, str]:
    """An alpha mask's wrap along u and v, and its filter, each checked against the names
    the core reads."""
    axes = (wrap, wrap) if isinstance(wrap, str) else wrap
    if not (
        isinstance(axes, tuple | list)
        and len(axes) == 2
        and all(axis in _MASK_WRAPS for axis in axes)
    ):
        raise invalid(
            f"masks[{index}].wrap",
            f"must be one of {', '.join(_MASK_WRAPS)} or a (u, v) pair of them, got {wrap!r}",
        )
    if filter_ not in _MASK_FILTERS:
        raise invalid(
            f"masks[{index}].filter",
            f"must be one of {', '.join(_MASK_FILTERS)}, got {filter_!r}",
        )
    return str(axes[0]), str(axes[1]), str(filter_)


def point(value: npt.ArrayLike, name: str) -> tuple[float, float, float]:
    """Three coordinates for `name`, as float64; the core checks that they are finite."""
    array = np.asarray(value)
    if array.shape != (3,):
        raise invalid(name, f"must have shape (3,), got {_shape(array)}")
    _require_real(array, name)
    x, y, z = (float(v) for v in array)
    return x, y, z


def depth_map(value: npt.ArrayLike | None) -> npt.NDArray[np.float32] | None:
    """A (height, width) float32 camera depth map; the core checks it against the camera."""
    if value is None:
        return None
    array = np.asarray(value)
    if array.ndim != 2:
        raise invalid("camera_depth", f"must have shape (height, width), got {_shape(array)}")
    _require_real(array, "camera_depth")
    return _contiguous(array, np.float32)


def _shape(array: npt.NDArray[Any]) -> str:
    return str(tuple(int(side) for side in array.shape))


def _require_real(array: npt.NDArray[Any], name: str) -> None:
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise invalid(name, f"must hold real numbers, got dtype {array.dtype}")


def _uint32(array: npt.NDArray[Any], name: str) -> npt.NDArray[np.uint32]:
    if array.dtype != np.uint32 and array.size > 0:
        if not np.issubdtype(array.dtype, np.integer):
            raise invalid(name, f"must hold integers, got dtype {array.dtype}")
        low = int(array.min())
        high = int(array.max())
        if low < 0 or high > _U32_MAX:
            bad = int(np.argmin(array)) if low < 0 else int(np.argmax(array))
            row = int(np.unravel_index(bad, array.shape)[0])
            value = low if low < 0 else high
            raise invalid(f"{name}[{row}]", f"{value} is outside the uint32 range 0..={_U32_MAX}")
    return _contiguous(array, np.uint32)


def _contiguous(array: npt.NDArray[Any], dtype: type[_Scalar]) -> npt.NDArray[_Scalar]:
    """`array` itself when it already fits, else one converted copy."""
    result: npt.NDArray[_Scalar] = np.ascontiguousarray(array, dtype=dtype)
    if not result.flags.aligned:
        result = result.copy()
    return result
