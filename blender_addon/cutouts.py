"""Alpha cutouts from materials: leaf cards, fences and grilles whose image's alpha makes
them partly transparent in Cycles, found in their node trees and handed to the core as
alpha masks (`crepuscular.AlphaMask`), which cut the triangles in the shadow map and the
camera's depth.

Recognised, as artists build them for Cycles: a Principled BSDF whose Alpha is an Image
Texture's Alpha (or Color), and a Mix Shader between a Transparent BSDF and another shader
whose factor is an Image Texture's Alpha (or Color). A constant Alpha or factor, or a
Transparent BSDF alone, is one alpha everywhere, clipped as masks are; a material with a
Volume shader and no Surface one is alpha 0, as Cycles draws no surface there. The texture's
coordinates are its UV Map node's map, or the mesh's default (active render) map when
nothing feeds its Vector, mapped by any Mapping nodes between (Point, Texture or Vector),
and its extension (Repeat, Extend, Mirror or Clip) and Closest interpolation read the mask
as Cycles reads the image. Links are followed through reroutes, muted nodes and node groups.

Value nodes between the image and the alpha (Math, Invert, Map Range, Color Ramp) move the
cut to a threshold on the texture's value (`alpha_chains`).

A Mix Shader whose factor is Light Path's Is Shadow Ray or Is Camera Ray shows each kind of
ray one input: a Transparent BSDF there hides the surface from those rays only
(`MaskSource.rays`, which the export turns into triangle visibility flags).

The core clips at alpha 0.5, where Cycles lets each shadow ray through by the alpha: the
same for the nearly binary masks of cutouts, and within their filtered edges otherwise.
Any other use of transparency leaves the material opaque, and a note says which.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import bpy
import numpy as np
from mathutils import Euler

import crepuscular

from . import alpha_chains, node_links

LUMINANCE = node_links.LUMINANCE.astype(np.float32)
#: Where the core cuts: alpha below this lets light and sight through.
THRESHOLD = 0.5
#: The core's wrap for each Image Texture extension.
_WRAPS = {"REPEAT": "repeat", "EXTEND": "extend", "MIRROR": "mirror", "CLIP": "clip"}


@dataclass(frozen=True)
class MaskSource:
    """Where a material's alpha comes from."""

    image: str
    #: The UV map by name; "" for the mesh's default one.
    uv_map: str
    #: "alpha", or "luminance" where a Color output feeds the alpha.
    channel: str
    #: True where the texture's value is the transparent share (a Mix Shader's factor
    #: towards its second input, the Transparent BSDF).
    invert: bool
    #: The alpha of a material transparent alike everywhere (no image), else None.
    constant: float | None = None
    #: Where the texture value (one minus it where `invert`) cuts: `THRESHOLD`, or where
    #: value nodes between the image and the alpha put the alpha's one half
    #: (`alpha_chains`).
    threshold: float = THRESHOLD
    #: How the image is read past its edges (`crepuscular.MaskWrap`), from the Image
    #: Texture's extension.
    wrap: str = "repeat"
    #: "closest" for the Image Texture's Closest interpolation, else "linear" (Cubic and
    #: Smart, whose smoother alpha crosses the cut within a texel of the linear one, too).
    filter: str = "linear"
    #: The Mapping nodes between the UV map and the texture, as the affine map of
    #: (u, v) they make: (a, b, c, d, e, f) reads (a·u + b·v + c, d·u + e·v + f). None
    #: where no node maps them.
    uv_transform: tuple[float, ...] | None = None
    #: Which rays see the surface (`crepuscular.BLOCKS_SUN` | `SEEN_BY_CAMERA`): fewer
    #: where a Mix Shader's factor is Light Path's Is Shadow Ray or Is Camera Ray and a
    #: Transparent BSDF is what those rays see.
    rays: int = crepuscular.BLOCKS_SUN | crepuscular.SEEN_BY_CAMERA

    @property
    def pixels(self) -> tuple[str, str, bool, float | None]:
        """What its alpha array depends on (`mask_alpha`): sources that differ only in how
        the array is read (wrap, filter, threshold, mapping, rays) share one."""
        return self.image, self.channel, self.invert, self.constant


def material_mask(material: bpy.types.Material | None) -> tuple[MaskSource | None, str | None]:
    """The mask a material cuts with, or None; and a note where its transparency is of a
    kind this cannot map (the material then stays opaque). Links are followed through
    reroutes, muted nodes and node groups (`node_links`)."""
    if material is None or material.node_tree is None:
        return None, None
    output = material.node_tree.get_output_node("CYCLES")
    if output is None:
        return None, None
    surface = node_links.traced(output.inputs["Surface"])
    where = f"material '{material.name}'"
    if not surface.is_linked:
        if not node_links.traced(output.inputs["Volume"]).is_linked:
            return None, None
        # Cycles draws no surface where a material has only a volume: its faces bound the
        # volume and let light and sight through.
        return MaskSource("", "", "alpha", invert=False, constant=0.0), (
            f"{where}: only a volume shader: its faces neither cast nor hide the fog, and "
            "its volume is not rendered (the medium is the scene's Medium setting)"
        )
    return _surface_mask(surface, where)


def _surface_mask(surface: node_links.Traced, where: str) -> tuple[MaskSource | None, str | None]:
    """`material_mask` of the shader `surface` (a linked shader socket)."""
    shader, groups = surface.node, surface.groups
    if shader.bl_idname == "ShaderNodeBsdfPrincipled":
        alpha = node_links.traced(shader.inputs["Alpha"], groups)
        if alpha.is_constant:
            value = float(alpha.value("VALUE"))
            return _constant_source(value, where, nan=math.isnan(value))
        return _image_source(alpha, invert=False, where=where)
    if shader.bl_idname == "ShaderNodeBsdfTransparent":
        color = node_links.traced(shader.inputs["Color"], groups)
        if not color.is_constant:
            return None, f"{where}: its Transparent BSDF's Color is linked; it casts as opaque"
        rgb = np.array(color.value("RGBA")[:3], dtype=np.float64)
        if not np.isfinite(rgb).all():
            # Cycles drops a closure of NaN weight: the surface is then opaque black.
            return None, f"{where}: its Transparent BSDF's Color is not finite; it casts as opaque"
        return _constant_source(1.0 - float(rgb @ LUMINANCE), where)
    if shader.bl_idname == "ShaderNodeMixShader":
        factor, first, second = (node_links.traced(socket, groups) for socket in shader.inputs[:3])
        if factor.is_linked and factor.node.bl_idname == "ShaderNodeLightPath":
            return _ray_split(factor.socket.name, first, second, where)
        transparent = [
            shaded.is_linked and shaded.node.bl_idname == "ShaderNodeBsdfTransparent"
            for shaded in (first, second)
        ]
        if not any(transparent):
            return None, None
        if factor.is_constant:
            value = float(factor.value("VALUE"))
            fac = _saturated(value)
            return _constant_source(
                1.0 - fac if transparent[1] else fac, where, nan=math.isnan(value)
            )
        # The factor blends towards the second input: it is the alpha where the first is
        # the Transparent BSDF, and the transparency where the second is.
        return _image_source(factor, invert=transparent[1], where=where)
    return None, None


def _ray_split(
    output: str, first: node_links.Traced, second: node_links.Traced, where: str
) -> tuple[MaskSource | None, str | None]:
    """A Mix Shader whose factor is Light Path's `output`: Is Shadow Ray shows shadow rays
    its second input and camera rays its first, Is Camera Ray the other way round. The
    rays that see a Transparent BSDF (or any surface clipped away) pass; the others see
    their input's own cut, or an opaque surface (an unlinked input, no closure, or one
    whose transparency is noted as not mapped)."""
    sides = {
        "Is Shadow Ray": (second, first),
        "Is Camera Ray": (first, second),
    }.get(output)
    if sides is None:
        return None, f"{where}: its mix factor is Light Path's '{output}'; it casts as opaque"
    seen: dict[int, MaskSource | None] = {}
    notes = []
    for flag, side in zip((crepuscular.BLOCKS_SUN, crepuscular.SEEN_BY_CAMERA), sides, strict=True):
        source, note = _surface_mask(side, where) if side.is_linked else (None, None)
        if note is not None and note not in notes:
            notes.append(note)
        clear = source is not None and source.constant is not None and source.constant < THRESHOLD
        if not clear:
            seen[flag] = source
    note = "; ".join(notes) or None
    if not seen:
        return MaskSource("", "", "alpha", invert=False, constant=0.0), note
    if len(seen) == 2:
        sun, camera = seen.values()
        if sun != camera:
            return None, (
                f"{where}: shadow and camera rays see different cutouts through Light Path; "
                "it casts as opaque"
            )
        return sun, note
    ((flag, source),) = seen.items()
    opaque = MaskSource("", "", "alpha", invert=False, constant=1.0)
    return dataclasses.replace(source or opaque, rays=flag), note


def _saturated(value: float) -> float:
    """`value` clamped to [0, 1] as Cycles saturates an alpha or a mix factor: NaN is 0
    (for a Mix Shader, its first input alone)."""
    return 0.0 if math.isnan(value) else min(max(value, 0.0), 1.0)


def _constant_source(
    alpha: float, where: str, *, nan: bool = False
) -> tuple[MaskSource | None, str | None]:
    """A material of one alpha everywhere, clipped at `THRESHOLD` as masks are: below it,
    a mask that cuts every triangle (it neither casts nor hides the fog), else opaque; a
    note where the alpha is partial, since Cycles lets the rest through, or where it came
    from a NaN (`nan`), which Cycles reads as 0."""
    alpha = _saturated(alpha)
    note = None
    if nan:
        effect = "casts as opaque" if alpha >= THRESHOLD else "neither casts nor hides the fog"
        note = f"{where}: its alpha or mix factor is NaN, which Cycles reads as 0: it {effect}"
    elif 0.0 < alpha < 1.0:
        effect = "casts as opaque" if alpha >= THRESHOLD else "neither casts nor hides the fog"
        note = (
            f"{where}: its alpha {alpha:.2f} is clipped at {THRESHOLD}: it {effect} "
            f"(Cycles lets {1 - alpha:.0%} of the light through)"
        )
    if alpha >= THRESHOLD:
        return None, note
    return MaskSource("", "", "alpha", invert=False, constant=alpha), note


def _image_source(
    source: node_links.Traced, *, invert: bool, where: str
) -> tuple[MaskSource | None, str | None]:
    try:
        steps, source = alpha_chains.follow(source, where)
    except alpha_chains.ChainError as error:
        return None, f"{error}; it casts as opaque"
    node = source.node
    if node.bl_idname != "ShaderNodeTexImage" or node.image is None:
        return None, f"{where}: its alpha is not an Image Texture's; it casts as opaque"
    channel = {"Alpha": "alpha", "Color": "luminance"}.get(source.socket.name)
    if channel is None:
        return None, f"{where}: its alpha comes from '{source.socket.name}'; it casts as opaque"
    if node.image.source == "TILED":
        # `Image.pixels` holds the first tile only, where Cycles reads each by its UDIM.
        return None, f"{where}: image '{node.image.name}' is tiled (UDIM); it casts as opaque"
    if node.projection != "FLAT":
        return None, (
            f"{where}: image '{node.image.name}' is projected {node.projection.lower()}, not "
            "flat; it casts as opaque"
        )
    vector = node_links.traced(node.inputs["Vector"], source.groups)
    # Mapping nodes, outermost (nearest the texture) first: each maps what the next
    # gives it.
    mapped = np.eye(4)
    while vector.is_linked and vector.node.bl_idname == "ShaderNodeMapping":
        try:
            mapped = mapped @ _mapping_matrix(vector.node, vector.groups, where)
        except node_links.NodeLinkError as error:
            return None, f"{error}; it casts as opaque"
        vector = node_links.traced(vector.node.inputs["Vector"], vector.groups)
        if not vector.is_linked:
            return None, (
                f"{where}: image '{node.image.name}' is mapped from no coordinates (its "
                "Mapping node's Vector is unlinked); it casts as opaque"
            )
    uv_map = ""
    if vector.is_linked:
        mapping = vector.node
        if mapping.bl_idname == "ShaderNodeUVMap":
            uv_map = mapping.uv_map
        elif not (mapping.bl_idname == "ShaderNodeTexCoord" and vector.socket.name == "UV"):
            return None, (
                f"{where}: image '{node.image.name}' is mapped by "
                f"'{mapping.name}', not a UV map; it casts as opaque"
            )
    if not np.isfinite(mapped).all():
        return None, (
            f"{where}: image '{node.image.name}' is mapped by values that are not finite; it "
            "casts as opaque"
        )
    cut = alpha_chains.Cut(invert=invert)
    if steps:
        # The alpha, or a Mix Shader's factor towards a Transparent BSDF (its transparency).
        def alpha(value: np.ndarray) -> np.ndarray:
            return 1.0 - np.clip(value, 0.0, 1.0) if invert else value

        try:
            cut = alpha_chains.cut_of(steps, alpha, where)
        except alpha_chains.ChainError as error:
            return None, f"{error}; it casts as opaque"
        if cut.solid:
            return None, None
        if cut.empty:
            return MaskSource("", "", "alpha", invert=False, constant=0.0), None
    # A UV map gives (u, v, 0): the map's columns u, v and its translation, rows x and y.
    transform = None
    if not np.array_equal(mapped, np.eye(4)):
        transform = tuple(float(value) for value in mapped[:2][:, [0, 1, 3]].ravel())
    return MaskSource(
        node.image.name_full,
        uv_map,
        channel,
        cut.invert,
        threshold=cut.threshold,
        wrap=_WRAPS.get(node.extension, "repeat"),
        filter="closest" if node.interpolation == "Closest" else "linear",
        uv_transform=transform,
    ), None


def _mapping_matrix(
    node: bpy.types.Node, groups: tuple[bpy.types.Node, ...], where: str
) -> np.ndarray:
    """The 4x4 affine map of a Mapping node, as Cycles applies it: Point scales, rotates
    (Euler XYZ) and then moves; Texture undoes that (dividing by a zero scale gives 0);
    Vector scales and rotates. Normal, which normalizes, is not affine: NodeLinkError."""
    kind = node.vector_type
    if kind == "NORMAL":
        raise node_links.NodeLinkError(
            f"{where}: Mapping node '{node.name}' maps normals, which is not affine"
        )

    def vector(name: str) -> np.ndarray:
        return np.array(node_links.constant(node, name, groups, where)[:3], dtype=np.float64)

    rotation = np.array(Euler(vector("Rotation"), "XYZ").to_matrix(), dtype=np.float64)
    scale = vector("Scale")
    matrix = np.eye(4)
    if kind == "TEXTURE":
        inverse_scale = np.divide(1.0, scale, out=np.zeros(3), where=scale != 0)
        matrix[:3, :3] = inverse_scale[:, None] * rotation.T
        matrix[:3, 3] = -matrix[:3, :3] @ vector("Location")
    else:
        matrix[:3, :3] = rotation * scale
        if kind == "POINT":
            matrix[:3, 3] = vector("Location")
    return matrix


def mask_alpha(source: MaskSource) -> np.ndarray:
    """The (height, width) float32 alpha of `source`, rows from the image's bottom."""
    if source.constant is not None:
        return np.full((1, 1), source.constant, dtype=np.float32)
    image = bpy.data.images[source.image]
    width, height = image.size
    if width == 0 or height == 0:
        raise ValueError(f"image '{image.name}' has no pixels (is its file missing?)")
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    rgba = pixels.reshape(height, width, 4)
    if source.channel == "alpha":
        # An image whose alpha is set to be ignored gives an Alpha of 1, in Cycles too.
        alpha = np.ones_like(rgba[..., 3]) if image.alpha_mode == "NONE" else rgba[..., 3]
    else:
        alpha = _linear(image, rgba[..., :3]) @ LUMINANCE
    # Saturated as Cycles saturates an alpha or a mix factor: NaN is 0.
    alpha = np.clip(np.nan_to_num(alpha, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.ascontiguousarray(1.0 - alpha if source.invert else alpha, dtype=np.float32)


def _linear(image: bpy.types.Image, rgb: np.ndarray) -> np.ndarray:
    """An image's colours as Cycles reads them, in scene-linear values: `Image.pixels` gives
    an 8-bit image's as stored, which for an sRGB file (the default for 8-bit images) are
    sRGB-encoded; float images and data (Non-Color) are read as they are."""
    if image.is_float or image.colorspace_settings.name != "sRGB":
        return rgb
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4).astype(np.float32)


@dataclass
class MaskTable:
    """The masks of one export, each source once, in the order first used. `kept` holds
    alphas across exports, by `MaskSource.pixels` (reading an image's pixels takes a
    while); the geometry cache owns it and drops those of changed images."""

    kept: dict[tuple[str, str, bool, float | None], np.ndarray] = field(default_factory=dict)
    sources: list[MaskSource] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    _index: dict[MaskSource, int] = field(default_factory=dict)

    def add(self, material: bpy.types.Material | None) -> tuple[int, str]:
        """The mask index of `material` in this export (-1 where it does not cut) and the
        UV map its mask reads ("" for the default)."""
        source, note = material_mask(material)
        if note is not None and note not in self.notes:
            self.notes.append(note)
        if source is None:
            return -1, ""
        if source not in self._index:
            self._index[source] = len(self.sources)
            self.sources.append(source)
        return self._index[source], source.uv_map

    def masks(self) -> list[crepuscular.AlphaMask]:
        masks = []
        for source in self.sources:
            alpha = self.kept.get(source.pixels)
            if alpha is None:
                alpha = self.kept[source.pixels] = mask_alpha(source)
            # Clipped, Cycles reads the image as 0 past its edges: an alpha of 0, or of 1
            # where the value is a Mix Shader's factor towards a Transparent BSDF.
            border = 1.0 if source.invert else 0.0
            masks.append(
                crepuscular.AlphaMask(
                    alpha,
                    source.threshold,
                    wrap=source.wrap,
                    filter=source.filter,
                    border=border,
                )
            )
        return masks
