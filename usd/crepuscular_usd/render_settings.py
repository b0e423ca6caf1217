"""The image a stage's RenderSettings prim asks for: camera, resolution, pixel aspect, how
the camera's aperture is conformed to the image, its data window, and which purposes
render.

The prim is the one named on the command line, else the stage's `renderSettingsPrimPath`
metadata, else the stage's only RenderSettings prim, as farm renderers look for it. A
RenderProduct it targets overrides its camera, resolution, pixel aspect, conform policy
and data window where the product authors them, as UsdRender's spec computes a
product's image: the one named on the command line, else its only product, else the
first where its products' images differ (they are several renders here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pxr import Sdf, Usd, UsdRender

__all__ = [
    "ImageSettings",
    "RenderSettingsError",
    "fitted_vertically",
    "pixel_window",
    "read_render_settings",
]

#: Purposes a RenderSettings prim renders where `includedPurposes` is unauthored.
DEFAULT_PURPOSES = ("default", "render")
PURPOSES = ("default", "render", "proxy", "guide")
CONFORM_POLICIES = (
    "expandAperture",
    "cropAperture",
    "adjustApertureWidth",
    "adjustApertureHeight",
    "adjustPixelAspectRatio",
)


class RenderSettingsError(ValueError):
    """The RenderSettings prim asked for is missing, or holds a value that cannot render."""


@dataclass(frozen=True)
class ImageSettings:
    """A RenderSettings prim's image; defaults are the schema's fallbacks."""

    path: Sdf.Path | None = None
    #: The RenderProduct whose overrides apply, if any.
    product: Sdf.Path | None = None
    camera: Sdf.Path | None = None
    resolution: tuple[int, int] | None = None
    pixel_aspect: float = 1.0
    conform: str = "expandAperture"
    purposes: tuple[str, ...] = DEFAULT_PURPOSES
    #: `dataWindowNDC` (x min, y min, x max, y max; y up) where not the whole image.
    data_window: tuple[float, float, float, float] | None = None
    #: What of the prim (or of finding one) is not followed, for warnings.
    notes: tuple[str, ...] = ()
    #: The attributes the product overrides, by name (the rest are the settings').
    overridden: tuple[str, ...] = ()

    def attribute(self, name: str) -> str:
        """`name` on the prim that gives it, for messages."""
        where = self.product if name in self.overridden else self.path
        return f"{where}.{name}" if where is not None else name


def fitted_vertically(
    conform: str, image_aspect: float, aperture_aspect: float
) -> tuple[bool, float | None]:
    """Whether the aperture's height (rather than its width) spans the image, by the
    conform policy, for an image `image_aspect` wide per unit of height (pixel aspect
    included); and the pixel aspect `adjustPixelAspectRatio` sets in place of the given
    one, as a factor on it (None for the other policies)."""
    wider = image_aspect > aperture_aspect
    if conform == "cropAperture":
        return not wider, None
    if conform == "adjustApertureWidth":
        return True, None
    if conform == "adjustApertureHeight":
        return False, None
    if conform == "adjustPixelAspectRatio":
        return False, aperture_aspect / image_aspect
    return wider, None


def pixel_window(
    data_window: tuple[float, float, float, float], width: int, height: int
) -> dict[str, int] | None:
    """The pixels of a `width` x `height` image whose centres lie in `data_window` (NDC,
    y up), as the core's camera window (from the top-left corner); None where none does.
    Overscan past the image is left out."""
    x_min, y_min, x_max, y_max = data_window
    left = max(0, math.ceil(x_min * width - 0.5))
    right = min(width, math.floor(x_max * width - 0.5) + 1)
    top = max(0, math.ceil((1.0 - y_max) * height - 0.5))
    bottom = min(height, math.floor((1.0 - y_min) * height - 0.5) + 1)
    if right <= left or bottom <= top:
        return None
    return {"x": left, "y": top, "width": right - left, "height": bottom - top}


def _typed_prim(stage: Usd.Stage, path: Sdf.Path, schema: type, what: str) -> Usd.Prim:
    """The prim at `path`, which must be a UsdRender `schema` (named `what` in messages)."""
    prim = stage.GetPrimAtPath(path)
    if not prim:
        raise RenderSettingsError(f"{what} {path} does not exist on the stage")
    if not prim.IsA(schema):
        kind = prim.GetTypeName() or "typeless prim"
        raise RenderSettingsError(f"{what} {path} is a {kind}, not a Render{schema.__name__}")
    return prim


def _find(stage: Usd.Stage, path: str | None) -> UsdRender.Settings | list[Sdf.Path]:
    """The prim, else the paths of the stage's RenderSettings prims, none of them chosen."""
    if path is not None:
        if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
            raise RenderSettingsError(f"render settings path {path!r} is not an absolute prim path")
        return UsdRender.Settings(
            _typed_prim(stage, Sdf.Path(path), UsdRender.Settings, "render settings")
        )
    named = stage.GetMetadata(UsdRender.Tokens.renderSettingsPrimPath)
    if named:
        settings = UsdRender.Settings.GetStageRenderSettings(stage)
        if not settings:
            raise RenderSettingsError(
                f"the stage's renderSettingsPrimPath names {named}, which is not a "
                "RenderSettings prim on the stage"
            )
        return settings
    found = [p for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
    return UsdRender.Settings(found[0]) if len(found) == 1 else [p.GetPath() for p in found]


#: The image attributes a RenderProduct overrides where it authors them.
_OVERRIDABLE = (
    "camera",
    "resolution",
    "pixelAspectRatio",
    "aspectRatioConformPolicy",
    "dataWindowNDC",
)


def _image_values(base: UsdRender.SettingsBase, authored_only: bool) -> dict[str, object]:
    """`base`'s image attributes by name (the camera as its targets), the fallbacks
    included unless `authored_only`."""
    attributes = {
        "resolution": base.GetResolutionAttr(),
        "pixelAspectRatio": base.GetPixelAspectRatioAttr(),
        "aspectRatioConformPolicy": base.GetAspectRatioConformPolicyAttr(),
        "dataWindowNDC": base.GetDataWindowNDCAttr(),
    }
    values: dict[str, object] = {}
    camera = base.GetCameraRel()
    if not authored_only or (camera and camera.HasAuthoredTargets()):
        values["camera"] = tuple(camera.GetForwardedTargets()) if camera else ()
    for name, attribute in attributes.items():
        if not authored_only or attribute.HasAuthoredValue():
            values[name] = attribute.Get()
    return values


def _as_product(stage: Usd.Stage, path: Sdf.Path, named_by: str) -> UsdRender.Product:
    return UsdRender.Product(
        _typed_prim(stage, path, UsdRender.Product, f"render product (from {named_by})")
    )


def _product(
    stage: Usd.Stage, settings: UsdRender.Settings, path: str | None, notes: list[str]
) -> tuple[Sdf.Path | None, dict[str, object]]:
    """The product whose overrides apply and those overrides: the one at `path`, else the
    settings' only product, else their first where their overrides differ."""
    if path is not None:
        if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
            raise RenderSettingsError(f"render product path {path!r} is not an absolute prim path")
        product = _as_product(stage, Sdf.Path(path), "--renderProduct")
        return product.GetPath(), _image_values(product, authored_only=True)
    where = settings.GetPath()
    targets = settings.GetProductsRel().GetForwardedTargets()
    products = [_as_product(stage, target, f"{where}.products") for target in targets]
    if not products:
        return None, {}
    overrides = [_image_values(product, authored_only=True) for product in products]
    if any(other != overrides[0] for other in overrides[1:]):
        listed = ", ".join(str(p.GetPath()) for p in products)
        notes.append(
            f"{where}.products: {len(products)} products ({listed}) override the image "
            f"differently; the first, {products[0].GetPath()}, is rendered (give "
            "--renderProduct)"
        )
    return products[0].GetPath(), overrides[0]


def read_render_settings(
    stage: Usd.Stage, path: str | None, product_path: str | None = None
) -> ImageSettings:
    """The image settings of the RenderSettings prim at `path`, else of the stage's own,
    with the overrides of its product at `product_path`, else of its own (see the
    module's doc); the schema's defaults where there is none."""
    settings = _find(stage, path)
    if isinstance(settings, list):
        if product_path is not None:
            raise RenderSettingsError(
                f"--renderProduct {product_path} needs the RenderSettings prim it belongs to "
                "(give --renderSettingsPrimPath)"
            )
        if not settings:
            return ImageSettings()
        listed = ", ".join(str(p) for p in settings)
        return ImageSettings(
            notes=(
                f"the stage has {len(settings)} RenderSettings prims ({listed}) and no "
                "renderSettingsPrimPath; none is read (give --renderSettingsPrimPath)",
            )
        )
    notes: list[str] = []
    # Read at the default time: UsdRender's image settings are not meant to vary.
    values = _image_values(settings, authored_only=False)
    product, overrides = _product(stage, settings, product_path, notes)
    values.update(overrides)
    overridden = tuple(name for name in _OVERRIDABLE if name in overrides)

    def where(name: str) -> str:
        return f"{product if name in overridden else settings.GetPath()}.{name}"

    cameras = values["camera"]
    if len(cameras) > 1:
        notes.append(
            f"{where('camera')} targets {len(cameras)} prims; the first, {cameras[0]}, is read"
        )
    resolution = values["resolution"]
    width, height = (int(resolution[0]), int(resolution[1])) if resolution else (0, 0)
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise RenderSettingsError(f"{where('resolution')} {width}x{height} is outside 1..16384")
    aspect = values["pixelAspectRatio"]
    if aspect is None or not (math.isfinite(aspect) and aspect > 0):
        raise RenderSettingsError(f"{where('pixelAspectRatio')} {aspect} must be positive")
    conform = str(values["aspectRatioConformPolicy"])
    if conform not in CONFORM_POLICIES:
        raise RenderSettingsError(
            f"{where('aspectRatioConformPolicy')} {conform!r} is none of "
            f"{', '.join(CONFORM_POLICIES)}"
        )
    purposes = tuple(str(p) for p in settings.GetIncludedPurposesAttr().Get() or ())
    unknown = sorted(set(purposes) - set(PURPOSES))
    if unknown:
        raise RenderSettingsError(
            f"{settings.GetPath()}.includedPurposes holds {', '.join(unknown)}, none of "
            f"{', '.join(PURPOSES)}"
        )
    window = values["dataWindowNDC"]
    data_window = None
    if window is not None and tuple(window) != (0.0, 0.0, 1.0, 1.0):
        data_window = tuple(float(v) for v in window)
        if not all(math.isfinite(v) for v in data_window):
            raise RenderSettingsError(f"{where('dataWindowNDC')} {data_window} is not finite")
    return ImageSettings(
        path=settings.GetPath(),
        product=product,
        camera=cameras[0] if cameras else None,
        resolution=(width, height),
        pixel_aspect=float(aspect),
        conform=conform,
        purposes=purposes,
        data_window=data_window,
        notes=tuple(notes),
        overridden=overridden,
    )
