"""The `crepuscular` Python API over the Rust core (core/python)."""

from __future__ import annotations

import ast
import contextlib
import copy
import gc
import inspect
import json
import math
import os
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scenes import move_occluder_off_the_float32_grid

import crepuscular
from crepuscular import (
    CancelledError,
    CrepuscularError,
    ExrError,
    InvalidInputError,
    Layers,
    _convert,
    _core,
    errors,
    render,
    render_arrays,
    scene_from_json,
    validate_scene,
)

# Rendering is implemented in parallel with these bindings; drop this marker after the merge.


@contextlib.contextmanager
def raises_invalid(field_prefix: str, *fragments: str) -> Iterator[None]:
    """Expects an InvalidInputError whose `field` starts with `field_prefix` and whose
    message names that field and contains every fragment."""
    with pytest.raises(InvalidInputError) as info:
        yield
    error = info.value
    message = str(error)
    assert error.field is not None, message
    assert error.field.startswith(field_prefix), (error.field, message)
    assert field_prefix in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


# --- scene descriptions ------------------------------------------------------------------


def test_valid_scene_passes_validation(scene: dict[str, Any]) -> None:
    validate_scene(scene)
    validate_scene(json.dumps(scene))


def test_scene_from_json_fills_defaults_and_round_trips(scene: dict[str, Any]) -> None:
    del scene["render"]
    normalized = scene_from_json(json.dumps(scene))
    assert normalized["render"]["method"] == "prefiltered"
    assert normalized["render"]["shadow_bias"] is None
    assert normalized["sun"]["color"] == [1.0, 1.0, 1.0]
    assert normalized["medium"]["extent"] == {"kind": "unbounded"}
    assert normalized["camera"]["projection"]["sensor_width"] == 36.0
    assert scene_from_json(json.dumps(normalized)) == normalized


def test_scene_from_a_path(scene: dict[str, Any], tmp_path: Path) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene), encoding="utf-8")
    validate_scene(path)
    validate_scene(str(path))
    with pytest.raises(FileNotFoundError):
        validate_scene(tmp_path / "missing.json")


def test_scene_of_the_wrong_type_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="scene must be"):
        validate_scene(42)  # type: ignore[arg-type]


def test_numpy_values_inside_a_scene_dict(scene: dict[str, Any]) -> None:
    scene["camera"]["world_from_camera"] = np.asarray(
        scene["camera"]["world_from_camera"], dtype=np.float32
    )
    scene["sun"]["strength"] = np.float32(2.5)
    scene["camera"]["width"] = np.int64(64)
    validate_scene(scene)


@pytest.mark.parametrize(
    ("path", "key"),
    [((), "colour"), (("camera",), "fov"), (("render",), "quality"), (("meshes", 0), "uv")],
)
def test_unknown_key_is_named(scene: dict[str, Any], path: tuple[Any, ...], key: str) -> None:
    target: Any = scene
    for step in path:
        target = target[step]
    target[key] = 1
    with pytest.raises(InvalidInputError, match=key) as info:
        validate_scene(scene)
    expected = ".".join(str(step) for step in (*path, key)).replace(".0.", "[0].")
    assert info.value.field == expected
    assert f"unknown field `{key}`" in str(info.value)


def test_unknown_key_inside_a_tagged_member_is_named(scene: dict[str, Any]) -> None:
    scene["camera"]["projection"]["zoom"] = 2
    with pytest.raises(InvalidInputError, match="unknown field `zoom`") as info:
        validate_scene(scene)
    assert info.value.field is not None
    assert info.value.field.startswith("camera.projection")


def test_nan_in_camera_matrix_is_named(scene: dict[str, Any]) -> None:
    scene["camera"]["world_from_camera"][5] = math.nan
    with raises_invalid("camera.world_from_camera", "not finite"):
        validate_scene(scene)


def test_nan_in_a_numpy_camera_matrix_is_named(scene: dict[str, Any]) -> None:
    matrix = np.asarray(scene["camera"]["world_from_camera"], dtype=np.float32)
    matrix[12] = np.nan
    scene["camera"]["world_from_camera"] = matrix
    with raises_invalid("camera.world_from_camera"):
        validate_scene(scene)


def test_infinity_in_render_arrays_camera_is_named(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["camera"]["world_from_camera"][0] = math.inf
    with raises_invalid("camera.world_from_camera"):
        render_arrays(**scene_arrays)


def test_nan_token_in_json_text_is_invalid_input(scene: dict[str, Any]) -> None:
    scene["camera"]["world_from_camera"][5] = math.nan
    text = json.dumps(scene)  # Python writes the non-standard token NaN
    assert "NaN" in text
    with pytest.raises(InvalidInputError, match=r"camera\.world_from_camera"):
        validate_scene(text)


def test_singular_camera_matrix(scene: dict[str, Any]) -> None:
    scene["camera"]["world_from_camera"] = [0.0] * 16
    with raises_invalid("camera.world_from_camera", "singular"):
        validate_scene(scene)


def test_zero_width(scene: dict[str, Any]) -> None:
    scene["camera"]["width"] = 0
    with raises_invalid("camera.width", "outside the supported range"):
        validate_scene(scene)


def test_negative_width_is_a_format_error(scene: dict[str, Any]) -> None:
    scene["camera"]["width"] = -3
    with pytest.raises(InvalidInputError, match=r"camera\.width"):
        validate_scene(scene)


def test_shadow_map_too_large(scene: dict[str, Any]) -> None:
    scene["render"]["shadow_map_size"] = 1 << 20
    with raises_invalid("render.shadow_map_size", "16..=16384"):
        validate_scene(scene)


def test_zero_length_sun_direction(scene: dict[str, Any]) -> None:
    scene["sun"]["direction"] = [0.0, 0.0, 0.0]
    with raises_invalid("sun.direction", "zero length"):
        validate_scene(scene)


def test_anisotropy_out_of_range(scene: dict[str, Any]) -> None:
    scene["medium"]["anisotropy"] = 1.0
    with raises_invalid("medium.anisotropy"):
        validate_scene(scene)


def test_unsupported_version(scene: dict[str, Any]) -> None:
    scene["version"] = crepuscular.SCENE_VERSION + 1
    with raises_invalid("version", "not supported"):
        validate_scene(scene)


@pytest.mark.parametrize("meshes", [None, []])
def test_empty_scene(scene: dict[str, Any], meshes: list[Any] | None) -> None:
    if meshes is None:
        del scene["meshes"]
    else:
        scene["meshes"] = meshes
    with raises_invalid("meshes", "empty"):
        validate_scene(scene)
    with raises_invalid("meshes", "empty"):
        render(scene)


def test_mesh_index_past_its_positions(scene: dict[str, Any]) -> None:
    scene["meshes"][1]["triangles"][1] = [0, 2, 4]
    with raises_invalid("meshes[1].triangles[1]", "indexes past the 4 positions"):
        validate_scene(scene)


def test_render_validates_before_rendering(scene: dict[str, Any]) -> None:
    scene["camera"]["clip_end"] = 0.05
    with raises_invalid("camera.clip_end"):
        render(scene)


def test_unknown_depth_kind(scene: dict[str, Any]) -> None:
    with raises_invalid("depth_kind", "planar, ray_distance"):
        render(scene, depth_kind="z")  # type: ignore[arg-type]


def test_progress_must_be_callable(scene: dict[str, Any]) -> None:
    with pytest.raises(TypeError, match="progress must be callable"):
        render(scene, progress=1.0)  # type: ignore[arg-type]


OUT_OF_MEMORY_CHILD = """
import json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1])))
import crepuscular
scene = crepuscular.builtin_scene("torus")
results = {}
for name, (width, height, shadow_map_size) in {
    "image": (16384, 16384, 256),
    "shadow_map": (64, 36, 16384),
}.items():
    scene["camera"]["width"], scene["camera"]["height"] = width, height
    scene["render"]["shadow_map_size"] = shadow_map_size
    try:
        crepuscular.render(scene)
        results[name] = None
    except crepuscular.InvalidInputError as error:
        results[name] = [error.field, str(error)]
scene["camera"]["width"], scene["camera"]["height"] = 64, 36
scene["render"]["shadow_map_size"] = 256
results["after"] = float(crepuscular.render(scene).volume[..., :3].mean())
print(json.dumps(results))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits are Linux's")
def test_a_frame_too_large_for_memory_names_the_settings_to_lower() -> None:
    """Under a 2.5 GB address-space limit, a 16384² image (1 GiB of camera depth, then
    4 GiB of layers) and a 16384² shadow map (2 GiB) each raise an error naming what to
    lower, rather than aborting the interpreter, which then renders a small frame."""
    limit = str(5 << 29)
    # Each thread's malloc arena reserves address space too: few threads and arenas keep the
    # limit about the frame's buffers on a machine of many cores.
    env = {**os.environ, "RAYON_NUM_THREADS": "2", "MALLOC_ARENA_MAX": "2"}
    child = subprocess.run(
        [sys.executable, "-c", OUT_OF_MEMORY_CHILD, limit],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert child.returncode == 0, child.stderr
    results = json.loads(child.stdout)
    field, message = results["image"]
    assert field == "camera", message
    assert "GiB, more memory than could be allocated" in message
    assert "lower camera.width and camera.height, or render.supersampling" in message
    field, message = results["shadow_map"]
    assert field == "render", message
    assert "16384\u00d716384" in message
    assert "render.shadow_map_size" in message
    assert results["after"] > 0.0


# --- exceptions --------------------------------------------------------------------------


def test_exception_hierarchy() -> None:
    assert issubclass(CrepuscularError, Exception)
    assert issubclass(InvalidInputError, CrepuscularError)
    assert issubclass(InvalidInputError, ValueError)
    assert issubclass(ExrError, CrepuscularError)
    assert issubclass(ExrError, OSError)
    assert issubclass(CancelledError, CrepuscularError)
    assert not issubclass(CancelledError, ValueError)
    assert not issubclass(InvalidInputError, OSError)
    for name in ("CrepuscularError", "InvalidInputError", "ExrError", "CancelledError"):
        assert getattr(errors, name) is getattr(crepuscular, name) is getattr(_core, name)
        assert getattr(_core, name).__module__ == "crepuscular._core"


def test_invalid_input_is_caught_as_value_error(scene: dict[str, Any]) -> None:
    scene["camera"]["height"] = 0
    with pytest.raises(ValueError, match=r"camera\.height"):
        validate_scene(scene)
    with pytest.raises(CrepuscularError):
        validate_scene(scene)


def test_field_defaults_to_none() -> None:
    assert InvalidInputError("plain").field is None
    assert InvalidInputError.field is None


# --- array inputs ------------------------------------------------------------------------


def test_positions_wrong_shape(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["positions"] = np.zeros((5, 2), dtype=np.float32)
    with raises_invalid("positions", "must have shape (N, 3), got (5, 2)"):
        render_arrays(**scene_arrays)


def test_positions_wrong_ndim(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["positions"] = np.zeros(12, dtype=np.float32)
    with raises_invalid("positions", "got (12,)"):
        render_arrays(**scene_arrays)


def test_positions_must_be_real(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["positions"] = scene_arrays["positions"].astype(np.complex64)
    with raises_invalid("positions", "real numbers"):
        render_arrays(**scene_arrays)


def test_nan_position_is_named(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["positions"][5, 1] = np.nan
    with raises_invalid("positions[5]", "not finite"):
        render_arrays(**scene_arrays)


def test_positions_relative_to_a_far_origin_render_as_near_the_world_origin(
    scene: dict[str, Any], to_arrays: Callable[[dict[str, Any]], dict[str, Any]]
) -> None:
    # 100 km away float32 world positions lie 8 mm apart; relative to an origin at the
    # camera they keep their precision (as world positions, this occluder's depths moved by
    # 2.3e-3). The offset keeps the camera's float32 translation exact.
    move_occluder_off_the_float32_grid(scene)
    offset = np.array([1e5, -7e4, 32.0])
    near = render(scene)
    far = copy.deepcopy(scene)
    far["camera"]["world_from_camera"][12:15] = (
        np.asarray(scene["camera"]["world_from_camera"][12:15]) + offset
    ).tolist()
    arrays = to_arrays(scene)
    origin = np.asarray(far["camera"]["world_from_camera"][12:15], dtype=np.float64)
    world = arrays["positions"].astype(np.float64) + offset
    arrays["positions"] = (world - origin).astype(np.float32)
    arrays["camera"] = far["camera"]
    layers = render_arrays(**arrays, origin=origin)
    scale = np.abs(near.volume).mean()
    assert np.abs(layers.volume - near.volume).mean() <= 1e-5 * scale
    assert np.allclose(layers.depth, near.depth, rtol=1e-5)


@pytest.mark.parametrize(
    ("origin", "reason"),
    [((0.0, np.nan, 0.0), "must be finite"), ((1.0, 2.0), "must have shape (3,), got (2,)")],
)
def test_origin_is_checked(scene_arrays: dict[str, Any], origin: Any, reason: str) -> None:
    with raises_invalid("origin", reason):
        render_arrays(**scene_arrays, origin=origin)


def test_triangles_wrong_shape(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["triangles"] = np.zeros((4, 4), dtype=np.uint32)
    with raises_invalid("triangles", "must have shape (M, 3), got (4, 4)"):
        render_arrays(**scene_arrays)


def test_triangles_must_be_integers(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["triangles"] = scene_arrays["triangles"].astype(np.float64)
    with raises_invalid("triangles", "integers"):
        render_arrays(**scene_arrays)


def test_negative_triangle_index_is_named(scene_arrays: dict[str, Any]) -> None:
    triangles = scene_arrays["triangles"].astype(np.int64)
    triangles[2, 1] = -1
    scene_arrays["triangles"] = triangles
    with raises_invalid("triangles[2]", "-1 is outside the uint32 range"):
        render_arrays(**scene_arrays)


def test_triangle_index_too_large_for_uint32(scene_arrays: dict[str, Any]) -> None:
    triangles = scene_arrays["triangles"].astype(np.int64)
    triangles[3, 0] = 1 << 32
    scene_arrays["triangles"] = triangles
    with raises_invalid("triangles[3]", "outside the uint32 range"):
        render_arrays(**scene_arrays)


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint16, np.uint64, ">u4"])
def test_triangle_indices_convert_to_uint32(scene_arrays: dict[str, Any], dtype: Any) -> None:
    converted = _convert.index_rows(scene_arrays["triangles"].astype(dtype), "triangles")
    assert converted.dtype == np.dtype(np.uint32)
    assert converted.flags.c_contiguous
    np.testing.assert_array_equal(converted, scene_arrays["triangles"])
    # The converted indices reach the core: an index past the positions is caught there.
    triangles = scene_arrays["triangles"].astype(dtype)
    triangles[1] = [0, 1, 8]
    scene_arrays["triangles"] = triangles
    with raises_invalid("triangles[1]", "[0, 1, 8] indexes past the 8 positions"):
        render_arrays(**scene_arrays)


def test_triangles_from_nested_lists(scene_arrays: dict[str, Any]) -> None:
    triangles = scene_arrays["triangles"].tolist()
    triangles[0] = [0, 1, 99]
    scene_arrays["triangles"] = triangles
    with raises_invalid("triangles[0]", "indexes past"):
        render_arrays(**scene_arrays)


def test_object_ids_must_match_triangles(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["object_ids"] = np.zeros(3, dtype=np.uint32)
    with raises_invalid("object_ids", "(M,) = (4,)", "got (3,)"):
        render_arrays(**scene_arrays)


def test_object_ids_default_to_zero() -> None:
    ids = _convert.object_ids(None, 5)
    assert ids.dtype == np.dtype(np.uint32)
    np.testing.assert_array_equal(ids, np.zeros(5))


def test_empty_geometry(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["triangles"] = np.zeros((0, 3), dtype=np.uint32)
    scene_arrays["object_ids"] = None
    with raises_invalid("triangles", "empty"):
        render_arrays(**scene_arrays)


def test_render_arrays_unknown_key_is_named(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["medium"]["density"] = 1.0
    with pytest.raises(InvalidInputError, match="density") as info:
        render_arrays(**scene_arrays)
    assert info.value.field == "medium.density"
    scene_arrays["medium"].pop("density")
    scene_arrays["settings"]["fast"] = True
    with pytest.raises(InvalidInputError, match="fast") as info:
        render_arrays(**scene_arrays)
    assert info.value.field == "render.fast"


def test_render_arrays_validates_settings(scene_arrays: dict[str, Any]) -> None:
    scene_arrays["settings"]["shadow_map_size"] = 8
    with raises_invalid("render.shadow_map_size"):
        render_arrays(**scene_arrays)


def test_matching_arrays_cross_without_copies() -> None:
    """Arrays that already fit are handed to the core as they are; the core borrows them
    with `as_slice` (no copy) and fails on anything that is not C-contiguous and aligned."""
    positions = np.zeros((6, 3), dtype=np.float32)
    triangles = np.zeros((2, 3), dtype=np.uint32)
    ids = np.arange(2, dtype=np.uint32)
    depth = np.zeros((4, 5), dtype=np.float32)
    assert _convert.float_rows(positions, "positions") is positions
    assert _convert.index_rows(triangles, "triangles") is triangles
    assert _convert.object_ids(ids, 2) is ids
    assert _convert.depth_map(depth) is depth
    positions.flags.writeable = False
    assert _convert.float_rows(positions, "positions") is positions


def test_other_layouts_are_converted_once() -> None:
    wide = np.arange(36, dtype=np.float64).reshape(6, 6)
    strided = wide[:, ::2]
    assert not strided.flags.c_contiguous
    converted = _convert.float_rows(strided, "positions")
    assert converted.dtype == np.dtype(np.float32)
    assert converted.flags.c_contiguous
    assert converted.flags.aligned
    np.testing.assert_array_equal(converted, strided)
    fortran = np.asfortranarray(np.ones((5, 3), dtype=np.float32))
    assert _convert.float_rows(fortran, "positions").flags.c_contiguous


def test_non_contiguous_inputs_still_render_path(scene_arrays: dict[str, Any]) -> None:
    """A non-contiguous, float64 view gets past the array checks into the core."""
    positions = scene_arrays["positions"].astype(np.float64)
    padded = np.zeros((len(positions), 6))
    padded[:, ::2] = positions
    padded[2, 2] = np.inf  # make the core reject it, proving the data crossed
    scene_arrays["positions"] = padded[:, ::2]
    with raises_invalid("positions[2]", "not finite"):
        render_arrays(**scene_arrays)


# --- camera depth ------------------------------------------------------------------------


def test_camera_depth_nan_is_located(scene: dict[str, Any]) -> None:
    depth = np.full((36, 64), 5.0, dtype=np.float32)
    depth[2, 3] = np.nan
    with raises_invalid("camera_depth", "contains NaN at pixel (3, 2)"):
        render(scene, camera_depth=depth)


def test_a_windows_camera_depth_is_the_windows(scene_arrays: dict[str, Any]) -> None:
    """A camera window renders its own pixels: a given depth pass is the window's size,
    and the layers placed in their frame hold that depth there and nothing around."""
    camera = dict(scene_arrays["camera"], window={"x": 10, "y": 5, "width": 20, "height": 8})
    kwargs = dict(scene_arrays, camera=camera)
    with raises_invalid("camera_depth", "must have shape (height, width) = (8, 20)"):
        render_arrays(**kwargs, camera_depth=np.full((36, 64), 5.0, dtype=np.float32))
    layers = render_arrays(**kwargs, camera_depth=np.full((8, 20), 5.0, dtype=np.float32))
    assert (layers.width, layers.height) == (20, 8)
    framed = layers.in_frame(camera)
    assert framed.depth.shape == (36, 64)
    np.testing.assert_allclose(framed.depth[5:13, 10:30], layers.depth)
    assert not framed.depth[:5].any()
    assert not framed.volume[:, :10].any()
    with raises_invalid("camera.window", "is 20x8, the layers 64x36"):
        render_arrays(**scene_arrays).in_frame(camera)


def test_camera_depth_negative(scene_arrays: dict[str, Any]) -> None:
    depth = np.full((36, 64), 5.0)
    depth[10, 20] = -1.0
    with raises_invalid("camera_depth", "pixel (20, 10)"):
        render_arrays(**scene_arrays, camera_depth=depth)


def test_camera_depth_shape_must_match_camera(scene: dict[str, Any]) -> None:
    with raises_invalid("camera_depth", "(height, width) = (36, 64), got (64, 36)"):
        render(scene, camera_depth=np.ones((64, 36), dtype=np.float32))


def test_camera_depth_must_be_two_dimensional(scene: dict[str, Any]) -> None:
    with raises_invalid("camera_depth", "got (36, 64, 1)"):
        render(scene, camera_depth=np.ones((36, 64, 1), dtype=np.float32))


# --- the stubs ---------------------------------------------------------------------------


def _stub() -> ast.Module:
    path = Path(crepuscular.__file__).with_name("_core.pyi")
    return ast.parse(path.read_text(encoding="utf-8"))


def test_stub_names_match_the_module() -> None:
    stubbed: set[str] = set()
    for node in _stub().body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef):
            stubbed.add(node.name)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            stubbed.add(node.target.id)
    public_stub = {name for name in stubbed if not name.startswith("_")}
    public_runtime = {name for name in dir(_core) if not name.startswith("_")}
    assert public_stub == public_runtime
    assert "__version__" in stubbed


def test_stub_signatures_match_the_module() -> None:
    for node in _stub().body:
        if isinstance(node, ast.FunctionDef):
            args = node.args
            stub_params = [
                *(arg.arg for arg in args.posonlyargs),
                *(arg.arg for arg in args.args),
                *(arg.arg for arg in args.kwonlyargs),
            ]
            runtime = inspect.signature(getattr(_core, node.name))
            assert list(runtime.parameters) == stub_params, node.name
            kinds = {name: param.kind for name, param in runtime.parameters.items()}
            for arg in args.posonlyargs:
                assert kinds[arg.arg] is inspect.Parameter.POSITIONAL_ONLY
            for arg in args.kwonlyargs:
                assert kinds[arg.arg] is inspect.Parameter.KEYWORD_ONLY
        elif isinstance(node, ast.ClassDef):
            runtime_bases = [base.__name__ for base in getattr(_core, node.name).__bases__]
            stub_bases = [base.id for base in node.bases if isinstance(base, ast.Name)]
            assert runtime_bases == stub_bases, node.name


def test_public_api() -> None:
    for name in crepuscular.__all__:
        assert hasattr(crepuscular, name), name
    assert crepuscular.__version__ == _core.__version__
    assert isinstance(crepuscular.SCENE_VERSION, int)
    assert (Path(crepuscular.__file__).parent / "py.typed").exists()


# --- rendering ---------------------------------------------------------------------------


def _check_layers(layers: Layers, width: int, height: int) -> None:
    assert (layers.width, layers.height) == (width, height)
    assert layers.volume.shape == (height, width, 4)
    assert layers.visibility.shape == (height, width)
    assert layers.depth.shape == (height, width)
    for array in (layers.volume, layers.visibility, layers.depth):
        assert array.dtype == np.dtype(np.float32)
        assert array.flags.c_contiguous
        assert np.isfinite(array).all()
    alpha = layers.volume[..., 3]
    assert alpha.min() >= 0.0
    assert alpha.max() <= 1.0
    assert layers.volume[..., :3].min() >= 0.0
    assert layers.visibility.min() >= 0.0
    assert layers.visibility.max() <= 1.0
    assert layers.depth.min() > 0.0


def test_render_layers(scene: dict[str, Any]) -> None:
    layers = render(scene)
    _check_layers(layers, 64, 36)
    # Fog in front of the camera scatters some light; the occluder shadows some of it.
    assert layers.volume[..., 3].max() > 0.0
    assert layers.visibility.min() < layers.visibility.max()
    with pytest.raises(AttributeError):
        layers.width = 3  # type: ignore[misc]
    assert repr(layers) == "Layers(width=64, height=36)"


def test_render_outputs_are_not_copied(scene: dict[str, Any]) -> None:
    layers = render(scene)
    for array in (layers.volume, layers.visibility, layers.depth):
        # A reshaped view of the 1-D array that owns the core's Vec, not numpy memory.
        assert not array.flags.owndata
        flat = array.base
        assert isinstance(flat, np.ndarray)
        assert flat.ndim == 1
        assert not flat.flags.owndata
        assert not isinstance(flat.base, np.ndarray)


def test_released_layers_serve_later_frames_without_stale_values(
    scene: dict[str, Any],
) -> None:
    # Arrays numpy lets go of hand their buffers back for a later frame's layers: every
    # value of that frame must be its own, and arrays still alive (or viewed) keep theirs.
    first = render(scene)
    expected = {name: getattr(first, name).copy() for name in ("volume", "visibility", "depth")}
    kept_view = first.volume[5:9, 10:20]
    kept_copy = kept_view.copy()
    del first
    gc.collect()
    other = copy.deepcopy(scene)
    other["sun"]["direction"] = [-0.5, 0.4, -1.0]
    for _ in range(2):
        between = render(other)
        assert between.volume.tobytes() != expected["volume"].tobytes()
        del between
        gc.collect()
    again = render(scene)
    for name, values in expected.items():
        assert getattr(again, name).tobytes() == values.tobytes(), name
    np.testing.assert_array_equal(kept_view, kept_copy)


def _resident_bytes() -> int:
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux's /proc")
def test_released_buffers_go_back_to_the_system_and_frames_stay_the_same() -> None:
    scene = crepuscular.builtin_scene("torus")
    first = render(scene)
    kept = first.volume.tobytes()
    del first
    gc.collect()
    before = _resident_bytes()
    crepuscular.release_kept_buffers()
    after = _resident_bytes()
    # The filtered basis alone is about 68 MB at 1920x1080.
    assert before - after > 50 * 2**20, (before, after)
    again = render(scene)
    assert again.volume.tobytes() == kept


def test_render_is_deterministic(scene: dict[str, Any]) -> None:
    first = render(scene)
    second = render(json.dumps(scene))
    for name in ("volume", "visibility", "depth"):
        a, b = getattr(first, name), getattr(second, name)
        assert a.tobytes() == b.tobytes(), name


def test_render_arrays_equals_render(scene: dict[str, Any], to_arrays: Any) -> None:
    from_dict = render(scene)
    from_arrays = render_arrays(**to_arrays(scene))
    for name in ("volume", "visibility", "depth"):
        np.testing.assert_array_equal(getattr(from_arrays, name), getattr(from_dict, name))


def test_render_arrays_with_converted_inputs(scene: dict[str, Any], to_arrays: Any) -> None:
    reference = render_arrays(**to_arrays(scene))
    arrays = to_arrays(scene)
    arrays["positions"] = arrays["positions"].astype(np.float64).tolist()
    arrays["triangles"] = arrays["triangles"].astype(np.int64)
    arrays["object_ids"] = arrays["object_ids"].astype(np.int32)
    converted = render_arrays(**arrays)
    np.testing.assert_array_equal(converted.volume, reference.volume)


def test_progress_is_monotonic_and_ends_at_one(make_scene: Any) -> None:
    fractions: list[float] = []
    layers = render(make_scene(width=160, height=90, steps=256), progress=fractions.append)
    _check_layers(layers, 160, 90)
    assert fractions, "progress was never called"
    assert fractions[-1] == 1.0
    assert all(0.0 <= f <= 1.0 for f in fractions)
    assert fractions == sorted(fractions)


def test_progress_exception_propagates_and_cancels(make_scene: Any) -> None:
    class Stop(Exception):
        pass

    calls: list[float] = []
    stop = Stop("from the callback")

    def progress(fraction: float) -> None:
        calls.append(fraction)
        raise stop

    with pytest.raises(Stop) as info:
        render(make_scene(width=320, height=180, steps=1024), progress=progress)
    assert info.value is stop
    assert len(calls) == 1  # no call after the one that raised: the render was abandoned
    # The module is still usable afterwards.
    _check_layers(render(make_scene()), 64, 36)


def test_render_from_another_thread(scene: dict[str, Any]) -> None:
    results: list[Layers | BaseException] = []

    def work() -> None:
        try:
            results.append(render(scene))
        except BaseException as error:  # re-raised on the test's thread below
            results.append(error)

    worker = threading.Thread(target=work)
    worker.start()
    worker.join(timeout=120)
    assert results, "the render thread did not finish"
    if isinstance(results[0], BaseException):
        raise results[0]
    _check_layers(results[0], 64, 36)


@pytest.mark.parametrize("depth_kind", ["planar", "ray_distance"])
def test_background_camera_depth(scene: dict[str, Any], depth_kind: str) -> None:
    background = np.full((36, 64), np.inf, dtype=np.float32)
    layers = render(scene, camera_depth=background, depth_kind=depth_kind)  # type: ignore[arg-type]
    _check_layers(layers, 64, 36)
    np.testing.assert_allclose(layers.depth, scene["render"]["max_distance"], rtol=1e-5)


@pytest.mark.parametrize("method", ["reference", "minmax", "prefiltered"])
def test_coloured_extinction_takes_each_channel_from_a_grey_render(
    make_scene: Callable[..., dict[str, Any]], method: str
) -> None:
    """Each channel of a medium with `channel_extinction` is that channel of the grey medium
    of its extinction, bit for bit; opacity and visibility blend the channels' by luminance."""
    base = make_scene(width=96, height=54, steps=64, shadow_map_size=128)
    base["render"]["method"] = method
    base["medium"]["albedo"] = [0.9, 0.7, 0.5]
    tinted = copy.deepcopy(base)
    tinted["medium"]["channel_extinction"] = [0.03, 0.4, 0.03]
    layers = render(tinted)
    grey = {}
    for extinction in (0.03, 0.4):
        scene = copy.deepcopy(base)
        scene["medium"]["extinction"] = extinction
        grey[extinction] = render(scene)
    thin, dense = grey[0.03], grey[0.4]
    volume = np.asarray(layers.volume)
    np.testing.assert_array_equal(volume[..., 0], np.asarray(thin.volume)[..., 0])
    np.testing.assert_array_equal(volume[..., 1], np.asarray(dense.volume)[..., 1])
    np.testing.assert_array_equal(volume[..., 2], np.asarray(thin.volume)[..., 2])
    weights = (0.2126 + 0.0722, 0.7152)
    for name, tinted_value, parts in (
        ("alpha", volume[..., 3], (thin.volume[..., 3], dense.volume[..., 3])),
        ("visibility", layers.visibility, (thin.visibility, dense.visibility)),
    ):
        blend = weights[0] * np.asarray(parts[0]) + weights[1] * np.asarray(parts[1])
        np.testing.assert_allclose(tinted_value, blend, rtol=1e-5, atol=1e-7, err_msg=name)
    np.testing.assert_array_equal(layers.depth, thin.depth)
    # The dense channel differs: the test would pass on a grey render otherwise.
    assert np.abs(np.asarray(thin.volume)[..., 1] - volume[..., 1]).max() > 1e-3


def test_equal_channel_extinctions_render_as_that_grey_medium(scene: dict[str, Any]) -> None:
    tinted = copy.deepcopy(scene)
    tinted["medium"]["channel_extinction"] = [0.2, 0.2, 0.2]
    scene["medium"]["extinction"] = 0.2
    np.testing.assert_array_equal(render(tinted).volume, render(scene).volume)


@pytest.mark.parametrize("value", [[0.1, -0.1, 0.1], [0.1, float("nan"), 0.1], [0.1, 0.2]])
def test_a_bad_channel_extinction_is_named(scene: dict[str, Any], value: list[float]) -> None:
    scene["medium"]["channel_extinction"] = value
    with pytest.raises(InvalidInputError) as info:
        render(scene)
    assert "medium.channel_extinction" in str(info.value)


# --- backends ----------------------------------------------------------------------------


def test_backend_setting_selects_vulkan_or_cpu_with_matching_layers(
    scene: dict[str, Any],
) -> None:
    # `vulkan` runs on any Vulkan device (lavapipe in CI) and falls back to the CPU with a
    # message where there is none, so both renders must agree either way.
    layers = {}
    for backend in ("cpu", "vulkan", "auto"):
        variant = json.loads(json.dumps(scene))
        variant.setdefault("render", {})["backend"] = backend
        layers[backend] = render(variant)
    cpu = layers["cpu"]
    for backend in ("vulkan", "auto"):
        other = layers[backend]
        assert other.volume.shape == cpu.volume.shape
        error = np.abs(other.volume - cpu.volume).sum() / max(np.abs(cpu.volume).sum(), 1e-30)
        assert error <= 1e-3, (backend, error)
        # Vulkan rasterizes the camera depth itself, interpolating in f32.
        np.testing.assert_allclose(other.depth, cpu.depth, rtol=1e-3)


def test_a_tinted_medium_renders_per_channel_on_either_backend(
    scene: dict[str, Any], capfd: pytest.CaptureFixture[str]
) -> None:
    """Each channel pass takes the backend's path (or its fallback, announced once)."""
    scene["medium"]["channel_extinction"] = [0.03, 0.3, 0.1]
    layers = {}
    for backend in ("cpu", "vulkan"):
        variant = json.loads(json.dumps(scene))
        variant["render"]["backend"] = backend
        layers[backend] = render(variant)
    error = (
        np.abs(layers["vulkan"].volume - layers["cpu"].volume).sum()
        / np.abs(layers["cpu"].volume).sum()
    )
    assert error <= 1e-3, error
    assert capfd.readouterr().err.count("rendering on the CPU instead") <= 1


def test_unknown_backend_is_named(scene: dict[str, Any]) -> None:
    scene.setdefault("render", {})["backend"] = "cuda"
    with raises_invalid("render.backend", "cuda"):
        validate_scene(scene)


def test_strand_tubes_follow_catmull_rom_splines_through_their_points() -> None:
    """`strand_tubes` with Catmull-Rom steps: rings centred on the uniform spline through
    the points (at each point exactly, between them on the curve, here a bend bulging past
    the chord), each at the tube radius; without, on the polyline."""
    points = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0]], dtype=np.float64)
    sides = crepuscular.TUBE_SIDES
    steps = crepuscular.CATMULL_ROM_STEPS
    positions, triangles = crepuscular.strand_tubes(points, [4], [0.1] * 4, catmull_rom=steps)
    assert len(triangles) == 3 * steps * sides * 2
    centres = positions.reshape(-1, sides, 3).mean(axis=1)
    np.testing.assert_allclose(centres[::steps], points, atol=1e-6)
    # Halfway along the middle segment the uniform spline is at its chord's midpoint, and
    # a quarter along it lies off the chord, towards the bend.
    np.testing.assert_allclose(centres[steps + 2], [1.5, 0.5, 0.0], atol=1e-6)
    assert centres[steps + 1][1] < 0.25 - 1e-3
    ring = np.linalg.norm(positions.reshape(-1, sides, 3) - centres[:, None], axis=2)
    np.testing.assert_allclose(ring, 0.1 * crepuscular._strands.TUBE_RADIUS, rtol=1e-5)
    straight, _ = crepuscular.strand_tubes(points, [4], [0.1] * 4)
    np.testing.assert_allclose(straight.reshape(-1, sides, 3).mean(axis=1), points, atol=1e-6)
    with pytest.raises(ValueError, match="strands"):
        crepuscular.strand_tubes(points, [3], [0.1] * 4)


def test_point_spheres_cast_a_round_shadow_from_every_direction() -> None:
    """`point_spheres`: a closed polyhedron around each point, wound outwards, whose shadow
    (projected area: half the sum of area times |n . d| over its faces) is the sphere's
    pi r^2 within 1.2% from any direction, so a cloud of them blocks the sun as Cycles'
    spheres do; larger points are split finer, so that every outline stays within
    `SPHERE_OUTLINE_TOLERANCE` of the round sphere's."""
    centres = np.array([[0.0, 0.0, 0.0], [5.0, -2.0, 1.0], [-3.0, 4.0, 9.0]])
    radii = [0.5, 2.0, 8.0]
    positions, triangles = crepuscular.point_spheres(centres, radii)
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    vertex_base = triangle_base = 0
    for centre, radius, count in zip(centres, radii, [80, 320, 1280], strict=True):
        alone, faces = crepuscular.point_spheres([centre], [radius])
        assert len(faces) == count
        # In the points' order, each with its own vertices.
        rows = slice(triangle_base, triangle_base + count)
        np.testing.assert_array_equal(triangles[rows], faces + vertex_base)
        np.testing.assert_array_equal(positions[vertex_base : vertex_base + len(alone)], alone)
        vertex_base, triangle_base = vertex_base + len(alone), triangle_base + count
        corners = alone.astype(np.float64)[faces]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        outward = np.einsum("ij,ij->i", normals, corners.mean(axis=1) - centre)
        assert (outward > 0).all()
        # Each cross product is twice its face's area; front and back both count.
        shadow = 0.25 * np.abs(normals @ directions.T).sum(axis=0)
        np.testing.assert_allclose(shadow, np.pi * radius**2, rtol=0.012)
        # The mean over directions is the disc's exactly (Cauchy), not just within 1.2%.
        assert shadow.mean() == pytest.approx(np.pi * radius**2, rel=2e-3)
        # The outline's half-width along each direction (the support function).
        half_width = ((alone - centre) @ directions.T).max(axis=0)
        assert np.abs(half_width - radius).max() <= crepuscular.SPHERE_OUTLINE_TOLERANCE
        # Every edge is shared by two faces: closed, so no light slips through.
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert (counts == 2).all()
    assert triangle_base == len(triangles)


def test_point_spheres_skip_empty_points_and_name_bad_input() -> None:
    positions, triangles = crepuscular.point_spheres(
        [[0, 0, 0], [1, 1, 1], [2, 2, 2]], [0.1, 0, -1]
    )
    assert len(triangles) == crepuscular.SPHERE_TRIANGLES
    assert positions[:, 0].max() < 0.5
    one_radius, _ = crepuscular.point_spheres([[0, 0, 0], [1, 1, 1]], 0.1)
    assert len(one_radius) == 2 * len(positions)
    empty, none = crepuscular.point_spheres(np.zeros((0, 3)), np.zeros(0))
    assert empty.shape == (0, 3)
    assert none.shape == (0, 3)
    with pytest.raises(ValueError, match="3 points but 2 radii"):
        crepuscular.point_spheres(np.zeros((3, 3)), [0.1, 0.1])
    with pytest.raises(ValueError, match="finite"):
        crepuscular.point_spheres([[0, float("nan"), 0]], [0.1])


def test_point_sphere_visibility_culls_each_views_back_side() -> None:
    """`point_sphere_visibility`: the camera sees the triangles of a point's sphere that
    face it, the sun's shadow map holds those that face away from the sun (Cycles culls a
    point's back side for every ray). Each set covers the whole outline (its projected area
    is the closed sphere's shadow), a camera inside a point sees none of it, and points of
    no radius are skipped as `point_spheres` skips them."""
    centres = np.array([[0.0, 0.0, 0.0], [5.0, -2.0, 1.0], [9.0, 9.0, 9.0], [1.0, 1.0, 0.5]])
    radii = [0.5, 2.0, 0.0, 0.4]
    sizes = [80, 320, 80]
    positions, triangles = crepuscular.point_spheres(centres, radii)
    corners = positions.astype(np.float64)[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    sun = np.array([0.3, 0.2, -1.0])
    eye = np.array([4.0, -8.0, 3.0])
    flags = crepuscular.point_sphere_visibility(centres, radii, sun=sun, eye=eye)
    assert flags.shape == (len(triangles),)
    blocks = (flags & crepuscular.BLOCKS_SUN) > 0
    seen = (flags & crepuscular.SEEN_BY_CAMERA) > 0
    np.testing.assert_array_equal(blocks, normals @ sun > 0)
    np.testing.assert_array_equal(seen, np.einsum("ij,ij->i", normals, corners[:, 0] - eye) < 0)
    view = np.array([-0.5, 1.0, -0.2])
    ortho = crepuscular.point_sphere_visibility(centres, radii, sun=sun, view=view)
    for direction, faces in ((sun, blocks), (view, (ortho & crepuscular.SEEN_BY_CAMERA) > 0)):
        unit = direction / np.linalg.norm(direction)
        points = np.repeat(np.arange(3), sizes)
        whole = np.bincount(points, 0.25 * np.abs(normals @ unit))
        culled = np.bincount(points, 0.5 * np.where(faces, np.abs(normals @ unit), 0.0))
        np.testing.assert_allclose(culled, whole, rtol=1e-5)
    # One direction per point, here the point's own eye: inside it, nothing is seen.
    inside = crepuscular.point_sphere_visibility(centres, radii, sun=sun, eye=centres)
    assert not (inside & crepuscular.SEEN_BY_CAMERA).any()
    np.testing.assert_array_equal(inside & crepuscular.BLOCKS_SUN, flags & crepuscular.BLOCKS_SUN)
    for bad, words in (
        ({"sun": sun}, "eye"),
        ({"sun": sun, "eye": eye, "view": view}, "eye"),
        ({"sun": [0.0, 0.0, 0.0], "eye": eye}, "sun"),
        ({"sun": [sun] * 2, "eye": eye}, "one per point"),
        ({"sun": sun, "eye": [np.nan, 0.0, 0.0]}, "eye"),
    ):
        with pytest.raises(ValueError, match=words):
            crepuscular.point_sphere_visibility(centres, radii, **bad)


def _extent_along(vertices: np.ndarray, axis: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """The (min, max) of `vertices` along `axis` as seen along `facing`: both projected
    onto the plane across `facing`."""
    facing = facing / np.linalg.norm(facing)
    seen = axis - (axis @ facing) * facing
    seen /= np.linalg.norm(seen)
    along = vertices @ seen
    return np.array([along.min(), along.max()])


def test_strand_tube_ends_are_cut_across_the_facing_direction() -> None:
    """With `facing`, a strand's tube seen along that direction ends at its end points,
    as Cycles cuts a strand's ends across each ray; cut across the strand (no `facing`),
    it reaches past them by r cos(angle between the strand and the view), the half
    ellipse each end adds to its shadow. The middle of the tube is untouched."""
    strand = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 0.0, 1.0], [3.0, 0.0, 1.5]])
    radius = 0.2
    facing = np.array([0.3, 0.2, -1.0])
    axis = (strand[-1] - strand[0]) / np.linalg.norm(strand[-1] - strand[0])
    ends = _extent_along(strand, axis, facing)
    plain, triangles = crepuscular.strand_tubes(strand, [4], [radius] * 4)
    cut, cut_triangles = crepuscular.strand_tubes(strand, [4], [radius] * 4, facing=facing)
    np.testing.assert_array_equal(triangles, cut_triangles)
    np.testing.assert_allclose(_extent_along(cut.astype(np.float64), axis, facing), ends, atol=1e-5)
    # Cut into short pieces and seen at 20° to the strand, the plane reaches past the end
    # ring into the next ones.
    steps = crepuscular.CATMULL_ROM_STEPS
    grazing = axis + np.tan(np.radians(20.0)) * np.array([0.0, 1.0, 0.0])
    for direction in (facing, grazing):
        fine, _ = crepuscular.strand_tubes(
            strand, [4], [radius] * 4, catmull_rom=steps, facing=direction
        )
        extent = _extent_along(fine.astype(np.float64), axis, direction)
        np.testing.assert_allclose(extent, _extent_along(strand, axis, direction), atol=1e-5)
    seen_along = facing / np.linalg.norm(facing)
    reach = radius * crepuscular._strands.TUBE_RADIUS * abs(axis @ seen_along)
    plain_extent = _extent_along(plain.astype(np.float64), axis, facing)
    np.testing.assert_allclose(plain_extent, ends + np.array([-reach, reach]), rtol=0.02)
    sides = crepuscular.TUBE_SIDES
    np.testing.assert_array_equal(plain[sides:-sides], cut[sides:-sides])
    # One direction per strand, here opposite ones: both cut alike (a plane holds either).
    two, _ = crepuscular.strand_tubes(
        np.concatenate([strand, strand + 5.0]), [4, 4], [radius] * 8, facing=[facing, -facing]
    )
    np.testing.assert_allclose(two[: len(cut)], cut, atol=1e-6)
    # A strand seen end-on keeps its ends across it.
    end_on, _ = crepuscular.strand_tubes(strand, [4], [radius] * 4, facing=axis)
    np.testing.assert_array_equal(end_on, plain)
    for bad in ([0.0, 0.0, 0.0], [[0.0, 0.0, 1.0]] * 2, [np.nan, 0.0, 1.0]):
        with pytest.raises(ValueError, match="facing"):
            crepuscular.strand_tubes(strand, [4], [radius] * 4, facing=bad)


def test_strand_ribbons_lie_across_the_sun_and_the_camera() -> None:
    """`strand_ribbons`: per strand, a ribbon for the sun's shadow map and one for the
    camera's depth (flagged so), each reaching the radius either side of the strand across
    both the strand and its view, so that each view sees the strand's exact width and ends;
    with `view`, an orthographic camera's. The camera's lies at the strand's axis, the sun's
    `shadow_gap` radii past it along the sun's travel (Cycles' shadow begins there), which
    moves it in depth alone: the sun sees the same outline."""
    strand = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, 0.5], [2.0, 0.0, 1.0], [3.0, 0.3, 1.5]])
    radii = np.array([0.2, 0.15, 0.1, 0.05])
    sun = np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])
    eye = np.array([1.0, -6.0, 2.0])
    positions, triangles, flags = crepuscular.strand_ribbons(strand, [4], radii, sun=sun, eye=eye)
    assert len(triangles) == 2 * 2 * 3
    assert flags.tolist() == [crepuscular.BLOCKS_SUN] * 6 + [crepuscular.SEEN_BY_CAMERA] * 6
    pairs = positions.astype(np.float64).reshape(2, 4, 2, 3)  # view, point, edge
    gap = crepuscular.STRAND_SHADOW_GAP * radii[:, None] * sun
    for ribbon, toward, axis in (
        (pairs[0], np.broadcast_to(sun, (4, 3)), strand + gap),
        (pairs[1], strand - eye, strand),
    ):
        centres = ribbon.mean(axis=1)
        np.testing.assert_allclose(centres, axis, atol=1e-6)
        half = ribbon[:, 1] - centres
        np.testing.assert_allclose(np.linalg.norm(half, axis=1), radii, rtol=1e-5)
        np.testing.assert_allclose(np.einsum("ij,ij->i", half, toward), 0.0, atol=1e-5)
    at_axis, _, _ = crepuscular.strand_ribbons(strand, [4], radii, sun=sun, eye=eye, shadow_gap=0.0)
    np.testing.assert_allclose(at_axis[:8], positions[:8] - np.repeat(gap, 2, axis=0), atol=1e-6)
    np.testing.assert_array_equal(at_axis[8:], positions[8:])
    view = np.array([0.0, 1.0, 0.0])
    ortho, _, _ = crepuscular.strand_ribbons(strand, [4], radii, sun=sun, view=view)
    camera = ortho.astype(np.float64).reshape(2, 4, 2, 3)[1]
    np.testing.assert_allclose((camera[:, 1] - camera.mean(axis=1)) @ view, 0.0, atol=1e-6)
    for bad, words in (
        ({"sun": sun}, "eye"),
        ({"sun": sun, "eye": eye, "view": view}, "eye"),
        ({"sun": [0.0, 0.0, 0.0], "eye": eye}, "sun"),
        ({"sun": sun, "eye": [np.inf, 0.0, 0.0]}, "eye"),
        ({"sun": sun, "eye": eye, "shadow_gap": -1.0}, "shadow_gap"),
        ({"sun": sun, "eye": eye, "shadow_gap": np.nan}, "shadow_gap"),
    ):
        with pytest.raises(ValueError, match=words):
            crepuscular.strand_ribbons(strand, [4], radii, **bad)


def test_fog_box_unreached_tells_a_box_no_view_ray_crosses() -> None:
    """A box of fog out of view leaves every alpha at 0, which hosts name; a box in view,
    unbounded fog and a box of clear air do not count."""
    scene = crepuscular.builtin_scene("plane")
    scene["camera"]["width"], scene["camera"]["height"] = 48, 27
    scene["render"]["shadow_map_size"] = 128

    def box_at(x: float) -> dict[str, Any]:
        return {"kind": "box", "world_from_cube": [4, 0, 0, 0, 0, 4, 0, 0, 0, 0, 4, 0, x, 0, 2, 1]}

    for extent, extinction, unreached in [
        (box_at(0.0), 0.1, False),
        (box_at(1e4), 0.1, True),
        (box_at(1e4), 0.0, False),
        ({"kind": "unbounded"}, 0.1, False),
    ]:
        scene["medium"] |= {"extent": extent, "extinction": extinction}
        layers = render(scene)
        assert (layers.volume[..., 3].max() == 0) == (unreached or extinction == 0)
        assert crepuscular.fog_box_unreached(scene["medium"], layers.volume) == unreached


@pytest.mark.parametrize("method", ["reference", "minmax", "prefiltered"])
def test_extreme_but_finite_scenes_render_finite_layers(method: str) -> None:
    """Values a scene may hold, however far from the built-in ones, render finite layers
    with every method. Found by mutating a scene's every value: in a box of fog, a sun a
    hair's breadth (10⁻²⁵) off straight down, and fog of 1000 /m, read NaN pixels (an
    integral's exponential 0 times ∞); a camera 10³⁰ m from the scene stopped prefiltering
    with an internal error."""
    box = {"kind": "box", "world_from_cube": [4, 0, 0, 0, 0, 4, 0, 0, 0, 0, 4, 0, 0, 0, 2, 1]}

    def scene(change: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
        plane = crepuscular.builtin_scene("plane")
        plane["camera"]["width"], plane["camera"]["height"] = 24, 14
        plane["render"].update(method=method, shadow_map_size=64, steps=16)
        plane["medium"]["extent"] = box
        change(plane)
        return plane

    for what, change in {
        "sun 1e-25 off straight down": lambda s: s["sun"].update(direction=[1e-25, 0.0, -1.0]),
        "sun 1e-20 off the horizon": lambda s: s["sun"].update(direction=[1.0, 0.0, -1e-20]),
        "fog of 1000 /m": lambda s: s["medium"].update(extinction=1000.0),
        "camera 1e30 m away": lambda s: s["camera"]["world_from_camera"].__setitem__(12, 1e30),
    }.items():
        layers = crepuscular.render(scene(change))
        for name in ("volume", "visibility", "depth"):
            assert np.isfinite(np.asarray(getattr(layers, name))).all(), f"{what}: {name}"
