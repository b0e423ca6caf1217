"""Built-in scenes, EXR and PNG files, and compositing through the Python API."""

from __future__ import annotations

import errno
import struct
import typing
from pathlib import Path

import numpy as np
import pytest

import crepuscular


def small(scene: dict) -> dict:
    scene["camera"]["width"], scene["camera"]["height"] = 96, 54
    scene["render"]["steps"] = 64
    scene["render"]["shadow_map_size"] = 256
    return scene


@pytest.mark.parametrize("name", ["torus", "tree", "plane", "colonnade"])
def test_builtin_scenes_render_with_shafts(name: str) -> None:
    assert name in crepuscular.builtin_scene_names()
    scene = crepuscular.builtin_scene(name)
    assert (scene["camera"]["width"], scene["camera"]["height"]) == (1920, 1080)
    layers = crepuscular.render(small(scene))
    assert np.isfinite(layers.volume).all()
    assert np.isfinite(layers.depth).all()
    assert (layers.volume[..., 3] >= 0).all()
    assert (layers.volume[..., 3] <= 1).all()
    # Shafts: some rays are partly shadowed and some fully lit or nearly so.
    assert ((layers.visibility > 0.05) & (layers.visibility < 0.95)).mean() > 0.05
    assert layers.volume[..., :3].max() > 0


def test_builtin_scenes_are_deterministic() -> None:
    assert crepuscular.builtin_scene("tree") == crepuscular.builtin_scene("tree")


def test_unknown_builtin_scene_names_the_choices() -> None:
    with pytest.raises(crepuscular.InvalidInputError, match="torus"):
        crepuscular.builtin_scene("teapot")


def test_exr_round_trip_is_exact(tmp_path: Path) -> None:
    layers = crepuscular.render(small(crepuscular.builtin_scene("plane")))
    path = tmp_path / "plane.exr"
    crepuscular.write_exr(path, layers)
    channels = crepuscular.read_exr(path)
    assert sorted(channels) == sorted(
        ["volume.R", "volume.G", "volume.B", "volume.A", "visibility", "depth"]
    )
    for c, name in enumerate("RGBA"):
        np.testing.assert_array_equal(channels[f"volume.{name}"], layers.volume[..., c])
    np.testing.assert_array_equal(channels["visibility"], layers.visibility)
    np.testing.assert_array_equal(channels["depth"], layers.depth)


def exr_codec(path: Path) -> int:
    """The OpenEXR code of the file's codec: its header attribute `compression`."""
    data = path.read_bytes()
    attribute = b"compression\0compression\0" + struct.pack("<i", 1)
    return data[data.index(attribute) + len(attribute)]


def test_every_exr_codec_is_written_and_read_back(tmp_path: Path) -> None:
    layers = crepuscular.render(small(crepuscular.builtin_scene("tree")))
    assert crepuscular.EXR_COMPRESSIONS[0] == "zip"
    codes = {"none": 0, "rle": 1, "zips": 2, "zip": 3, "piz": 4, "pxr24": 5}
    assert sorted(crepuscular.EXR_COMPRESSIONS) == sorted(codes)
    # The type's literals, spelled out for type checkers, are the core's names.
    assert sorted(typing.get_args(crepuscular.ExrCompression)) == sorted(codes)
    default = tmp_path / "default.exr"
    crepuscular.write_exr(default, layers)
    assert exr_codec(default) == codes["zip"]
    for name, code in codes.items():
        path = tmp_path / f"{name}.exr"
        crepuscular.write_exr(path, layers, compression=name.upper() if code % 2 else name)
        assert exr_codec(path) == code, name
        channels = crepuscular.read_exr(path)
        # Pxr24 rounds f32 to 24 bits; the others are lossless.
        rtol = 2.0**-16 if name == "pxr24" else 0.0
        np.testing.assert_allclose(channels["volume.G"], layers.volume[..., 1], rtol=rtol, atol=0)
        np.testing.assert_allclose(channels["depth"], layers.depth, rtol=rtol, atol=0)
    planes = {"R": layers.visibility}
    crepuscular.write_exr_channels(tmp_path / "piz_rgba.exr", planes, compression="piz")
    assert exr_codec(tmp_path / "piz_rgba.exr") == codes["piz"]
    for write in (
        lambda: crepuscular.write_exr(tmp_path / "bad.exr", layers, compression="dwaa"),
        lambda: crepuscular.write_exr_channels(tmp_path / "bad.exr", planes, compression="b44"),
    ):
        message = r'compression: "(dwaa|b44)" is not an EXR codec; use one of .*piz'
        with pytest.raises(crepuscular.InvalidInputError, match=message) as info:
            write()
        assert info.value.field == "compression"
    assert not (tmp_path / "bad.exr").exists()


def test_half_float_exr_keeps_values_to_half_precision(tmp_path: Path) -> None:
    layers = crepuscular.render(small(crepuscular.builtin_scene("torus")))
    path = tmp_path / "torus_half.exr"
    crepuscular.write_exr(path, layers, half=True)
    channels = crepuscular.read_exr(path)
    np.testing.assert_allclose(channels["volume.R"], layers.volume[..., 0], rtol=1e-3, atol=1e-6)


def test_truncated_exr_is_a_named_error(tmp_path: Path) -> None:
    layers = crepuscular.render(small(crepuscular.builtin_scene("torus")))
    path = tmp_path / "cut.exr"
    crepuscular.write_exr(path, layers)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(crepuscular.ExrError, match=r"cut\.exr") as truncated:
        crepuscular.read_exr(path)
    assert truncated.value.filename == str(path)
    # The message says what is wrong, not OSError's "[Errno None] None: 'path'".
    assert "None" not in str(truncated.value)
    assert str(truncated.value) == truncated.value.args[0]
    with pytest.raises(crepuscular.ExrError, match=r"missing\.exr: No such file") as missing:
        crepuscular.read_exr(tmp_path / "missing.exr")
    assert missing.value.errno == errno.ENOENT


def test_composite_is_premultiplied_over() -> None:
    volume = np.array([[[0.2, 0.1, 0.0, 0.25]]], dtype=np.float32)
    beauty = np.array([[[0.8, 0.4, 1.0, 1.0]]], dtype=np.float32)
    out = crepuscular.composite(volume, beauty)
    np.testing.assert_allclose(out, [[[0.8, 0.4, 0.75, 1.0]]], rtol=1e-6)
    with pytest.raises(crepuscular.InvalidInputError, match="beauty"):
        crepuscular.composite(volume, np.zeros((2, 1, 4), dtype=np.float32))


def test_preview_png_is_an_image_of_the_right_size(tmp_path: Path) -> None:
    layers = crepuscular.render(small(crepuscular.builtin_scene("colonnade")))
    path = tmp_path / "preview.png"
    crepuscular.write_preview_png(path, layers.volume)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    assert (width, height) == (96, 54)


def test_minmax_method_agrees_with_the_reference() -> None:
    scene = small(crepuscular.builtin_scene("colonnade"))
    scene["render"]["steps"] = 2048
    scene["render"]["shadow_map_size"] = 1024
    scene["render"]["method"] = "reference"
    reference = crepuscular.render(scene)
    scene["render"]["method"] = "minmax"
    fast = crepuscular.render(scene)
    error = np.abs(fast.volume[..., :3] - reference.volume[..., :3]).mean()
    assert error / reference.volume[..., :3].mean() < 0.01
    np.testing.assert_array_equal(fast.depth, reference.depth)


def test_unknown_method_names_the_field() -> None:
    scene = small(crepuscular.builtin_scene("torus"))
    scene["render"]["method"] = "raytraced"
    with pytest.raises(crepuscular.InvalidInputError, match=r"render\.method"):
        crepuscular.render(scene)


def test_named_channels_round_trip_and_mismatches_name_the_channel(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    planes = {name: rng.uniform(-2, 2, (5, 7)).astype(np.float32) for name in "RGBA"}
    planes["Z"] = np.full((5, 7), 1e10, dtype=np.float32)
    crepuscular.write_exr_channels(tmp_path / "rgba.exr", planes)
    back = crepuscular.read_exr(tmp_path / "rgba.exr")
    assert set(back) == set(planes)
    for name, plane in planes.items():
        np.testing.assert_array_equal(back[name], plane)
    crepuscular.write_exr_channels(tmp_path / "half.exr", {"R": planes["R"]}, half=True)
    np.testing.assert_allclose(
        crepuscular.read_exr(tmp_path / "half.exr")["R"], planes["R"], rtol=1e-3
    )
    with pytest.raises(crepuscular.InvalidInputError, match=r"must have shape \(5, 7\)") as info:
        crepuscular.write_exr_channels(
            tmp_path / "bad.exr", {"R": planes["R"], "G": np.zeros((5, 6), np.float32)}
        )
    assert info.value.field == "channels.G"
    with pytest.raises(crepuscular.InvalidInputError, match="no channels"):
        crepuscular.write_exr_channels(tmp_path / "none.exr", {})


def test_anamorphic_layers_carry_their_pixel_aspect_into_exr(tmp_path: Path) -> None:
    """An EXR viewer (Nuke, Blender) shows an anamorphic image unsqueezed by the header's
    pixelAspectRatio, which Blender writes for its own renders: the layers of a camera of
    2:1 pixels carry it, as does a composite given it; the pixels read back unchanged."""
    scene = small(crepuscular.builtin_scene("torus"))
    scene["camera"]["pixel_aspect"] = 2.0
    layers = crepuscular.render(scene)
    assert layers.pixel_aspect == 2.0
    crepuscular.write_exr(tmp_path / "wide.exr", layers)
    assert crepuscular.read_exr_pixel_aspect(tmp_path / "wide.exr") == 2.0
    np.testing.assert_array_equal(
        crepuscular.read_exr(tmp_path / "wide.exr")["depth"], layers.depth
    )
    plane = {"R": np.ones((3, 4), np.float32)}
    crepuscular.write_exr_channels(tmp_path / "tall.exr", plane, pixel_aspect=0.5)
    assert crepuscular.read_exr_pixel_aspect(tmp_path / "tall.exr") == 0.5
    crepuscular.write_exr_channels(tmp_path / "square.exr", plane)
    assert crepuscular.read_exr_pixel_aspect(tmp_path / "square.exr") == 1.0
    for aspect in (0.0, -1.0, float("nan")):
        with pytest.raises(crepuscular.InvalidInputError, match="must be positive") as info:
            crepuscular.write_exr_channels(tmp_path / "bad.exr", plane, pixel_aspect=aspect)
        assert info.value.field == "pixel_aspect"
    assert not (tmp_path / "bad.exr").exists()
