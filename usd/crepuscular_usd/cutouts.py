"""Alpha cutouts of a stage's meshes: leaf cards, fences and grilles whose
`UsdPreviewSurface` takes its `opacity` from a `UsdUVTexture`, cut as the core's alpha masks
(`crepuscular.AlphaMask`) in the shadow map and the camera's depth.

A mesh's material is its bound one for full rendering (`ComputeBoundMaterial`), per face
where `GeomSubset`s bind their own. The texture's coordinates are the primvar its
`UsdPrimvarReader_float2` names, at any interpolation; its `scale` and `bias` apply, and a
colour channel is decoded from sRGB where its `sourceColorSpace` says (or, on `auto`, an
8-bit file implies). Past the image's edges it is read as `wrapS` and `wrapT` say; where
they are left to the file's metadata (`useMetadata`, the default), as black, USD's fallback
(Blender's USD import repeats such a texture instead, and a note says so where the
coordinates leave the image). The cut is at `opacityThreshold` where that is above 0, else at 0.5: a
renderer lets a shadow ray through by the opacity itself, which for the nearly binary masks
of cutouts is the same. Textures are PNG, JPEG, TGA, TIFF or BMP (read with Pillow) or EXR.

Inputs are read as USD's renderers resolve them: through NodeGraphs, and from the
material's interface inputs they are connected to. A constant opacity is one value
everywhere, cut the same way (below the cut, the surface neither casts nor hides the fog).
A primvar the mesh lacks reads the reader's `fallback`, and an `st` given as a value reads
there. Coordinates mapped by `UsdTransform2d` nodes (what Blender's exporter writes for a Mapping
node) are mapped so too. Anything else that makes a surface transparent (another shader,
UDIM tiles, coordinates computed otherwise) leaves it opaque, with a note that names it.
"""

from __future__ import annotations

import io
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pxr import Ar, Sdf, Usd, UsdGeom, UsdShade

import crepuscular

__all__ = ["MaskSource", "MaskTable", "face_masks"]

#: The cut where a material sets no `opacityThreshold`.
DEFAULT_THRESHOLD = 0.5
_CHANNELS = {"r": 0, "g": 1, "b": 2, "a": 3}
#: The core's wrap for each of `UsdUVTexture`'s wrap modes but `useMetadata`.
_WRAPS = {"repeat": "repeat", "clamp": "extend", "mirror": "mirror", "black": "clip"}


@dataclass(frozen=True)
class MaskSource:
    """Where a material's opacity comes from."""

    file: str
    #: "r", "g", "b" or "a".
    channel: str
    scale: float
    bias: float
    #: Whether a colour channel is decoded from sRGB.
    srgb: bool
    threshold: float
    #: The primvar of the texture coordinates ("" where none is read: all (0, 0)).
    primvar: str
    #: The opacity of a material opaque alike everywhere (no file), else None.
    constant: float | None = None
    #: How the texture is read past its edges along s and t (`crepuscular.MaskWrap`).
    wrap: tuple[str, str] = ("repeat", "repeat")
    #: Whether some axis's wrap was left to the file (`useMetadata`, the default), which
    #: reads black past the edges (USD's fallback, as no file's wrap metadata is read).
    wrap_unauthored: bool = False
    #: The `UsdTransform2d` nodes between the primvar reader and the texture, as the
    #: affine map of (s, t) they make: (a, b, c, d, e, f) reads (a·s + b·t + c,
    #: d·s + e·t + f). None where none maps them.
    uv_transform: tuple[float, ...] | None = None
    #: The coordinates read where the primvar is missing, or where no primvar is read.
    st_fallback: tuple[float, float] = (0.0, 0.0)


def face_masks(prim: Usd.Prim, face_count: int, table: MaskTable) -> npt.NDArray[np.int64] | None:
    """Per face of the mesh `prim`, its mask's index in `table` (-1 where the face is
    opaque), or None where no face is cut."""
    faces = np.full(face_count, -1, dtype=np.int64)
    binding = UsdShade.MaterialBindingAPI(prim)
    whole = table.index(_bound_material(prim), str(prim.GetPath()))
    faces[:] = whole
    for subset in binding.GetMaterialBindSubsets():
        indices = np.asarray(subset.GetIndicesAttr().Get() or [], dtype=np.int64)
        indices = indices[(indices >= 0) & (indices < face_count)]
        faces[indices] = table.index(_bound_material(subset.GetPrim()), str(subset.GetPath()))
    return faces if (faces >= 0).any() else None


def _bound_material(prim: Usd.Prim) -> UsdShade.Material | None:
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial(UsdShade.Tokens.full)
    return material if material else None


def mask_source(material: UsdShade.Material | None) -> tuple[MaskSource | None, str | None]:
    """The mask `material` cuts with, or None; and a note where its opacity is of a kind
    this cannot map (it then stays opaque)."""
    if material is None:
        return None, None
    surface = material.ComputeSurfaceSource()
    shader = surface[0] if isinstance(surface, tuple) else surface
    if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
        return None, None
    where = f"material {material.GetPath()}"
    opacity = shader.GetInput("opacity")
    threshold = float(_value(shader.GetInput("opacityThreshold")) or 0.0)
    if not math.isfinite(threshold):
        return None, f"{where}: its opacityThreshold is not finite; it casts as opaque"
    cut = threshold if threshold > 0.0 else DEFAULT_THRESHOLD
    produced = _source_output(opacity)
    if produced is None:
        value = _value(opacity)
        if value is not None and math.isnan(value):
            return None, f"{where}: its opacity is NaN; it casts as opaque"
        if value is None or value >= 1.0:
            return None, None
        return _constant_source(float(value), cut, threshold > 0.0, where)
    texture, output = produced
    if texture.GetIdAttr().Get() != "UsdUVTexture" or output not in _CHANNELS:
        return None, f"{where}: its opacity is not a UsdUVTexture's channel; it casts as opaque"
    asset = _value(texture.GetInput("file"))
    if asset is None or "<UDIM>" in asset.path:
        return None, f"{where}: its opacity texture has no file or is tiled; it casts as opaque"
    if not asset.resolvedPath:
        return None, f"{where}: texture {asset.path} was not found; it casts as opaque"
    primvar, st_fallback, transform, note = _primvar(texture, where)
    if note is not None:
        return None, note
    channel = _CHANNELS[output]
    scale = _float4(texture, "scale", 1.0)[channel]
    bias = _float4(texture, "bias", 0.0)[channel]
    if not (math.isfinite(scale) and math.isfinite(bias)):
        return None, (
            f"{where}: its opacity texture's scale or bias is not finite; it casts as opaque"
        )
    wraps = [_value(texture.GetInput(name)) for name in ("wrapS", "wrapT")]
    unknown = [str(wrap) for wrap in wraps if wrap not in (*_WRAPS, "useMetadata", None)]
    if unknown:
        return None, (
            f"{where}: its opacity texture's wrap '{unknown[0]}' is none of "
            f"{', '.join(_WRAPS)} or useMetadata; it casts as opaque"
        )
    wrap_s, wrap_t = (_WRAPS.get(str(wrap), "clip") for wrap in wraps)
    space = _value(texture.GetInput("sourceColorSpace")) or "auto"
    srgb = output != "a" and (
        space == "sRGB" or (space == "auto" and not asset.resolvedPath.lower().endswith(".exr"))
    )
    source_record = MaskSource(
        asset.resolvedPath,
        output,
        float(scale),
        float(bias),
        srgb,
        cut,
        primvar,
        wrap=(wrap_s, wrap_t),
        wrap_unauthored=any(wrap not in _WRAPS for wrap in wraps),
        uv_transform=transform,
        st_fallback=st_fallback,
    )
    return source_record, None


def _producer(shader_input: UsdShade.Input | None) -> Usd.Attribute | None:
    """The attribute that gives `shader_input` its value: a shader's output or an authored
    input, through NodeGraphs and the material's interface inputs, as USD's own
    renderers resolve it (the Pixar tutorial's primvar reader takes its varname from the
    material's `inputs:frame:stPrimvarName`); None where none is authored."""
    if not shader_input:
        return None
    attributes = shader_input.GetValueProducingAttributes()
    return attributes[0] if attributes else None


def _source_output(shader_input: UsdShade.Input | None) -> tuple[UsdShade.Shader, str] | None:
    """The shader and output name `shader_input` is computed by, or None where a value
    (or nothing) gives it."""
    attribute = _producer(shader_input)
    if attribute is None:
        return None
    name, kind = UsdShade.Utils.GetBaseNameAndType(attribute.GetName())
    if kind != UsdShade.AttributeType.Output:
        return None
    return UsdShade.Shader(attribute.GetPrim()), name


def _value(shader_input: UsdShade.Input | None) -> Any:
    """`shader_input`'s value: its own or an interface input's it is connected to; None
    where none is authored or a shader computes it."""
    attribute = _producer(shader_input)
    if attribute is None:
        return None
    _, kind = UsdShade.Utils.GetBaseNameAndType(attribute.GetName())
    return None if kind == UsdShade.AttributeType.Output else attribute.Get()


def _constant_source(
    opacity: float, cut: float, masked: bool, where: str
) -> tuple[MaskSource | None, str | None]:
    """A material of one opacity everywhere, cut at `cut` as masks are: below it, a mask
    that cuts every face (it neither casts nor hides the fog), else opaque. With an
    `opacityThreshold` (`masked`) that is USD's own meaning; without, a renderer lets the
    rest through, and a note says so."""
    opacity = min(max(opacity, 0.0), 1.0)
    note = None
    if not masked and opacity > 0.0:
        effect = "casts as opaque" if opacity >= cut else "neither casts nor hides the fog"
        note = (
            f"{where}: its opacity {opacity:.2f} is cut at {cut}: it {effect} (a renderer "
            f"lets {1 - opacity:.0%} of the light through)"
        )
    if opacity >= cut:
        return None, note
    return MaskSource("", "a", 1.0, 0.0, False, cut, "", constant=opacity), note


def _primvar(
    texture: UsdShade.Shader, where: str
) -> tuple[str, tuple[float, float], tuple[float, ...] | None, str | None]:
    """The primvar `texture` reads its coordinates from, through any `UsdTransform2d`
    nodes; the coordinates read where that primvar is missing (the reader's `fallback`),
    or where none is read (the value of the input left unconnected, `st` (0, 0) by
    default); the affine map the nodes make (None for none); or a note where the
    coordinates come from anything else."""
    unlinked = texture.GetInput("st")
    produced = _source_output(unlinked)
    mapped = np.eye(3)
    while produced is not None and produced[0].GetIdAttr().Get() == "UsdTransform2d":
        node = produced[0]
        mapped = mapped @ _transform_2d(node)
        if not np.isfinite(mapped).all():
            note = (
                f"{where}: {node.GetPath()} maps its texture coordinates by values that are "
                "not finite; it casts as opaque"
            )
            return "", (0.0, 0.0), None, note
        unlinked = node.GetInput("in")
        produced = _source_output(unlinked)
    transform = None
    if not np.array_equal(mapped, np.eye(3)):
        transform = tuple(float(value) for value in mapped[:2].ravel())
    if produced is None:
        return "", _float2(_value(unlinked)), transform, None
    reader, _ = produced
    if reader.GetIdAttr().Get() != "UsdPrimvarReader_float2":
        note = (
            f"{where}: its texture coordinates come from {reader.GetPath()}, not a primvar "
            "reader; it casts as opaque"
        )
        return "", (0.0, 0.0), None, note
    fallback = _float2(_value(reader.GetInput("fallback")))
    return str(_value(reader.GetInput("varname")) or ""), fallback, transform, None


def _float2(value: Any) -> tuple[float, float]:
    """An authored float2, where it is two finite numbers; else (0, 0), USD's default."""
    if value is None or len(value) != 2 or not all(math.isfinite(v) for v in value):
        return 0.0, 0.0
    return float(value[0]), float(value[1])


def _transform_2d(node: UsdShade.Shader) -> npt.NDArray[np.float64]:
    """A `UsdTransform2d` node's 3x3 affine map: it scales, rotates by `rotation` degrees
    counter-clockwise, then translates."""
    rotation = math.radians(float(_value(node.GetInput("rotation")) or 0.0))
    scale = _value(node.GetInput("scale"))
    translation = _value(node.GetInput("translation"))
    scale = (1.0, 1.0) if scale is None else tuple(scale)
    translation = (0.0, 0.0) if translation is None else tuple(translation)
    cos, sin = math.cos(rotation), math.sin(rotation)
    return np.array(
        [
            [cos * scale[0], -sin * scale[1], translation[0]],
            [sin * scale[0], cos * scale[1], translation[1]],
            [0.0, 0.0, 1.0],
        ]
    )


def _float4(shader: UsdShade.Shader, name: str, fallback: float) -> tuple[float, ...]:
    value = _value(shader.GetInput(name))
    return tuple(value) if value is not None else (fallback,) * 4


def corner_uvs(
    prim: Usd.Prim,
    primvar: str,
    time: Usd.TimeCode,
    corners: npt.NDArray[np.int64],
    points_of_corners: npt.NDArray[np.int64],
    faces: npt.NDArray[np.int64],
) -> npt.NDArray[np.float64] | None:
    """The primvar's values at each triangle corner ((M, 3, 2)), from its interpolation:
    `corners` index the face-vertex list, `points_of_corners` the points, `faces` the
    triangles' faces. None where the primvar is missing."""
    reader = UsdGeom.PrimvarsAPI(prim).GetPrimvar(primvar) if primvar else None
    if reader is None or not reader.HasValue():
        return None
    values = reader.ComputeFlattened(time)
    if values is None:
        return None
    array = np.asarray(values, dtype=np.float64).reshape(-1, 2)
    interpolation = reader.GetInterpolation()
    if interpolation == UsdGeom.Tokens.faceVarying:
        index = corners
    elif interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        index = points_of_corners
    elif interpolation == UsdGeom.Tokens.uniform:
        index = np.repeat(faces[:, None], 3, axis=1)
    else:
        index = np.zeros_like(corners)
    if len(array) == 0 or index.max(initial=0) >= len(array):
        return None
    return array[index]


@dataclass
class MaskTable:
    """The masks of a collector, each source once, in the order first used; their alpha is
    read once."""

    sources: list[MaskSource] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    _index: dict[MaskSource, int] = field(default_factory=dict)
    # What each material's network maps to: a stage binds one material to many meshes.
    _by_material: dict[Sdf.Path, tuple[MaskSource | None, str | None]] = field(default_factory=dict)
    _alpha: dict[MaskSource, npt.NDArray[np.float32]] = field(default_factory=dict)
    _noted: set[Sdf.Path] = field(default_factory=set)

    def index(self, material: UsdShade.Material | None, where: str) -> int:
        if material is None:
            return -1
        path = material.GetPath()
        if path not in self._by_material:
            self._by_material[path] = mask_source(material)
        source, note = self._by_material[path]
        if note is not None and path not in self._noted:
            # Once per material, on the first mesh bound to it: a stage binds one material
            # to many meshes, and the table lives for every frame of a range.
            self._noted.add(path)
            self.notes.append(f"{where}: {note}")
        if source is None:
            return -1
        if source not in self._index:
            self._index[source] = len(self.sources)
            self.sources.append(source)
        return self._index[source]

    def source(self, index: int) -> MaskSource:
        return self.sources[index]

    def masks(self) -> list[crepuscular.AlphaMask]:
        """Every mask, its alpha read from its file the first time. A texture that cannot
        be read is named in a note and cuts nothing."""
        masks = []
        for source in self.sources:
            alpha = self._alpha.get(source)
            if alpha is None:
                try:
                    alpha = read_mask(source)
                except (OSError, ValueError) as error:
                    self.notes.append(
                        f"texture {source.file} could not be read ({error}); what it cuts "
                        "casts as opaque"
                    )
                    alpha = np.ones((1, 1), dtype=np.float32)
                self._alpha[source] = alpha
            # Past a black edge the texel reads 0, then is scaled and biased.
            masks.append(
                crepuscular.AlphaMask(alpha, source.threshold, wrap=source.wrap, border=source.bias)
            )
        return masks


def _asset_bytes(resolved: str) -> bytes:
    """The file's bytes through USD's asset resolver, so that textures inside a .usdz
    package (`shot.usdz[textures/leaf.png]`) read as loose files do."""
    asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved))
    if not asset:
        raise ValueError(f"texture {resolved} could not be opened")
    return bytes(asset.GetBuffer())


def read_mask(source: MaskSource) -> npt.NDArray[np.float32]:
    """The (height, width) values of the source's channel, scaled and biased, rows from
    v = 0 (the image's bottom) up."""
    if source.constant is not None:
        return np.full((1, 1), source.constant, dtype=np.float32)
    suffix = Path(source.file.rstrip("]")).suffix.lower()
    if suffix == ".exr":
        values = _exr_channel(source)
    else:
        from PIL import Image

        with Image.open(io.BytesIO(_asset_bytes(source.file))) as image:
            rgba = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
        values = rgba[..., _CHANNELS[source.channel]]
        if source.srgb:
            values = np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)
    values = values * source.scale + source.bias
    # A NaN texel (an EXR's) is opaque, as an opacity that cannot be read is.
    values = np.nan_to_num(values, nan=1.0, posinf=1.0, neginf=0.0)
    return np.ascontiguousarray(np.flipud(values), dtype=np.float32)


def _exr_channel(source: MaskSource) -> npt.NDArray[np.float32]:
    """The source's channel of an EXR texture, rows as the file stores them (top first)."""
    if Path(source.file).is_file():
        channels = crepuscular.read_exr(source.file)
    else:
        # The EXR reader takes a path: a packaged file goes through a temporary copy.
        with tempfile.TemporaryDirectory(prefix="crepuscular-usd-") as folder:
            copy = Path(folder) / "mask.exr"
            copy.write_bytes(_asset_bytes(source.file))
            channels = crepuscular.read_exr(copy)
    name = source.channel.upper()
    found = [key for key in channels if key == name or key.endswith(f".{name}")]
    if found:
        return channels[found[0]]
    if name == "A":
        return np.ones_like(next(iter(channels.values())))
    raise ValueError(f"texture {source.file}: no {name} channel")
