"""The image a stage's RenderSettings prim asks for: camera, resolution, pixel aspect, how
the camera's aperture is conformed to the image, its data window, and which purposes
render.

The prim is the one named on the command line, else the stage's `renderSettingsPrimPath`
metadata, else the stage's only RenderSettings prim, as farm renderers look for it. Its
products' own overrides are not read: a render of several products at different sizes
is several renders here.
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
    camera: Sdf.Path | None = None
    resolution: tuple[int, int] | None = None
    pixel_aspect: float = 1.0
    conform: str = "expandAperture"
    purposes: tuple[str, ...] = DEFAULT_PURPOSES
    #: `dataWindowNDC` (x min, y min, x max, y max; y up) where not the whole image.
    data_window: tuple[float, float, float, float] | None = None
    #: What of the prim (or of finding one) is not followed, for warnings.
    notes: tuple[str, ...] = ()

    def attribute(self, name: str) -> str:
        """`name` on the prim, for messages."""
        return f"{self.path}.{name}" if self.path is not None else name


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


def _find(stage: Usd.Stage, path: str | None) -> UsdRender.Settings | list[Sdf.Path]:
    """The prim, else the paths of the stage's RenderSettings prims, none of them chosen."""
    if path is not None:
        if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
            raise RenderSettingsError(f"render settings path {path!r} is not an absolute prim path")
        prim = stage.GetPrimAtPath(path)
        if not prim:
            raise RenderSettingsError(f"render settings {path} does not exist on the stage")
        if not prim.IsA(UsdRender.Settings):
            kind = prim.GetTypeName() or "typeless prim"
            raise RenderSettingsError(f"render settings {path} is a {kind}, not a RenderSettings")
        return UsdRender.Settings(prim)
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


def read_render_settings(stage: Usd.Stage, path: str | None) -> ImageSettings:
    """The image settings of the RenderSettings prim at `path`, else of the stage's own
    (see the module's doc); the schema's defaults where there is none."""
    settings = _find(stage, path)
    if isinstance(settings, list):
        if not settings:
            return ImageSettings()
        listed = ", ".join(str(p) for p in settings)
        return ImageSettings(
            notes=(
                f"the stage has {len(settings)} RenderSettings prims ({listed}) and no "
                "renderSettingsPrimPath; none is read (give --renderSettingsPrimPath)",
            )
        )
    where = settings.GetPath()
    notes = []
    # Read at the default time: UsdRender's image settings are not meant to vary.
    cameras = settings.GetCameraRel().GetForwardedTargets()
    if len(cameras) > 1:
        notes.append(
            f"{where}.camera targets {len(cameras)} prims; the first, {cameras[0]}, is read"
        )
    resolution = settings.GetResolutionAttr().Get()
    width, height = (int(resolution[0]), int(resolution[1])) if resolution else (0, 0)
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise RenderSettingsError(f"{where}.resolution {width}x{height} is outside 1..16384")
    aspect = settings.GetPixelAspectRatioAttr().Get()
    if aspect is None or not (math.isfinite(aspect) and aspect > 0):
        raise RenderSettingsError(f"{where}.pixelAspectRatio {aspect} must be positive")
    conform = str(settings.GetAspectRatioConformPolicyAttr().Get())
    if conform not in CONFORM_POLICIES:
        raise RenderSettingsError(
            f"{where}.aspectRatioConformPolicy {conform!r} is none of {', '.join(CONFORM_POLICIES)}"
        )
    purposes = tuple(str(p) for p in settings.GetIncludedPurposesAttr().Get() or ())
    unknown = sorted(set(purposes) - set(PURPOSES))
    if unknown:
        raise RenderSettingsError(
            f"{where}.includedPurposes holds {', '.join(unknown)}, none of {', '.join(PURPOSES)}"
        )
    window = settings.GetDataWindowNDCAttr().Get()
    data_window = None
    if window is not None and tuple(window) != (0.0, 0.0, 1.0, 1.0):
        data_window = tuple(float(v) for v in window)
        if not all(math.isfinite(v) for v in data_window):
            raise RenderSettingsError(f"{where}.dataWindowNDC {data_window} is not finite")
    return ImageSettings(
        path=where,
        camera=cameras[0] if cameras else None,
        resolution=(width, height),
        pixel_aspect=float(aspect),
        conform=conform,
        purposes=purposes,
        data_window=data_window,
        notes=tuple(notes),
    )
