"""The USD layer a render writes: RenderProducts and RenderVars for the EXR sequences.

The layer is meant to be sublayered into the shot. Under `/Render` it holds:

- `CrepuscularSettings` (RenderSettings): camera, resolution, pixel aspect and aperture
  conform policy where not the defaults, products, and the exact
  scene description used per frame (everything but the meshes) as the time-sampled
  string `crepuscular:sceneSettings`, plus the command's inputs in `customData`;
- `Products/shafts` (and `Products/composite` with `--beauty`): RenderProducts whose
  time-sampled `productName` is each frame's file, relative to the layer;
- `Vars/*`: one RenderVar per AOV (`volume`, `visibility`, `depth`; `composite`), each
  with the channels it reads and a time-sampled asset `crepuscular:file`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender

__all__ = ["OutputLayerError", "RenderRecord", "write_output_layer"]

ROOT = Sdf.Path("/Render")


class OutputLayerError(RuntimeError):
    """The output layer could not be authored or saved."""


@dataclass
class RenderRecord:
    """What one render command produced, frame by frame."""

    camera_path: Sdf.Path
    light_path: Sdf.Path
    stage_path: str
    resolution: tuple[int, int]
    meters_per_unit: float
    up_axis: str
    time_codes_per_second: float
    #: A pixel's width over its height, and how the camera's aperture was fitted.
    pixel_aspect: float = 1.0
    conform: str = "expandAperture"
    #: Per frame: the layer EXR written.
    shafts: dict[float | None, str] = field(default_factory=dict)
    #: Per frame: the composited EXR written (with --beauty).
    composites: dict[float | None, str] = field(default_factory=dict)
    beauties: dict[float | None, str] = field(default_factory=dict)
    #: Per frame: the exact settings (scene description without meshes).
    settings: dict[float | None, dict[str, Any]] = field(default_factory=dict)
    inputs: dict[str, Any] = field(default_factory=dict)


#: AOV name -> (data type, channels in the EXR).
LAYER_VARS: Mapping[str, tuple[str, Sequence[str]]] = {
    "volume": ("color4f", ("volume.R", "volume.G", "volume.B", "volume.A")),
    "visibility": ("float", ("visibility",)),
    "depth": ("float", ("depth",)),
}
COMPOSITE_VARS: Mapping[str, tuple[str, Sequence[str]]] = {
    "composite": ("color4f", ("R", "G", "B", "A")),
}


def _time_code(frame: float | None) -> Usd.TimeCode:
    return Usd.TimeCode.Default() if frame is None else Usd.TimeCode(frame)


def _check(ok: object, what: str) -> None:
    if not ok:
        raise OutputLayerError(f"could not author {what}")


def _relative(path: str, layer_dir: str) -> str:
    try:
        relative = os.path.relpath(path, layer_dir)
    except ValueError:  # another drive on Windows
        return os.path.abspath(path)
    return relative if relative.startswith("..") else "./" + relative.replace(os.sep, "/")


def _author_vars(
    stage: Usd.Stage,
    aovs: Mapping[str, tuple[str, Sequence[str]]],
    files: Mapping[float | None, str],
    layer_dir: str,
) -> list[Sdf.Path]:
    paths = []
    for name, (data_type, channels) in aovs.items():
        var = UsdRender.Var.Define(stage, ROOT.AppendPath(f"Vars/{name}"))
        _check(var, f"RenderVar {name}")
        _check(var.CreateSourceNameAttr().Set(name), f"{name}.sourceName")
        _check(var.CreateSourceTypeAttr().Set(UsdRender.Tokens.raw), f"{name}.sourceType")
        _check(var.CreateDataTypeAttr().Set(data_type), f"{name}.dataType")
        prim = var.GetPrim()
        channels_attr = prim.CreateAttribute("crepuscular:channels", Sdf.ValueTypeNames.StringArray)
        _check(channels_attr.Set(list(channels)), f"{name}.crepuscular:channels")
        file_attr = prim.CreateAttribute("crepuscular:file", Sdf.ValueTypeNames.Asset)
        for frame, path in files.items():
            _check(
                file_attr.Set(Sdf.AssetPath(_relative(path, layer_dir)), _time_code(frame)),
                f"{name}.crepuscular:file at {frame}",
            )
        paths.append(var.GetPath())
    return paths


def _author_image(prim: UsdRender.SettingsBase, record: RenderRecord, name: str) -> None:
    """The pixel aspect and conform policy the image was rendered with, where they are not
    the schema's fallbacks."""
    if record.pixel_aspect != 1.0:
        attribute = prim.CreatePixelAspectRatioAttr()
        _check(attribute.Set(record.pixel_aspect), f"{name}.pixelAspectRatio")
    if record.conform != UsdRender.Tokens.expandAperture:
        attribute = prim.CreateAspectRatioConformPolicyAttr()
        _check(attribute.Set(record.conform), f"{name}.aspectRatioConformPolicy")


def _author_product(
    stage: Usd.Stage,
    name: str,
    record: RenderRecord,
    files: Mapping[float | None, str],
    var_paths: list[Sdf.Path],
    layer_dir: str,
) -> Sdf.Path:
    product = UsdRender.Product.Define(stage, ROOT.AppendPath(f"Products/{name}"))
    _check(product, f"RenderProduct {name}")
    _check(product.CreateProductTypeAttr().Set(UsdRender.Tokens.raster), f"{name}.productType")
    name_attr = product.CreateProductNameAttr()
    for frame, path in files.items():
        _check(name_attr.Set(_relative(path, layer_dir), _time_code(frame)), f"{name}.productName")
    _check(product.CreateCameraRel().SetTargets([record.camera_path]), f"{name}.camera")
    _check(product.CreateResolutionAttr().Set(Gf.Vec2i(*record.resolution)), f"{name}.resolution")
    _author_image(product, record, name)
    _check(product.CreateOrderedVarsRel().SetTargets(var_paths), f"{name}.orderedVars")
    return product.GetPath()


def write_output_layer(path: str, record: RenderRecord) -> None:
    """Authors and saves the layer; raises OutputLayerError on any refusal."""
    layer_dir = os.path.dirname(os.path.abspath(path))
    try:
        stage = Usd.Stage.CreateNew(path)
    except Exception as error:  # Tf.ErrorException
        raise OutputLayerError(f"cannot create {path}: {error}") from error
    _check(stage, f"the layer {path}")
    _check(UsdGeom.SetStageMetersPerUnit(stage, record.meters_per_unit), "metersPerUnit")
    _check(UsdGeom.SetStageUpAxis(stage, record.up_axis), "upAxis")
    frames = sorted(frame for frame in record.shafts if frame is not None)
    if frames:
        stage.SetStartTimeCode(frames[0])
        stage.SetEndTimeCode(frames[-1])
    stage.SetTimeCodesPerSecond(record.time_codes_per_second)
    root = UsdGeom.Scope.Define(stage, ROOT)
    _check(root, "/Render")
    stage.SetDefaultPrim(root.GetPrim())
    _check(UsdGeom.Scope.Define(stage, ROOT.AppendChild("Products")), "/Render/Products")
    _check(UsdGeom.Scope.Define(stage, ROOT.AppendChild("Vars")), "/Render/Vars")
    products = [
        _author_product(
            stage,
            "shafts",
            record,
            record.shafts,
            _author_vars(stage, LAYER_VARS, record.shafts, layer_dir),
            layer_dir,
        )
    ]
    if record.composites:
        products.append(
            _author_product(
                stage,
                "composite",
                record,
                record.composites,
                _author_vars(stage, COMPOSITE_VARS, record.composites, layer_dir),
                layer_dir,
            )
        )
    settings = UsdRender.Settings.Define(stage, ROOT.AppendChild("CrepuscularSettings"))
    _check(settings, "RenderSettings")
    _check(settings.CreateCameraRel().SetTargets([record.camera_path]), "settings camera")
    _check(settings.CreateProductsRel().SetTargets(products), "settings products")
    _check(settings.CreateResolutionAttr().Set(Gf.Vec2i(*record.resolution)), "settings resolution")
    _author_image(settings, record, "settings")
    prim = settings.GetPrim()
    scene_attr = prim.CreateAttribute("crepuscular:sceneSettings", Sdf.ValueTypeNames.String)
    for frame, values in record.settings.items():
        text = json.dumps(values, sort_keys=True)
        _check(scene_attr.Set(text, _time_code(frame)), f"crepuscular:sceneSettings at {frame}")
    light_rel = prim.CreateRelationship("crepuscular:light")
    _check(light_rel.SetTargets([record.light_path]), "crepuscular:light")
    prim.SetCustomDataByKey("crepuscular:stage", record.stage_path)
    prim.SetCustomDataByKey("crepuscular:inputs", json.dumps(record.inputs, sort_keys=True))
    if record.beauties:
        beauty_attr = prim.CreateAttribute("crepuscular:beauty", Sdf.ValueTypeNames.Asset)
        for frame, beauty in record.beauties.items():
            _check(
                beauty_attr.Set(Sdf.AssetPath(_relative(beauty, layer_dir)), _time_code(frame)),
                "crepuscular:beauty",
            )
    if not stage.GetRootLayer().Save():
        raise OutputLayerError(f"cannot save {path}")
