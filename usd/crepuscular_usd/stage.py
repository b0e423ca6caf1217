"""A USD stage at one time code as the renderer's frame: camera, sun, medium, triangles.

The renderer works right-handed, Z up, in metres. Stage space converts with
`metersPerUnit` (a uniform scale) and, for Y-up stages, a +90 degree rotation about X,
the same as Blender's USD importer. Cameras map exactly:

- perspective: the aperture side that spans the image by the RenderSettings' conform
  policy (`expandAperture` where there are none, as Hydra's default) becomes the fitted
  sensor side, and aperture offsets become lens shifts in units of that side; the
  settings' pixel aspect carries over;
- orthographic: apertures are tenths of a stage unit (Gf.Camera's convention);
- clipping range in stage units along the view axis, like the renderer's clip planes.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdLux

import crepuscular
from crepuscular_usd.attributes import ATTRIBUTES, MEDIUM_EXTENT, TF_ASSET, TF_JSON
from crepuscular_usd.geometry import (
    GeometryCollector,
    SceneGeometry,
    row_matrix,
    sun_and_camera,
    tf_message,
)
from crepuscular_usd.render_settings import ImageSettings, fitted_vertically, pixel_window
from crepuscular_usd.schema import LightSettings, box_from_extent_prim, read_light_settings

__all__ = ["Frame", "StageError", "StageReader", "core_from_stage", "open_stage", "tf_message"]

F64 = npt.NDArray[np.float64]

#: The light's and camera's USD properties behind the renderer's other fields that they
#: feed: the schema's attributes name their own ([`ATTRIBUTES`]).
LIGHT_SOURCES = {
    "sun.color": "inputs:color (with inputs:colorTemperature)",
    "sun.strength": "inputs:intensity (with inputs:exposure)",
    "sun.angular_diameter": "inputs:angle",
    "sun.direction": "its transform",
    "medium.extent": MEDIUM_EXTENT,
    "style.tf": f"{TF_JSON} or {TF_ASSET}",
}
CAMERA_SOURCES = {
    "camera.projection.focal_length": "focalLength",
    "camera.projection.sensor_width": "horizontalAperture",
    "camera.projection.sensor_height": "verticalAperture",
    "camera.projection.ortho_scale": "horizontalAperture and verticalAperture",
    "camera.projection.shift_x": "horizontalApertureOffset",
    "camera.projection.shift_y": "verticalApertureOffset",
    "camera.clip_start": "clippingRange",
    "camera.clip_end": "clippingRange",
    "camera.world_from_camera": "its transform",
}

#: A side derived from the camera's aperture aspect beyond this is no image size at all
#: (the renderer names sides beyond its own, smaller limit).
MAX_DERIVED_SIDE = 1 << 20


class StageError(ValueError):
    """A stage, camera or light that cannot be rendered; the message says which and why."""


@contextmanager
def _naming(what: str) -> Iterator[None]:
    """Turns USD's errors in the block into a `StageError` that begins with `what`: USD's
    own, for an xformOpOrder of no op, name no prim."""
    try:
        yield
    except Tf.ErrorException as error:
        raise StageError(f"{what}: USD: {tf_message(error)}") from error


def open_stage(path: str) -> Usd.Stage:
    """Opens a stage, raising StageError with USD's reason when it cannot be read."""
    try:
        stage = Usd.Stage.Open(path)
    except Tf.ErrorException as error:
        raise StageError(f"cannot open stage {path}: {tf_message(error)}") from error
    if not stage:
        raise StageError(f"cannot open stage {path}")
    return stage


def core_from_stage(stage: Usd.Stage) -> tuple[F64, float]:
    """Column-vector 4x4 from stage world space to renderer space, and metersPerUnit."""
    meters = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not (math.isfinite(meters) and meters > 0):
        raise StageError(f"metersPerUnit is {meters}; it must be a positive number")
    rotation = np.eye(4)
    up = UsdGeom.GetStageUpAxis(stage)
    if up == UsdGeom.Tokens.y:
        rotation[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    elif up != UsdGeom.Tokens.z:
        raise StageError(f"upAxis is {up!r}; USD allows Y or Z")
    scale = np.diag([meters, meters, meters, 1.0])
    return scale @ rotation, meters


def _column_major(matrix: F64) -> list[float]:
    return [float(v) for v in matrix.flatten(order="F")]


@dataclass
class Frame:
    """Everything `crepuscular.render_arrays` needs for one time code."""

    time: Usd.TimeCode
    geometry: SceneGeometry
    camera: dict[str, Any]
    sun: dict[str, Any]
    medium: dict[str, Any]
    settings: dict[str, Any]
    style: dict[str, Any]
    light_settings: LightSettings

    def render_kwargs(self) -> dict[str, Any]:
        cutouts: dict[str, Any] = {}
        if self.geometry.triangle_masks is not None:
            cutouts = {
                "uvs": self.geometry.uvs,
                "triangle_masks": self.geometry.triangle_masks,
                "masks": self.geometry.masks,
            }
        if self.geometry.visibility is not None:
            cutouts["triangle_visibility"] = self.geometry.visibility
        return {
            **cutouts,
            "positions": self.geometry.positions,
            "triangles": self.geometry.triangles,
            "object_ids": self.geometry.object_ids,
            "origin": self.geometry.origin,
            "camera": self.camera,
            "sun": self.sun,
            "medium": self.medium,
            "settings": self.settings,
            "style": self.style,
        }

    def settings_record(self) -> dict[str, Any]:
        """The exact scene description without meshes, for the output layer."""
        return {
            "camera": self.camera,
            "sun": self.sun,
            "medium": self.medium,
            "render": self.settings,
            "style": self.style,
        }


def _membership(collection: Usd.CollectionAPI) -> Usd.UsdCollectionMembershipQuery | None:
    """The collection's membership query, or None where it holds every prim (a light
    linking collection's fallback: the root included, nothing excluded), so that frames
    without linking test no paths."""
    if not collection:
        return None
    holds_everything = (
        collection.GetIncludeRootAttr().Get()
        and not collection.GetExcludesRel().HasAuthoredTargets()
        and not collection.GetMembershipExpressionAttr().HasAuthoredValue()
    )
    return None if holds_everything else collection.ComputeMembershipQuery()


class _NoMembers:
    """A membership query that holds no prim: the blockers of a light that casts no
    shadows."""

    @staticmethod
    def IsPathIncluded(path: Sdf.Path) -> bool:
        return False


_NO_MEMBERS: Any = _NoMembers()


class StageReader:
    """Reads frames of one stage for one camera and one DistantLight."""

    def __init__(
        self,
        stage: Usd.Stage,
        camera_path: str | None,
        light_path: str | None,
        *,
        width: int | None = None,
        height: int | None = None,
        image: ImageSettings | None = None,
        subdivision_levels: int = 0,
    ) -> None:
        self.stage = stage
        #: Levels to refine Catmull-Clark meshes that do not name their own (0: cages).
        self.subdivision_levels = subdivision_levels
        self.core_from_stage, self.meters_per_unit = core_from_stage(stage)
        self.image = image or ImageSettings()
        self.camera_prim = self._find_camera(camera_path)
        self.light_prim = self._find_light(light_path)
        self._width = width
        self._height = height
        self._collectors: dict[Sdf.Path | None, GeometryCollector] = {}
        # The light's shadow linking (UsdLuxLightAPI's shadowLink collection): its owners
        # outside it do not block the light. Unauthored, it holds everything.
        light_api = UsdLux.LightAPI(self.light_prim)
        self._shadow_link = _membership(light_api.GetShadowLinkCollectionAPI())
        self._light_link = _membership(light_api.GetLightLinkCollectionAPI())
        self.time_codes_per_second = float(stage.GetTimeCodesPerSecond()) or 24.0

    def _casts_shadows(self, time: Usd.TimeCode) -> bool:
        """Whether the light casts shadows at `time`: UsdLuxShadowAPI's `shadow:enable`,
        true unless authored false."""
        enable = self.light_prim.GetAttribute("inputs:shadow:enable")
        return not enable or enable.Get(time) is not False

    def source_of(self, field: str) -> str | None:
        """The USD property behind the renderer's scene field `field` (as its invalid-input
        errors name it, `medium.albedo[0]`), for messages that a stage's author can act on;
        None for fields of no one property (the meshes', the image size)."""
        path = re.sub(r"\[\d+\]", "", field)
        light, camera = self.light_prim.GetPath(), self.camera_prim.GetPath()
        for name, attribute in ATTRIBUTES.items():
            target = ".".join(attribute.target)
            if target and (path == target or path.startswith(target + ".")):
                return f"{light}.{name}"
        for prefix, source in LIGHT_SOURCES.items():
            if path == prefix or path.startswith(prefix + "."):
                return f"{light} {source}"
        if path in CAMERA_SOURCES:
            return f"{camera} {CAMERA_SOURCES[path]}"
        if path == "camera.pixel_aspect":
            return self.image.attribute("pixelAspectRatio")
        return None

    # --- prims ----------------------------------------------------------------------

    def _find_camera(self, path: str | None) -> Usd.Prim:
        if path is None and self.image.camera is not None:
            path = str(self.image.camera)
            prim = self.stage.GetPrimAtPath(path)
            if not (prim and prim.IsActive() and prim.IsA(UsdGeom.Camera)):
                raise StageError(
                    f"{self.image.attribute('camera')} targets {path}, which is not an active "
                    "Camera on the stage"
                )
            return prim
        if path is None:
            cameras = [p for p in self.stage.Traverse() if p.IsA(UsdGeom.Camera)]
            if len(cameras) != 1:
                found = ", ".join(str(p.GetPath()) for p in cameras) or "none"
                raise StageError(f"give --camera: the stage has {len(cameras)} cameras ({found})")
            return cameras[0]
        prim = self._prim(path, "camera")
        if not prim.IsA(UsdGeom.Camera):
            raise StageError(
                f"camera {path} is a {prim.GetTypeName() or 'typeless prim'}, not a Camera"
            )
        return prim

    def _find_light(self, path: str | None) -> Usd.Prim:
        if path is None:
            lights = [p for p in self.stage.Traverse() if p.IsA(UsdLux.DistantLight)]
            with_api = [p for p in lights if p.HasAPI("CrepuscularLightAPI")]
            candidates = with_api or lights
            if len(candidates) != 1:
                found = ", ".join(str(p.GetPath()) for p in candidates) or "none"
                raise StageError(
                    f"give --light: the stage has {len(candidates)} DistantLights ({found})"
                )
            return candidates[0]
        prim = self._prim(path, "light")
        if not prim.IsA(UsdLux.DistantLight):
            raise StageError(
                f"light {path} is a {prim.GetTypeName() or 'typeless prim'}, not a DistantLight"
            )
        return prim

    def _prim(self, path: str, what: str) -> Usd.Prim:
        if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
            raise StageError(f"{what} path {path!r} is not an absolute prim path")
        prim = self.stage.GetPrimAtPath(path)
        if not prim:
            raise StageError(f"{what} {path} does not exist on the stage")
        if not prim.IsActive():
            raise StageError(f"{what} {path} is deactivated")
        return prim

    # --- per frame ------------------------------------------------------------------

    def seconds(self, time: Usd.TimeCode) -> float:
        return 0.0 if time.IsDefault() else time.GetValue() / self.time_codes_per_second

    def read(self, time: Usd.TimeCode) -> Frame:
        light = read_light_settings(self.light_prim, time, self.meters_per_unit)
        extent_path = light.extent_prim.GetPath() if light.extent_prim is not None else None
        collector = self._collectors.get(extent_path)
        if collector is None:
            skip = [extent_path] if extent_path is not None else []
            collector = GeometryCollector(
                self.stage,
                self.core_from_stage,
                skip=skip,
                purposes=self.image.purposes,
                subdivision_levels=self.subdivision_levels,
            )
            self._collectors[extent_path] = collector
        camera = self.camera(time)
        sun = self.sun(
            time,
            intensity_scale=light.sun["intensity_scale"],
            angle_scale=light.sun["angle_scale"],
        )
        casts = self._casts_shadows(time)
        geometry = collector.collect(
            time,
            np.asarray(camera["world_from_camera"][12:15]),
            seen=sun_and_camera(sun, camera),
            shadow_link=self._shadow_link if casts else _NO_MEMBERS,
        )
        # Nor does the fog dim a light that casts no shadows: a renderer traces no shadow
        # rays for it, through the fog no more than through surfaces.
        sun["attenuated_by_medium"] = casts
        if not casts:
            geometry.notes.append(
                f"{self.light_prim.GetPath()} casts no shadows (inputs:shadow:enable is "
                "false): nothing casts shafts, and the fog is lit everywhere, its light not "
                "fading through the fog towards the light"
            )
        medium = dict(light.medium)
        medium["extent"] = self._extent(light, time)
        if light.extent_prim is not None:
            geometry.notes.extend(self._linking_notes(light.extent_prim.GetPath()))
        style: dict[str, Any] = {"version": crepuscular.STYLE_VERSION, "time": self.seconds(time)}
        style.update(light.style)
        if "holes" in style:
            pivot = self.core_from_stage @ np.array([*style["holes"]["pivot"], 1.0])
            style["holes"]["pivot"] = [float(v) for v in pivot[:3]]
            style["holes"]["objects"] = geometry.ids_under(light.holes_roots)
        return Frame(
            time=time,
            geometry=geometry,
            camera=camera,
            sun=sun,
            medium=medium,
            settings={
                **light.render,
                "sun_disc_samples": crepuscular.sun_disc_samples(sun["angular_diameter"]),
            },
            style=style,
            light_settings=light,
        )

    def _linking_notes(self, extent: Sdf.Path) -> list[str]:
        """Notes where the light's lightLink or shadowLink collection leaves the medium's
        extent prim out: a renderer then lights no fog there (Cycles renders none); the
        shafts are rendered as if it were in."""
        notes = []
        light = self.light_prim.GetPath()
        for query, name in ((self._light_link, "lightLink"), (self._shadow_link, "shadowLink")):
            if query is not None and not query.IsPathIncluded(extent):
                notes.append(
                    f"{light}: its {name} collection leaves the medium {extent} out, so a "
                    "path tracer lights no fog in it; the shafts are rendered as if it were in"
                )
        return notes

    def _extent(self, light: LightSettings, time: Usd.TimeCode) -> dict[str, Any]:
        if light.extent_prim is None:
            return {"kind": "unbounded"}
        prim = light.extent_prim
        local = box_from_extent_prim(prim, time)
        with _naming(f"medium extent {prim.GetPath()}: its transform"):
            world = row_matrix(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time)).T
        return {
            "kind": "box",
            "world_from_cube": _column_major(self.core_from_stage @ world @ local),
        }

    def resolution(self, aperture_aspect: float) -> tuple[int, int]:
        """The image size: as given, or the other side from the aperture's aspect ratio
        (and the pixels')."""
        pixel_aspect = self.image.pixel_aspect
        if self._width and self._height:
            return self._width, self._height
        if self._height:
            return max(1, round(self._height * aperture_aspect / pixel_aspect)), self._height
        width = self._width or 1920
        return width, max(1, round(width * pixel_aspect / aperture_aspect))

    def camera(self, time: Usd.TimeCode) -> dict[str, Any]:
        where = str(self.camera_prim.GetPath())
        with _naming(f"camera {where}"):
            camera = UsdGeom.Camera(self.camera_prim).GetCamera(time)
        h_aperture, v_aperture = camera.horizontalAperture, camera.verticalAperture
        if not (0 < h_aperture < math.inf and 0 < v_aperture < math.inf):
            raise StageError(
                f"camera {where}: apertures must be positive and finite, got {h_aperture} x "
                f"{v_aperture}"
            )
        width, height = self.resolution(h_aperture / v_aperture)
        derived = not (self._width and self._height)
        if derived and max(width, height) > MAX_DERIVED_SIDE:
            raise StageError(
                f"camera {where}: its apertures {h_aperture} x {v_aperture} give a {width} x "
                f"{height} image; give both --width and --height"
            )
        pixel_aspect = self.image.pixel_aspect
        vertical, adjusted = fitted_vertically(
            self.image.conform, width * pixel_aspect / height, h_aperture / v_aperture
        )
        if adjusted is not None:
            pixel_aspect *= adjusted
        fitted = v_aperture if vertical else h_aperture
        fit = "vertical" if vertical else "horizontal"
        shift_x = camera.horizontalApertureOffset / fitted
        shift_y = camera.verticalApertureOffset / fitted
        if camera.projection == Gf.Camera.Orthographic:
            # Gf.Camera: apertures in tenths of a stage unit for orthographic views.
            projection: dict[str, Any] = {
                "kind": "orthographic",
                "ortho_scale": fitted * 0.1 * self.meters_per_unit,
                "sensor_fit": fit,
                "shift_x": shift_x,
                "shift_y": shift_y,
            }
        else:
            if not camera.focalLength > 0:
                raise StageError(f"camera {where}: focalLength must be positive")
            projection = {
                "kind": "perspective",
                "focal_length": camera.focalLength,
                "sensor_width": h_aperture,
                "sensor_height": v_aperture,
                "sensor_fit": fit,
                "shift_x": shift_x,
                "shift_y": shift_y,
            }
        window = None
        if self.image.data_window is not None:
            window = pixel_window(self.image.data_window, width, height)
            if window is None:
                shown = tuple(round(v, 4) for v in self.image.data_window)
                raise StageError(
                    f"{self.image.attribute('dataWindowNDC')} {shown} holds no pixel of the "
                    f"{width}x{height} image"
                )
        transform = Gf.Matrix4d(camera.transform)
        # A camera's scale does not change its projection; keep rotation and position.
        transform.Orthonormalize()
        world = row_matrix(transform).T
        rotation = self.core_from_stage[:3, :3] / self.meters_per_unit
        core = np.eye(4)
        core[:3, :3] = rotation @ world[:3, :3]
        core[:3, 3] = self.core_from_stage[:3, :3] @ world[:3, 3]
        clip = camera.clippingRange
        return {
            "world_from_camera": _column_major(core),
            "projection": projection,
            "clip_start": float(clip.min) * self.meters_per_unit,
            "clip_end": float(clip.max) * self.meters_per_unit,
            "width": width,
            "height": height,
            "pixel_aspect": pixel_aspect,
            **({"window": window} if window is not None else {}),
        }

    def sun(
        self, time: Usd.TimeCode, *, intensity_scale: float = 1.0, angle_scale: float = 1.0
    ) -> dict[str, Any]:
        """Direction, colour, strength and angle of the light at `time`; `intensity_scale`
        and `angle_scale` are the schema's `crepuscular:intensityScale` and `:angleScale`."""
        light = UsdLux.DistantLight(self.light_prim)
        where = str(self.light_prim.GetPath())
        with _naming(f"light {where}: its transform"):
            matrix = UsdGeom.Xformable(self.light_prim).ComputeLocalToWorldTransform(time)
        travel = matrix.TransformDir(Gf.Vec3d(0, 0, -1))
        direction = self.core_from_stage[:3, :3] @ np.array(travel)
        norm = float(np.linalg.norm(direction))
        if not (math.isfinite(norm) and norm > 0):
            raise StageError(f"light {where}: its transform gives no direction")
        intensity = float(light.GetIntensityAttr().Get(time))
        exposure = float(light.GetExposureAttr().Get(time))
        color = np.array(light.GetColorAttr().Get(time), dtype=np.float64)
        if light.GetEnableColorTemperatureAttr().Get(time):
            kelvin = float(light.GetColorTemperatureAttr().Get(time))
            color = color * np.array(UsdLux.BlackbodyTemperatureAsRgb(kelvin))
        visible = (
            UsdGeom.Imageable(self.light_prim).ComputeVisibility(time) != UsdGeom.Tokens.invisible
        )
        strength = intensity * 2.0**exposure * intensity_scale if visible else 0.0
        if not (math.isfinite(strength) and strength >= 0):
            raise StageError(
                f"light {where}: intensity x 2^exposure x crepuscular:intensityScale is {strength}"
            )
        diameter = math.radians(float(light.GetAngleAttr().Get(time))) * angle_scale
        if not (math.isfinite(diameter) and diameter >= 0):
            raise StageError(
                f"light {where}: inputs:angle x crepuscular:angleScale is {math.degrees(diameter)}°"
            )
        return {
            "direction": [float(v) for v in direction / norm],
            "color": [float(v) for v in color],
            "strength": strength,
            "angular_diameter": diameter,
        }
