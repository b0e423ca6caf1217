"""Style presets through the Python API: loading, applying, and errors that name fields."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import crepuscular
from crepuscular import InvalidInputError

PRESETS = sorted((Path(__file__).parent.parent / "examples" / "presets").glob("*.json"))

HALF_GREY_TF = {
    "version": crepuscular.STYLE_VERSION,
    "tf": {
        "mode": "monochrome",
        "depth_range": {"near": 0.0, "far": 50.0},
        "layers": [{"kind": "solid", "color": [0.5, 0.5, 0.5, 1.0]}],
    },
}


def test_the_four_shipped_presets_are_there() -> None:
    names = {path.stem for path in PRESETS}
    assert {"hole-filled-torus", "extruded-colonnade", "holes-in-tree", "alarm"} <= names


@pytest.mark.parametrize("path", PRESETS, ids=lambda path: path.stem)
def test_presets_load_and_round_trip(path: Path) -> None:
    loaded = crepuscular.load_style(path)
    assert loaded["version"] == crepuscular.STYLE_VERSION
    assert crepuscular.load_style(loaded) == loaded
    assert crepuscular.load_style(json.dumps(loaded)) == loaded


def test_a_grey_monochrome_tf_halves_the_light_and_keeps_alpha(scene: dict[str, Any]) -> None:
    physical = crepuscular.render(scene)
    styled = crepuscular.render(scene, style=HALF_GREY_TF)
    np.testing.assert_allclose(styled.volume[..., :3], 0.5 * physical.volume[..., :3], rtol=1e-5)
    np.testing.assert_array_equal(styled.volume[..., 3], physical.volume[..., 3])
    np.testing.assert_array_equal(styled.depth, physical.depth)


def test_style_as_path_dict_text_or_scene_key_gives_one_frame(
    scene: dict[str, Any], tmp_path: Path
) -> None:
    preset = tmp_path / "dilate.json"
    style = {"version": 1, "closing": {"operation": "dilate", "kernel": "box", "radius": 2.0}}
    preset.write_text(json.dumps(style))
    from_path = crepuscular.render(scene, style=preset)
    from_dict = crepuscular.render(scene, style=style)
    from_text = crepuscular.render(scene, style=json.dumps(style))
    from_scene = crepuscular.render({**scene, "style": style})
    for other in (from_dict, from_text, from_scene):
        np.testing.assert_array_equal(other.volume, from_path.volume)
    # Dilating the occluders shadows more of the medium and leaves surfaces alone.
    physical = crepuscular.render(scene)
    assert from_path.visibility.mean() < physical.visibility.mean() - 1e-3
    np.testing.assert_array_equal(from_path.depth, physical.depth)


def test_render_arrays_takes_a_style(scene: dict[str, Any], scene_arrays: dict[str, Any]) -> None:
    styled = crepuscular.render_arrays(**scene_arrays, style=HALF_GREY_TF)
    physical = crepuscular.render_arrays(**scene_arrays)
    np.testing.assert_allclose(styled.volume[..., :3], 0.5 * physical.volume[..., :3], rtol=1e-5)


@pytest.mark.parametrize(
    ("style", "field"),
    [
        ({"version": 1, "closing": {"radius": -1.0}}, "style.closing.radius"),
        ({"version": 1, "silhouette": {"length": float("inf")}}, "style.silhouette.length"),
        ({"version": 1, "holes": {"octaves": 0}}, "style.holes.octaves"),
        ({"version": 1, "closing": {"radius": 1.0, "shape": "disk"}}, "style.closing"),
        ({"version": 99}, "style.version"),
    ],
)
def test_bad_styles_name_it(scene: dict[str, Any], style: dict[str, Any], field: str) -> None:
    with pytest.raises(InvalidInputError) as info:
        crepuscular.render(scene, style=style)
    assert field in str(info.value), str(info.value)
    with pytest.raises(InvalidInputError):
        crepuscular.load_style(style)


def test_a_missing_preset_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.json"
    with pytest.raises(FileNotFoundError, match=r"nowhere\.json"):
        crepuscular.load_style(missing)


def _preset_beside_an_image(folder: Path) -> tuple[Path, Path]:
    """A preset whose TF layer names a two-pixel EXR beside it by a relative path."""
    folder.mkdir()
    image = folder / "ramp.exr"
    crepuscular.write_exr_channels(
        image,
        {
            "R": np.array([[0.0, 1.0]], dtype=np.float32),
            "G": np.array([[0.2, 0.2]], dtype=np.float32),
            "B": np.array([[1.0, 0.0]], dtype=np.float32),
        },
    )
    preset = folder / "ramp-look.json"
    preset.write_text(
        json.dumps(
            {
                "version": crepuscular.STYLE_VERSION,
                "tf": {
                    "mode": "color",
                    "depth_range": {"near": 0.0, "far": 50.0},
                    "layers": [{"kind": "image", "image": {"kind": "file", "path": "ramp.exr"}}],
                },
            }
        ),
        encoding="utf-8",
    )
    return preset, image


def test_a_presets_images_are_found_beside_it_from_any_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, scene: dict[str, Any]
) -> None:
    preset, image = _preset_beside_an_image(tmp_path / "looks")
    elsewhere = tmp_path / "farm-job"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)

    loaded = crepuscular.load_style(preset)
    assert Path(loaded["tf"]["layers"][0]["image"]["path"]) == image
    baked = crepuscular.bake_tf(str(preset))
    assert baked[0, 0, 2] > 0.9, "the ramp's blue end"
    assert baked[0, -1, 0] > 0.9, "the ramp's red end"
    np.testing.assert_array_equal(baked, crepuscular.bake_tf(loaded))
    styled = crepuscular.render(scene, style=preset)
    assert np.isfinite(styled.volume).all()

    # As text, a relative path is the working directory's, and a miss names the file.
    with pytest.raises(crepuscular.CrepuscularError, match=r"ramp\.exr"):
        crepuscular.bake_tf(preset.read_text(encoding="utf-8"))


def test_hole_objects_that_no_mesh_has_warn() -> None:
    preset = next(path for path in PRESETS if path.stem == "holes-in-tree")
    (chosen,) = crepuscular.load_style(preset)["holes"]["objects"]

    def small(name: str) -> dict[str, Any]:
        scene = crepuscular.builtin_scene(name)
        scene["camera"]["width"], scene["camera"]["height"] = 48, 27
        scene["render"]["shadow_map_size"] = 128
        return scene

    torus = small("torus")
    assert chosen not in {mesh["object_id"] for mesh in torus["meshes"]}
    with pytest.warns(UserWarning, match=rf"no mesh has \({chosen}\): no holes are made"):
        crepuscular.render(torus, style=preset)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        crepuscular.render(small("tree"), style=preset)
