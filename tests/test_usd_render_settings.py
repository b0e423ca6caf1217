"""A stage's RenderSettings prim: camera, resolution, pixel aspect, aperture conform
policy and included purposes, as farm renderers read them, through `crepuscular-usd`."""

from __future__ import annotations

import copy
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender
from scenes import build_scene
from usd_helpers import author_camera, author_stage

import crepuscular
from crepuscular_usd import StageReader
from crepuscular_usd.cli import main
from crepuscular_usd.render_settings import ImageSettings, read_render_settings

SMALL = {"steps": 32, "shadow_map_size": 128}


def run(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    status = main(list(argv), stderr=err)
    return status, err.getvalue()


def _settings(
    stage: Usd.Stage, path: str = "/Render/settings", *, name_on_stage: bool = True, **values: Any
) -> UsdRender.Settings:
    """A RenderSettings prim with `values` (camera, resolution, pixel_aspect, conform,
    purposes, window) authored; named by the stage's metadata unless told not to."""
    settings = UsdRender.Settings.Define(stage, path)
    assert settings
    if "camera" in values:
        assert settings.CreateCameraRel().SetTargets([Sdf.Path(values["camera"])])
    if "resolution" in values:
        assert settings.CreateResolutionAttr().Set(Gf.Vec2i(*values["resolution"]))
    if "pixel_aspect" in values:
        assert settings.CreatePixelAspectRatioAttr().Set(values["pixel_aspect"])
    if "conform" in values:
        assert settings.CreateAspectRatioConformPolicyAttr().Set(values["conform"])
    if "purposes" in values:
        assert settings.CreateIncludedPurposesAttr().Set(values["purposes"])
    if "window" in values:
        assert settings.CreateDataWindowNDCAttr().Set(Gf.Vec4f(*values["window"]))
    if name_on_stage:
        stage.SetMetadata(UsdRender.Tokens.renderSettingsPrimPath, path)
    return settings


def _shot(tmp_path: Path, name: str = "shot.usda") -> tuple[Path, Usd.Stage, dict[str, Any]]:
    """The test scene as a stage with a second camera, so that no camera is the only one."""
    path = tmp_path / name
    scene = build_scene(**SMALL)
    stage = author_stage(str(path), scene)
    other = copy.deepcopy(scene["camera"])
    other["world_from_camera"][12] += 3.0
    author_camera(stage, "/World/Other", other)
    return path, stage, scene


def _volume(path: Path) -> np.ndarray:
    channels = crepuscular.read_exr(path)
    return np.stack([channels[f"volume.{c}"] for c in "RGBA"], axis=-1)


def test_the_stage_s_settings_give_camera_resolution_and_pixel_aspect(tmp_path: Path) -> None:
    """Named by the stage's metadata, the settings choose the camera among two, the image
    size and 2:1 anamorphic pixels; the layers are the core's render of that camera, and
    the output layer records the pixel aspect."""
    path, stage, scene = _shot(tmp_path)
    _settings(stage, camera="/World/Camera", resolution=(48, 27), pixel_aspect=2.0)
    assert stage.GetRootLayer().Save()
    out = tmp_path / "out"
    status, err = run(
        "render", str(path), "--out", str(out / "s.exr"), "--out-layer",
        str(out / "shafts.usda"), "--quiet",
    )  # fmt: skip
    assert status == 0, err
    written = _volume(out / "s.exr")
    assert written.shape == (27, 48, 4)
    assert crepuscular.read_exr_pixel_aspect(out / "s.exr") == 2.0
    # The stage's aperture is 36 x 20.25 mm; 48 x 27 pixels of 2:1 span 96 x 27 square
    # units, wider than it: expandAperture fits its height.
    direct = copy.deepcopy(scene)
    direct["camera"].update(width=48, height=27, pixel_aspect=2.0)
    direct["camera"]["projection"].update(
        sensor_fit="vertical", sensor_width=36.0, sensor_height=36.0 * 36 / 64
    )
    expected = crepuscular.render(direct)
    np.testing.assert_allclose(written, expected.volume, atol=1e-4 * expected.volume.max())
    assert written[..., 3].mean() > 0.01
    # Square pixels see another image: the test can tell.
    direct["camera"]["pixel_aspect"] = 1.0
    assert np.abs(crepuscular.render(direct).volume - written).max() > 0.05 * written.max()
    record = Usd.Stage.Open(str(out / "shafts.usda"))
    recorded = UsdRender.Settings(record.GetPrimAtPath("/Render/CrepuscularSettings"))
    assert recorded.GetPixelAspectRatioAttr().Get() == 2.0
    assert recorded.GetCameraRel().GetTargets() == [Sdf.Path("/World/Camera")]
    assert tuple(recorded.GetResolutionAttr().Get()) == (48, 27)
    product = UsdRender.Product(record.GetPrimAtPath("/Render/Products/shafts"))
    assert product.GetPixelAspectRatioAttr().Get() == 2.0


def test_the_command_line_overrides_the_settings(tmp_path: Path) -> None:
    """--camera and both sides replace the settings'; one side scales their image."""
    path, stage, _ = _shot(tmp_path)
    _settings(stage, camera="/World/Other", resolution=(48, 27))
    assert stage.GetRootLayer().Save()
    out = tmp_path / "out"
    common = ["render", str(path), "--quiet", "--out-layer", str(out / "l.usda")]
    status, err = run(*common, "--out", str(out / "a.exr"), "--width", "96")
    assert status == 0, err
    assert _volume(out / "a.exr").shape[:2] == (54, 96)
    status, err = run(*common, "--out", str(out / "b.exr"), "--height", "9")
    assert status == 0, err
    assert _volume(out / "b.exr").shape[:2] == (9, 16)
    status, err = run(
        *common, "--out", str(out / "c.exr"), "--width", "40", "--height", "40",
        "--camera", "/World/Camera",
    )  # fmt: skip
    assert status == 0, err
    assert _volume(out / "c.exr").shape[:2] == (40, 40)
    layer = Usd.Stage.Open(str(out / "l.usda"))
    recorded = UsdRender.Settings(layer.GetPrimAtPath("/Render/CrepuscularSettings"))
    assert recorded.GetCameraRel().GetTargets() == [Sdf.Path("/World/Camera")]
    assert not recorded.GetPixelAspectRatioAttr().HasAuthoredValue()
    other = _volume(out / "a.exr")
    mine = StageReader(stage, "/World/Other", None, width=96, height=54)
    expected = crepuscular.render_arrays(**mine.read(Usd.TimeCode.Default()).render_kwargs())
    np.testing.assert_array_equal(other, expected.volume)


@pytest.mark.parametrize(
    ("conform", "size", "fit", "pixel_aspect"),
    [
        ("expandAperture", (64, 32), "vertical", 1.0),
        ("expandAperture", (32, 64), "horizontal", 1.0),
        ("cropAperture", (64, 32), "horizontal", 1.0),
        ("cropAperture", (32, 64), "vertical", 1.0),
        ("adjustApertureWidth", (32, 64), "vertical", 1.0),
        ("adjustApertureHeight", (64, 32), "horizontal", 1.0),
        # 64 x 32 pixels of 1:2 cover the square aperture exactly.
        ("adjustPixelAspectRatio", (64, 32), "horizontal", 0.5),
    ],
)
def test_conform_policies_fit_the_aperture_as_named(
    tmp_path: Path, conform: str, size: tuple[int, int], fit: str, pixel_aspect: float
) -> None:
    """A square aperture in a wide or a tall image. expandAperture shows all of it (the
    image's longer side sees more), cropAperture fills the image with it, the adjust
    policies keep one side, or the pixels' shape."""
    _, stage, _ = _shot(tmp_path)
    camera = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    camera.GetVerticalApertureAttr().Set(36.0)
    camera.CreateHorizontalApertureOffsetAttr().Set(3.0)
    _settings(stage, camera="/World/Camera", resolution=size, conform=conform)
    image = read_render_settings(stage, None)
    reader = StageReader(stage, None, "/World/Sun", width=size[0], height=size[1], image=image)
    view = reader.camera(Usd.TimeCode.Default())
    assert view["projection"]["sensor_fit"] == fit
    assert view["pixel_aspect"] == pytest.approx(pixel_aspect)
    assert view["projection"]["shift_x"] == pytest.approx(3.0 / 36.0)


def test_included_purposes_decide_what_casts(tmp_path: Path) -> None:
    """A proxy occluder casts only where the settings include the proxy purpose."""
    _, stage, _ = _shot(tmp_path)
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/occluder")).CreatePurposeAttr("proxy")
    plain = StageReader(stage, "/World/Camera", "/World/Sun", width=48, height=27)
    _settings(stage, purposes=["default", "proxy"], resolution=(48, 27), camera="/World/Camera")
    with_proxy = StageReader(
        stage, None, "/World/Sun", width=48, height=27, image=read_render_settings(stage, None)
    )
    time = Usd.TimeCode.Default()
    without = crepuscular.render_arrays(**plain.read(time).render_kwargs())
    casting = crepuscular.render_arrays(**with_proxy.read(time).render_kwargs())
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/occluder")).GetPurposeAttr().Set("default")
    fresh = StageReader(stage, "/World/Camera", "/World/Sun", width=48, height=27)
    expected = crepuscular.render_arrays(**fresh.read(time).render_kwargs())
    np.testing.assert_array_equal(casting.volume, expected.volume)
    assert np.abs(without.volume - casting.volume).max() > 0.05 * casting.volume.max()


def test_settings_the_stage_cannot_render_are_named(tmp_path: Path) -> None:
    path, stage, _ = _shot(tmp_path)
    out = str(tmp_path / "out" / "s.exr")
    common = ("render", str(path), "--quiet", "--out", out, "--camera", "/World/Camera")
    cases = [
        ({"path": "/Render/gone"}, "renderSettingsPrimPath names /Render/gone"),
        ({"resolution": (0, 10)}, "/Render/settings.resolution 0x10 is outside"),
        ({"pixel_aspect": 0.0}, "/Render/settings.pixelAspectRatio 0.0 must be positive"),
        ({"conform": "stretch"}, "aspectRatioConformPolicy 'stretch' is none of"),
        ({"purposes": ["render", "hero"]}, "includedPurposes holds hero"),
        ({"camera": "/World/Sun"}, "/Render/settings.camera targets /World/Sun, which is not"),
    ]
    for values, message in cases:
        settings = _settings(stage, **{k: v for k, v in values.items() if k != "path"})
        if "path" in values:
            stage.SetMetadata(UsdRender.Tokens.renderSettingsPrimPath, values["path"])
        assert stage.GetRootLayer().Save()
        argv = ["render", str(path), "--quiet", "--out", out]
        status, err = run(*argv, *(() if "camera" in values else ("--camera", "/World/Camera")))
        assert status == 1, (values, err)
        assert message in err, (values, err)
        stage.RemovePrim(settings.GetPath())
        stage.ClearMetadata(UsdRender.Tokens.renderSettingsPrimPath)
    status, err = run(*common, "-rs", "/World/Camera")
    assert status == 1
    assert "/World/Camera is a Camera, not a RenderSettings" in err, err
    status, err = run(*common, "-rs", "/Render/none")
    assert status == 1
    assert "render settings /Render/none does not exist" in err, err


def test_a_data_window_renders_its_pixels_in_the_whole_image(tmp_path: Path) -> None:
    """dataWindowNDC: the pixels whose centres it holds are rendered, the frame's own (the
    shadow map is fitted to the whole view), and sit in the whole image with nothing
    around them, as in a renderer's display window; a window that holds no pixel is
    named. Two settings prims and no metadata choose none; several camera targets read
    the first."""
    path, stage, _ = _shot(tmp_path)
    # Columns 7.52 to 24.48 of 32 hold the centres of 8 to 23; rows 4.68 to 18 of 18 from
    # the top (y up 0 to 0.74) those of 5 to 17.
    _settings(stage, camera="/World/Camera", resolution=(32, 18), window=(0.235, 0.0, 0.765, 0.74))
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/settings"))
    settings.GetCameraRel().AddTarget("/World/Other")
    assert stage.GetRootLayer().Save()
    out = tmp_path / "out"
    status, err = run("render", str(path), "--quiet", "--out", str(out / "a.exr"))
    assert status == 0, err
    assert "targets 2 prims; the first, /World/Camera, is read" in err
    windowed = _volume(out / "a.exr")
    assert windowed.shape[:2] == (18, 32)
    inside = np.zeros((18, 32), dtype=bool)
    inside[5:18, 8:24] = True
    assert not windowed[~inside].any()
    whole = StageReader(stage, "/World/Camera", None, width=32, height=18)
    expected = crepuscular.render_arrays(**whole.read(Usd.TimeCode.Default()).render_kwargs())
    np.testing.assert_allclose(windowed[inside], expected.volume[inside], rtol=1e-5, atol=1e-6)
    assert expected.volume[inside][:, 3].mean() > 0.01
    settings.GetDataWindowNDCAttr().Set(Gf.Vec4f(0.5, 0.5, 0.51, 0.51))
    assert stage.GetRootLayer().Save()
    status, err = run("render", str(path), "--quiet", "--out", str(out / "b.exr"))
    assert status == 1
    assert "dataWindowNDC (0.5, 0.5, 0.51" in err
    assert "holds no pixel of the 32x18 image" in err
    _settings(stage, "/Render/preview", name_on_stage=False, resolution=(16, 9))
    stage.ClearMetadata(UsdRender.Tokens.renderSettingsPrimPath)
    assert stage.GetRootLayer().Save()
    image = read_render_settings(stage, None)
    assert image == ImageSettings(notes=image.notes)
    assert "2 RenderSettings prims (/Render/settings, /Render/preview)" in image.notes[0]
    status, err = run(
        "render", str(path), "--quiet", "--camera", "/World/Camera", "--width", "32", "--out",
        str(out / "b.exr"),
    )  # fmt: skip
    assert status == 0, err
    assert "none is read (give --renderSettingsPrimPath)" in err, err
    # The aperture's aspect, not the settings' 16 x 9 nor 32 x 18.
    assert _volume(out / "b.exr").shape[:2] == (18, 32)


def test_purposes_are_inherited_as_usd_computes_them(tmp_path: Path) -> None:
    """A prim's own authored purpose wins over its ancestors' (`ComputePurpose`): a render
    mesh under a proxy scope renders, an unauthored one there is a proxy, and an
    authored default under a guide scope renders."""
    _, stage, _ = _shot(tmp_path)
    occluder = stage.GetPrimAtPath("/World/occluder")
    points = UsdGeom.Mesh(occluder).GetPointsAttr().Get()
    scopes = {"/World/Proxies": "proxy", "/World/Guides": "guide"}
    meshes = {
        "/World/Proxies/Hero": "render",
        "/World/Proxies/Stand": None,
        "/World/Guides/Kept": "default",
    }
    for path, purpose in scopes.items():
        UsdGeom.Xform.Define(stage, path).CreatePurposeAttr(purpose)
    for path, purpose in meshes.items():
        mesh = UsdGeom.Mesh.Define(stage, path)
        mesh.CreatePointsAttr([p + Gf.Vec3f(0, 0, 0.1) for p in points])
        mesh.CreateFaceVertexCountsAttr([4])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        if purpose is not None:
            mesh.CreatePurposeAttr(purpose)
    for path in meshes:
        assert (
            UsdGeom.Imageable(stage.GetPrimAtPath(path)).ComputePurpose() in ("render", "default")
        ) == (path != "/World/Proxies/Stand")
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=48, height=27)
    owners = set(reader.read(Usd.TimeCode.Default()).geometry.ids_by_path)
    assert Sdf.Path("/World/Proxies/Hero") in owners
    assert Sdf.Path("/World/Guides/Kept") in owners
    assert Sdf.Path("/World/Proxies/Stand") not in owners
    image = ImageSettings(purposes=("default", "render", "proxy"))
    with_proxies = StageReader(
        stage, "/World/Camera", "/World/Sun", width=48, height=27, image=image
    )
    owners = set(with_proxies.read(Usd.TimeCode.Default()).geometry.ids_by_path)
    assert Sdf.Path("/World/Proxies/Stand") in owners


def test_a_beauty_composites_through_the_settings_image(tmp_path: Path) -> None:
    """Anamorphic settings with a data window over a beauty of the full resolution: the
    beauty's depth is cropped to the window, the composite carries the pixel aspect, and
    a beauty whose own pixelAspectRatio differs is named once."""
    path, stage, _ = _shot(tmp_path)
    _settings(
        stage,
        camera="/World/Camera",
        resolution=(48, 27),
        pixel_aspect=2.0,
        window=(0.25, 0.25, 0.75, 0.75),
    )
    assert stage.GetRootLayer().Save()
    beauty = np.full((27, 48), 0.5, dtype=np.float32)
    planes = {"R": beauty, "G": beauty, "B": beauty, "A": np.ones_like(beauty)}
    planes["depth"] = np.full((27, 48), 3.0, dtype=np.float32)
    for frame, aspect in ((1, 1.0), (2, 2.0)):
        crepuscular.write_exr_channels(
            tmp_path / f"beauty.{frame:04d}.exr", planes, pixel_aspect=aspect
        )
    out = tmp_path / "out"
    for frames, named in (("1", True), ("2", False)):
        status, err = run(
            "render", str(path), "--quiet", "--frames", frames, "--out",
            str(out / "s.####.exr"), "--beauty", str(tmp_path / "beauty.####.exr"),
        )  # fmt: skip
        assert status == 0, err
        assert ("has pixels 1:1 (its pixelAspectRatio) but the camera renders 2:1" in err) == named
    comp = out / "comp.s.0002.exr"
    assert crepuscular.read_exr_pixel_aspect(comp) == 2.0
    layers = crepuscular.read_exr(out / "s.0002.exr")
    assert layers["depth"].shape == (27, 48)
    # Inside the window the beauty's 3 m depth shortens the rays; outside, nothing.
    window = np.zeros((27, 48), dtype=bool)
    window[7:20, 12:36] = True
    assert not layers["volume.A"][~window].any()
    assert np.allclose(layers["depth"][window], 3.0, rtol=1e-3)


def _product(stage: Usd.Stage, path: str, **values: Any) -> UsdRender.Product:
    """A RenderProduct with `values` (camera, resolution, pixel_aspect, window) authored,
    added to /Render/settings' products."""
    product = UsdRender.Product.Define(stage, path)
    assert product
    if "camera" in values:
        assert product.CreateCameraRel().SetTargets([Sdf.Path(values["camera"])])
    if "resolution" in values:
        assert product.CreateResolutionAttr().Set(Gf.Vec2i(*values["resolution"]))
    if "pixel_aspect" in values:
        assert product.CreatePixelAspectRatioAttr().Set(values["pixel_aspect"])
    if "window" in values:
        assert product.CreateDataWindowNDCAttr().Set(Gf.Vec4f(*values["window"]))
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/settings"))
    assert settings.GetProductsRel().AddTarget(product.GetPath())
    return product


def test_a_render_product_overrides_what_it_authors(tmp_path: Path) -> None:
    """A product's authored camera, resolution, pixel aspect and data window replace the
    settings' (as UsdRender's spec computes a product's image); what it leaves unauthored,
    here the conform policy, stays the settings'. The render equals one of settings that
    hold those values themselves, bit for bit."""
    path, stage, _ = _shot(tmp_path)
    _settings(
        stage,
        camera="/World/Other",
        resolution=(48, 27),
        conform="cropAperture",
        window=(0, 0, 1, 0.5),
    )
    _product(
        stage, "/Render/Products/beauty", camera="/World/Camera", resolution=(40, 30),
        pixel_aspect=2.0, window=(0.0, 0.0, 1.0, 1.0),
    )  # fmt: skip
    assert stage.GetRootLayer().Save()
    image = read_render_settings(stage, None)
    assert image.product == Sdf.Path("/Render/Products/beauty")
    assert (image.camera, image.resolution, image.pixel_aspect, image.conform) == (
        Sdf.Path("/World/Camera"), (40, 30), 2.0, "cropAperture",
    )  # fmt: skip
    # The product's whole-image window clears the settings' half.
    assert image.data_window is None
    assert image.attribute("resolution") == "/Render/Products/beauty.resolution"
    assert (
        image.attribute("aspectRatioConformPolicy") == "/Render/settings.aspectRatioConformPolicy"
    )
    out = tmp_path / "out"
    status, err = run("render", str(path), "--quiet", "--out", str(out / "product.exr"))
    assert status == 0, err
    by_product = _volume(out / "product.exr")
    assert by_product.shape == (30, 40, 4)
    assert crepuscular.read_exr_pixel_aspect(out / "product.exr") == 2.0
    # The same image authored on the settings alone.
    plain = tmp_path / "plain.usda"
    _, plain_stage, _ = _shot(tmp_path, plain.name)
    _settings(
        plain_stage, camera="/World/Camera", resolution=(40, 30), conform="cropAperture",
        pixel_aspect=2.0,
    )  # fmt: skip
    assert plain_stage.GetRootLayer().Save()
    status, err = run("render", str(plain), "--quiet", "--out", str(out / "plain.exr"))
    assert status == 0, err
    np.testing.assert_array_equal(by_product, _volume(out / "plain.exr"))
    assert by_product[..., 3].mean() > 0.01


def test_several_products_render_the_first_or_the_one_named(tmp_path: Path) -> None:
    """Products that agree are one image. Where they differ the first is rendered and the
    choice named; --renderProduct picks another. Targets that are no product, and bad
    overrides, are named with the product's path."""
    path, stage, _ = _shot(tmp_path)
    _settings(stage, camera="/World/Camera", resolution=(48, 27))
    _product(stage, "/Render/Products/a", resolution=(32, 18))
    _product(stage, "/Render/Products/b", resolution=(32, 18))
    image = read_render_settings(stage, None)
    assert (image.product, image.resolution, image.notes) == (
        Sdf.Path("/Render/Products/a"), (32, 18), (),
    )  # fmt: skip
    _product(stage, "/Render/Products/c", resolution=(16, 9))
    image = read_render_settings(stage, None)
    assert image.resolution == (32, 18)
    assert (
        "3 products (/Render/Products/a, /Render/Products/b, /Render/Products/c)"
        in (image.notes[0])
    )
    assert "the first, /Render/Products/a, is rendered (give --renderProduct)" in image.notes[0]
    assert stage.GetRootLayer().Save()
    out = tmp_path / "out"
    status, err = run(
        "render", str(path), "--quiet", "--renderProduct", "/Render/Products/c", "--out",
        str(out / "c.exr"),
    )  # fmt: skip
    assert status == 0, err
    assert "override the image differently" not in err
    assert _volume(out / "c.exr").shape[:2] == (9, 16)
    common = ("render", str(path), "--quiet", "--out", str(out / "x.exr"))
    status, err = run(*common, "--renderProduct", "/World/Camera")
    assert status == 1
    assert "render product (from --renderProduct) /World/Camera is a Camera, not a " in err, err
    UsdRender.Product(stage.GetPrimAtPath("/Render/Products/c")).GetResolutionAttr().Set(
        Gf.Vec2i(0, 9)
    )
    assert stage.GetRootLayer().Save()
    status, err = run(*common, "--renderProduct", "/Render/Products/c")
    assert status == 1
    assert "/Render/Products/c.resolution 0x9 is outside 1..16384" in err, err
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/settings"))
    assert settings.GetProductsRel().AddTarget("/World/Sun", Usd.ListPositionFrontOfPrependList)
    assert stage.GetRootLayer().Save()
    status, err = run(*common)
    assert status == 1
    assert "(from /Render/settings.products) /World/Sun is a DistantLight, not a Render" in err
