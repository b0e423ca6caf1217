"""The codeless `CrepuscularLightAPI` schema: registration, reading and authoring.

The schema ships as `resources/plugInfo.json` + `resources/generatedSchema.usda` and is
registered with `Plug.Registry` when this package is imported. Its attributes map one to
one onto the renderer's scene description (`medium`, `render`, the sun's intensity scale)
and style preset; `attributes.py` holds that map as plain data, shared with the Blender
add-on's export hook, and this module adds the conversions. Lengths are authored in stage
units and converted to metres here.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Plug, Sdf, Usd, UsdGeom, UsdLux, UsdVol

import crepuscular
from crepuscular_usd.attributes import (
    API_NAME,
    ATTRIBUTES,
    HOLES_OBJECTS,
    MEDIUM_EXTENT,
    TF_ASSET,
    TF_JSON,
)

__all__ = [
    "API_NAME",
    "PROPERTY_NAMES",
    "SchemaError",
    "apply_schema",
    "fallback",
    "read_light_settings",
    "register",
]

RESOURCES = Path(__file__).resolve().parent / "resources"


class SchemaError(ValueError):
    """An unusable CrepuscularLightAPI value; the message names the prim and attribute."""


def register() -> None:
    """Registers the schema plug-in (idempotent). Raises RuntimeError if USD refuses it."""
    registry = Plug.Registry()
    registry.RegisterPlugins(os.fspath(RESOURCES / "plugInfo.json"))
    if not Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(API_NAME):
        raise RuntimeError(f"{API_NAME} did not register from {RESOURCES}")


def _definition() -> Usd.PrimDefinition:
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(API_NAME)
    if not definition:
        raise RuntimeError(f"{API_NAME} is not registered")
    return definition


@functools.cache
def _allowed_tokens(name: str) -> tuple[str, ...]:
    """The tokens the schema allows for attribute `name`; empty where it lists none."""
    return tuple(_definition().GetPropertyMetadata(name, "allowedTokens") or ())


def fallback(name: str) -> Any:
    """The schema's fallback value for attribute `name`."""
    return _definition().GetAttributeFallbackValue(name)


@dataclass(frozen=True)
class _Field:
    """One attribute: where its value goes and how it converts."""

    #: ("medium", "extinction"), ("render", "steps"), ("style", "closing", "radius") ...
    target: tuple[str, ...]
    #: Stage units per unit of the value: 1 for lengths, -1 for per-length, 0 for none.
    length_power: int = 0
    convert: Callable[[Any], Any] | None = None
    #: Negative means "unset" (the key is left out), for the core's optional values.
    negative_unset: bool = False


def _token_to_snake(value: Any) -> str:
    text = str(value)
    return "".join("_" + c.lower() if c.isupper() else c for c in text)


def _setting_or_flag(value: Any) -> str:
    # Layers written while the attribute was a bool still author one.
    if isinstance(value, bool):
        return "on" if value else "off"
    return str(value)


def _vec3(value: Any) -> list[float]:
    return [float(c) for c in value]


#: Conversions by USD value type, and where one attribute differs from its type's.
_CONVERT_BY_TYPE: dict[str, Callable[[Any], Any]] = {
    "float": float,
    "int": int,
    "bool": bool,
    "token": str,
    "color3f": _vec3,
    "point3f": _vec3,
}
_CONVERT_BY_NAME: dict[str, Callable[[Any], Any]] = {
    "crepuscular:medium:phase": _token_to_snake,
    "crepuscular:exactRayEnds": _setting_or_flag,
}

#: The attributes that map onto one scene-description value (the shared table in
#: `attributes.py`, with conversions); the transfer function is read on its own.
FIELDS: dict[str, _Field] = {
    name: _Field(
        attribute.target,
        attribute.length_power,
        _CONVERT_BY_NAME.get(name, _CONVERT_BY_TYPE[attribute.type_name]),
        attribute.negative_unset,
    )
    for name, attribute in ATTRIBUTES.items()
    if attribute.target
}

#: Every property the schema defines; tests check that the definition has exactly these.
PROPERTY_NAMES = frozenset(ATTRIBUTES) | {MEDIUM_EXTENT, HOLES_OBJECTS}


@dataclass
class LightSettings:
    """What the schema on a light says at one time code, in renderer units."""

    medium: dict[str, Any]
    #: What the schema adds to the light's own attributes: `intensity_scale`, `angle_scale`.
    sun: dict[str, Any]
    render: dict[str, Any]
    style: dict[str, Any]
    #: Prim whose bounds make the medium's box, or None for an unbounded medium.
    extent_prim: Usd.Prim | None
    #: Roots whose meshes get holes (the `crepuscular:holes:objects` targets).
    holes_roots: list[Sdf.Path]
    has_api: bool


def _value(prim: Usd.Prim, name: str, time: Usd.TimeCode, has_api: bool) -> Any:
    return _authored_or_fallback(prim, name, time, has_api)[0]


def _authored_or_fallback(
    prim: Usd.Prim, name: str, time: Usd.TimeCode, has_api: bool
) -> tuple[Any, bool]:
    """The attribute's value at `time` and True, or its fallback and False where the API is
    absent or the attribute has no value."""
    if has_api:
        attr = prim.GetAttribute(name)
        if attr:
            value = attr.Get(time)
            if value is not None:
                return value, True
    return fallback(name), False


def _stage_units_per_metre_power(meters_per_unit: float, length_power: int) -> float:
    """The factor that takes a value of `length_power` from metres into stage units."""
    return meters_per_unit ** (-length_power)


def _negative(value: Any) -> bool:
    """Whether a number, or any component of a vector, is negative: an optional value's
    "unset"."""
    if isinstance(value, (int, float)):
        return value < 0
    return any(float(component) < 0 for component in value)


def _fallbacks_in_metres(stage: Usd.Stage) -> bool:
    """Whether the fallbacks count in metres on `stage`: where it declares `metersPerUnit`.
    A stage that does not is read in centimetres, as USD has it, but is most often authored
    with no unit in mind, and the fallbacks count in its own units, as if it were metres."""
    return bool(UsdGeom.StageHasAuthoredMetersPerUnit(stage))


def _single_target(prim: Usd.Prim, name: str) -> Usd.Prim | None:
    rel = prim.GetRelationship(name)
    if not rel:
        return None
    targets = rel.GetForwardedTargets()
    if not targets:
        return None
    if len(targets) > 1:
        raise SchemaError(f"{prim.GetPath()}.{name} targets {len(targets)} prims; give exactly one")
    target = prim.GetStage().GetPrimAtPath(targets[0])
    if not target or not target.IsActive():
        raise SchemaError(f"{prim.GetPath()}.{name} targets {targets[0]}, which does not exist")
    return target


def read_light_settings(
    prim: Usd.Prim, time: Usd.TimeCode, meters_per_unit: float
) -> LightSettings:
    """Reads every schema attribute of `prim` at `time` (fallbacks where the API is absent).

    Authored lengths become metres. Fallbacks are the renderer's defaults in metres where
    the stage declares its units, so that a light without the API renders a centimetre stage
    as it does the same stage in metres (read as stage units, they made its fog 100 times as
    dense and its reach 1 m), and in stage units where it does not
    (`_fallbacks_in_metres`). `crepuscular:holes:pivot` stays in stage space for the
    caller to transform. Raises `SchemaError` naming the attribute for unusable values.
    """
    has_api = prim.HasAPI(API_NAME)
    fallbacks_in_metres = _fallbacks_in_metres(prim.GetStage())
    groups: dict[str, dict[str, Any]] = {"medium": {}, "sun": {}, "render": {}, "style": {}}
    for name, spec in FIELDS.items():
        raw, authored = _authored_or_fallback(prim, name, time, has_api)
        allowed = _allowed_tokens(name)
        if allowed and isinstance(raw, str) and raw not in allowed:
            raise SchemaError(
                f"{prim.GetPath()}.{name}: {raw!r} is not one of {', '.join(allowed)}"
            )
        if isinstance(raw, int) and not isinstance(raw, bool) and raw < 0:
            raise SchemaError(f"{prim.GetPath()}.{name}: {raw} is negative")
        try:
            value = spec.convert(raw) if spec.convert else raw
        except (TypeError, ValueError) as error:
            raise SchemaError(f"{prim.GetPath()}.{name}: unusable value {raw!r}") from error
        if isinstance(value, float) and not math.isfinite(value):
            raise SchemaError(f"{prim.GetPath()}.{name}: {value} is not finite")
        if spec.negative_unset and _negative(value):
            continue
        if spec.length_power and (authored or not fallbacks_in_metres):
            factor = _stage_units_per_metre_power(meters_per_unit, spec.length_power)
            value = [v / factor for v in value] if isinstance(value, list) else value / factor
        node = groups[spec.target[0]]
        for key in spec.target[1:-1]:
            node = node.setdefault(key, {})
        node[spec.target[-1]] = value
    style = groups["style"]
    for operator in ("closing", "silhouette", "holes"):
        if not style[operator].pop("enable"):
            del style[operator]
    holes_roots: list[Sdf.Path] = []
    if has_api:
        rel = prim.GetRelationship(HOLES_OBJECTS)
        holes_roots = list(rel.GetForwardedTargets()) if rel else []
    tf = _read_tf(prim, time, has_api)
    if tf is not None:
        style["tf"] = tf
    return LightSettings(
        medium=groups["medium"],
        sun=groups["sun"],
        render=groups["render"],
        style=style,
        extent_prim=_single_target(prim, MEDIUM_EXTENT) if has_api else None,
        holes_roots=holes_roots,
        has_api=has_api,
    )


def _read_tf(prim: Usd.Prim, time: Usd.TimeCode, has_api: bool) -> dict[str, Any] | None:
    if not has_api:
        return None
    asset = _value(prim, TF_ASSET, time, has_api)
    inline = str(_value(prim, TF_JSON, time, has_api) or "")
    authored = asset.path if asset is not None else ""
    if authored and inline.strip():
        raise SchemaError(
            f"{prim.GetPath()}: both {TF_ASSET} and {TF_JSON} are set; author only one"
        )
    if authored:
        resolved = asset.resolvedPath
        if not resolved:
            raise SchemaError(f"{prim.GetPath()}.{TF_ASSET}: cannot resolve @{authored}@")
        try:
            text = Path(resolved).read_text(encoding="utf-8")
        except OSError as error:
            raise SchemaError(
                f"{prim.GetPath()}.{TF_ASSET}: cannot read {resolved}: {error}"
            ) from error
        where = f"{prim.GetPath()}.{TF_ASSET} ({resolved})"
        return _beside(_parse_tf(text, where), Path(resolved).parent, where)
    if inline.strip():
        return _parse_tf(inline, f"{prim.GetPath()}.{TF_JSON}")
    return None


def _parse_tf(text: str, where: str) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise SchemaError(f"{where}: not JSON: {error}") from error
    if not isinstance(data, dict):
        raise SchemaError(f"{where}: expected a JSON object")
    # A whole style preset carries its TF under "tf"; anything else is the TF itself.
    if "tf" in data:
        tf = data["tf"]
    elif "version" in data:
        raise SchemaError(f"{where}: the style preset has no tf")
    else:
        tf = data
    if not isinstance(tf, dict):
        raise SchemaError(f"{where}: its tf is not a JSON object")
    return tf


def _beside(tf: dict[str, Any], folder: Path, where: str) -> dict[str, Any]:
    """The TF with its relative image paths joined to `folder`, the preset asset's own, as
    USD resolves asset paths relative to the layer that authors them."""
    style = {"version": crepuscular.STYLE_VERSION, "tf": tf}
    try:
        rebased: dict[str, Any] = crepuscular.load_style(style, base_dir=folder)["tf"]
    except crepuscular.InvalidInputError as error:
        raise SchemaError(f"{where}: {error}") from error
    return rebased


def box_from_extent_prim(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    """Column-vector 4x4 mapping the cube [-1, 1]^3 onto the prim's local box."""
    where = str(prim.GetPath())
    if prim.IsA(UsdGeom.Cube):
        size = UsdGeom.Cube(prim).GetSizeAttr().Get(time)
        low = np.full(3, -0.5 * float(size))
        high = -low
    elif prim.IsA(UsdGeom.Mesh):
        points = UsdGeom.Mesh(prim).GetPointsAttr().Get(time)
        if points is None or len(points) == 0:
            raise SchemaError(f"medium extent {where}: the mesh has no points")
        array = np.array(points, dtype=np.float64).reshape(-1, 3)
        low, high = array.min(axis=0), array.max(axis=0)
    elif prim.IsA(UsdVol.Volume) or prim.IsA(UsdGeom.Boundable):
        extent = UsdGeom.Boundable(prim).GetExtentAttr().Get(time)
        if extent is None or len(extent) != 2:
            raise SchemaError(f"medium extent {where}: author its extent attribute")
        low = np.array(extent[0], dtype=np.float64)
        high = np.array(extent[1], dtype=np.float64)
    else:
        raise SchemaError(
            f"medium extent {where} is a {prim.GetTypeName() or 'typeless prim'}; "
            "use a Cube, a box Mesh or a Volume"
        )
    half = 0.5 * (high - low)
    if not np.all(np.isfinite(half)) or np.any(half <= 0):
        raise SchemaError(f"medium extent {where} has an empty box ({low} to {high})")
    box = np.diag([*half, 1.0])
    box[:3, 3] = 0.5 * (high + low)
    return box


def _default_in_stage_units(name: str, meters_per_unit: float) -> Any:
    """The fallback of attribute `name`, a renderer default in metres, in stage units; the
    negative "unset" of an optional length stays as it is."""
    value = fallback(name)
    field = FIELDS.get(name)
    if field is None or not field.length_power or (field.negative_unset and _negative(value)):
        return value
    return value * _stage_units_per_metre_power(meters_per_unit, field.length_power)


def apply_schema(
    light: Usd.Prim,
    *,
    medium_extent: Sdf.Path | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> None:
    """Applies CrepuscularLightAPI to a DistantLight and authors every attribute's default,
    lengths in the stage's units where it declares them (`_fallbacks_in_metres`);
    `overrides` are in stage units already."""
    if not light.IsA(UsdLux.DistantLight):
        raise SchemaError(
            f"{light.GetPath()} is a {light.GetTypeName() or 'typeless prim'}; "
            f"{API_NAME} applies to DistantLight only"
        )
    if not light.ApplyAPI(API_NAME):
        raise SchemaError(f"could not apply {API_NAME} to {light.GetPath()}")
    definition = _definition()
    stage = light.GetStage()
    meters_per_unit = UsdGeom.GetStageMetersPerUnit(stage) if _fallbacks_in_metres(stage) else 1.0
    overrides = overrides or {}
    for name in sorted(PROPERTY_NAMES - {MEDIUM_EXTENT, HOLES_OBJECTS}):
        spec = definition.GetAttributeDefinition(name)
        attr = light.CreateAttribute(name, spec.GetTypeName())
        if name in overrides:
            value = overrides[name]
        else:
            value = _default_in_stage_units(name, meters_per_unit)
        if not attr or not attr.Set(value):
            raise SchemaError(f"could not author {light.GetPath()}.{name}")
    extent_rel = light.CreateRelationship(MEDIUM_EXTENT)
    holes_rel = light.CreateRelationship(HOLES_OBJECTS)
    if not extent_rel or not holes_rel:
        raise SchemaError(f"could not author the relationships of {light.GetPath()}")
    if medium_extent is not None and not extent_rel.SetTargets([medium_extent]):
        raise SchemaError(f"could not target {medium_extent} from {light.GetPath()}")
