"""Authoring real USD stages from the tests' scene descriptions.

`author_stage` writes a scene description (renderer space: Z up, metres) as a USD stage
with any up axis and metersPerUnit, converting every point, transform and length, so
that reading it back must give the same frame.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel

import crepuscular_usd

# Stage space from renderer space, without the scale: the inverse of the +90 degree
# rotation about X that takes a Y-up stage to Z up.
_Y_UP_FROM_Z_UP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)


def stage_rotation(up: str) -> np.ndarray:
    return _Y_UP_FROM_Z_UP if up == "Y" else np.eye(3)


def _gf_rows(column_major: list[float]) -> Gf.Matrix4d:
    """A Gf matrix (row vectors) from a column-major 4x4 (column vectors)."""
    return Gf.Matrix4d(*[float(v) for v in column_major])


def author_stage(
    path: str,
    scene: dict[str, Any],
    *,
    up: str = "Z",
    meters_per_unit: float = 1.0,
    apply_api: bool = True,
    method: str = "reference",
) -> Usd.Stage:
    """Writes `scene` to a new stage at `path` with the given up axis and units."""
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    rotation = stage_rotation(up)
    scale = 1.0 / meters_per_unit
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    for mesh_desc in scene["meshes"]:
        mesh = UsdGeom.Mesh.Define(stage, f"/World/{mesh_desc['name']}")
        local = np.asarray(mesh_desc["positions"], dtype=np.float64)
        matrix = (
            np.asarray(mesh_desc.get("world_from_object", np.eye(4).ravel()), dtype=np.float64)
            .reshape(4, 4)
            .T
        )
        points = (local @ matrix[:3, :3].T + matrix[:3, 3]) @ rotation.T * scale
        mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in points])
        triangles = np.asarray(mesh_desc["triangles"], dtype=np.int64)
        mesh.CreateFaceVertexCountsAttr([3] * len(triangles))
        mesh.CreateFaceVertexIndicesAttr([int(i) for i in triangles.ravel()])
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    author_camera(stage, "/World/Camera", scene["camera"], up=up, meters_per_unit=meters_per_unit)
    author_light(stage, "/World/Sun", scene["sun"], up=up)
    if apply_api:
        light = stage.GetPrimAtPath("/World/Sun")
        crepuscular_usd.apply_schema(light)
        render = scene.get("render", {})
        medium = scene["medium"]
        values = {
            "crepuscular:medium:extinction": medium["extinction"] * meters_per_unit,
            "crepuscular:medium:anisotropy": medium.get("anisotropy", 0.0),
            "crepuscular:method": method,
            "crepuscular:shadowMapSize": render.get("shadow_map_size", 1024),
            "crepuscular:steps": render.get("steps", 2048),
            "crepuscular:maxDistance": render.get("max_distance", 100.0) * scale,
        }
        for name, value in values.items():
            light.GetAttribute(name).Set(value)
    stage.GetRootLayer().Save()
    return stage


def author_camera(
    stage: Usd.Stage,
    path: str,
    camera: dict[str, Any],
    *,
    up: str = "Z",
    meters_per_unit: float = 1.0,
    time: Usd.TimeCode | None = None,
) -> UsdGeom.Camera:
    """A UsdGeom.Camera matching a horizontally fitted perspective camera description."""
    time = time if time is not None else Usd.TimeCode.Default()
    usd_camera = UsdGeom.Camera.Define(stage, path)
    matrix = np.asarray(camera["world_from_camera"], dtype=np.float64).reshape(4, 4).T
    rotation = stage_rotation(up)
    stage_matrix = np.eye(4)
    stage_matrix[:3, :3] = rotation @ matrix[:3, :3]
    stage_matrix[:3, 3] = rotation @ matrix[:3, 3] / meters_per_unit
    op = _transform_op(usd_camera)
    op.Set(_gf_rows(list(stage_matrix.flatten(order="F"))), time)
    projection = camera["projection"]
    sensor = projection.get("sensor_width", 36.0)
    usd_camera.CreateFocalLengthAttr().Set(projection["focal_length"], time)
    usd_camera.CreateHorizontalApertureAttr().Set(sensor, time)
    usd_camera.CreateVerticalApertureAttr().Set(sensor * camera["height"] / camera["width"], time)
    usd_camera.CreateClippingRangeAttr().Set(
        Gf.Vec2f(camera["clip_start"] / meters_per_unit, camera["clip_end"] / meters_per_unit), time
    )
    return usd_camera


def _transform_op(xformable: UsdGeom.Xformable) -> UsdGeom.XformOp:
    ops = xformable.GetOrderedXformOps()
    if ops:
        return ops[0]
    return xformable.AddTransformOp()


def light_matrix(direction: list[float], up: str) -> Gf.Matrix4d:
    """A rotation (row-vector Gf matrix) whose -Z axis travels along `direction`."""
    travel = stage_rotation(up) @ np.asarray(direction, dtype=np.float64)
    travel /= np.linalg.norm(travel)
    rotation = Gf.Rotation(Gf.Vec3d(0, 0, -1), Gf.Vec3d(*travel))
    return Gf.Matrix4d().SetRotate(rotation)


def author_light(
    stage: Usd.Stage,
    path: str,
    sun: dict[str, Any],
    *,
    up: str = "Z",
    time: Usd.TimeCode | None = None,
) -> UsdLux.DistantLight:
    time = time if time is not None else Usd.TimeCode.Default()
    light = UsdLux.DistantLight.Define(stage, path)
    _transform_op(light).Set(light_matrix(sun["direction"], up), time)
    light.CreateIntensityAttr().Set(float(sun.get("strength", 1.0)), time)
    light.CreateColorAttr().Set(Gf.Vec3f(*sun.get("color", [1.0, 1.0, 1.0])), time)
    angle = sun.get("angular_diameter", math.radians(0.526))
    light.CreateAngleAttr().Set(math.degrees(angle), time)
    return light


# A strip up the z axis, skinned by joint "a" at the rig's origin and joint "a/b" 1 up:
# its bottom on a, its top on b, and a point halfway between them by weight; the top
# points also carry a blend shape that moves them 0.1 along x.
STRIP_REST = [(0, 0, 0), (0.5, 0, 0), (0.5, 0, 1.5), (0, 0, 1.5), (0, 0, 2), (0.5, 0, 2)]
STRIP_JOINTS = [(0, 0), (0, 0), (0, 1), (0, 1), (1, 0), (1, 0)]
STRIP_WEIGHTS = [(1, 0), (1, 0), (0.5, 0.5), (0.5, 0.5), (1, 0), (1, 0)]


def author_rig(stage: Usd.Stage, root: str, turns: dict[float, float]) -> UsdSkel.Skeleton:
    """A SkelRoot 10 along x whose joint b turns about x by `turns[time]` degrees."""
    rig = UsdSkel.Root.Define(stage, root)
    rig.AddTranslateOp().Set(Gf.Vec3d(10.0, 0.0, 0.0))
    skeleton = UsdSkel.Skeleton.Define(stage, f"{root}/Skel")
    skeleton.CreateJointsAttr(["a", "a/b"])
    up = Gf.Matrix4d().SetTranslate(Gf.Vec3d(0.0, 0.0, 1.0))
    skeleton.CreateBindTransformsAttr([Gf.Matrix4d(1.0), up])
    skeleton.CreateRestTransformsAttr([Gf.Matrix4d(1.0), up])
    animation = UsdSkel.Animation.Define(stage, f"{root}/Skel/Anim")
    animation.CreateJointsAttr(["a", "a/b"])
    animation.CreateTranslationsAttr([Gf.Vec3f(0.0), Gf.Vec3f(0.0, 0.0, 1.0)])
    animation.CreateScalesAttr([Gf.Vec3h(1.0)] * 2)
    rotations = animation.CreateRotationsAttr()
    for time, degrees in turns.items():
        turn = Gf.Quatf(Gf.Rotation(Gf.Vec3d(1.0, 0.0, 0.0), degrees).GetQuat())
        rotations.Set([Gf.Quatf(1.0), turn], Usd.TimeCode(time))
    animation.CreateBlendShapesAttr(["wide"])
    animation.CreateBlendShapeWeightsAttr([1.0])
    binding = UsdSkel.BindingAPI.Apply(skeleton.GetPrim())
    assert binding.CreateAnimationSourceRel().SetTargets([animation.GetPath()])
    return skeleton


def author_skinned_strip(stage: Usd.Stage, path: str, skeleton: UsdSkel.Skeleton) -> None:
    strip = UsdGeom.Mesh.Define(stage, path)
    strip.AddTranslateOp().Set(Gf.Vec3d(100.0, 100.0, 100.0))  # UsdSkel ignores it
    strip.CreatePointsAttr(STRIP_REST)
    strip.CreateFaceVertexCountsAttr([4, 4])
    strip.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 3, 2, 5, 4])
    binding = UsdSkel.BindingAPI.Apply(strip.GetPrim())
    assert binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 2).Set([j for pair in STRIP_JOINTS for j in pair])
    binding.CreateJointWeightsPrimvar(False, 2).Set([w for pair in STRIP_WEIGHTS for w in pair])
    binding.CreateBlendShapesAttr(["wide"])
    shape = UsdSkel.BlendShape.Define(stage, f"{path}/Wide")
    shape.CreateOffsetsAttr([Gf.Vec3f(0.1, 0.0, 0.0)] * 2)
    shape.CreatePointIndicesAttr([4, 5])
    assert binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])


def posed_strip(degrees: float) -> np.ndarray:
    """The strip posed by hand: the blend shape, then linear blend skinning, at x + 10."""
    rest = np.array(STRIP_REST, dtype=np.float64)
    rest[4:, 0] += 0.1
    angle = np.radians(degrees)
    cos, sin = np.cos(angle), np.sin(angle)
    turn = np.array([[1, 0, 0], [0, cos, -sin], [0, sin, cos]])
    pivot = np.array([0.0, 0.0, 1.0])
    on_b = (rest - pivot) @ turn.T + pivot
    pairs = zip(STRIP_JOINTS, STRIP_WEIGHTS, strict=True)
    weights_b = np.array([w[j.index(1)] if 1 in j else 0.0 for j, w in pairs])
    posed = rest * (1 - weights_b[:, None]) + on_b * weights_b[:, None]
    return posed + np.array([10.0, 0.0, 0.0])


def write_alpha_png(path: Path, alpha: np.ndarray) -> str:
    """An RGBA PNG whose alpha is `alpha`, rows top (v = 1) to bottom as files store them."""
    rgba = np.zeros((*alpha.shape, 4), dtype=np.uint8)
    rgba[..., 3] = np.round(alpha * 255).astype(np.uint8)
    Image.fromarray(rgba).save(path)
    return path.name


def cut_material(stage: Usd.Stage, path: str, file: str, **inputs: Any) -> UsdShade.Material:
    """A material whose UsdPreviewSurface takes its opacity from a UsdUVTexture of `file`
    (its "a" output, or `channel`), read at the "st" primvar, cut at 0.5, and repeating
    (`wrap` for both axes, as Blender's USD export authors them; None authors none)."""
    wrap = inputs.pop("wrap", "repeat")
    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    texture = UsdShade.Shader.Define(stage, f"{path}/Alpha")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    if wrap is not None:
        for name in ("wrapS", "wrapT"):
            texture.CreateInput(name, Sdf.ValueTypeNames.Token).Set(wrap)
    texture.CreateOutput(inputs.pop("channel", "a"), Sdf.ValueTypeNames.Float)
    reader = UsdShade.Shader.Define(stage, f"{path}/St")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    opacity = surface.CreateInput("opacity", Sdf.ValueTypeNames.Float)
    opacity.ConnectToSource(texture.ConnectableAPI(), texture.GetOutputs()[0].GetBaseName())
    surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    return material
