"""Round trip from Blender: a bpy scene exported with Blender's own USD exporter, its shaft
settings authored by the add-on's export hook, rendered by `crepuscular-usd`, against the
add-on's `render_layers` output of the same frame.

Blender runs in a subprocess (blender_job.py): only Blender's own USD bindings can take its
stage, and this process holds usd-core's for the USD step.

Tolerance. Both sides run the same core on the same triangles, camera, sun, medium, settings
and style; what differs is the path: Blender's exporter writes transforms, points and light
values in single precision, and the reader composes them again in double; Blender's armature
and UsdSkel each skin the posed column in single precision (their points agree within 5e-7).
So the layers may differ by float32 rounding (measured: at most 8e-6 mean relative error per
layer; depth within 8e-6 scene units, but 4e-4 at a pixel that sees a face of the column
almost edge on), and by a shadow-map texel that such rounding flips at an edge. The bounds,
a mean relative error of 1e-4 per layer and 1e-3 scene units of depth per pixel, leave room
for that and for other machines' rounding, and stay orders of magnitude below any real
mismatch: the sun's exposure of 0.5 stop is 41 %, Blender's strength / 4 is 75 %, its
6500 K tint is 4 % in red and blue, a camera shift in the wrong units moves depth edges by
whole pixels, the column read at rest is 0.07 to 0.7 % off per layer and 39 units off in
depth, the leaf card (a PNG's alpha, which the exporter writes as a UsdPreviewSurface's
opacity) read as opaque 3 to 13 %, the hair strands (BasisCurves) left out 23 to 55 %,
the point cloud (Points) left out 0.07 to 2.9 %, and the light's shadowLink collection
(which the hook authors for the objects that do not block the sun: one hidden from shadow
rays, one left out by the sun's shadow linking) left out 12 to 32 %, and the veil and
lattice cards' cuts (Mix Shaders with a Transparent BSDF, which the exporter writes as
opaque surfaces and the hook as masks) read as opaque 1.6 % and 2.1 % in red through the
orthographic view, the geometry-nodes dust (an empty mesh from the exporter, Points
from the hook) left out 0.69 % in red through the region and 1.9 % through the
orthographic view, the particle fur (left out by the exporter, curves from the hook)
0.63 % through the orthographic view, the bevelled curve and NURBS sphere (a curve's
path and no surface from the exporter, meshes from the hook) 0.94 % through the region, and
the subdivided lantern's cut-out read with its texture coordinates refined linearly rather
than smoothed as its *UV Smooth* says 0.08 % in blue (4.8 units in depth where its cuts
move), and the skylight's concave faces around its window fanned rather than ear-clipped
0.17 % in blue in the animation's first frame (0.17 units in depth through the
orthographic view).
The fog is tinted, so its extinction travels per channel
(`crepuscular:medium:channelExtinction`).
"""

from __future__ import annotations

import io
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

import crepuscular

bpy = pytest.importorskip("bpy")
pxr = pytest.importorskip("pxr")

import blender_scenes  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade  # noqa: E402

from crepuscular_usd.attributes import ATTRIBUTES  # noqa: E402
from crepuscular_usd.cli import main  # noqa: E402
from crepuscular_usd.schema import API_NAME  # noqa: E402

WIDTH, HEIGHT = 96, 54
LAYERS = ("volume.R", "volume.G", "volume.B", "volume.A", "visibility")
MEAN_RELATIVE = 1e-4
DEPTH_ABSOLUTE = 1e-3


def _render(stage: Path, out: str, *frames: str) -> str:
    """Renders with the image the hook's RenderSettings give; returns the warnings."""
    err = io.StringIO()
    status = main(["render", str(stage), "--out", out, *frames, "--quiet"], stderr=err)
    assert status == 0, err.getvalue()
    return err.getvalue()


def _errors(blender: Path, usd: Path) -> dict[str, float]:
    """Mean relative error per layer, and the largest depth difference (scene units)."""
    ours, theirs = crepuscular.read_exr(blender), crepuscular.read_exr(usd)
    assert sorted(ours) == sorted(theirs)
    errors = {
        name: float(np.abs(ours[name] - theirs[name]).mean() / np.abs(ours[name]).mean())
        for name in (*LAYERS, "depth")
    }
    errors["depth max"] = float(np.abs(ours["depth"] - theirs["depth"]).max())
    return errors


def _assert_close(errors: dict[str, float], label: str) -> None:
    print(label, ", ".join(f"{name} {value:.2g}" for name, value in errors.items()))
    for name in (*LAYERS, "depth"):
        assert errors[name] <= MEAN_RELATIVE, (label, name, errors)
    assert errors["depth max"] <= DEPTH_ABSOLUTE, (label, errors)


def _round_trip(factory: pytest.TempPathFactory, variant: str, **spec: Any) -> Path:
    """Runs the round trip job (`blender_job.job_usd_round_trip`) for `variant`."""
    out = factory.mktemp(f"round_trip_{variant}")
    blender_scenes.run_job(out, "usd_round_trip", width=WIDTH, height=HEIGHT, **spec)
    return out


@pytest.fixture(scope="module")
def still(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _round_trip(tmp_path_factory, "still", animated=False)


@pytest.fixture(scope="module")
def animated(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _round_trip(tmp_path_factory, "animated", animated=True)


@pytest.fixture(scope="module")
def orthographic(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _round_trip(tmp_path_factory, "orthographic", animated=False, orthographic=True)


def test_layers_match_the_addons(still: Path) -> None:
    """Blender's default export options (Z up, metres, polygons as they are), rendered at
    the stage's own time, which the hook makes the Blender frame's."""
    blender = crepuscular.read_exr(still / "blender.0001.exr")
    # Not a vacuous comparison: the fog box, the slats' shadows and the styled light.
    assert 0.2 < blender["volume.A"].mean() < 0.9
    assert 0.05 < blender["visibility"].mean() < 0.95
    assert blender["volume.R"].max() > 0.01
    _render(still / "shot.usda", str(still / "usd.exr"))
    _assert_close(_errors(still / "blender_region.0001.exr", still / "usd.exr"), "Z up, metres:")
    # The exported render region is the data window: layers there, nothing around it
    # (Blender truncates the border, columns 24 to 73 of 96 and rows 22 to 48 of 54 from
    # the top; USD takes the pixels whose centres the window holds, which the hook makes
    # the same pixels).
    region = crepuscular.read_exr(still / "usd.exr")["volume.A"]
    inside = np.zeros_like(region, dtype=bool)
    inside[22:49, 24:74] = True
    assert not region[~inside].any()
    assert region[inside].mean() > 0.2
    # The whole frame's opacity there (a depth edge's samples may round apart).
    whole = crepuscular.read_exr(still / "blender.0001.exr")["volume.A"]
    assert np.abs(region[inside] - whole[inside]).mean() < 1e-5
    np.testing.assert_allclose(region[inside], whole[inside], atol=2e-3)


def test_y_up_centimetre_export_renders_the_same(still: Path) -> None:
    stage = Usd.Stage.Open(str(still / "shot_y_up_cm.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    light = stage.GetPrimAtPath("/root/Sun/Sun")
    # Lengths in stage units: the add-on's 0.3 m closing radius, and the tinted fog's
    # 0.12 per metre times its colour per channel (the scalar is their luminance).
    assert light.GetAttribute("crepuscular:closing:radius").Get() == pytest.approx(30.0)
    channels = light.GetAttribute("crepuscular:medium:channelExtinction").Get()
    assert tuple(channels) == pytest.approx((0.0012, 0.00096, 0.00066))
    luminance = 0.2126 * 0.0012 + 0.7152 * 0.00096 + 0.0722 * 0.00066
    assert light.GetAttribute("crepuscular:medium:extinction").Get() == pytest.approx(luminance)
    _render(still / "shot_y_up_cm.usda", str(still / "usd_y_up_cm.exr"))
    errors = _errors(still / "blender_region.0001.exr", still / "usd_y_up_cm.exr")
    _assert_close(errors, "Y up, centimetres:")


def test_orthographic_camera_renders_the_same(orthographic: Path) -> None:
    """Blender's exporter writes an orthographic camera as its transform alone; the hook
    authors its Camera prim (16 units across the vertical fit through 4:5 pixels, so
    16 x 96 / 54 x 0.8 across, shift and clip in tenths of a stage unit and in stage
    units), and the USD step renders the add-on's layers, in metres and in centimetres."""
    for name, units in (("shot.usda", 1.0), ("shot_y_up_cm.usda", 100.0)):
        stage = Usd.Stage.Open(str(orthographic / name))
        camera = UsdGeom.Camera(stage.GetPrimAtPath("/root/Camera/Camera"))
        assert camera.GetProjectionAttr().Get() == UsdGeom.Tokens.orthographic
        settings = UsdRender.Settings.GetStageRenderSettings(stage)
        assert settings.GetCameraRel().GetTargets() == [camera.GetPath()]
        across = 16.0 * (WIDTH / HEIGHT) / 1.25
        assert camera.GetHorizontalApertureAttr().Get() == pytest.approx(10 * units * across)
        assert camera.GetVerticalApertureAttr().Get() == pytest.approx(10 * units * 16.0)
        offsets = (
            camera.GetHorizontalApertureOffsetAttr().Get(),
            camera.GetVerticalApertureOffsetAttr().Get(),
        )
        assert offsets == pytest.approx((10 * units * 16 * 0.06, -10 * units * 16 * 0.04))
        assert tuple(camera.GetClippingRangeAttr().Get()) == pytest.approx(
            (0.3 * units, 90.0 * units)
        )
        # The cards' cuts, which the exporter dropped: the hook's masks as their opacity,
        # read through a UsdTransform2d, or through coordinates mapped on the mesh.
        for material, wrap, varname in (
            ("Cutout_inverted", "clamp", "st"),
            ("Cutout_mix", "black", "crepuscular_st_Cutout_mix"),
        ):
            surface = UsdShade.Shader(
                stage.GetPrimAtPath(f"/root/_materials/{material}/Principled_BSDF")
            )
            (source,) = surface.GetInput("opacity").GetConnectedSources()[0]
            mask = UsdShade.Shader(source.source.GetPrim())
            assert mask.GetIdAttr().Get() == "UsdUVTexture"
            assert mask.GetInput("wrapS").Get() == wrap
            assert surface.GetInput("opacityThreshold").Get() == pytest.approx(0.5)
            assert (orthographic / mask.GetInput("file").Get().path).is_file()
            reader = stage.GetPrimAtPath(f"/root/_materials/{material}/crepuscular_uv")
            assert reader.GetAttribute("inputs:varname").Get() == varname
        # The bevelled curve and the NURBS sphere as meshes; the exporter's curves of the
        # circle's path (its radius as width) inactive.
        for mesh in ("ring", "SurfSphere"):
            assert stage.GetPrimAtPath(f"/root/crepuscularMeshes/{mesh}").IsA(UsdGeom.Mesh)
        exported = [
            prim
            for prim in Usd.PrimRange.AllPrims(stage.GetPrimAtPath("/root/ring"))
            if prim.IsA(UsdGeom.BasisCurves)
        ]
        assert exported
        assert not any(prim.IsActive() for prim in exported)
        # The particle fur, which the exporter left out: Catmull-Rom curves with widths.
        fur = UsdGeom.BasisCurves(stage.GetPrimAtPath("/root/fur/crepuscularHair"))
        assert fur.GetBasisAttr().Get() == UsdGeom.Tokens.catmullRom
        assert len(fur.GetWidthsAttr().Get()) == len(fur.GetPointsAttr().Get()) > 0
        # The dust geometry nodes make, which the exporter wrote as an empty mesh.
        dust = UsdGeom.Points(stage.GetPrimAtPath("/root/dust/crepuscularPoints"))
        assert len(dust.GetPointsAttr().Get()) == 40
        assert dust.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
        out = str(orthographic / name.replace(".usda", ".exr"))
        _render(orthographic / name, out)
        _assert_close(_errors(orthographic / "blender.0001.exr", Path(out)), name)


@pytest.fixture(scope="module")
def shadowless(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _round_trip(tmp_path_factory, "shadowless", animated=False, shadowless=True)


def test_a_sun_that_casts_no_shadows_renders_the_same(shadowless: Path, still: Path) -> None:
    """The sun's Cast Shadow off: the hook authors `inputs:shadow:enable` false (Blender's
    exporter writes none), and the USD step, like the add-on, lets nothing block the sun
    and the fog not dim it. The layers are not the still's (no shafts, brighter fog)."""
    stage = Usd.Stage.Open(str(shadowless / "shot.usda"))
    assert _light(stage).GetAttribute("inputs:shadow:enable").Get() is False
    _render(shadowless / "shot.usda", str(shadowless / "usd.exr"))
    blender = shadowless / "blender.0001.exr"
    _assert_close(_errors(blender, shadowless / "usd.exr"), "shadowless:")
    lit = crepuscular.read_exr(blender)["volume.G"]
    shafts = crepuscular.read_exr(still / "blender.0001.exr")["volume.G"]
    assert lit.mean() > 1.2 * shafts.mean()


def test_animated_export_renders_every_frame(animated: Path) -> None:
    """Camera, lens, sun and closing radius keyed over three frames, through 3:2 pixels
    (the hook's RenderSettings carry the pixel aspect, which Blender's exporter bakes into
    the apertures); the fog box is hidden from renders, so the exporter leaves it out and
    the hook authors its box."""
    _render(animated / "shot.usda", str(animated / "usd.####.exr"), "--frames", "1-3")
    for frame in (1, 2, 3):
        errors = _errors(animated / f"blender.{frame:04d}.exr", animated / f"usd.{frame:04d}.exr")
        _assert_close(errors, f"frame {frame}:")
    first = crepuscular.read_exr(animated / "blender.0001.exr")
    last = crepuscular.read_exr(animated / "blender.0003.exr")
    assert np.abs(first["depth"] - last["depth"]).max() > 0.1  # the camera moved


def _light(stage: Usd.Stage) -> Usd.Prim:
    lights = [p for p in stage.Traverse() if p.IsA(UsdLux.DistantLight)]
    assert len(lights) == 1
    return lights[0]


def test_hook_authors_the_schema(still: Path, animated: Path) -> None:
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(API_NAME)
    stage = Usd.Stage.Open(str(still / "shot.usda"))
    light = _light(stage)
    assert light.HasAPI(API_NAME)
    authored = [p for p in light.GetAuthoredPropertyNames() if p.startswith("crepuscular:")]
    assert "crepuscular:method" in authored
    for name in authored:
        assert name in definition.GetPropertyNames(), name
        if name in ATTRIBUTES:
            expected = definition.GetAttributeDefinition(name).GetTypeName()
            assert light.GetAttribute(name).GetTypeName() == expected, name
    # The exported fog mesh is the medium's box; the slat that takes holes gets them.
    extent = light.GetRelationship("crepuscular:mediumExtent").GetTargets()
    assert extent == [Sdf.Path("/root/Fog/Fog")]
    holes = light.GetRelationship("crepuscular:holes:objects").GetTargets()
    assert holes == [Sdf.Path("/root/slat_1")]
    values = {name: light.GetAttribute(name).Get() for name in authored}
    assert values["crepuscular:method"] == "prefiltered"
    assert values["crepuscular:exactRayEnds"] == "auto"
    assert values["crepuscular:supersampling"] == 2  # the add-on's edge samples
    assert values["crepuscular:intensityScale"] == pytest.approx(4.0)
    # Blender writes the lamp's Temperature checkbox as true; the hook writes its value.
    lux = UsdLux.LightAPI(light)
    assert lux.GetEnableColorTemperatureAttr().Get() is False
    assert lux.GetIntensityAttr().Get() == pytest.approx(2.5 / 4)  # Blender's own, untouched
    # Subdivision Surface modifiers written as cages carry their render levels; other
    # meshes carry none.
    levels = {
        str(prim.GetPath()): (
            prim.GetAttribute("crepuscular:subdivision:levels").Get(),
            prim.GetAttribute("crepuscular:subdivision:limitSurface").Get(),
        )
        for prim in stage.Traverse()
        if prim.HasAttribute("crepuscular:subdivision:levels")
    }
    assert levels == {
        "/root/capsule/Cylinder_001": (2, True),
        "/root/Rig/Cylinder/Cylinder": (1, True),
        "/root/pillow/Cube_001": (2, True),
        "/root/lantern/Sphere": (2, True),
    }
    # The capsule's corner stays; the pillow's creases, which its modifier ignores, are
    # blocked.
    capsule = UsdGeom.Mesh(stage.GetPrimAtPath("/root/capsule/Cylinder_001"))
    assert list(capsule.GetCornerSharpnessesAttr().Get()) == [10.0]
    pillow = UsdGeom.Mesh(stage.GetPrimAtPath("/root/pillow/Cube_001"))
    assert pillow.GetCreaseIndicesAttr().Get() is None
    assert pillow.GetCreaseSharpnessesAttr().Get() is None
    # The lantern's *UV Smooth*, which the USD step refines its coordinates by.
    lantern = UsdGeom.Mesh(stage.GetPrimAtPath("/root/lantern/Sphere"))
    assert lantern.GetFaceVaryingLinearInterpolationAttr().Get() == "none"
    # Animated: keyed values are time-sampled, constant ones are not; the fog box, left
    # out of the export, becomes a guide Cube.
    stage = Usd.Stage.Open(str(animated / "shot.usda"))
    light = _light(stage)
    radius = light.GetAttribute("crepuscular:closing:radius")
    assert radius.GetTimeSamples() == [1.0, 2.0, 3.0]
    assert radius.Get(Usd.TimeCode(2)) == pytest.approx(0.4)
    assert light.GetAttribute("crepuscular:medium:extinction").GetNumTimeSamples() == 0
    (cube_path,) = light.GetRelationship("crepuscular:mediumExtent").GetTargets()
    cube = stage.GetPrimAtPath(cube_path)
    assert cube.IsA(UsdGeom.Cube)
    assert UsdGeom.Imageable(cube).ComputePurpose() == UsdGeom.Tokens.guide
    # The render's image: the scene camera, its size and pixel aspect, and (on the still,
    # exported with one) its render region, from the bottom-left corner as Blender's: the
    # edges of the pixels Blender renders (columns 24 to 73, rows 5 to 31 from the
    # bottom), not the border's fractions (0.26 to 0.78 across, whose pixel centres are
    # columns 25 to 74).
    for out, aspect, window in (
        (still, 1.0, Gf.Vec4f(24 / WIDTH, 5 / HEIGHT, 74 / WIDTH, 32 / HEIGHT)),
        (animated, 1.5, None),
    ):
        stage = Usd.Stage.Open(str(out / "shot.usda"))
        settings = UsdRender.Settings.GetStageRenderSettings(stage)
        assert settings.GetPath() == Sdf.Path("/Render/settings")
        assert settings.GetCameraRel().GetTargets() == [Sdf.Path("/root/Camera/Camera")]
        assert tuple(settings.GetResolutionAttr().Get()) == (WIDTH, HEIGHT)
        assert settings.GetPixelAspectRatioAttr().Get() == pytest.approx(aspect)
        assert settings.GetDataWindowNDCAttr().HasAuthoredValue() == (window is not None)
        if window is not None:
            assert settings.GetDataWindowNDCAttr().Get() == window


def test_hook_names_are_the_usd_steps(installed: ModuleType) -> None:
    """The hook's attribute table is the USD package's own file, shipped in the zip."""
    shipped = Path(installed.__file__).parent / "usd_attributes.py"
    source = blender_scenes.ROOT / "usd" / "crepuscular_usd" / "attributes.py"
    assert shipped.read_bytes() == source.read_bytes()
    assert installed.usd_hook.ATTRIBUTES.keys() == ATTRIBUTES.keys()


def _scene_with_a_sun(shafts: bool) -> Any:
    scene = bpy.context.scene
    blender_scenes.add_camera(scene, blender_scenes.look_at((0, -10, 3), (0, 0, 1)))
    blender_scenes.add_sun(scene, (0.2, 0.3, -1.0), enabled=shafts)
    return scene


def test_export_without_shafts_is_left_alone(addon: ModuleType, tmp_path: Path) -> None:
    _scene_with_a_sun(shafts=False)
    path = tmp_path / "plain.usda"
    assert bpy.ops.wm.usd_export(filepath=str(path)) == {"FINISHED"}
    assert not _light(Usd.Stage.Open(str(path))).HasAPI(API_NAME)


def test_a_foreign_pxr_is_refused_by_name(
    addon: ModuleType, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """This process imported usd-core's pxr first: Blender's stage cannot reach the hook,
    and the export fails with a message saying so, instead of crashing."""
    _scene_with_a_sun(shafts=True)
    with pytest.raises(RuntimeError, match="USD hook"):
        bpy.ops.wm.usd_export(filepath=str(tmp_path / "shot.usda"))
    assert "not from Blender's own USD" in capfd.readouterr().err
