"""A sun lamp's style settings to and from the core's style-preset format.

`style_from_light` builds the preset dict the core takes (`style=`), `apply_preset` fills a
lamp's settings from a preset (read and validated by `crepuscular.load_style`), and
`save_preset` writes the lamp's style back as a preset file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any

import bpy
import numpy as np

import crepuscular


class StyleError(ValueError):
    """A style setting the add-on cannot express; the message names the setting."""


def style_from_light(
    settings: Any, *, time: float, hole_objects: Sequence[int], name: str = "light"
) -> dict[str, Any]:
    """The style preset of a lamp's `crepuscular` settings at `time` seconds."""
    style: dict[str, Any] = {"version": crepuscular.STYLE_VERSION, "time": float(time)}
    if settings.use_closing:
        style["closing"] = {
            "operation": settings.closing_operation,
            "kernel": settings.closing_kernel,
            "radius": float(settings.closing_radius),
        }
    if settings.use_silhouette:
        style["silhouette"] = {
            "operation": settings.silhouette_operation,
            "length": float(settings.silhouette_length),
        }
    if settings.use_holes:
        style["holes"] = {
            "frequency": float(settings.holes_frequency),
            "persistence": float(settings.holes_persistence),
            "octaves": int(settings.holes_octaves),
            "threshold": float(settings.holes_threshold),
            "grid_size": int(settings.holes_grid_size),
            "seed": int(settings.holes_seed),
            "speed": float(settings.holes_speed),
            "warp": float(settings.holes_warp),
            "pivot": [float(v) for v in settings.holes_pivot],
            "objects": [int(i) for i in hole_objects],
        }
    if settings.use_tf:
        style["tf"] = {
            "mode": settings.tf_mode,
            "depth_range": {
                "near": float(settings.tf_depth_near),
                "far": float(settings.tf_depth_far),
            },
            "resolution": int(settings.tf_resolution),
            "layers": [
                _layer_dict(layer, f"{name}.crepuscular.tf_layers[{i}]")
                for i, layer in enumerate(settings.tf_layers)
            ],
        }
    return style


def _rgba(value: Any) -> list[float]:
    return [float(v) for v in value]


def _layer_dict(layer: Any, path: str) -> dict[str, Any]:
    result: dict[str, Any] = {
        "kind": layer.kind,
        "opacity": float(layer.opacity),
        "blend": layer.blend,
    }
    if layer.kind == "solid":
        result["color"] = _rgba(layer.color)
    elif layer.kind == "gradient":
        if layer.shape == "linear":
            result["shape"] = {"kind": "linear", "from": list(layer.start), "to": list(layer.end)}
        else:
            result["shape"] = {
                "kind": "radial",
                "center": list(layer.center),
                "radius": float(layer.radius),
            }
        result["stops"] = [
            {"position": float(s.position), "color": _rgba(s.color)} for s in layer.stops
        ]
    elif layer.kind == "image":
        result["image"] = _image_pixels(layer.image, path)
    else:
        constraints = []
        for c in layer.constraints:
            entry: dict[str, Any] = {"position": list(c.position), "color": _rgba(c.color)}
            if c.use_world_point:
                entry["world_point"] = [float(v) for v in c.world_point]
            constraints.append(entry)
        result["constraints"] = constraints
    return result


def _image_pixels(image: bpy.types.Image | None, path: str) -> dict[str, Any]:
    """An Image datablock as straight linear RGBA pixels, rows top to bottom."""
    if image is None:
        raise StyleError(f"{path}.image: an image layer needs an image")
    width, height = image.size
    if width == 0 or height == 0:
        raise StyleError(f"{path}.image: '{image.name}' has no pixels (missing file?)")
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    rows = pixels.reshape(height, width, 4)[::-1]  # Blender stores rows bottom up
    if image.alpha_mode == "PREMUL":
        alpha = rows[..., 3:4]
        rows = np.where(alpha > 0, rows / np.maximum(alpha, 1e-12), 0.0)
        rows[..., 3:4] = alpha
    return {
        "kind": "pixels",
        "width": width,
        "height": height,
        "rgba": np.asarray(rows, dtype=np.float32).reshape(-1, 4).tolist(),
    }


def apply_preset(settings: Any, preset: str | os.PathLike[str] | dict[str, Any]) -> None:
    """Fills a lamp's style settings from a preset (path, JSON text or dict).

    Operators and the TF missing from the preset are switched off. Hole `objects` ids are
    not read: in Blender, the objects marked 'Takes Holes' get holes.
    """
    style = crepuscular.load_style(preset)
    tf = style.get("tf")
    if tf is not None and tf.get("keyframes"):
        raise StyleError(
            "style.tf.keyframes: TF key frames are not read into Blender; keyframe the TF "
            "layers' values with Blender keyframes instead"
        )
    closing = style.get("closing")
    settings.use_closing = closing is not None
    if closing is not None:
        settings.closing_operation = closing["operation"]
        settings.closing_kernel = closing["kernel"]
        settings.closing_radius = closing["radius"]
    silhouette = style.get("silhouette")
    settings.use_silhouette = silhouette is not None
    if silhouette is not None:
        settings.silhouette_operation = silhouette["operation"]
        settings.silhouette_length = silhouette["length"]
    holes = style.get("holes")
    settings.use_holes = holes is not None
    if holes is not None:
        for key in (
            "frequency",
            "persistence",
            "octaves",
            "threshold",
            "grid_size",
            "seed",
            "speed",
            "warp",
            "pivot",
        ):
            setattr(settings, f"holes_{key}", holes[key])
    settings.use_tf = tf is not None
    settings.tf_layers.clear()
    if tf is None:
        return
    settings.tf_mode = tf["mode"]
    settings.tf_depth_near = tf["depth_range"]["near"]
    settings.tf_depth_far = tf["depth_range"]["far"]
    settings.tf_resolution = tf["resolution"]
    for index, source in enumerate(tf["layers"]):
        layer = settings.tf_layers.add()
        layer.name = f"{source['kind'].title()} {index + 1}"
        layer.kind = source["kind"]
        layer.opacity = source["opacity"]
        layer.blend = source["blend"]
        if layer.kind == "solid":
            layer.color = source["color"]
        elif layer.kind == "gradient":
            shape = source["shape"]
            layer.shape = shape["kind"]
            if shape["kind"] == "linear":
                layer.start, layer.end = shape["from"], shape["to"]
            else:
                layer.center, layer.radius = shape["center"], shape["radius"]
            for stop in source["stops"]:
                item = layer.stops.add()
                item.position, item.color = stop["position"], stop["color"]
        elif layer.kind == "image":
            layer.image = _image_from_source(source["image"], f"style.tf.layers[{index}]")
        else:
            for constraint in source["constraints"]:
                item = layer.constraints.add()
                item.position, item.color = constraint["position"], constraint["color"]
                if constraint.get("world_point") is not None:
                    item.use_world_point = True
                    item.world_point = constraint["world_point"]
    settings.active_tf_layer = max(0, len(settings.tf_layers) - 1)


def _image_from_source(source: dict[str, Any], path: str) -> bpy.types.Image:
    if source["kind"] == "file":
        try:
            return bpy.data.images.load(os.fspath(source["path"]), check_existing=True)
        except RuntimeError as error:
            raise StyleError(f"{path}.image.path: {error}") from error
    width, height = int(source["width"]), int(source["height"])
    image = bpy.data.images.new("TF Layer", width, height, alpha=True, float_buffer=True)
    rows = np.asarray(source["rgba"], dtype=np.float32).reshape(height, width, 4)[::-1]
    image.alpha_mode = "STRAIGHT"
    image.pixels.foreach_set(np.ascontiguousarray(rows).ravel())
    image.pack()
    return image


def bake_tf_image(settings: Any, *, time: float, name: str) -> bpy.types.Image:
    """Bakes a lamp's TF stack at `time` seconds into the float Image `TF <name>` (created
    or resized), stores it in `settings.tf_image`, and returns it."""
    style = style_from_light(settings, time=time, hole_objects=[], name=name)
    if "tf" not in style:
        raise StyleError(f"{name}.crepuscular.use_tf: the transfer function is off")
    texels = crepuscular.bake_tf(style, time=time)
    size = texels.shape[0]
    image = settings.tf_image
    if image is None:
        image = bpy.data.images.new(f"TF {name}", size, size, alpha=True, float_buffer=True)
        settings.tf_image = image
    elif tuple(image.size) != (size, size):
        image.scale(size, size)
    image.alpha_mode = "PREMUL"
    # Row j of the texture is depth u rising, as Blender stores rows bottom up.
    image.pixels.foreach_set(np.ascontiguousarray(texels, dtype=np.float32).ravel())
    image.update()
    return image


def save_preset(settings: Any, path: str | os.PathLike[str], *, name: str = "light") -> None:
    """Writes a lamp's style as a preset file (validated by the core before writing)."""
    style = style_from_light(settings, time=0.0, hole_objects=[], name=name)
    style.pop("time")
    if "holes" in style:
        style["holes"].pop("objects")
    crepuscular.load_style(style)  # raises naming the field if the core would refuse it
    with open(path, "w", encoding="utf-8") as file:
        json.dump(style, file, indent=2)
        file.write("\n")
