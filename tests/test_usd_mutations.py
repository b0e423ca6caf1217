"""Stages mutated one attribute at a time: every authored value of a stage with fog, hair,
points, an instancer, a sphere, cut cards (a texture's alpha and a constant opacity) and
every style set, replaced in turn by zeros, negatives, NaN, huge values, empty or short
arrays, unknown tokens and broken xformOpOrders, must render to finite layers or end
`crepuscular-usd` with one line that names the prim or property to fix (and the frame,
where the bad value is one sample of an animation). Nothing may escape as a Python
exception, as it would end a render farm's job with a traceback."""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt
from scenes import build_scene
from usd_helpers import author_stage, cut_material, write_alpha_png

import crepuscular
from crepuscular_usd.cli import main

NAN = math.nan

# Bad values are named once, by the step: not also by numpy on their way there.
pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def _rich_stage(path: Path) -> Usd.Stage:
    stage = author_stage(str(path), build_scene(steps=16, shadow_map_size=64), method="prefiltered")
    light = stage.GetPrimAtPath("/World/Sun")
    for name, value in {
        "crepuscular:closing:enable": True,
        "crepuscular:closing:radius": 0.3,
        "crepuscular:silhouette:enable": True,
        "crepuscular:silhouette:length": 0.5,
        "crepuscular:holes:enable": True,
        "crepuscular:bases": 8,
    }.items():
        assert light.GetAttribute(name).Set(value)
    light.GetRelationship("crepuscular:holes:objects").SetTargets([Sdf.Path("/World/occluder")])
    fog = UsdGeom.Cube.Define(stage, "/World/Fog")
    fog.CreateSizeAttr(8.0)
    fog.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.0))
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([fog.GetPath()])
    hair = UsdGeom.BasisCurves.Define(stage, "/World/Hair")
    hair.CreatePointsAttr([Gf.Vec3f(x, 2.0, z) for x in (0.0, 0.5) for z in (0.0, 1.0, 2.0, 3.0)])
    hair.CreateCurveVertexCountsAttr([4, 4])
    hair.CreateTypeAttr(UsdGeom.Tokens.cubic)
    hair.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
    hair.CreateWidthsAttr([0.05])
    dust = UsdGeom.Points.Define(stage, "/World/Dust")
    dust.CreatePointsAttr([Gf.Vec3f(-1.0, 1.5, 1.0), Gf.Vec3f(1.0, 1.0, 2.0)])
    dust.CreateWidthsAttr([0.2, 0.4])
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(0.4)
    ball.AddTranslateOp().Set(Gf.Vec3d(2.0, 2.0, 1.0))
    box = UsdGeom.Cube.Define(stage, "/World/Prototypes/Box")
    box.CreateSizeAttr(0.3)
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Boxes")
    instancer.CreatePrototypesRel().SetTargets([box.GetPath()])
    instancer.CreateProtoIndicesAttr([0, 0])
    instancer.CreatePositionsAttr([Gf.Vec3f(-2.0, 2.5, 0.0), Gf.Vec3f(-2.0, 2.5, 1.0)])
    instancer.CreateOrientationsAttr(Vt.QuathArray([Gf.Quath(1.0), Gf.Quath(1.0)]))
    instancer.CreateScalesAttr([Gf.Vec3f(1.0), Gf.Vec3f(2.0)])
    # A card cut by a texture's alpha, and one of a constant opacity.
    stripes = np.array([[0, 1, 0, 1, 0, 1, 0, 1]], dtype=np.float32)
    leaf = cut_material(
        stage, "/World/Looks/Leaf", write_alpha_png(path.parent / "leaf.png", stripes)
    )
    veil = UsdShade.Material.Define(stage, "/World/Looks/Veil")
    surface = UsdShade.Shader.Define(stage, "/World/Looks/Veil/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.3)
    veil.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    for name, x, material in (("Card", -1.0, leaf), ("Veiled", 1.5, veil)):
        card = UsdGeom.Mesh.Define(stage, f"/World/{name}")
        card.CreatePointsAttr([(x, 3, 0), (x + 1, 3, 0), (x + 1, 3, 2), (x, 3, 2)])
        card.CreateFaceVertexCountsAttr([4])
        card.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        st = UsdGeom.PrimvarsAPI(card).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
        )
        st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
        UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material)
    assert stage.GetRootLayer().Save()
    return stage


def _scalars(type_name: Sdf.ValueTypeName, value: object) -> list[object]:
    """Replacements for a value of one of the scalar types."""
    scalar = type_name.scalarType
    if scalar in (Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Double, Sdf.ValueTypeNames.Half):
        return [0.0, -1.0, NAN, math.inf, 1e30]
    if scalar in (Sdf.ValueTypeNames.Int, Sdf.ValueTypeNames.UInt):
        return [0, -1, 2**31 - 1] if scalar == Sdf.ValueTypeNames.Int else [0, 2**32 - 1]
    if scalar == Sdf.ValueTypeNames.Bool:
        return [not value]
    if scalar in (Sdf.ValueTypeNames.Token, Sdf.ValueTypeNames.String):
        return ["bogus", "", "{not json"]
    if scalar == Sdf.ValueTypeNames.Asset:
        return [Sdf.AssetPath("missing.json")]
    if scalar == Sdf.ValueTypeNames.Matrix4d:
        return [Gf.Matrix4d(0.0), Gf.Matrix4d(NAN), Gf.Matrix4d(1e20)]
    if scalar == Sdf.ValueTypeNames.Quath:
        return [Gf.Quath(0.0), Gf.Quath(NAN)]
    if hasattr(value, "__len__"):
        size = len(value)  # type: ignore[arg-type]
        return [type(value)(*[x] * size) for x in (0.0, -1.0, NAN, 1e30)]
    raise AssertionError(f"no replacements for {type_name}")


def _replacements(attribute: Usd.Attribute) -> Iterator[object]:
    type_name = attribute.GetTypeName()
    value = attribute.Get()
    if not type_name.isArray:
        yield from _scalars(type_name, value)
        return
    items = list(value)
    yield []
    if items:
        yield items[:-1]
        for replacement in _scalars(type_name.scalarType, items[0]):
            yield [replacement] * len(items)
    if type_name == Sdf.ValueTypeNames.IntArray:
        yield [10**6] * max(len(items), 1)


def _targets(stage: Usd.Stage) -> Iterator[tuple[str, str]]:
    for prim in stage.Traverse():
        for attribute in prim.GetAttributes():
            if attribute.HasAuthoredValue():
                yield str(prim.GetPath()), attribute.GetName()


def _chosen(prim_name: str) -> Callable[[str], bool]:
    """Whether a prim's path is in the named group of the stage's prims."""
    groups = {
        "Sun": ["/World/Sun"],
        "Camera": ["/World/Camera"],
        "meshes": ["/World/ground", "/World/occluder"],
    }
    if prim_name in groups:
        return lambda path: path in groups[prim_name]
    return lambda path: not any(path in paths for paths in groups.values())


def _mutations_fail(tmp_path: Path, prim_name: str, *, animated: bool) -> list[str]:
    """Renders the stage once per mutation of each attribute of the group's prims: set as
    its value, or `animated` as its sample at frame 2 of 3, the others as authored. Returns
    what went wrong: a render that is not finite, an exception, or an error that names no
    prim or property (nor the frame, when animated). Of an animated range, the frames
    before a failing one must still be written."""
    path = tmp_path / "shot.usda"
    stage = _rich_stage(path)
    layer = stage.GetRootLayer()
    pristine = layer.ExportToString()
    out = tmp_path / "out" / "shafts.####.exr"
    frames = ["1", "2", "3"] if animated else ["1"]
    argv = ["render", str(path), "--out", str(out), "-f", f"{frames[0]}-{frames[-1]}"]
    argv += ["--width", "24", "-q", "--camera", "/World/Camera", "--light", "/World/Sun"]
    chosen = _chosen(prim_name)
    failures = []
    tried = rendered = 0
    for prim_path, name in list(_targets(stage)):
        if not chosen(prim_path):
            continue
        attribute = stage.GetPrimAtPath(prim_path).GetAttribute(name)
        if animated and attribute.GetVariability() == Sdf.VariabilityUniform:
            continue
        for replacement in list(_replacements(attribute)):
            assert layer.ImportFromString(pristine)
            attribute = stage.GetPrimAtPath(prim_path).GetAttribute(name)
            what = f"{prim_path}.{name} = {replacement!r}"[:160]
            if animated:
                authored = attribute.Get()
                samples = {1.0: authored, 2.0: replacement, 3.0: authored}
                ok = all(attribute.Set(value, time) for time, value in samples.items())
            else:
                ok = attribute.Set(replacement)
            if not ok:
                failures.append(f"{what}: could not be authored")
                continue
            assert layer.Save()
            for written in out.parent.glob("*.exr"):
                written.unlink()
            tried += 1
            err = io.StringIO()
            try:
                status = main(argv, stderr=err)
            except Exception as error:
                failures.append(f"{what}: raised {type(error).__name__}: {error}")
                continue
            lines = [line for line in err.getvalue().splitlines() if "error" in line]
            written = sorted(p.name for p in out.parent.glob("*.exr"))
            if status == 0:
                rendered += 1
                if written != [f"shafts.{int(f):04d}.exr" for f in frames]:
                    failures.append(f"{what}: rendered, but wrote {written}")
                for frame in written:
                    layers = crepuscular.read_exr(out.parent / frame)
                    if not all(np.isfinite(channel).all() for channel in layers.values()):
                        failures.append(f"{what}: rendered non-finite layers")
            elif status != 1 or len(lines) != 1 or "Traceback" in err.getvalue():
                failures.append(f"{what}: status {status}, {err.getvalue()!r}")
            elif "/World/" not in lines[0]:
                # The message must lead to what to fix: a prim or one of its properties.
                failures.append(f"{what}: names no prim: {lines[0]!r}")
            elif animated and ("frame 2: " not in lines[0] or written != ["shafts.0001.exr"]):
                failures.append(f"{what}: wrote {written}, and said {lines[0]!r}")
    assert layer.ImportFromString(pristine)
    assert tried > 0
    assert rendered > 0
    return failures


@pytest.mark.parametrize("prim_name", ["Sun", "Camera", "meshes", "others"])
def test_mutated_stages_render_or_say_what_is_wrong(tmp_path: Path, prim_name: str) -> None:
    failures = _mutations_fail(tmp_path, prim_name, animated=False)
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("prim_name", ["Sun", "Camera", "meshes", "others"])
def test_a_mutation_at_one_frame_is_named_with_its_frame(tmp_path: Path, prim_name: str) -> None:
    """A farm renders ranges of an animated stage: a value wrong at frame 2 must say so,
    and frame 1 must be on disk."""
    failures = _mutations_fail(tmp_path, prim_name, animated=True)
    assert not failures, "\n".join(failures)
