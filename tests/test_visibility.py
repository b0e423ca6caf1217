"""Triangles that block the sun and triangles the camera sees, apart (`render_arrays`'s
`triangle_visibility`, a mesh's `blocks_sun` and `seen_by_camera`): a card hidden from
shadow rays still hides the fog behind it, and one hidden from the camera still casts its
shadow. Each renders as the same frame built from its two halves: the shadow map of one
geometry and the camera depth of the other, given as a depth map."""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np
import pytest
from scenes import build_scene, flatten

import crepuscular
from crepuscular import BLOCKS_SUN, SEEN_BY_CAMERA, InvalidInputError, render_arrays

METHODS = ("reference", "minmax", "prefiltered")


def _scene(method: str, **render: Any) -> dict[str, Any]:
    scene = build_scene(width=96, height=54, steps=256, shadow_map_size=256, occluder=False)
    scene["render"].update(method=method, supersampling=1, **render)
    # The camera looks at the card from below its edge.
    scene["camera"]["world_from_camera"][13] = 2.2
    return scene


def _with_card(arrays: dict[str, Any], flags: int) -> dict[str, Any]:
    """The ground of `arrays` and a 4 m card at height 3, its triangles flagged `flags`."""
    card = np.array([[-2, 3, -2], [2, 3, -2], [2, 3, 2], [-2, 3, 2]], dtype=np.float32)
    base = len(arrays["positions"])
    card_triangles = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32) + base
    ground = len(arrays["triangles"])
    return {
        **arrays,
        "positions": np.concatenate([arrays["positions"], card]),
        "triangles": np.concatenate([arrays["triangles"], card_triangles]),
        "object_ids": np.r_[arrays["object_ids"], [9, 9]].astype(np.uint32),
        "triangle_visibility": np.r_[np.full(ground, 3), [flags, flags]].astype(np.uint8),
    }


def _layers(layers: crepuscular.Layers) -> dict[str, np.ndarray]:
    return {
        "volume": np.asarray(layers.volume),
        "visibility": np.asarray(layers.visibility),
        "depth": np.asarray(layers.depth),
    }


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    finite = np.isfinite(a) & np.isfinite(b)
    return float(np.abs(a[finite] - b[finite]).mean() / max(np.abs(b[finite]).mean(), 1e-12))


@pytest.mark.parametrize("method", METHODS)
def test_a_card_hidden_from_the_sun_still_hides_the_fog_behind_it(method: str) -> None:
    arrays = flatten(_scene(method))
    seen_only = _layers(render_arrays(**_with_card(arrays, SEEN_BY_CAMERA)))
    solid = _layers(render_arrays(**_with_card(arrays, BLOCKS_SUN | SEEN_BY_CAMERA)))
    # The sun's shadow map of the ground alone, the camera's depth of ground and card.
    expected = _layers(
        render_arrays(**arrays, camera_depth=solid["depth"], depth_kind="ray_distance")
    )
    for name, layer in seen_only.items():
        assert _relative(layer, expected[name]) < 1e-5, name
    # Not vacuous: the card's shadow is gone, and its outline still hides the fog.
    assert _relative(seen_only["volume"], solid["volume"]) > 0.02
    bare = _layers(render_arrays(**arrays))
    assert _relative(seen_only["volume"], bare["volume"]) > 0.02
    np.testing.assert_array_equal(seen_only["depth"], solid["depth"])


@pytest.mark.parametrize("method", METHODS)
def test_a_card_hidden_from_the_camera_still_casts_its_shadow(method: str) -> None:
    arrays = flatten(_scene(method))
    sun_only = _layers(render_arrays(**_with_card(arrays, BLOCKS_SUN)))
    bare = _layers(render_arrays(**arrays))
    # The shadow map of ground and card, the camera depth of the ground alone.
    solid_sun = _with_card(arrays, BLOCKS_SUN | SEEN_BY_CAMERA)
    expected = _layers(
        render_arrays(**solid_sun, camera_depth=bare["depth"], depth_kind="ray_distance")
    )
    for name, layer in sun_only.items():
        assert _relative(layer, expected[name]) < 1e-5, name
    assert _relative(sun_only["volume"], bare["volume"]) > 0.02
    np.testing.assert_array_equal(sun_only["depth"], bare["depth"])


def test_a_card_hidden_from_both_is_not_there() -> None:
    arrays = flatten(_scene("prefiltered"))
    hidden = render_arrays(**_with_card(arrays, 0))
    bare = render_arrays(**arrays)
    np.testing.assert_array_equal(hidden.volume, bare.volume)
    np.testing.assert_array_equal(hidden.depth, bare.depth)


def test_only_camera_triangles_render_a_fully_lit_fog() -> None:
    """No triangle blocks the sun: the frame renders (the camera still sees the ground)."""
    arrays = flatten(_scene("prefiltered"))
    flags = np.full(len(arrays["triangles"]), SEEN_BY_CAMERA, dtype=np.uint8)
    lit = render_arrays(**arrays, triangle_visibility=flags)
    assert np.isfinite(lit.volume).all()
    np.testing.assert_array_equal(lit.depth, render_arrays(**arrays).depth)
    with pytest.raises(InvalidInputError, match="the scene is empty"):
        render_arrays(**arrays, triangle_visibility=np.zeros_like(flags))


@pytest.mark.parametrize(
    ("flags", "field"),
    [([3, 4], "triangle_visibility[1]"), ([3], "triangle_visibility"), ([0.5, 1], "dtype")],
)
def test_bad_visibility_flags_are_named(flags: list[float], field: str) -> None:
    arrays = flatten(_scene("prefiltered"))
    arrays = {key: arrays[key] for key in arrays}
    arrays["triangles"] = arrays["triangles"][:2]
    arrays["object_ids"] = arrays["object_ids"][:2]
    with pytest.raises(InvalidInputError, match=field.replace("[", r"\[")):
        render_arrays(**arrays, triangle_visibility=np.array(flags))


def test_scene_meshes_carry_their_visibility() -> None:
    """A scene description's `blocks_sun` and `seen_by_camera` render as the same flags
    through `render_arrays`."""
    scene = _scene("prefiltered")
    card = {
        "name": "card",
        "object_id": 9,
        "positions": [[-2, 3, -2], [2, 3, -2], [2, 3, 2], [-2, 3, 2]],
        "triangles": [[0, 1, 2], [0, 2, 3]],
    }
    arrays = flatten(scene)
    for flags, keys in (
        (SEEN_BY_CAMERA, {"blocks_sun": False}),
        (BLOCKS_SUN, {"seen_by_camera": False}),
    ):
        described = copy.deepcopy(scene)
        described["meshes"].append({**card, **keys})
        from_file = crepuscular.render(described)
        from_arrays = render_arrays(**_with_card(arrays, flags))
        assert _relative(np.asarray(from_file.volume), np.asarray(from_arrays.volume)) < 1e-5
        np.testing.assert_allclose(from_file.depth, from_arrays.depth, rtol=1e-6)
    # Normalized, a mesh keeps the flags only where they are off.
    hidden = {**card, "blocks_sun": False}
    normalized = crepuscular.scene_from_json(
        json.dumps({**scene, "meshes": [*scene["meshes"], card, hidden]})
    )
    assert "blocks_sun" not in normalized["meshes"][-2]
    assert normalized["meshes"][-1]["blocks_sun"] is False
    assert "seen_by_camera" not in normalized["meshes"][-1]


def test_vulkan_splits_as_the_cpu_does() -> None:
    """On any Vulkan device (lavapipe in CI; the CPU where there is none), each view's
    triangles go to its own pass."""
    arrays = flatten(_scene("prefiltered"))
    layers = {}
    for backend in ("cpu", "vulkan"):
        with_backend = {**arrays, "settings": {**arrays["settings"], "backend": backend}}
        layers[backend] = render_arrays(**_with_card(with_backend, SEEN_BY_CAMERA))
    assert _relative(np.asarray(layers["vulkan"].volume), np.asarray(layers["cpu"].volume)) < 1e-3
    np.testing.assert_allclose(layers["vulkan"].depth, layers["cpu"].depth, rtol=1e-3)


def _looking(eye: np.ndarray, toward: np.ndarray) -> list[float]:
    """A column-major world-from-camera matrix at `eye` looking along `toward`."""
    forward = toward / np.linalg.norm(toward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    columns = [*right, 0.0, *up, 0.0, *(-forward), 0.0, *eye, 1.0]
    return [float(value) for value in columns]


def _with_point(arrays: dict[str, Any], centre: np.ndarray, radius: float, flags: Any) -> dict:
    """`arrays` with one point's sphere (`point_spheres`), its triangles flagged `flags`."""
    positions, triangles = crepuscular.point_spheres([centre], [radius])
    base = len(arrays["positions"])
    return {
        **arrays,
        "positions": np.concatenate([arrays["positions"], positions]),
        "triangles": np.concatenate([arrays["triangles"], triangles + np.uint32(base)]),
        "object_ids": np.r_[arrays["object_ids"], np.full(len(triangles), 9)].astype(np.uint32),
        "triangle_visibility": np.r_[
            np.full(len(arrays["triangles"]), 3), np.broadcast_to(flags, len(triangles))
        ].astype(np.uint8),
    }


@pytest.mark.parametrize("method", METHODS)
def test_a_camera_inside_a_point_sees_out_into_the_lit_fog(method: str) -> None:
    """Cycles culls a point's back side for every ray (`point_sphere_visibility`): from
    inside a point the camera sees out of it, and the fog inside it is lit. Looking towards
    the sun, no ray reaches the point's shadow, so the frame is the one without the point;
    looking away, its far side still shadows the fog beyond it. Drawn closed, the point
    hides everything from a camera inside it."""
    scene = _scene(method)
    travel = np.array(scene["sun"]["direction"], dtype=np.float64)
    travel /= np.linalg.norm(travel)
    eye, radius = np.array([0.5, 4.0, -1.0]), 1.5
    for toward, lit in ((-travel, True), (travel + np.array([0.0, 0.0, 0.5]), False)):
        scene["camera"]["world_from_camera"] = _looking(eye, toward)
        arrays = flatten(scene)
        flags = crepuscular.point_sphere_visibility([eye], [radius], sun=travel, eye=eye)
        assert not (flags & SEEN_BY_CAMERA).any()
        culled = _layers(render_arrays(**_with_point(arrays, eye, radius, flags)))
        bare = _layers(render_arrays(**_with_point(arrays, eye, radius, 0)))
        closed = _layers(render_arrays(**_with_point(arrays, eye, radius, 3)))
        np.testing.assert_array_equal(culled["depth"], bare["depth"])
        radiance = closed["volume"][..., :3].mean()
        assert radiance < 0.2 * bare["volume"][..., :3].mean()
        difference = _relative(culled["volume"], bare["volume"])
        if lit:
            assert difference < 1e-3, difference
        else:
            assert difference > 0.05, difference
            # The point only takes light away.
            assert (culled["volume"][..., :3] <= bare["volume"][..., :3] + 1e-6).all()


def test_vulkan_culls_points_as_the_cpu_does() -> None:
    """A camera inside a point on any Vulkan device (lavapipe in CI): the culled sides go
    to their own passes, triangles flagged for neither to none."""
    scene = _scene("prefiltered")
    travel = np.array(scene["sun"]["direction"], dtype=np.float64)
    travel /= np.linalg.norm(travel)
    eye = np.array([0.5, 4.0, -1.0])
    scene["camera"]["world_from_camera"] = _looking(eye, travel + np.array([0.0, 0.0, 0.5]))
    arrays = flatten(scene)
    flags = crepuscular.point_sphere_visibility([eye], [1.5], sun=travel, eye=eye)
    assert (flags == 0).any()
    layers = {}
    for backend in ("cpu", "vulkan"):
        culled = _with_point(arrays, eye, 1.5, flags)
        culled["settings"] = {**culled["settings"], "backend": backend}
        layers[backend] = render_arrays(**culled)
    assert _relative(np.asarray(layers["vulkan"].volume), np.asarray(layers["cpu"].volume)) < 1e-3
    np.testing.assert_allclose(layers["vulkan"].depth, layers["cpu"].depth, rtol=1e-3)
