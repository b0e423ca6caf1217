"""crepuscular: stylized volumetric light shafts.

Render a scene description (a dict, JSON text or a .json file) with `render`, or render
geometry you already hold in numpy arrays with `render_arrays`. Both return `Layers`.

The scene description is the JSON schema of the Rust core: the keys `version`, `camera`,
`sun`, `medium`, `meshes` and `render`. Unknown keys are errors that name the key, and every
unusable value raises `InvalidInputError` whose `field` names it (e.g. "camera.width").

Renders release the GIL. While one runs, the calling thread wakes every 50 ms to call
`progress(fraction)` and to handle Ctrl-C; an exception from either cancels the render and
propagates. Do not modify the input arrays from the progress callback: the renderer reads
them in place.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, TypeAlias

import numpy as np
import numpy.typing as npt

from crepuscular import _convert, _core
from crepuscular._points import (
    SPHERE_OUTLINE_TOLERANCE,
    SPHERE_TRIANGLES,
    SPHERE_VERTICES,
    point_sphere_visibility,
    point_spheres,
)
from crepuscular._strands import (
    BLOCKS_SUN,
    CATMULL_ROM_STEPS,
    SEEN_BY_CAMERA,
    STRAND_SHADOW_GAP,
    TUBE_SIDES,
    strand_ribbons,
    strand_tubes,
)
from crepuscular.errors import CancelledError, CrepuscularError, ExrError, InvalidInputError

__all__ = [
    "BLOCKS_SUN",
    "CATMULL_ROM_STEPS",
    "EXR_COMPRESSIONS",
    "SCENE_VERSION",
    "SEEN_BY_CAMERA",
    "SPHERE_OUTLINE_TOLERANCE",
    "SPHERE_TRIANGLES",
    "SPHERE_VERTICES",
    "STRAND_SHADOW_GAP",
    "STYLE_VERSION",
    "SUN_DISC_AS_POINT",
    "SUN_DISC_SAMPLES",
    "TUBE_SIDES",
    "AlphaMask",
    "CancelledError",
    "CrepuscularError",
    "DepthKind",
    "ExrCompression",
    "ExrError",
    "InvalidInputError",
    "Layers",
    "MaskFilter",
    "MaskWrap",
    "ProgressCallback",
    "SceneLike",
    "StyleLike",
    "__version__",
    "bake_tf",
    "builtin_scene",
    "builtin_scene_names",
    "composite",
    "fog_box_unreached",
    "load_style",
    "point_sphere_visibility",
    "point_spheres",
    "read_exr",
    "read_exr_pixel_aspect",
    "release_kept_buffers",
    "render",
    "render_arrays",
    "scene_from_json",
    "strand_ribbons",
    "strand_tubes",
    "sun_disc_samples",
    "validate_scene",
    "write_exr",
    "write_exr_channels",
    "write_preview_png",
]

__version__: str = _core.__version__

#: The scene-description version this build reads and writes.
SCENE_VERSION: int = _core.SCENE_VERSION

#: The style-preset version this build reads and writes.
STYLE_VERSION: int = _core.STYLE_VERSION

#: The widest sun disc (angular diameter, radians) that hosts render as a point sun: a
#: little over the real sun's 0.53°, whose penumbrae are narrower than most shafts' detail.
SUN_DISC_AS_POINT: float = math.radians(0.6)

#: Directions over a wider disc whose frames the hosts average (`render.sun_disc_samples`):
#: under a straight roof edge and a 6° disc, the penumbra's light is within 2.6% of the
#: disc's exact share on average (64 directions: 0.9%; a point sun: 21%). Each direction
#: costs a frame's scattering.
SUN_DISC_SAMPLES: int = 16


def fog_box_unreached(medium: Mapping[str, Any], volume: npt.ArrayLike) -> bool:
    """Whether `medium` (a scene description's member) is a box of fog that attenuates
    light and that no view ray of the frame whose `volume` layer (H, W, 4) this is crossed:
    every alpha 0. The box is then out of view, behind surfaces or past the maximum
    distance, which a host should say, as the frame shows no fog at all."""
    extent = medium.get("extent") or {}
    densest = max([medium.get("extinction", 0.0), *(medium.get("channel_extinction") or [])])
    alpha = np.asarray(volume)[..., 3]
    return extent.get("kind") == "box" and densest > 0 and not alpha.any()


def sun_disc_samples(angular_diameter: float) -> int:
    """`render.sun_disc_samples` for a sun of `angular_diameter` radians, as the hosts set
    it: one direction (a point sun) up to `SUN_DISC_AS_POINT`, else `SUN_DISC_SAMPLES`."""
    return 1 if angular_diameter <= SUN_DISC_AS_POINT else SUN_DISC_SAMPLES


#: A scene description: a mapping, JSON text (starting with "{") or a path to a .json file.
SceneLike: TypeAlias = Mapping[str, Any] | str | os.PathLike[str]
#: A style preset: a mapping, JSON text (starting with "{") or a path to a .json file.
StyleLike: TypeAlias = Mapping[str, Any] | str | os.PathLike[str]
#: How a supplied camera depth measures distance: along the view axis (Blender's Z pass)
#: or along each pixel's ray.
DepthKind: TypeAlias = Literal["planar", "ray_distance"]
#: Called on the calling thread with the fraction done, in [0, 1], ending with 1.0.
ProgressCallback: TypeAlias = Callable[[float], object]
#: An EXR codec, by Blender's name (lower case; any case is accepted).
ExrCompression: TypeAlias = Literal["zip", "zips", "piz", "rle", "none", "pxr24"]
#: The EXR codecs `write_exr` takes, the default first.
EXR_COMPRESSIONS: tuple[str, ...] = _core.EXR_COMPRESSIONS


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Layers:
    """Linear float layers at the camera's resolution, rows top to bottom."""

    width: int
    height: int
    #: (height, width, 4) premultiplied RGBA: RGB in-scattered light, A = 1 - transmittance.
    volume: npt.NDArray[np.float32]
    #: (height, width) average light visibility along each view ray.
    visibility: npt.NDArray[np.float32]
    #: (height, width) distance along the view ray to the first surface (or the max distance).
    depth: npt.NDArray[np.float32]
    #: A pixel's width over its height, the camera's; `write_exr` puts it in the header.
    pixel_aspect: float = 1.0

    def __repr__(self) -> str:
        return f"Layers(width={self.width}, height={self.height})"

    def in_frame(self, camera: Mapping[str, Any]) -> Layers:
        """These layers, rendered for `camera`'s `window`, placed in its whole `width` x
        `height` frame with nothing around them (every layer 0 there), as a renderer
        leaves a render region uncropped; themselves where the camera has no window."""
        window = camera.get("window")
        if window is None:
            return self
        x, y = int(window["x"]), int(window["y"])
        if (self.width, self.height) != (int(window["width"]), int(window["height"])):
            raise _convert.invalid(
                "camera.window",
                f"is {window['width']}x{window['height']}, the layers {self.width}x{self.height}",
            )
        width, height = int(camera["width"]), int(camera["height"])
        placed = []
        for layer in (self.volume, self.visibility, self.depth):
            whole = np.zeros((height, width, *layer.shape[2:]), dtype=np.float32)
            whole[y : y + self.height, x : x + self.width] = layer
            placed.append(whole)
        return Layers(width, height, *placed, self.pixel_aspect)


def release_kept_buffers() -> None:
    """Lets go of the buffers kept from earlier frames for the next.

    Frames rendered one after another reuse the previous frame's large buffers (about 170 MB
    for a 1920x1080 frame), which saves faulting in fresh memory every frame. A host that stops
    rendering for a while can hand that memory back; the next frame allocates it afresh.
    """
    _core.release_kept_buffers()


def render(
    scene: SceneLike,
    *,
    style: StyleLike | None = None,
    camera_depth: npt.ArrayLike | None = None,
    depth_kind: DepthKind = "planar",
    progress: ProgressCallback | None = None,
) -> Layers:
    """Renders a scene description.

    `camera_depth`, when given, is a renderer's depth pass of shape (height, width) that
    replaces the depth rasterized from the scene's meshes; `depth_kind` says how it measures
    distance. Values at or beyond the camera's `clip_end`, and +inf, are background.
    `style`, when given, is a style preset that replaces the scene's own `style`.
    """
    _check_progress(progress)
    raw = _core.render_json(
        _convert.scene_json(scene),
        base_dir=_convert.base_dir(scene),
        style_json=_style_json(style),
        camera_depth=_convert.depth_map(camera_depth),
        depth_kind=depth_kind,
        progress=progress,
    )
    return Layers(*raw)


#: How an `AlphaMask` is read past its edges, as Blender's Image Texture extension: it
#: tiles, its edge texels continue ("extend"; USD's "clamp"), it tiles flipped every other
#: copy, or it is empty outside ("clip"; USD's "black").
MaskWrap: TypeAlias = Literal["repeat", "extend", "mirror", "clip"]
#: How an `AlphaMask` is filtered: bilinearly between texel centres, or the texel a point
#: lies in (Blender's Closest interpolation).
MaskFilter: TypeAlias = Literal["linear", "closest"]


@dataclass(frozen=True)
class AlphaMask:
    """An alpha texture that cuts the triangles `render_arrays` assigns it (leaf cards,
    fences), as a renderer's alpha clip does: where its alpha, filtered at a sample's
    texture coordinates, is below `threshold`, the triangle is empty there, to the sun's
    shadow map and to the camera's depth alike.

    `alpha` is (height, width); row 0 holds v = 0, the bottom of the image (the order of
    Blender's `Image.pixels` and of OpenGL textures). `wrap` says how it is read past its
    edges, one mode for both axes or a (u, v) pair; `filter` how it is filtered; `border`
    the alpha read past a clipped edge (1 where the alpha is inverted, as a Mix Shader's
    factor towards a Transparent BSDF is).
    """

    alpha: npt.ArrayLike
    threshold: float = 0.5
    wrap: MaskWrap | tuple[MaskWrap, MaskWrap] = "repeat"
    filter: MaskFilter = "linear"
    border: float = 0.0


def _alpha_mask(mask: object, index: int) -> AlphaMask:
    if not isinstance(mask, AlphaMask):
        kind = type(mask).__name__
        raise TypeError(f"masks[{index}] must be a crepuscular.AlphaMask, got {kind}")
    return mask


def render_arrays(
    *,
    positions: npt.ArrayLike,
    triangles: npt.ArrayLike,
    object_ids: npt.ArrayLike | None = None,
    camera: Mapping[str, Any],
    sun: Mapping[str, Any],
    medium: Mapping[str, Any],
    settings: Mapping[str, Any] | None = None,
    style: StyleLike | None = None,
    camera_depth: npt.ArrayLike | None = None,
    depth_kind: DepthKind = "planar",
    progress: ProgressCallback | None = None,
    origin: npt.ArrayLike | None = None,
    uvs: npt.ArrayLike | None = None,
    triangle_masks: npt.ArrayLike | None = None,
    masks: Sequence[AlphaMask] = (),
    triangle_visibility: npt.ArrayLike | None = None,
) -> Layers:
    """Renders triangles held in arrays.

    `positions` is (N, 3) float32, `triangles` (M, 3) vertex indices and `object_ids` (M,)
    one id per triangle (all 0 when omitted). Arrays that are already C-contiguous with
    those dtypes (uint32 for indices and ids) are read in place without a copy; others are
    converted once. `camera`, `sun`, `medium` and `settings` are the members `camera`,
    `sun`, `medium` and `render` of a scene description; `style` is a style preset.

    `positions` are relative to the world point `origin` (the world's origin when omitted).
    Far from the world's origin, pass one near the camera and subtract it in float64 before
    converting to float32: at 100 km float32 world positions lie 8 mm apart.

    Alpha cutouts: `uvs` (N, 2) gives each position texture coordinates, `triangle_masks`
    (M,) each triangle the index of its `AlphaMask` in `masks`, or -1 for none. Both or
    neither. Both backends cut.

    `triangle_visibility` (M,) flags each triangle: `BLOCKS_SUN` (1) puts it in the sun's
    shadow map, `SEEN_BY_CAMERA` (2) in the camera's depth (3, both, when omitted). An
    object hidden from shadow rays still hides the fog behind it from the camera; one
    hidden from the camera still casts shafts.
    """
    _check_progress(progress)
    triangle_rows = _convert.index_rows(triangles, "triangles")
    position_rows = _convert.float_rows(positions, "positions")
    cutouts: dict[str, Any] = {}
    if len(masks) and triangle_masks is None:
        # Masks no triangle reads were ignored, whatever they held.
        raise _convert.invalid(
            "masks", "alpha masks need uvs and triangle_masks to say which triangles they cut"
        )
    if uvs is not None or triangle_masks is not None:
        if uvs is None or triangle_masks is None:
            raise _convert.invalid(
                "triangle_masks", "uvs and triangle_masks come together (give both or neither)"
            )
        cutouts = {
            "uvs": _convert.uv_rows(uvs, len(position_rows)),
            "triangle_masks": _convert.triangle_masks(triangle_masks, len(triangle_rows)),
            "masks": [
                (
                    _convert.alpha_mask(_alpha_mask(mask, k).alpha, k),
                    float(mask.threshold),
                    *_convert.mask_sampling(mask.wrap, mask.filter, k),
                    float(mask.border),
                )
                for k, mask in enumerate(masks)
            ],
        }
    raw = _core.render_arrays(
        position_rows,
        triangle_rows,
        _convert.object_ids(object_ids, len(triangle_rows)),
        _convert.to_json(camera, "camera"),
        _convert.to_json(sun, "sun"),
        _convert.to_json(medium, "medium"),
        _convert.to_json({} if settings is None else settings, "render"),
        style_json=_style_json(style),
        camera_depth=_convert.depth_map(camera_depth),
        depth_kind=depth_kind,
        progress=progress,
        origin=None if origin is None else _convert.point(origin, "origin"),
        triangle_visibility=(
            None
            if triangle_visibility is None
            else _convert.triangle_visibility(triangle_visibility, len(triangle_rows))
        ),
        **cutouts,
    )
    return Layers(*raw)


def load_style(
    style: StyleLike, *, base_dir: str | os.PathLike[str] | None = None
) -> dict[str, Any]:
    """Reads and validates a style preset; returns it with every default filled in.

    Relative image paths in its transfer function are joined to `base_dir` when given, else
    to the preset file's directory; in text and mappings without `base_dir` they stay as
    they are (the working directory's when baked). Unknown keys and out-of-range values
    raise errors that name the field, e.g. "style.closing.radius".
    """
    folder = _convert.base_dir(style) if base_dir is None else base_dir
    text = _convert.scene_json(style)
    result: dict[str, Any] = json.loads(_core.normalize_style_json(text, base_dir=folder))
    return result


def bake_tf(style: StyleLike, *, time: float = 0.0) -> npt.NDArray[np.float32]:
    """Bakes a style's transfer function at `time` (seconds, for key frames).

    Returns (size, size, 4) premultiplied linear RGBA, row j at normalized depth
    u = (j + 0.5)/size (rising) and column i at V̄ = (i + 0.5)/size. A style without `tf`
    raises `InvalidInputError` naming "style.tf".
    """
    json_text = _style_json(style)
    if json_text is None:
        raise TypeError("style must be a preset path, a mapping or JSON text, not None")
    return _core.bake_tf(json_text, time=float(time))


def _style_json(style: StyleLike | None) -> str | None:
    if style is None:
        return None
    if isinstance(style, Mapping):
        return _convert.to_json(style, "style")
    return _convert.style_json(style)


def scene_from_json(text: str) -> dict[str, Any]:
    """Parses and validates JSON text; returns the scene with every default filled in."""
    result: dict[str, Any] = json.loads(_core.normalize_scene_json(text))
    return result


def validate_scene(scene: SceneLike) -> None:
    """Raises `InvalidInputError` naming the first unusable field of a scene description."""
    _core.normalize_scene_json(_convert.scene_json(scene))


def _check_progress(progress: object) -> None:
    if progress is not None and not callable(progress):
        raise TypeError(f"progress must be callable, got {type(progress).__name__}")


def builtin_scene(name: str) -> dict[str, Any]:
    """The scene description of a built-in scene (torus, tree, plane, colonnade)."""
    result: dict[str, Any] = json.loads(_core.builtin_scene_json(name))
    return result


def builtin_scene_names() -> list[str]:
    """The names `builtin_scene` accepts."""
    return _core.builtin_scene_names()


def read_exr(path: str | os.PathLike[str]) -> dict[str, npt.NDArray[np.float32]]:
    """Reads every channel of every part of an EXR file (Blender's multi-part files too).

    Keys are full channel names such as "volume.R" or "ViewLayer.Depth.Z"; values are
    (height, width) float32 arrays.
    """
    _, _, channels = _core.read_exr(os.fspath(path))
    return channels


def read_exr_pixel_aspect(path: str | os.PathLike[str]) -> float:
    """An EXR file's `pixelAspectRatio`: a pixel's width over its height, read from its
    header alone."""
    return _core.read_exr_pixel_aspect(os.fspath(path))


def write_exr(
    path: str | os.PathLike[str],
    layers: Layers,
    *,
    half: bool = False,
    compression: ExrCompression = "zip",
) -> None:
    """Writes `layers` as one multi-layer EXR (channels volume.R/G/B/A, visibility, depth).

    `compression` is the EXR codec (Blender's names; see `EXR_COMPRESSIONS`): "zip", the
    default, is compact and fast to read; "piz" writes faster and reads slower; "none"
    writes fastest; "pxr24" is lossy (float channels rounded to 24 bits). An unknown name
    raises `InvalidInputError`. The header's `pixelAspectRatio` is the layers'.
    """
    _core.write_layers_exr(
        os.fspath(path),
        np.ascontiguousarray(layers.volume, dtype=np.float32),
        np.ascontiguousarray(layers.visibility, dtype=np.float32),
        np.ascontiguousarray(layers.depth, dtype=np.float32),
        half=half,
        compression=compression,
        pixel_aspect=layers.pixel_aspect,
    )


def write_exr_channels(
    path: str | os.PathLike[str],
    channels: Mapping[str, npt.ArrayLike],
    *,
    half: bool = False,
    compression: ExrCompression = "zip",
    pixel_aspect: float = 1.0,
) -> None:
    """Writes named (height, width) planes as one EXR, in the mapping's order.

    For images that are not a layer set, such as a composited frame (`R`, `G`, `B`, `A`).
    `compression` as in `write_exr`; `pixel_aspect` (a pixel's width over its height)
    goes in the header.
    """
    _core.write_channels_exr(
        os.fspath(path),
        [(name, np.ascontiguousarray(plane, dtype=np.float32)) for name, plane in channels.items()],
        half=half,
        compression=compression,
        pixel_aspect=pixel_aspect,
    )


def composite(volume: npt.ArrayLike, beauty: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Premultiplied over of the volume layer onto a beauty image, both (H, W, 4)."""
    return _core.composite(
        np.ascontiguousarray(volume, dtype=np.float32),
        np.ascontiguousarray(beauty, dtype=np.float32),
    )


def write_preview_png(
    path: str | os.PathLike[str],
    rgba: npt.ArrayLike,
    *,
    exposure: float | None = None,
    tone_map: bool = True,
) -> None:
    """Writes a quick-look sRGB PNG of premultiplied RGBA; exposure in stops (None: auto)."""
    _core.write_preview_png(
        os.fspath(path),
        np.ascontiguousarray(rgba, dtype=np.float32),
        exposure=exposure,
        tone_map=tone_map,
    )
