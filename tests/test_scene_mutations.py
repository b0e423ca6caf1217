"""Scene descriptions mutated one value at a time: every camera, sun, medium (with a fog
box) and render value of a small `plane` frame, replaced in turn by zero, -1, ±10³⁰, NaN,
infinity, a string and null, must render finite layers with every method, or be refused
with a `CrepuscularError` that names the field, through a perspective camera and an
orthographic one. The first runs of this found NaN pixels (a sun 10⁻²⁵ off an axis, fog of
1000 /m, an orthographic camera 10³⁰ m out) and an internal error (a perspective camera
10³⁰ m out)."""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

import crepuscular

#: Fields whose values stay: the meshes (arrays of thousands of numbers, which the mesh
#: tests cover) and the format version.
LEFT_ALONE = ("meshes", "version")
REPLACEMENTS: list[Any] = [0, -1, 1e30, -1e30, math.nan, math.inf, "x", None]


def _scene(method: str, projection: str) -> dict[str, Any]:
    scene = crepuscular.builtin_scene("plane")
    scene["camera"]["width"], scene["camera"]["height"] = 24, 14
    if projection == "orthographic":
        scene["camera"]["projection"] = {"kind": "orthographic", "ortho_scale": 8.0}
    scene["render"].update(method=method, shadow_map_size=64, steps=16)
    scene["medium"]["extent"] = {
        "kind": "box",
        "world_from_cube": [4, 0, 0, 0, 0, 4, 0, 0, 0, 0, 4, 0, 0, 0, 2, 1],
    }
    return scene


def _leaves(value: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Paths to every number, string and boolean, and to every list, of `value`."""
    if isinstance(value, dict):
        for key, item in value.items():
            if path or key not in LEFT_ALONE:
                yield from _leaves(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _leaves(item, (*path, index))
        yield path
    else:
        yield path


def _set(scene: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    for key in path[:-1]:
        scene = scene[key]
    scene[path[-1]] = value


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
@pytest.mark.parametrize("method", ["reference", "minmax", "prefiltered"])
def test_a_mutated_scene_renders_finite_layers_or_names_the_field(
    method: str, projection: str
) -> None:
    base = _scene(method, projection)
    failures = []
    for path in list(_leaves(base)):
        named = [str(key) for key in path if not isinstance(key, int)]
        for replacement in REPLACEMENTS:
            scene = copy.deepcopy(base)
            _set(scene, path, replacement)
            what = f"{'.'.join(map(str, path))} = {replacement!r}"
            try:
                layers = crepuscular.render(scene)
            except crepuscular.CrepuscularError as error:
                if not any(name in str(error) for name in named[-2:]):
                    failures.append(f"{what}: names no field: {error}")
                continue
            except Exception as error:  # anything else would reach a host as a traceback
                failures.append(f"{what}: raised {type(error).__name__}: {error}")
                continue
            for name in ("volume", "visibility", "depth"):
                if not np.isfinite(np.asarray(getattr(layers, name))).all():
                    failures.append(f"{what}: non-finite {name}")
    assert not failures, "\n".join(failures)
