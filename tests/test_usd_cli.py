"""The `crepuscular-usd` command end to end: renders, compositing, output layer, errors."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdSkel, UsdValidation
from scenes import build_scene
from usd_helpers import author_rig, author_skinned_strip, author_stage

import crepuscular
from crepuscular_usd import StageReader
from crepuscular_usd.cli import main

SMALL = {"steps": 32, "shadow_map_size": 128}


def run(*argv: str) -> tuple[int, str]:
    """main() with its stderr captured."""
    err = io.StringIO()
    status = main(list(argv), stderr=err)
    return status, err.getvalue()


@pytest.fixture
def stage_path(tmp_path: Path) -> Path:
    path = tmp_path / "shot.usda"
    stage = author_stage(str(path), build_scene(**SMALL))
    light = stage.GetPrimAtPath("/World/Sun")
    # Animate the sun's strength so that frames differ.
    intensity = light.GetAttribute("inputs:intensity")
    intensity.Set(2.0, Usd.TimeCode(1))
    intensity.Set(6.0, Usd.TimeCode(5))
    stage.GetRootLayer().Save()
    return path


def render_args(stage_path: Path, out: Path, *extra: str) -> list[str]:
    return [
        "render",
        str(stage_path),
        "--camera",
        "/World/Camera",
        "--out",
        str(out / "shafts.####.exr"),
        "--width",
        "64",
        "--quiet",
        *extra,
    ]


def test_render_writes_each_frames_layers(stage_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    status, err = run(*render_args(stage_path, out, "--frames", "1-5x2"))
    assert status == 0, err
    assert sorted(os.listdir(out)) == ["shafts.0001.exr", "shafts.0003.exr", "shafts.0005.exr"]
    reader = StageReader(Usd.Stage.Open(str(stage_path)), "/World/Camera", None, width=64)
    for frame in (1, 3, 5):
        written = crepuscular.read_exr(out / f"shafts.{frame:04d}.exr")
        assert set(written) == {
            "volume.R",
            "volume.G",
            "volume.B",
            "volume.A",
            "visibility",
            "depth",
        }
        expected = crepuscular.render_arrays(**reader.read(Usd.TimeCode(frame)).render_kwargs())
        np.testing.assert_array_equal(written["volume.G"], expected.volume[..., 1])
        np.testing.assert_array_equal(written["depth"], expected.depth)
    first = crepuscular.read_exr(out / "shafts.0001.exr")["volume.R"]
    last = crepuscular.read_exr(out / "shafts.0005.exr")["volume.R"]
    np.testing.assert_allclose(last, 3.0 * first, rtol=1e-5)


def test_complexity_refines_catmull_clark_meshes_as_usdrecord_s(
    stage_path: Path, tmp_path: Path
) -> None:
    """`--complexity` (`-c`) low casts a Catmull-Clark occluder's cage, with a warning
    naming it and the option; high renders the layers of the mesh refined two levels, whose
    rounded corners (boundary edgeOnly) cast another shadow."""
    stage = Usd.Stage.Open(str(stage_path))
    occluder = UsdGeom.Mesh(stage.GetPrimAtPath("/World/occluder"))
    occluder.CreateSubdivisionSchemeAttr().Set(UsdGeom.Tokens.catmullClark)
    occluder.CreateInterpolateBoundaryAttr().Set(UsdGeom.Tokens.edgeOnly)
    stage.GetRootLayer().Save()
    written = {}
    for complexity in ("low", "high"):
        out = tmp_path / complexity
        status, err = run(*render_args(stage_path, out, "-f", "1", "-c", complexity))
        assert status == 0, err
        assert ("give --complexity medium, high or veryhigh" in err) == (complexity == "low")
        written[complexity] = crepuscular.read_exr(out / "shafts.0001.exr")["visibility"]
    reader = StageReader(stage, "/World/Camera", None, width=64, subdivision_levels=2)
    expected = crepuscular.render_arrays(**reader.read(Usd.TimeCode(1)).render_kwargs())
    np.testing.assert_array_equal(written["high"], expected.visibility)
    assert np.abs(written["high"] - written["low"]).mean() > 1e-3 * written["low"].mean()
    status, err = run(*render_args(stage_path, tmp_path / "bad", "-c", "ultra"))
    assert status == 2
    assert "invalid choice: 'ultra'" in err


def test_rerendering_a_frame_is_bit_identical(stage_path: Path, tmp_path: Path) -> None:
    for name in ("a", "b"):
        status, err = run(*render_args(stage_path, tmp_path / name, "--frames", "3"))
        assert status == 0, err
    a = (tmp_path / "a" / "shafts.0003.exr").read_bytes()
    assert a == (tmp_path / "b" / "shafts.0003.exr").read_bytes()


def test_progress_bar_and_timing_go_to_stderr(stage_path: Path, tmp_path: Path) -> None:
    args = [a for a in render_args(stage_path, tmp_path, "--frames", "1,2") if a != "--quiet"]
    status, err = run(*args)
    assert status == 0, err
    assert "100.0% frame 2" in err
    assert "read USD" in err


def test_exr_compression_applies_to_layers_and_composites(stage_path: Path, tmp_path: Path) -> None:
    frame = tmp_path / "beauty.0001.exr"
    rgba = np.full((36, 64), 0.5, dtype=np.float32)
    crepuscular.write_exr_channels(frame, {c: rgba for c in "RGBA"})
    out = tmp_path / "out"
    status, err = run(
        "render",
        str(stage_path),
        "--frames",
        "1",
        "--out",
        str(out / "shafts.####.exr"),
        "--beauty",
        str(tmp_path / "beauty.####.exr"),
        "--exr-compression",
        "piz",
        "--quiet",
    )
    assert status == 0, err
    piz = b"compression\0compression\0\x01\0\0\0\x04"
    assert piz in (out / "shafts.0001.exr").read_bytes()
    assert piz in (out / "comp.shafts.0001.exr").read_bytes()
    status, err = run(*render_args(stage_path, out, "-f", "1", "--exr-compression", "dwaa"))
    assert status == 2, err
    assert "invalid choice: 'dwaa'" in err, err


def test_hole_creation_that_reaches_no_mesh_warns(stage_path: Path, tmp_path: Path) -> None:
    stage = Usd.Stage.Open(str(stage_path))
    light = stage.GetPrimAtPath("/World/Sun")
    assert light.GetAttribute("crepuscular:holes:enable").Set(True)
    targets = light.CreateRelationship("crepuscular:holes:objects")
    cases = [
        ([], "crepuscular:holes:objects names no prim: no holes are made"),
        (
            ["/World/Nowhere"],
            "crepuscular:holes:objects (/World/Nowhere) holds no rendered mesh: no holes are made",
        ),
        (["/World/occluder"], None),
    ]
    for paths, warning in cases:
        assert targets.SetTargets(paths)
        assert stage.GetRootLayer().Save()
        status, err = run(*render_args(stage_path, tmp_path / "out", "-f", "1"))
        assert status == 0, err
        if warning is None:
            assert "holes" not in err, err
        else:
            assert f"crepuscular-usd: warning: hole creation is on, but {warning}" in err, err


def test_a_sun_disc_wider_than_the_sun_s_softens_the_shafts(
    stage_path: Path, tmp_path: Path
) -> None:
    status, err = run(*render_args(stage_path, tmp_path / "out", "-f", "1"))
    assert status == 0, err
    assert "disc" not in err, err
    stage = Usd.Stage.Open(str(stage_path))
    assert UsdLux.DistantLight(stage.GetPrimAtPath("/World/Sun")).GetAngleAttr().Set(4.0)
    assert stage.GetRootLayer().Save()
    status, err = run(*render_args(stage_path, tmp_path / "out", "-f", "1"))
    assert status == 0, err
    warning = "crepuscular-usd: warning: the 4.0° disc of /World/Sun softens the shafts: 16"
    assert warning in err, err


def test_beauty_composite_uses_the_beauty_depth(stage_path: Path, tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    height, width = 36, 64
    rng = np.random.default_rng(3)
    beauty = rng.uniform(0.0, 1.0, (height, width, 4)).astype(np.float32)
    beauty[..., 3] = 1.0
    # A planar depth pass (view-axis distance) nearer than the scene: shorter shafts.
    depth = np.full((height, width), 4.0, dtype=np.float32)
    for frame in (2, 3):
        channels = {c: beauty[..., i] for i, c in enumerate("RGBA")}
        channels["ViewLayer.Depth.Z"] = depth
        crepuscular.write_exr_channels(tmp_path / f"beauty.{frame:04d}.exr", channels)
    out = tmp_path / "out"
    status, err = run(
        "render",
        str(stage_path),
        "--frames",
        "2-3",
        "--out",
        str(out / "shafts.####.exr"),
        "--beauty",
        str(tmp_path / "beauty.####.exr"),
        "--quiet",
    )
    assert status == 0, err
    reader = StageReader(Usd.Stage.Open(str(stage_path)), "/World/Camera", None, width=width)
    frame = reader.read(Usd.TimeCode(3))
    assert (frame.camera["width"], frame.camera["height"]) == (width, height)
    expected = crepuscular.render_arrays(
        **frame.render_kwargs(), camera_depth=depth, depth_kind="planar"
    )
    layers = crepuscular.read_exr(out / "shafts.0003.exr")
    np.testing.assert_array_equal(layers["volume.A"], expected.volume[..., 3])
    no_depth = crepuscular.render_arrays(**frame.render_kwargs())
    assert float(np.abs(no_depth.volume[..., 3] - expected.volume[..., 3]).max()) > 1e-3
    comp = crepuscular.read_exr(out / "comp.shafts.0003.exr")
    over = crepuscular.composite(expected.volume, beauty)
    for i, channel in enumerate("RGBA"):
        np.testing.assert_allclose(comp[channel], over[..., i], rtol=1e-6, atol=1e-7)
    assert scene["camera"]["width"] == width


def _validation_errors(stage: Usd.Stage) -> list[str]:
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [
        error.GetMessage()
        for error in context.Validate(stage)
        if error.GetType() == UsdValidation.ValidationErrorType.Error
    ]


def test_output_layer_validates_and_points_at_the_files(stage_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "renders"
    beauty = np.ones((36, 64), dtype=np.float32)
    for frame in (1, 2):
        crepuscular.write_exr_channels(
            tmp_path / f"b.{frame}.exr", {"R": beauty, "G": beauty, "B": beauty}
        )
    layer_path = tmp_path / "layers" / "shafts.usda"
    status, err = run(
        *render_args(
            stage_path,
            out,
            "--frames",
            "1,2",
            "--out-layer",
            str(layer_path),
            "--beauty",
            str(tmp_path / "b.#.exr"),
            "--comp",
            str(out / "comp.####.exr"),
        )
    )
    assert status == 0, err
    layer = Usd.Stage.Open(str(layer_path))
    assert layer, "the output layer does not open"
    assert _validation_errors(layer) == []
    products = UsdRender.Settings(layer.GetPrimAtPath("/Render/CrepuscularSettings"))
    assert [str(p) for p in products.GetProductsRel().GetTargets()] == [
        "/Render/Products/shafts",
        "/Render/Products/composite",
    ]
    var_names = set()
    for product_path in products.GetProductsRel().GetTargets():
        product = UsdRender.Product(layer.GetPrimAtPath(product_path))
        assert product.GetResolutionAttr().Get() == Gf.Vec2i(64, 36)
        for var_path in product.GetOrderedVarsRel().GetTargets():
            var = layer.GetPrimAtPath(var_path)
            var_names.add(var.GetName())
            file_attr = var.GetAttribute("crepuscular:file")
            assert file_attr.GetTimeSamples() == [1.0, 2.0]
            for frame in (1.0, 2.0):
                asset = file_attr.Get(Usd.TimeCode(frame))
                assert asset.resolvedPath, asset
                assert Path(asset.resolvedPath).is_file()
                channels = crepuscular.read_exr(asset.resolvedPath)
                assert set(var.GetAttribute("crepuscular:channels").Get()) <= set(channels)
                name = product.GetProductNameAttr().Get(Usd.TimeCode(frame))
                assert (layer_path.parent / name).resolve() == Path(asset.resolvedPath).resolve()
    assert var_names == {"volume", "visibility", "depth", "composite"}
    # The exact settings per frame: the scene description (without meshes) that rendered it.
    settings = layer.GetPrimAtPath("/Render/CrepuscularSettings")
    recorded = json.loads(settings.GetAttribute("crepuscular:sceneSettings").Get(2.0))
    reader = StageReader(Usd.Stage.Open(str(stage_path)), "/World/Camera", None, width=64)
    assert recorded == json.loads(json.dumps(reader.read(Usd.TimeCode(2)).settings_record()))
    assert recorded["sun"]["strength"] == pytest.approx(3.0)
    # Sublayered into the shot, the products' camera resolves to the shot's camera.
    shot = Usd.Stage.Open(str(stage_path))
    shot.GetRootLayer().subLayerPaths.append(str(layer_path))
    camera = UsdRender.Product(shot.GetPrimAtPath("/Render/Products/shafts")).GetCameraRel()
    assert shot.GetPrimAtPath(camera.GetTargets()[0]).IsA(UsdGeom.Camera)


def test_apply_schema_authors_the_defaults(stage_path: Path, tmp_path: Path) -> None:
    stage = Usd.Stage.Open(str(stage_path))
    UsdLux.DistantLight.Define(stage, "/World/Moon")
    UsdGeom.Cube.Define(stage, "/World/Fog")
    stage.GetRootLayer().Save()
    edited = tmp_path / "edited.usda"
    status, err = run(
        "apply-schema",
        str(stage_path),
        "--light",
        "/World/Moon",
        "--medium-extent",
        "/World/Fog",
        "-o",
        str(edited),
    )
    assert status == 0, err
    edited_stage = Usd.Stage.Open(str(edited))
    moon = edited_stage.GetPrimAtPath("/World/Moon")
    assert moon.HasAPI("CrepuscularLightAPI")
    assert moon.GetAttribute("crepuscular:medium:extinction").HasAuthoredValue()
    assert moon.GetAttribute("crepuscular:method").Get() == "prefiltered"
    assert [str(t) for t in moon.GetRelationship("crepuscular:mediumExtent").GetTargets()] == [
        "/World/Fog"
    ]
    status, err = run("apply-schema", str(stage_path), "--light", "/World/Camera")
    assert status == 1
    assert "/World/Camera is a Camera; CrepuscularLightAPI applies to DistantLight only" in err


def test_stage_without_the_api_warns_once(tmp_path: Path) -> None:
    path = tmp_path / "plain.usda"
    stage = author_stage(str(path), build_scene(**SMALL), apply_api=False)
    UsdGeom.NurbsCurves.Define(stage, "/World/Wire")
    UsdGeom.BasisCurves.Define(stage, "/World/Hair")  # drawn (with no points, nothing)
    UsdGeom.Points.Define(stage, "/World/Dust")  # drawn (with no points, nothing)
    UsdGeom.NurbsCurves.Define(stage, "/World/Wire2")
    UsdGeom.Sphere.Define(stage, "/World/Ball")  # drawn, not skipped
    UsdLux.SphereLight.Define(stage, "/World/Lamp")
    stage.GetRootLayer().Save()
    light = stage.GetPrimAtPath("/World/Sun")
    assert not light.HasAPI("CrepuscularLightAPI")
    status, err = run(*render_args(path, tmp_path / "o", "--frames", "1-3", "--height", "36"))
    assert status == 0, err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 2, err
    assert "/World/Sun has no CrepuscularLightAPI" in warnings[0]
    assert warnings[1].endswith("skipped 3 unsupported prims: 2 NurbsCurves, 1 SphereLight")


def test_an_unusable_mesh_is_named_and_the_rest_renders(tmp_path: Path) -> None:
    """A skinned mesh whose joint influences do not fit its points: the warning names it
    and why, and the frame renders without it."""
    path = tmp_path / "rig.usda"
    stage = author_stage(str(path), build_scene(**SMALL))
    skeleton = author_rig(stage, "/World/Rig", {1.0: 30.0})
    author_skinned_strip(stage, "/World/Rig/Strip", skeleton)
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/World/Rig/Strip"))
    binding.GetJointIndicesPrimvar().Set([0] * 10)
    binding.GetJointWeightsPrimvar().Set([1.0] * 10)
    stage.GetRootLayer().Save()
    status, err = run(*render_args(path, tmp_path / "o", "--frames", "1", "--height", "36"))
    assert status == 0, err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert warnings == [
        "crepuscular-usd: warning: skipped 1 unsupported prims: 1 invalid Mesh",
        "crepuscular-usd: warning: /World/Rig/Strip: its 6 points could not be skinned (do its "
        "joint influences match its points and its skeleton's joints?)",
    ], err
    assert len(list((tmp_path / "o").iterdir())) == 1


def test_a_mesh_animated_into_nan_is_named_at_its_frame(tmp_path: Path) -> None:
    """An occluder whose points are NaN at frame 2 of 3 is left out of that frame alone,
    with a warning that names the frame; before, it vanished from it unsaid."""
    path = tmp_path / "shot.usda"
    stage = author_stage(str(path), build_scene(**SMALL))
    points = stage.GetPrimAtPath("/World/occluder").GetAttribute("points")
    authored = points.Get()
    broken = [Gf.Vec3f(float("nan"))] * len(authored)
    for frame, value in ((1.0, authored), (2.0, broken), (3.0, authored)):
        assert points.Set(value, frame)
    assert stage.GetRootLayer().Save()
    out = tmp_path / "o"
    status, err = run(*render_args(path, out, "--frames", "1-3", "--height", "36"))
    assert status == 0, err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert warnings == [
        f"crepuscular-usd: warning: frame 2: /World/occluder: {len(authored)} of its "
        f"{len(authored)} placed points are not finite (NaN or infinite points, widths, radii, "
        "transforms or instance attributes)"
    ], err
    # Frame 2 is the frame without the occluder; the others keep it.
    assert stage.GetPrimAtPath("/World/occluder").SetActive(False)
    assert stage.GetRootLayer().Export(str(tmp_path / "without.usda"))
    status, err = run(
        *render_args(tmp_path / "without.usda", tmp_path / "w", "--frames", "2", "--height", "36")
    )
    assert status == 0, err
    frames = [crepuscular.read_exr(out / f"shafts.{frame:04d}.exr") for frame in (1, 2, 3)]
    without = crepuscular.read_exr(tmp_path / "w" / "shafts.0002.exr")
    for name, plane in without.items():
        np.testing.assert_array_equal(frames[1][name], plane, err_msg=name)
        np.testing.assert_array_equal(frames[0][name], frames[2][name], err_msg=name)
    assert not np.array_equal(frames[0]["volume.R"], frames[1]["volume.R"])


# --- bad input ----------------------------------------------------------------------------


def test_bad_input_exit_codes_and_messages(stage_path: Path, tmp_path: Path) -> None:
    out = str(tmp_path / "o" / "s.####.exr")
    base = ["render", str(stage_path), "--out", out, "--width", "64", "--quiet"]
    corrupt = tmp_path / "corrupt.usda"
    corrupt.write_text('#usda 1.0\ndef Mesh "broken" {\n  int = \n')
    cases = [
        (
            ["render", str(tmp_path / "missing.usda"), "--out", out, "-f", "1"],
            1,
            "missing.usda: no such file",
        ),
        (["render", str(corrupt), "--out", out, "-f", "1"], 1, "corrupt.usda:3:"),
        ([*base, "-f", "1", "--beauty", out], 2, "must be different paths"),
        ([*base, "-f", "1", "--camera", "/World/Nope"], 1, "camera /World/Nope does not exist"),
        ([*base, "-f", "1", "--camera", "/World/Sun"], 1, "is a DistantLight, not a Camera"),
        ([*base, "-f", "1", "--camera", "World"], 1, "'World' is not an absolute prim path"),
        ([*base, "-f", "1", "--light", "/World/Gone"], 1, "light /World/Gone does not exist"),
        ([*base, "-f", "1", "--light", "/World/ground"], 1, "is a Mesh, not a DistantLight"),
        ([*base, "-f", "1-x"], 2, "invalid FrameSpec '1-x'"),
        ([*base, "-f", "1-10x0"], 2, "stride is 0"),
        ([*base, "-f", "1-2x0.5"], 2, "need 1 decimal(s)"),
        (["render", str(stage_path), "--out", "s.exr", "-f", "1"], 2, "frame placeholder"),
        (["render", str(stage_path), "--out", out], 2, "no --frames were given"),
        ([*base, "-f", "1", "-d"], 2, "not allowed with argument"),
        ([*base, "-f", "1", "--height", "0"], 2, "--height 0 is outside"),
        ([*base, "-f", "1", "--comp", "c.####.exr"], 2, "--comp needs --beauty"),
        ([*base, "-f", "1", "--beauty", str(tmp_path / "b.####.exr")], 1, "b.0001.exr does not"),
        (["render", str(stage_path)], 2, "the following arguments are required: --out"),
    ]
    for argv, status, message in cases:
        got, err = run(*argv)
        assert (got, message in err) == (status, True), (argv, err)
        assert err.startswith("crepuscular-usd: error: "), err
        assert len(err.strip().splitlines()) == 1, err


def test_bad_stage_content_exit_codes_and_messages(stage_path: Path, tmp_path: Path) -> None:
    out = str(tmp_path / "o" / "s.####.exr")
    stage = Usd.Stage.Open(str(stage_path))
    light = stage.GetPrimAtPath("/World/Sun")

    def check(message: str) -> None:
        stage.GetRootLayer().Save()
        status, err = run("render", str(stage_path), "--out", out, "-f", "1", "--width", "8", "-q")
        assert status == 1, err
        assert message in err, err

    light.GetAttribute("crepuscular:method").Set("fastest")
    check("/World/Sun.crepuscular:method: 'fastest' is not one of reference, minmax, prefiltered")
    light.GetAttribute("crepuscular:method").Set("reference")
    light.GetAttribute("crepuscular:medium:anisotropy").Set(1.5)
    # The renderer's own checks are named by the attribute that fed them.
    check("frame 1: /World/Sun.crepuscular:medium:anisotropy: invalid medium.anisotropy")
    light.GetAttribute("crepuscular:medium:anisotropy").Set(0.0)
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([Sdf.Path("/World/NoFog")])
    check("crepuscular:mediumExtent targets /World/NoFog, which does not exist")
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([Sdf.Path("/World/Camera")])
    check("medium extent /World/Camera is a Camera")
    light.GetRelationship("crepuscular:mediumExtent").ClearTargets(True)
    light.GetAttribute("crepuscular:tf:json").Set("{not json")
    check("/World/Sun.crepuscular:tf:json: not JSON")
    light.GetAttribute("crepuscular:tf:json").Set("")
    light.GetAttribute("crepuscular:tf:asset").Set(Sdf.AssetPath("missing.json"))
    check("crepuscular:tf:asset: cannot resolve @missing.json@")
    light.GetAttribute("crepuscular:tf:asset").Set(Sdf.AssetPath(""))
    for mesh in ("ground", "occluder"):
        UsdGeom.Imageable(stage.GetPrimAtPath(f"/World/{mesh}")).MakeInvisible()
    check("no visible mesh triangles")
    stage.GetRootLayer().Save()
    no_light = tmp_path / "nolight.usda"
    shutil.copy(stage_path, no_light)
    lightless = Usd.Stage.Open(str(no_light))
    lightless.RemovePrim("/World/Sun")
    lightless.GetRootLayer().Save()
    status, err = run("render", str(no_light), "--out", out, "-f", "1")
    assert status == 1
    assert "give --light: the stage has 0 DistantLights (none)" in err


def test_console_script_runs_in_a_subprocess(stage_path: Path, tmp_path: Path) -> None:
    script = shutil.which("crepuscular-usd", path=os.path.dirname(sys.executable))
    assert script is not None, "crepuscular-usd is not installed next to this Python"
    result = subprocess.run(
        [script, *render_args(stage_path, tmp_path, "--frames", "4", "--out-layer", "l.usda")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "shafts.0004.exr").is_file()
    assert (tmp_path / "l.usda").is_file()
    failed = subprocess.run(
        [script, "render", str(stage_path), "--out", "x.####.exr", "-f", "1:"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert failed.returncode == 2
    assert "invalid FrameSpec '1:'" in failed.stderr


def test_without_frames_renders_the_start_time_code(stage_path: Path, tmp_path: Path) -> None:
    stage = Usd.Stage.Open(str(stage_path))
    stage.SetStartTimeCode(5)
    stage.SetEndTimeCode(5)
    stage.GetRootLayer().Save()
    out = tmp_path / "still.exr"
    status, err = run("render", str(stage_path), "--out", str(out), "--width", "64", "-q")
    assert status == 0, err
    at_five = crepuscular.render_arrays(
        **StageReader(stage, "/World/Camera", None, width=64).read(Usd.TimeCode(5)).render_kwargs()
    )
    np.testing.assert_array_equal(crepuscular.read_exr(out)["volume.B"], at_five.volume[..., 2])
    layer_path = tmp_path / "default.usda"
    status, err = run(
        "render",
        str(stage_path),
        "-d",
        "--out",
        str(out),
        "--width",
        "64",
        "-q",
        "--out-layer",
        str(layer_path),
    )
    assert status == 0, err
    layer = Usd.Stage.Open(str(layer_path))
    product = UsdRender.Product(layer.GetPrimAtPath("/Render/Products/shafts"))
    assert product.GetProductNameAttr().Get() == "./still.exr"
    assert product.GetProductNameAttr().GetTimeSamples() == []


def test_a_fog_box_no_view_ray_reaches_is_named(stage_path: Path, tmp_path: Path) -> None:
    stage = Usd.Stage.Open(str(stage_path))
    fog = UsdGeom.Cube.Define(stage, "/World/Fog")
    fog.CreateSizeAttr(6.0)
    where = fog.AddTranslateOp()
    light = stage.GetPrimAtPath("/World/Sun")
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([fog.GetPath()])
    warning = "no view ray reaches the fog box /World/Fog: the frame has no fog"
    for offset, named in ((Gf.Vec3d(0.0, 1.0, 0.0), False), (Gf.Vec3d(0.0, 1.0, 1e4), True)):
        assert where.Set(offset)
        assert stage.GetRootLayer().Save()
        status, err = run(*render_args(stage_path, tmp_path / "o", "--frames", "1-2"))
        assert status == 0, err
        # Once per run, not per frame.
        assert err.count(warning) == (1 if named else 0), err
