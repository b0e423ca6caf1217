"""Blender's USD export hook: every sun lamp with shafts leaves its settings on the stage.

On `bpy.ops.wm.usd_export`, the hook applies `CrepuscularLightAPI` to the DistantLight of
each sun with shafts and authors what the add-on would render with, so that
`crepuscular-usd` renders the exported stage like `bpy.ops.crepuscular.render_layers`:

- the values come from the add-on's own conversion to the core's scene description
  (`export.medium_dict`, `export.settings_dict`, `style.style_from_light`), and are authored
  under the names of the USD step's attribute table (`usd_attributes`, the USD package's
  `crepuscular_usd/attributes.py`, which the build copies into the zip);
- a fog object becomes the `crepuscular:mediumExtent` target: its exported mesh, or, when it
  was not exported, a guide `Cube` with its box; objects that take holes become the
  `crepuscular:holes:objects` targets;
- lengths are converted to stage units with the exporter's own transform (units and up
  axis), read off the light's prim; the transfer function is authored in metres, as the
  USD step reads it;
- `crepuscular:intensityScale` restores the sun's strength, which Blender's exporter writes
  divided by 4, `crepuscular:angleScale` its disc, which it writes as half the angle (its
  importer doubles it back; USD's `inputs:angle` is the angular diameter), and
  `inputs:enableColorTemperature` is re-authored with the lamp's Temperature checkbox,
  which Blender 5.0's exporter authors as true on every light;
- objects that do not block the sun (Casts Shafts Off, no Shadow ray visibility, outside
  the sun's shadow linking) are excluded from the light's `shadowLink` collection, which
  Blender's exporter does not write; a sun whose Cast Shadow is off and that nothing
  blocks gets `inputs:shadow:enable` false instead;
- an animated export gets time samples wherever a value changes over the frame range;
- a `RenderSettings` prim, `/Render/settings`, named by the stage's
  `renderSettingsPrimPath`, holds the scene camera, the render's resolution, pixel aspect
  and render region (`dataWindowNDC`), which Blender's exporter does not write: the USD
  step, and farm renderers that read it, render the image F12 renders. A stage that
  already names its render settings keeps them;
- a cut-out material whose cut Blender's exporter drops (a Mix Shader towards a
  Transparent BSDF, a Transparent BSDF) gets its opacity: the add-on's mask as an EXR
  beside the stage, read by a UsdUVTexture (wrap, Mapping nodes as a UsdTransform2d) and
  cut at the add-on's threshold, so that every USD renderer cuts what Cycles cuts;
- legacy curves and NURBS surfaces, whose rendered surfaces the exporter does not write,
  get meshes;
- a point cloud that an object's modifiers make, which the exporter writes as an empty
  mesh, gets a `Points` prim under the object's transform, and legacy particle hair,
  which it leaves out (or writes without widths), Catmull-Rom `BasisCurves`;
- an orthographic scene camera, which Blender 5.0's exporter writes as its transform alone,
  gets its `Camera` prim: orthographic, its view's width and height as apertures (tenths
  of a stage unit), its lens shift as aperture offsets and its clip range, so that the
  stage has the camera F12 renders through.

Errors (a fog object that cannot be mapped, a setting the core refuses) are raised: Blender
reports them and the export operator fails.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import math
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import bpy
import numpy as np

import crepuscular

from . import cutouts, export, render
from .style import style_from_light
from .usd_attributes import (
    API_NAME,
    ATTRIBUTES,
    HOLES_OBJECTS,
    MEDIUM_EXTENT,
    SUBDIVISION_LEVELS,
    SUBDIVISION_LIMIT,
    TF_JSON,
)

#: The exporter's attribute holding an object's name (under its custom-property namespace).
OBJECT_NAME = "blender:object_name"
ENABLE_COLOR_TEMPERATURE = "inputs:enableColorTemperature"
#: Name of the guide Cube that carries a fog box the exporter left out, per sun.
MEDIUM_PRIM = "crepuscularMedium"
#: Stage (Y up) to renderer (Z up) rotation, as the USD step turns a Y-up stage.
Z_UP_FROM_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class USDExportError(RuntimeError):
    """The hook cannot author the stage; the message says which sun or object and why."""


# Blender's own USD bindings -------------------------------------------------------------


def _bundled_pxr() -> Path | None:
    """The `pxr` package in Blender's Python folder, where it has one."""
    python = Path(bpy.utils.system_resource("PYTHON"))
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    for site in (python / "lib" / version / "site-packages", python / "lib" / "site-packages"):
        if (site / "pxr" / "__init__.py").is_file():
            return (site / "pxr").resolve()
    return None


def load_blender_pxr() -> bool:
    """Makes Blender's own USD Python bindings the `pxr` that Python imports; False when
    there are none. Called before the hook registers.

    Blender imports `pxr` itself before it runs any USD hook, and only its own bindings can
    take its stage; with none importable at all, Blender 5.0 aborts the whole process on
    export. Blender's Python finds them on `sys.path`; the `bpy` module installed with pip
    bundles them without putting them there (and may find usd-core instead), so they are
    imported here from Blender's Python folder. A `pxr` imported before stays: the hook
    then refuses to author, naming both.
    """
    if "pxr" in sys.modules:
        return True
    bundled = _bundled_pxr()
    if bundled is None:
        return importlib.util.find_spec("pxr") is not None
    found = importlib.util.find_spec("pxr")
    if found is not None and found.origin and Path(found.origin).resolve().parent == bundled:
        return True
    spec = importlib.util.spec_from_file_location(
        "pxr", bundled / "__init__.py", submodule_search_locations=[str(bundled)]
    )
    if spec is None or spec.loader is None:
        return False
    module = importlib.util.module_from_spec(spec)
    sys.modules["pxr"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules["pxr"]
        raise
    return True


def check_blender_pxr() -> None:
    """Raises when the imported `pxr` is not Blender's own, which cannot take its stage."""
    bundled = _bundled_pxr()
    loaded = sys.modules.get("pxr")
    if bundled is None or loaded is None:
        return
    location = Path(loaded.__file__ or "").resolve().parent
    if location != bundled:
        raise USDExportError(
            f"the pxr module in use comes from {location}, not from Blender's own USD "
            f"({bundled}); Blender's stage cannot be handed to another USD build. Enable "
            "the add-on before anything imports another pxr (such as usd-core)"
        )


# Matrices -------------------------------------------------------------------------------


def _numpy(gf_matrix: Any) -> np.ndarray:
    """A Gf.Matrix4d (row vectors) as a column-vector numpy matrix."""
    return np.array(gf_matrix, dtype=np.float64).reshape(4, 4).T


def _gf(matrix: np.ndarray) -> Any:
    from pxr import Gf

    return Gf.Matrix4d(np.asarray(matrix, dtype=np.float64).T.tolist())


def _world(prim: Any, time: Any) -> np.ndarray:
    from pxr import UsdGeom

    if prim.IsPseudoRoot():
        return np.eye(4)
    return _numpy(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time))


def stage_from_blender(light: Any, sun: bpy.types.Object, time: Any) -> np.ndarray:
    """The exporter's transform from Blender's world to stage space (its unit scale and up
    axis), read off a light it exported: the prim's world matrix over the object's."""
    from pxr import UsdGeom

    blender = np.array(sun.matrix_world, dtype=np.float64)
    if abs(np.linalg.det(blender[:3, :3])) < 1e-12:
        raise USDExportError(f"sun '{sun.name}': its matrix is singular (zero scale)")
    transform = _world(light, time) @ np.linalg.inv(blender)
    scale = abs(np.linalg.det(transform[:3, :3])) ** (1.0 / 3.0)
    rotation = transform[:3, :3] / scale
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4):
        raise USDExportError(
            f"sun '{sun.name}': the exported light's transform is not Blender's times a "
            "rotation and a uniform scale"
        )
    # The exporter writes transforms in single precision. Its own conversions are axis
    # swaps and 1 / metersPerUnit: snap to those, so that constant values stay constant.
    exact = 1.0 / UsdGeom.GetStageMetersPerUnit(light.GetStage())
    if abs(scale / exact - 1.0) < 1e-5:
        scale = exact
    axes = np.round(rotation)
    if np.allclose(rotation, axes, atol=1e-5):
        rotation = axes
    translation = transform[:3, 3]
    if np.all(np.abs(translation) < 1e-5 * scale):
        translation = np.zeros(3)
    snapped = np.eye(4)
    snapped[:3, :3], snapped[:3, 3] = rotation * scale, translation
    return snapped


def renderer_from_stage(stage: Any) -> np.ndarray:
    """Stage space to the renderer's (Z up, metres), as the USD step converts a stage."""
    from pxr import UsdGeom

    matrix = np.eye(4)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y:
        matrix[:3, :3] = Z_UP_FROM_Y_UP
    return np.diag([UsdGeom.GetStageMetersPerUnit(stage)] * 3 + [1.0]) @ matrix


# Exported prims -------------------------------------------------------------------------


class ExportedPrims:
    """The prims the exporter wrote for each Blender object, found by the object name it
    authors on them (`userProperties:blender:object_name`), or by prim name when that was
    switched off."""

    def __init__(self, stage: Any) -> None:
        from pxr import Tf

        self._by_object: dict[str, list[Any]] = {}
        self._by_name: dict[str, list[Any]] = {}
        self._tf = Tf
        for prim in stage.Traverse():
            self._by_name.setdefault(prim.GetName(), []).append(prim)
            for name in prim.GetAuthoredPropertyNames():
                if name == OBJECT_NAME or name.endswith(":" + OBJECT_NAME):
                    value = prim.GetAttribute(name).Get()
                    if value:
                        self._by_object.setdefault(str(value), []).append(prim)

    def add(self, obj: bpy.types.Object, prim: Any) -> None:
        """Counts `prim`, authored after the pass over the stage, among `obj`'s."""
        if self._by_object:
            self._by_object.setdefault(obj.name, []).append(prim)
        else:
            self._by_name.setdefault(self._tf.MakeValidIdentifier(obj.name), []).append(prim)

    def of(self, obj: bpy.types.Object) -> list[Any]:
        """Prims of `obj`: its transform, or its data prim where the two were merged."""
        if self._by_object:
            return self._by_object.get(obj.name, [])
        return self._by_name.get(self._tf.MakeValidIdentifier(obj.name), [])

    def data(self, obj: bpy.types.Object, schema: Any) -> list[Any]:
        """Prims of `schema` type written for `obj`: the object's prim or its children."""
        found = []
        for prim in self.of(obj):
            candidates = [prim] if prim.IsA(schema) else list(prim.GetChildren())
            found += [c for c in candidates if c.IsA(schema) and c not in found]
        return found


# Values ---------------------------------------------------------------------------------


def _camel(token: str) -> str:
    """A scene-description value as the schema's token: `henyey_greenstein` ->
    `henyeyGreenstein`; one-word values stay as they are."""
    head, *rest = token.split("_")
    return head + "".join(part.capitalize() for part in rest)


def _lookup(sections: dict[str, dict[str, Any]], target: tuple[str, ...]) -> Any:
    section, *path = target
    node = sections[section]
    if section == "style" and path[-1] == "enable":
        return path[0] in node
    for key in path:
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    return node


def _tf_in_metres(tf: dict[str, Any], renderer_from_blender: np.ndarray) -> dict[str, Any]:
    """The add-on's TF (scene units) as the USD step reads it: depths in metres, 3D
    constraint points in the renderer's space."""
    metres = abs(np.linalg.det(renderer_from_blender[:3, :3])) ** (1.0 / 3.0)
    tf = json.loads(json.dumps(tf))
    tf["depth_range"] = {k: v * metres for k, v in tf["depth_range"].items()}
    for layer in tf["layers"]:
        for constraint in layer.get("constraints", []):
            point = constraint.get("world_point")
            if point is not None:
                moved = renderer_from_blender @ np.array([*point, 1.0])
                constraint["world_point"] = [float(v) for v in moved[:3]]
    return tf


def light_values(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    sun: bpy.types.Object,
    light: Any,
    time: Any,
    stage_time: float,
) -> dict[str, Any]:
    """Every attribute the hook authors on `light` for the depsgraph's frame, as plain
    Python values in stage units (None where the add-on has no value)."""
    from pxr import UsdLux

    stage = light.GetStage()
    evaluated = sun.evaluated_get(depsgraph)
    data = evaluated.data
    settings = data.crepuscular
    to_stage = stage_from_blender(light, evaluated, time)
    scale = abs(np.linalg.det(to_stage[:3, :3])) ** (1.0 / 3.0)
    fps = scene.render.fps / scene.render.fps_base
    seconds = depsgraph.scene.frame_current / fps
    name = f"bpy.data.lights['{data.original.name}']"
    style = style_from_light(settings, time=seconds, hole_objects=[], name=name)
    medium, _notes = export.medium_dict(scene, depsgraph)
    lux = UsdLux.LightAPI(light)
    exported = float(lux.GetIntensityAttr().Get(time)) * 2.0 ** float(
        lux.GetExposureAttr().Get(time)
    )
    sun_desc = export.sun_dict(evaluated)
    strength = sun_desc["strength"]
    exported_angle = math.radians(float(UsdLux.DistantLight(light).GetAngleAttr().Get(time)))
    diameter = sun_desc["angular_diameter"]
    sections = {
        "medium": medium,
        "render": export.settings_dict(settings),
        "style": style,
        "sun": {
            "intensity_scale": strength / exported if exported > 0 else 1.0,
            "angle_scale": diameter / exported_angle if exported_angle > 0 else 1.0,
        },
    }
    values: dict[str, Any] = {}
    for attr_name, attribute in ATTRIBUTES.items():
        if not attribute.target:
            continue
        value = _lookup(sections, attribute.target)
        if attr_name == "crepuscular:holes:time" and "holes" in style:
            # The USD step's time is time code / timeCodesPerSecond: make up the difference.
            value = seconds - stage_time / stage.GetTimeCodesPerSecond()
        if value is None:
            continue
        if attr_name == "crepuscular:holes:pivot":
            value = (to_stage @ np.array([*value, 1.0]))[:3]
        elif attribute.length_power:
            value = np.asarray(value, dtype=np.float64) * scale**attribute.length_power
        if attribute.type_name in ("color3f", "point3f"):
            value = tuple(float(v) for v in value)
        elif attribute.type_name == "token":
            value = _camel(str(value))
        values[attr_name] = value
    tf = style.get("tf")
    values[TF_JSON] = (
        json.dumps(_tf_in_metres(tf, renderer_from_stage(stage) @ to_stage), sort_keys=True)
        if tf is not None
        else ""
    )
    values[ENABLE_COLOR_TEMPERATURE] = bool(data.use_temperature)
    return values


def medium_box(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    parent: Any,
    to_stage: np.ndarray,
    time: Any,
) -> Any:
    """The fog box as the local matrix (Gf) of a guide Cube under `parent`: the cube
    [-1, 1]^3 mapped as the add-on maps it, in stage space."""
    medium, _notes = export.medium_dict(scene, depsgraph)
    world_from_cube = np.array(medium["extent"]["world_from_cube"], dtype=np.float64)
    local = np.linalg.inv(_world(parent, time)) @ to_stage @ world_from_cube.reshape(4, 4).T
    return _gf(local)


# Authoring ------------------------------------------------------------------------------


class _Samples:
    """Values per time code, authored as one default when they never change."""

    def __init__(self) -> None:
        self.values: dict[str, list[tuple[Any, Any]]] = {}

    def add(self, name: str, time: Any, value: Any) -> None:
        self.values.setdefault(name, []).append((time, value))

    def author(
        self, attribute: Any, name: str, convert: Callable[[Any], Any] = lambda v: v
    ) -> None:
        samples = self.values.get(name, [])
        if not samples:
            return
        first = samples[0][1]
        if len(samples) == 1 or all(value == first for _, value in samples):
            ok = attribute.Set(convert(first))
        else:
            ok = all(attribute.Set(convert(value), time) for time, value in samples)
        if not ok:
            raise USDExportError(f"could not author {attribute.GetPath()}")

    def author_arrays(self, attribute: Any, name: str, kind: Any) -> None:
        """`author` for numpy arrays, as `kind` (a Vt array type): one sample a frame (their
        length may change from frame to frame), or one default where they never change."""
        samples = self.values.get(name, [])
        if not samples:
            return
        first = samples[0][1]
        if all(np.array_equal(value, first) for _, value in samples):
            ok = attribute.Set(kind.FromNumpy(first))
        else:
            ok = all(attribute.Set(kind.FromNumpy(value), time) for time, value in samples)
        if not ok:
            raise USDExportError(f"could not author {attribute.GetPath()}")


def _value(type_name: str, value: Any) -> Any:
    from pxr import Gf, Sdf

    if type_name in ("color3f", "point3f"):
        return Gf.Vec3f(*value)
    if type_name == "asset":
        return Sdf.AssetPath(value)
    return value


class _SunRecord:
    """What the hook writes for one sun: its light prims and the values per frame."""

    def __init__(self, sun: bpy.types.Object, lights: list[Any], fog: list[Any]) -> None:
        self.sun = sun
        self.lights = lights
        #: The exported mesh prim of the fog object, when there is exactly one.
        self.fog = fog[0] if len(fog) == 1 else None
        self.samples = _Samples()
        #: The fog box's matrix per frame, for a guide Cube when the fog was not exported.
        self.box = _Samples()


def _frames(stage: Any) -> list[int] | None:
    """The frames of an animated export, or None for a still one."""
    if not stage.HasAuthoredTimeCodeRange():
        return None
    start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    return list(range(math.floor(start), math.ceil(end) + 1))


@contextlib.contextmanager
def _stepping_frames(stage: Any, depsgraph: bpy.types.Depsgraph) -> Iterator[Iterator[Any]]:
    """The export's frames to step through, each a time code (the default time for a still
    export, whose scene stays at its frame): the scene is set to each frame in turn, and
    back to its own frame afterwards, however the steps end."""
    from pxr import Usd

    scene = depsgraph.scene
    frames = _frames(stage)
    original = scene.frame_current

    def steps() -> Iterator[Any]:
        for frame in frames or [None]:
            if frame is None:
                yield Usd.TimeCode.Default()
                continue
            scene.frame_current = frame
            depsgraph.update()
            yield Usd.TimeCode(frame)

    try:
        yield steps()
    finally:
        if frames is not None:
            scene.frame_current = original
            depsgraph.update()


def author_shaft_settings(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> list[str]:
    """Applies CrepuscularLightAPI to the DistantLight of every exported sun with shafts
    (found among the exporter's `prims`) and authors its settings; returns the light prim
    paths. Suns that were not exported are named in the log."""
    from pxr import Sdf, Tf, UsdGeom, UsdLux

    scene = depsgraph.scene
    settings = scene.crepuscular
    fog = settings.fog_object if settings.medium_source == "fog_object" else None
    records = []
    for sun in export.shaft_suns(scene):
        lights = prims.data(sun, UsdLux.DistantLight)
        if not lights:
            render.log(f"USD export: sun '{sun.name}' has no DistantLight on the stage")
            continue
        fog_prims = prims.data(fog, UsdGeom.Mesh) if fog is not None else []
        records.append(_SunRecord(sun, lights, fog_prims))
    if not records:
        return []
    default = stage.GetDefaultPrim()
    parent = default if default else stage.GetPseudoRoot()
    with _stepping_frames(stage, depsgraph) as times:
        for time in times:
            stage_time = stage.GetStartTimeCode() if time.IsDefault() else time.GetValue()
            for record in records:
                for light in record.lights:
                    values = light_values(scene, depsgraph, record.sun, light, time, stage_time)
                    for name, value in values.items():
                        record.samples.add(name, time, value)
                if fog is not None and record.fog is None:
                    to_stage = stage_from_blender(
                        record.lights[0], record.sun.evaluated_get(depsgraph), time
                    )
                    box = medium_box(scene, depsgraph, parent, to_stage, time)
                    record.box.add("transform", time, box)

    authored = []
    holes = [
        prim.GetPath()
        for obj in scene.objects
        if obj.crepuscular.takes_holes
        for prim in prims.of(obj)
    ]
    for record in records:
        extent: Sdf.Path | None = None
        if record.fog is not None:
            extent = record.fog.GetPath()
        elif record.box.values:
            name = Tf.MakeValidIdentifier(f"{MEDIUM_PRIM}_{record.sun.name}")
            cube = UsdGeom.Cube.Define(stage, parent.GetPath().AppendChild(name))
            cube.CreateSizeAttr(2.0)
            # A guide: renderers leave it out, the USD step reads its box.
            cube.CreatePurposeAttr(UsdGeom.Tokens.guide)
            op = UsdGeom.Xformable(cube).AddTransformOp()
            record.box.author(op.GetAttr(), "transform")
            extent = cube.GetPath()
        for light in record.lights:
            if not light.AddAppliedSchema(API_NAME):
                raise USDExportError(f"could not apply {API_NAME} to {light.GetPath()}")
            for name in record.samples.values:
                if name == ENABLE_COLOR_TEMPERATURE:
                    attribute = UsdLux.LightAPI(light).CreateEnableColorTemperatureAttr()
                    attribute.Clear()  # Blender's own (wrong) value, time samples included
                    record.samples.author(attribute, name)
                else:
                    type_name = ATTRIBUTES[name].type_name
                    attribute = light.CreateAttribute(
                        name, Sdf.ValueTypeNames.Find(type_name), custom=False
                    )
                    record.samples.author(attribute, name, lambda v, t=type_name: _value(t, v))
            light.CreateRelationship(MEDIUM_EXTENT, custom=False).SetTargets(
                [extent] if extent is not None else []
            )
            light.CreateRelationship(HOLES_OBJECTS, custom=False).SetTargets(holes)
            author_shadow_link(light, scene, record.sun, prims, fog)
            authored.append(str(light.GetPath()))
    return authored


def orthographic_view(
    scene: bpy.types.Scene, data: bpy.types.Camera
) -> tuple[float, float, float, float]:
    """The width and height of the view of orthographic camera `data` and its shift, in
    Blender units, as Blender computes its view plane: `ortho_scale` spans the side the
    sensor fit names (under Auto, the wider in square units, pixel aspect included), and
    a shift moves the view by that many `ortho_scale`s."""
    width, height = export.render_size(scene)
    render_settings = scene.render
    across = width * render_settings.pixel_aspect_x
    down = height * render_settings.pixel_aspect_y
    fit = data.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if across >= down else "VERTICAL"
    scale = data.ortho_scale
    horizontal = fit == "HORIZONTAL"
    view_width = scale if horizontal else scale * across / down
    view_height = scale * down / across if horizontal else scale
    return view_width, view_height, data.shift_x * scale, data.shift_y * scale


def author_orthographic_camera(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> str | None:
    """The scene camera's `Camera` prim where it is orthographic and the exporter wrote
    its transform alone (see the module's doc), time-sampled where the view changes over
    an animated export; returns its path, None where there is nothing to author."""
    from pxr import Gf, Tf, UsdGeom

    scene = depsgraph.scene
    camera = scene.camera
    if camera is None or camera.type != "CAMERA" or camera.data.type != "ORTHO":
        return None
    if prims.data(camera, UsdGeom.Camera):
        return None
    exported = [prim for prim in prims.of(camera) if prim.IsA(UsdGeom.Xformable)]
    if not exported:
        return None
    transform = exported[0]
    prim = UsdGeom.Camera.Define(
        stage, transform.GetPath().AppendChild(Tf.MakeValidIdentifier(camera.data.name))
    )
    if not prim:
        raise USDExportError(f"could not define the Camera prim of camera '{camera.name}'")
    samples = _Samples()
    with _stepping_frames(stage, depsgraph) as times:
        for time in times:
            evaluated = camera.evaluated_get(depsgraph)
            blender = np.array(evaluated.matrix_world, dtype=np.float64)
            if abs(np.linalg.det(blender[:3, :3])) < 1e-12:
                raise USDExportError(f"camera '{camera.name}': its matrix is singular")
            # Stage units per Blender unit, off the exporter's own transform of the camera.
            to_stage = _world(transform, time) @ np.linalg.inv(blender)
            units = abs(np.linalg.det(to_stage[:3, :3])) ** (1.0 / 3.0)
            data = evaluated.data
            width, height, shift_x, shift_y = orthographic_view(scene, data)
            # Orthographic apertures and their offsets are in tenths of a stage unit.
            tenths = 10.0 * units
            samples.add("horizontalAperture", time, width * tenths)
            samples.add("verticalAperture", time, height * tenths)
            samples.add("horizontalApertureOffset", time, shift_x * tenths)
            samples.add("verticalApertureOffset", time, shift_y * tenths)
            samples.add("clippingRange", time, (data.clip_start * units, data.clip_end * units))
    if not prim.CreateProjectionAttr().Set(UsdGeom.Tokens.orthographic):
        raise USDExportError(f"could not author {prim.GetPath()}.projection")
    attributes = {
        "horizontalAperture": prim.CreateHorizontalApertureAttr(),
        "verticalAperture": prim.CreateVerticalApertureAttr(),
        "horizontalApertureOffset": prim.CreateHorizontalApertureOffsetAttr(),
        "verticalApertureOffset": prim.CreateVerticalApertureOffsetAttr(),
        "clippingRange": prim.CreateClippingRangeAttr(),
    }
    for name, attribute in attributes.items():
        convert = (lambda v: Gf.Vec2f(*v)) if name == "clippingRange" else float
        samples.author(attribute, name, convert)
    return str(prim.GetPath())


def author_render_settings(stage: Any, scene: bpy.types.Scene, prims: ExportedPrims) -> str | None:
    """The render's image as a RenderSettings prim named by the stage's metadata (see the
    module's doc); returns its path, None where the stage names one already."""
    from pxr import Gf, Sdf, UsdGeom, UsdRender

    if stage.GetMetadata(UsdRender.Tokens.renderSettingsPrimPath):
        return None
    root = UsdGeom.Scope.Define(stage, Sdf.Path("/Render"))
    settings = UsdRender.Settings.Define(stage, root.GetPath().AppendChild("settings"))
    if not (root and settings):
        raise USDExportError("could not define the render settings /Render/settings")
    cameras = prims.data(scene.camera, UsdGeom.Camera) if scene.camera else []
    if cameras:
        settings.CreateCameraRel().SetTargets([cameras[0].GetPath()])
    render_settings = scene.render
    settings.CreateResolutionAttr(Gf.Vec2i(*export.render_size(scene)))
    aspect = render_settings.pixel_aspect_x / render_settings.pixel_aspect_y
    settings.CreatePixelAspectRatioAttr(float(aspect))
    region = export.render_region(scene)
    if region is not None:
        # The edges of the pixels Blender renders (it truncates the border's fractions),
        # from the bottom-left corner: a renderer that takes the pixels whose centres lie
        # inside takes those, where the border's own fractions can gain or lose an edge's
        # row or column.
        width, height = export.render_size(scene)
        bottom = height - region.y - region.height
        window = Gf.Vec4f(
            region.x / width,
            bottom / height,
            (region.x + region.width) / width,
            (bottom + region.height) / height,
        )
        settings.CreateDataWindowNDCAttr(window)
    path = settings.GetPath()
    if not stage.SetMetadata(UsdRender.Tokens.renderSettingsPrimPath, str(path)):
        raise USDExportError(f"could not name {path} the stage's render settings")
    return str(path)


def author_shadow_link(
    light: Any,
    scene: bpy.types.Scene,
    sun: bpy.types.Object,
    prims: ExportedPrims,
    fog: bpy.types.Object | None,
) -> None:
    """Leaves the objects that do not block `sun` (Casts Shafts Off, no Shadow ray
    visibility, or outside its shadow linking; `export.blocks_sun`) out of the light's
    shadowLink collection, which Blender's exporter does not write, so that the USD step
    casts what the add-on casts. Nothing is authored where every object blocks. Objects are
    judged on their own: an instance that blocks only through its instancer's linking is
    judged by its instancer. A sun whose Cast Shadow is off and that no object blocks
    (none forced by Casts Shafts On) gets `inputs:shadow:enable` false, which Blender's
    exporter does not write either: renderers then trace no shadow rays for it, and its
    light does not fade through the fog, as in Cycles and the add-on."""
    from pxr import UsdLux

    blockers = export.LightLinking.of_blockers(sun)
    candidates = [
        obj for obj in scene.objects if obj.type in export.GEOMETRY_TYPES | {"EMPTY"} and obj != fog
    ]
    blocking = {
        obj.name_full
        for obj in candidates
        if export.blocks_sun([obj], blockers) and not _hidden_from_shadow_rays(obj)
    }
    if blockers is not None and blockers.takes_none and not blocking:
        shadow = UsdLux.ShadowAPI.Apply(light)
        if not shadow or not shadow.CreateShadowEnableAttr(False):
            raise USDExportError(f"could not author inputs:shadow:enable on {light.GetPath()}")
        return
    left_out = [
        prim.GetPath()
        for obj in candidates
        if obj.name_full not in blocking
        for prim in prims.of(obj)
    ]
    if not left_out:
        return
    link = UsdLux.LightAPI(light).GetShadowLinkCollectionAPI()
    link.CreateIncludeRootAttr(True)
    link.CreateExcludesRel().SetTargets(left_out)


def _hidden_from_shadow_rays(obj: bpy.types.Object) -> bool:
    """Whether every material of `obj` hides it from shadow rays through Light Path (a
    Mix Shader towards a Transparent BSDF by Is Shadow Ray), which Blender's exporter does
    not carry: the add-on then casts none of it, and neither may the USD step."""
    if obj.type == "EMPTY" or obj.original.crepuscular.casts_shafts == "on":
        return False
    materials = [slot.material for slot in obj.material_slots]
    if not materials:
        return False
    for material in materials:
        source, _ = cutouts.material_mask(material)
        if source is None or source.rays & crepuscular.BLOCKS_SUN:
            return False
    return True


#: UsdUVTexture's wrap for each of the core's mask wraps.
USD_WRAPS = {"repeat": "repeat", "extend": "clamp", "mirror": "mirror", "clip": "black"}
#: Folder, beside the stage, of the cut-out masks the hook writes.
MASK_FOLDER = "textures"


def _uv_transform_2d(transform: tuple[float, ...]) -> tuple[float, float, float, float, float]:
    """An affine map of (u, v), (a, b, c, d, e, f) reading (a·u + b·v + c, d·u + e·v + f), as
    UsdTransform2d's scale (x, y), rotation (degrees) and translation, which it applies in
    that order; USDExportError where it shears, which UsdTransform2d cannot."""
    a, b, c, d, e, f = transform
    # Columns (a, d) and (b, e): a rotation times a scale keeps them at right angles.
    first, second = math.hypot(a, d), math.hypot(b, e)
    if first == 0.0 or second == 0.0 or abs(a * b + d * e) > 1e-6 * first * second:
        raise USDExportError("its Mapping nodes shear or flatten the UV map")
    angle = math.atan2(d, a)
    # The second column is the first's quarter turn, scaled: negative where mirrored.
    sign = 1.0 if (-math.sin(angle) * b + math.cos(angle) * e) >= 0 else -1.0
    return first, sign * second, math.degrees(angle), c, f


def _exported_materials(stage: Any) -> dict[str, Any]:
    """The exporter's Material prims by the Blender material's name."""
    from pxr import UsdShade

    found: dict[str, Any] = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdShade.Material):
            continue
        names = [
            prim.GetAttribute(name).Get()
            for name in prim.GetAuthoredPropertyNames()
            if name.endswith("blender:data_name")
        ]
        found.setdefault(str(names[0]) if names and names[0] else prim.GetName(), prim)
    return found


def _bound_meshes(stage: Any) -> dict[Any, list[Any]]:
    """Per bound material's path, the Mesh prims bound to it, whole or through a
    GeomSubset: one pass over the stage for every material."""
    from pxr import UsdGeom, UsdShade

    meshes: dict[Any, list[Any]] = {}
    for prim in stage.Traverse():
        if not (prim.IsA(UsdGeom.Mesh) or prim.IsA(UsdGeom.Subset)):
            continue
        bound, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        if bound:
            mesh = prim if prim.IsA(UsdGeom.Mesh) else prim.GetParent()
            listed = meshes.setdefault(bound.GetPath(), [])
            if mesh not in listed:
                listed.append(mesh)
    return meshes


def _uv_primvar(meshes: list[Any], uv_map: str) -> str:
    """The primvar `meshes` hold UV map `uv_map` in ("" for the mesh's default map): the
    exporter names the default map `st`, others by their own names."""
    from pxr import UsdGeom

    if not uv_map:
        return "st"
    for mesh in meshes:
        primvars = UsdGeom.PrimvarsAPI(mesh)
        if primvars.HasPrimvar(uv_map):
            return uv_map
        if primvars.HasPrimvar("st"):
            return "st"
    return uv_map


def _mapped_primvar(
    meshes: list[Any], name: str, transform: tuple[float, ...], mapped_name: str
) -> str | None:
    """A primvar `mapped_name` on each of `meshes`: their primvar `name` through the affine
    map `transform` ((a, b, c, d, e, f) reads (a·u + b·v + c, d·u + e·v + f)), exact for
    any affine map since coordinates interpolate linearly; None where a mesh lacks `name`."""
    from pxr import Sdf, UsdGeom, Vt

    a, b, c, d, e, f = transform
    for mesh in meshes:
        primvars = UsdGeom.PrimvarsAPI(mesh)
        source = primvars.GetPrimvar(name)
        values = source.Get() if source else None
        if values is None:
            return None
        uv = np.asarray(values, dtype=np.float64).reshape(-1, 2)
        mapped = np.c_[a * uv[:, 0] + b * uv[:, 1] + c, d * uv[:, 0] + e * uv[:, 1] + f]
        target = primvars.CreatePrimvar(
            mapped_name, Sdf.ValueTypeNames.TexCoord2fArray, source.GetInterpolation()
        )
        target.Set(Vt.Vec2fArray.FromNumpy(mapped.astype(np.float32)))
        if source.IsIndexed():
            target.SetIndices(source.GetIndices())
    return mapped_name


def author_cutouts(stage: Any, depsgraph: bpy.types.Depsgraph) -> list[str]:
    """The opacity of every cut-out material, as the add-on cuts: a UsdPreviewSurface
    whose opacity is the add-on's mask, written as an EXR beside the stage and read by a
    UsdUVTexture (its wrap; the Mapping nodes as a UsdTransform2d, or, where they shear,
    as mapped coordinates on the meshes), cut at the add-on's threshold; or a constant
    opacity. Blender's exporter writes no cut for a Mix Shader towards a Transparent BSDF,
    a Transparent BSDF or node groups, and for an Image Texture's Alpha drops what lies
    between the two (Mapping nodes but one Point mapping, value chains): the mask replaces
    whatever it wrote. Returns the materials authored; those that UsdPreviewSurface cannot
    carry (a cut seen by only the sun's or the camera's rays) are named in the log and
    stay as exported.
    """
    from pxr import Gf, Sdf, UsdShade

    folder = Path(stage.GetRootLayer().realPath).parent if stage.GetRootLayer().realPath else None
    authored = []
    materials = _exported_materials(stage)
    bindings: dict[Any, list[Any]] | None = None
    used = {
        slot.material
        for obj in depsgraph.scene.objects
        for slot in obj.material_slots
        if slot.material is not None
    }
    for material in sorted(used, key=lambda m: m.name):
        prim = materials.get(material.name)
        if prim is None:
            continue
        source, _ = cutouts.material_mask(material)
        if source is None:
            continue
        usd_material = UsdShade.Material(prim)
        surface = usd_material.ComputeSurfaceSource()
        shader = surface[0] if isinstance(surface, tuple) else surface
        if not shader and not usd_material.GetSurfaceOutput().HasConnectedSource():
            # The exporter writes a material it cannot translate (one built of node
            # groups) with no surface, which renderers draw with their fallback: this one,
            # UsdPreviewSurface's defaults, then carries the cut.
            shader = UsdShade.Shader.Define(
                stage, prim.GetPath().AppendChild("crepuscular_surface")
            )
            shader.CreateIdAttr("UsdPreviewSurface")
            usd_material.CreateSurfaceOutput().ConnectToSource(
                shader.CreateOutput("surface", Sdf.ValueTypeNames.Token)
            )
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            continue
        where = f"USD export: material '{material.name}'"
        if source.rays != export.BOTH:
            render.log(f"{where}: its cut is seen by some rays only; left opaque on the stage")
            continue
        if source.constant is not None:
            constant = shader.CreateInput("opacity", Sdf.ValueTypeNames.Float)
            constant.DisconnectSource()
            constant.Set(float(source.constant))
            threshold = float(cutouts.THRESHOLD)
            shader.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(threshold)
            authored.append(material.name)
            continue
        if folder is None:
            render.log(f"{where}: the stage has no file to write its mask beside; left opaque")
            continue
        if not source.threshold > 0.0:
            # UsdPreviewSurface's threshold of 0 turns the cut off.
            render.log(f"{where}: it cuts at an alpha of 0; left opaque on the stage")
            continue
        if bindings is None:
            bindings = _bound_meshes(stage)
        meshes = bindings.get(prim.GetPath(), [])
        varname = _uv_primvar(meshes, source.uv_map)
        transform = None
        if source.uv_transform is not None:
            try:
                transform = _uv_transform_2d(source.uv_transform)
            except USDExportError:
                mapped_name = f"crepuscular_st_{prim.GetName()}"
                mapped = _mapped_primvar(meshes, varname, source.uv_transform, mapped_name)
                if mapped is None:
                    render.log(f"{where}: a mesh lacks UV map {varname}; left opaque")
                    continue
                varname = mapped
        alpha = np.flipud(cutouts.mask_alpha(source))  # files store rows from the top
        if source.invert:
            # The file holds the texture's own value and the reader inverts it, so that
            # past a clipped image's edges (black) the surface stays opaque, as in Cycles.
            alpha = 1.0 - alpha
        name = f"crepuscular_mask_{prim.GetName()}.exr"
        (folder / MASK_FOLDER).mkdir(parents=True, exist_ok=True)
        zeros = np.zeros_like(alpha)
        planes = {"R": zeros, "G": zeros, "B": zeros, "A": np.ascontiguousarray(alpha)}
        crepuscular.write_exr_channels(folder / MASK_FOLDER / name, planes)
        path = prim.GetPath()
        reader = UsdShade.Shader.Define(stage, path.AppendChild("crepuscular_uv"))
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set(varname)
        coordinates = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        if transform is not None:
            mapping = UsdShade.Shader.Define(stage, path.AppendChild("crepuscular_mapping"))
            mapping.CreateIdAttr("UsdTransform2d")
            mapping.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(coordinates)
            scale_x, scale_y, rotation, move_x, move_y = transform
            mapping.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(scale_x, scale_y))
            mapping.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(rotation)
            mapping.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(
                Gf.Vec2f(move_x, move_y)
            )
            coordinates = mapping.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        texture = UsdShade.Shader.Define(stage, path.AppendChild("crepuscular_mask"))
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(
            Sdf.AssetPath(f"./{MASK_FOLDER}/{name}")
        )
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(coordinates)
        wrap = USD_WRAPS[source.wrap]
        texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
        texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap)
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
        if source.invert:
            texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(1, 1, 1, -1))
            texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0, 0, 0, 1))
        opacity = shader.CreateInput("opacity", Sdf.ValueTypeNames.Float)
        opacity.DisconnectSource()
        opacity.ConnectToSource(texture.CreateOutput("a", Sdf.ValueTypeNames.Float))
        threshold = shader.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float)
        threshold.Set(float(source.threshold))
        authored.append(material.name)
    return authored


#: Name of the Points prim the hook adds under an object whose modifiers make points.
POINTS_PRIM = "crepuscularPoints"


def _modifier_points(depsgraph: bpy.types.Depsgraph) -> dict[str, tuple[Any, Any]]:
    """Per object (by name) whose own evaluated geometry holds a point cloud that its
    modifiers made (geometry nodes' Mesh to Points, Distribute Points), that point cloud's
    positions and radii in the object's space."""
    found: dict[str, tuple[Any, Any]] = {}
    for instance in depsgraph.object_instances:
        obj, parent = instance.object, instance.parent
        if obj.type != "POINTCLOUD" or not instance.is_instance or parent is None:
            continue
        if parent.original.type == "POINTCLOUD":
            continue
        # The object's own geometry, not a copy that an instancer placed elsewhere.
        if not np.allclose(np.array(instance.matrix_world), np.array(parent.matrix_world)):
            continue
        data = obj.data
        count = len(data.points)
        if count == 0:
            continue
        positions = np.empty(count * 3, dtype=np.float32)
        data.attributes["position"].data.foreach_get("vector", positions)
        radius = data.attributes.get("radius")
        radii = np.full(count, export.DEFAULT_POINT_RADIUS, dtype=np.float32)
        if radius is not None:
            radius.data.foreach_get("value", radii)
        found[parent.original.name] = (positions.reshape(-1, 3), radii)
    return found


def author_modifier_points(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> list[str]:
    """A `Points` prim (positions, widths of twice the radii) under the exported transform
    of every object whose modifiers make a point cloud, which Blender 5.0's exporter writes
    as an empty mesh: so that the stage holds the points Cycles renders (the add-on draws
    them as spheres, and so does the USD step from Points). Time-sampled over an animated
    export. Returns the prims' paths."""
    from pxr import UsdGeom, Vt

    scene = depsgraph.scene
    samples: dict[str, _Samples] = {}
    with _stepping_frames(stage, depsgraph) as times:
        for time in times:
            for name, (positions, radii) in _modifier_points(depsgraph).items():
                record = samples.setdefault(name, _Samples())
                record.add("points", time, positions)
                record.add("widths", time, 2.0 * radii)
    authored = []
    for name, record in samples.items():
        obj = scene.objects.get(name)
        exported = [p for p in prims.of(obj) if p.IsA(UsdGeom.Xformable)] if obj else []
        if not exported:
            continue
        points = UsdGeom.Points.Define(stage, exported[0].GetPath().AppendChild(POINTS_PRIM))
        if not points:
            raise USDExportError(f"could not define the points of object '{name}'")
        widths = points.CreateWidthsAttr()
        if not points.SetWidthsInterpolation(UsdGeom.Tokens.vertex):
            raise USDExportError(f"could not author {points.GetPath()}'s widths")
        record.author_arrays(points.CreatePointsAttr(), "points", Vt.Vec3fArray)
        record.author_arrays(widths, "widths", Vt.FloatArray)
        first = record.values
        extent = UsdGeom.Points.ComputeExtent(
            Vt.Vec3fArray.FromNumpy(first["points"][0][1]),
            Vt.FloatArray.FromNumpy(first["widths"][0][1]),
        )
        if extent is not None:
            points.CreateExtentAttr(extent)
        authored.append(str(points.GetPath()))
    return authored


#: Name of the BasisCurves prim the hook adds under an emitter of particle hair.
HAIR_PRIM = "crepuscularHair"


def author_particle_hair(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> list[str]:
    """A `BasisCurves` prim of the legacy particle hair of each emitter, as Cycles draws
    it (`export.particle_hair_strands`: cubic Catmull-Rom through its keys, widths twice
    the radii), under the emitter's exported transform, time-sampled over an animated
    export. Blender's exporter leaves particle hair out by default, and with its Hair
    option writes linear curves without widths, which no renderer gives a thickness: those
    are deactivated in favour of this one. Returns the prims' paths."""
    from pxr import UsdGeom, Vt

    scene = depsgraph.scene
    # Those the render evaluates: not hidden, nor in an excluded collection.
    rendered = {
        instance.object.original.name
        for instance in depsgraph.object_instances
        if not instance.is_instance and instance.object.type in export.GEOMETRY_TYPES
    }
    emitters = [
        obj
        for obj in scene.objects
        if obj.name in rendered
        and any(system.settings.type == "HAIR" for system in obj.particle_systems)
    ]
    samples: dict[str, _Samples] = {}
    with _stepping_frames(stage, depsgraph) as times:
        for time in times:
            for obj in emitters:
                strands = export.particle_hair_strands(obj.evaluated_get(depsgraph), True)
                if strands is None:
                    continue
                points, counts, radii = strands
                record = samples.setdefault(obj.name, _Samples())
                record.add("points", time, points.astype(np.float32))
                record.add("counts", time, counts.astype(np.int32))
                record.add("widths", time, (2.0 * radii).astype(np.float32))
    authored = []
    for name, record in samples.items():
        exported = [p for p in prims.of(scene.objects[name]) if p.IsA(UsdGeom.Xformable)]
        if not exported:
            continue
        for child in exported[0].GetChildren():
            if child.IsA(UsdGeom.BasisCurves) and child.GetName() != HAIR_PRIM:
                child.SetActive(False)
        curves = UsdGeom.BasisCurves.Define(stage, exported[0].GetPath().AppendChild(HAIR_PRIM))
        if not curves:
            raise USDExportError(f"could not define the particle hair of object '{name}'")
        curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
        curves.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
        curves.CreateWrapAttr(UsdGeom.Tokens.pinned)
        widths = curves.CreateWidthsAttr()
        curves.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        record.author_arrays(curves.CreatePointsAttr(), "points", Vt.Vec3fArray)
        record.author_arrays(curves.CreateCurveVertexCountsAttr(), "counts", Vt.IntArray)
        record.author_arrays(widths, "widths", Vt.FloatArray)
        authored.append(str(curves.GetPath()))
    return authored


#: Scope, under the stage's default prim, of the meshes the hook writes for legacy curves
#: and NURBS surfaces.
CONVERTED_SCOPE = "crepuscularMeshes"
#: Object types whose rendered surface Blender's exporter does not write as a mesh.
CONVERTED_TYPES = ("CURVE", "SURFACE")


def author_converted_meshes(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> list[str]:
    """Meshes of the surfaces Cycles renders for legacy curve and NURBS surface objects,
    which Blender's exporter does not write: it writes a curve as BasisCurves of its path
    with its radius as width (a bevelled curve's bevel is lost, and a curve with no bevel,
    which renders nothing, becomes a tube) and a surface not at all. Each becomes a Mesh
    under `crepuscularMeshes`, in stage space (the exporter's units and axes, read off the
    first shaft sun's light), carrying the object's name as the exporter does, so that
    the hook's shadow linking finds it; time-sampled. The exporter's curves of those
    objects are deactivated. Returns the meshes' paths."""
    from pxr import Sdf, Tf, UsdGeom, UsdLux, Vt

    scene = depsgraph.scene
    # Those the render evaluates: not hidden, nor in an excluded collection.
    rendered = {
        instance.object.original.name
        for instance in depsgraph.object_instances
        if instance.object.type in CONVERTED_TYPES and not instance.is_instance
    }
    objects = [obj for obj in scene.objects if obj.name in rendered]
    if not objects:
        return []
    sun = export.shaft_suns(scene)[0]
    lights = prims.data(sun, UsdLux.DistantLight)
    if not lights:
        return []
    default = stage.GetDefaultPrim()
    parent = default if default else stage.GetPseudoRoot()
    samples: dict[str, _Samples] = {}
    with _stepping_frames(stage, depsgraph) as times:
        for time in times:
            to_stage = stage_from_blender(lights[0], sun.evaluated_get(depsgraph), time)
            to_parent = np.linalg.inv(_world(parent, time)) @ to_stage
            for obj in objects:
                evaluated = obj.evaluated_get(depsgraph)
                mesh = evaluated.to_mesh()
                try:
                    arrays = export.mesh_arrays(mesh) if mesh is not None else None
                finally:
                    evaluated.to_mesh_clear()
                if arrays is None or len(arrays.triangles) == 0:
                    continue
                matrix = to_parent @ np.array(evaluated.matrix_world, dtype=np.float64)
                positions = arrays.positions.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
                record = samples.setdefault(obj.name, _Samples())
                record.add("points", time, positions.astype(np.float32))
                record.add("counts", time, np.full(len(arrays.triangles), 3, dtype=np.int32))
                record.add("indices", time, arrays.triangles.astype(np.int32).reshape(-1))
    for obj in objects:
        for prim in prims.of(obj):
            for curves in [prim, *prim.GetChildren()]:
                if curves.IsA(UsdGeom.BasisCurves):
                    curves.SetActive(False)
    authored = []
    scope = parent.GetPath().AppendChild(CONVERTED_SCOPE)
    for name, record in samples.items():
        mesh = UsdGeom.Mesh.Define(stage, scope.AppendChild(Tf.MakeValidIdentifier(name)))
        if not mesh:
            raise USDExportError(f"could not define the mesh of object '{name}'")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(True)
        record.author_arrays(mesh.CreatePointsAttr(), "points", Vt.Vec3fArray)
        record.author_arrays(mesh.CreateFaceVertexCountsAttr(), "counts", Vt.IntArray)
        record.author_arrays(mesh.CreateFaceVertexIndicesAttr(), "indices", Vt.IntArray)
        attribute = mesh.GetPrim().CreateAttribute(
            f"userProperties:{OBJECT_NAME}", Sdf.ValueTypeNames.String, custom=True
        )
        attribute.Set(name)
        prims.add(scene.objects[name], mesh.GetPrim())
        authored.append(str(mesh.GetPath()))
    return authored


#: The mesh attributes that crease a subdivision surface.
CREASE_ATTRIBUTES = (
    "creaseIndices",
    "creaseLengths",
    "creaseSharpnesses",
    "cornerIndices",
    "cornerSharpnesses",
)


def author_subdivision_levels(
    stage: Any, depsgraph: bpy.types.Depsgraph, prims: ExportedPrims
) -> list[str]:
    """The render levels, and whether on the limit surface, of every Subdivision Surface
    modifier that Blender's exporter writes as a Catmull-Clark cage (the modifier last,
    under its default 'Best Match'), on the cage's mesh: USD has no level of its own, and
    the USD step refines the cage as far as F12 does. A modifier that ignores creases
    gets the exporter's creases blocked. Returns the meshes' paths."""
    from pxr import Sdf, UsdGeom

    authored = []
    for obj in depsgraph.scene.objects:
        modifier = obj.modifiers[-1] if obj.type == "MESH" and obj.modifiers else None
        if modifier is None or modifier.type != "SUBSURF" or not modifier.show_render:
            continue
        for prim in prims.data(obj, UsdGeom.Mesh):
            scheme = UsdGeom.Mesh(prim).GetSubdivisionSchemeAttr()
            if not scheme.HasAuthoredValue() or scheme.Get() != UsdGeom.Tokens.catmullClark:
                continue
            for name, kind, value in (
                (SUBDIVISION_LEVELS, Sdf.ValueTypeNames.Int, int(modifier.render_levels)),
                (SUBDIVISION_LIMIT, Sdf.ValueTypeNames.Bool, bool(modifier.use_limit_surface)),
            ):
                attribute = prim.CreateAttribute(name, kind, custom=True)
                if not attribute or not attribute.Set(value):
                    raise USDExportError(f"could not author {prim.GetPath()}.{name}")
            if not modifier.use_creases:
                # The exporter writes the mesh's creases whether the modifier uses them or
                # not; blocked, the stage subdivides as smoothly as Blender renders.
                for name in CREASE_ATTRIBUTES:
                    attribute = prim.GetAttribute(name)
                    if attribute and attribute.HasAuthoredValue():
                        attribute.Block()
            authored.append(str(prim.GetPath()))
    return authored


class CREPUSCULAR_USDHook(bpy.types.USDHook):
    """Applies CrepuscularLightAPI to sun lamps with shafts on USD export"""

    bl_idname = "crepuscular"
    bl_label = "Crepuscular Light Shafts"
    bl_description = (
        "Applies CrepuscularLightAPI to the DistantLight of every sun lamp with shafts and "
        "authors its medium, method, quality and style, for the crepuscular-usd step"
    )

    @staticmethod
    def on_export(export_context: Any) -> bool:
        depsgraph = export_context.get_depsgraph()
        if not export.shaft_suns(depsgraph.scene):
            return True
        check_blender_pxr()
        stage = export_context.get_stage()
        # One pass over the exported prims serves every step; the prims the hook adds are
        # counted in as they are authored.
        prims = ExportedPrims(stage)
        # Before the shaft settings, whose shadow linking names these meshes too.
        converted = author_converted_meshes(stage, depsgraph, prims)
        if converted:
            render.log(f"USD export: curve and surface meshes authored as {', '.join(converted)}")
        paths = author_shaft_settings(stage, depsgraph, prims)
        if paths:
            render.log(f"USD export: {API_NAME} authored on {', '.join(paths)}")
            hair = author_particle_hair(stage, depsgraph, prims)
            if hair:
                render.log(f"USD export: particle hair authored as {', '.join(hair)}")
            points = author_modifier_points(stage, depsgraph, prims)
            if points:
                render.log(f"USD export: point clouds authored as {', '.join(points)}")
            cut = author_cutouts(stage, depsgraph)
            if cut:
                render.log(f"USD export: cut-out opacity authored for {', '.join(cut)}")
            camera = author_orthographic_camera(stage, depsgraph, prims)
            if camera is not None:
                render.log(f"USD export: the orthographic camera authored as {camera}")
            cages = author_subdivision_levels(stage, depsgraph, prims)
            if cages:
                render.log(f"USD export: subdivision levels authored on {', '.join(cages)}")
            settings = author_render_settings(stage, depsgraph.scene, prims)
            if settings is not None:
                render.log(f"USD export: the render's image authored as {settings}")
        return True


CLASSES = (CREPUSCULAR_USDHook,)


def register() -> None:
    if not load_blender_pxr():
        # A hook without importable USD bindings would abort every USD export.
        render.log("Blender's USD Python bindings are missing: the USD export hook is off")
        return
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    # Blender's pxr stays imported: its compiled modules cannot be loaded twice.
    for cls in reversed(CLASSES):
        if cls.is_registered:
            bpy.utils.unregister_class(cls)
