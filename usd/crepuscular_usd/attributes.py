"""The properties of the codeless `CrepuscularLightAPI` as plain data: each attribute's name,
its USD value type, and where its value goes in the renderer's scene description.

This module imports nothing but the standard library, because it is shared: `schema.py`
builds its reader on it, and the Blender add-on's USD export hook, which cannot import this
package (it ships separately, and Blender has its own USD), carries a copy of this very file
in its zip (`blender_addon/build_extension.py` puts it there as `usd_attributes.py`). Tests
check that these names and types are exactly those of `resources/generatedSchema.usda`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "API_NAME",
    "ATTRIBUTES",
    "HOLES_OBJECTS",
    "MEDIUM_EXTENT",
    "RELATIONSHIPS",
    "SUBDIVISION_LEVELS",
    "SUBDIVISION_LIMIT",
    "TF_ASSET",
    "TF_JSON",
    "Attribute",
]

API_NAME = "CrepuscularLightAPI"

MEDIUM_EXTENT = "crepuscular:mediumExtent"
HOLES_OBJECTS = "crepuscular:holes:objects"
TF_ASSET = "crepuscular:tf:asset"
#: On a Catmull-Clark mesh: how many levels to refine its cage (an int), and whether onto
#: its limit surface (a bool, true unless authored false). USD leaves the level to each
#: renderer; the add-on's export hook writes those Blender renders a mesh at.
SUBDIVISION_LEVELS = "crepuscular:subdivision:levels"
SUBDIVISION_LIMIT = "crepuscular:subdivision:limitSurface"
TF_JSON = "crepuscular:tf:json"
#: The schema's relationships: the medium's box, and the meshes that take holes.
RELATIONSHIPS = (MEDIUM_EXTENT, HOLES_OBJECTS)


@dataclass(frozen=True)
class Attribute:
    """One attribute of the schema and the scene-description value it carries."""

    #: USD value type name, as in generatedSchema.usda ("float", "color3f", "token", ...).
    type_name: str
    #: Path of the value in the scene description: ("medium", "extinction"),
    #: ("render", "steps"), ("style", "closing", "radius"), ("sun", "intensity_scale").
    #: Empty for the transfer function, which is read as a whole.
    target: tuple[str, ...] = ()
    #: Stage units per unit of the value: 1 for lengths, -1 for per-length, 0 for none.
    length_power: int = 0
    #: Negative (any component of a colour) means "unset" (the key is left out), for the
    #: renderer's optional values.
    negative_unset: bool = False


ATTRIBUTES: dict[str, Attribute] = {
    "crepuscular:medium:extinction": Attribute("float", ("medium", "extinction"), -1),
    "crepuscular:medium:albedo": Attribute("color3f", ("medium", "albedo")),
    "crepuscular:medium:channelExtinction": Attribute(
        "color3f", ("medium", "channel_extinction"), -1, True
    ),
    "crepuscular:medium:anisotropy": Attribute("float", ("medium", "anisotropy")),
    "crepuscular:medium:phase": Attribute("token", ("medium", "phase")),
    "crepuscular:intensityScale": Attribute("float", ("sun", "intensity_scale")),
    "crepuscular:angleScale": Attribute("float", ("sun", "angle_scale")),
    "crepuscular:method": Attribute("token", ("render", "method")),
    "crepuscular:shadowMapSize": Attribute("int", ("render", "shadow_map_size")),
    "crepuscular:maxDistance": Attribute("float", ("render", "max_distance"), 1),
    "crepuscular:steps": Attribute("int", ("render", "steps")),
    "crepuscular:supersampling": Attribute("int", ("render", "supersampling")),
    "crepuscular:shadowBias": Attribute("float", ("render", "shadow_bias"), 1, True),
    "crepuscular:epipolarSlices": Attribute("int", ("render", "epipolar_slices")),
    "crepuscular:epipoleBlock": Attribute("int", ("render", "epipole_block")),
    "crepuscular:downsample": Attribute("int", ("render", "downsample")),
    "crepuscular:adaptiveTolerance": Attribute("float", ("render", "adaptive_tolerance")),
    "crepuscular:bases": Attribute("int", ("render", "bases")),
    "crepuscular:nearPlaneCorrection": Attribute("bool", ("render", "near_plane_correction")),
    "crepuscular:exactRayEnds": Attribute("token", ("render", "exact_ray_ends")),
    "crepuscular:basisStorage": Attribute("token", ("render", "basis_storage")),
    "crepuscular:rectification": Attribute("token", ("render", "rectification")),
    "crepuscular:closing:enable": Attribute("bool", ("style", "closing", "enable")),
    "crepuscular:closing:operation": Attribute("token", ("style", "closing", "operation")),
    "crepuscular:closing:kernel": Attribute("token", ("style", "closing", "kernel")),
    "crepuscular:closing:radius": Attribute("float", ("style", "closing", "radius"), 1),
    "crepuscular:closing:radiusTexels": Attribute(
        "float", ("style", "closing", "radius_texels"), 0, True
    ),
    "crepuscular:silhouette:enable": Attribute("bool", ("style", "silhouette", "enable")),
    "crepuscular:silhouette:operation": Attribute("token", ("style", "silhouette", "operation")),
    "crepuscular:silhouette:length": Attribute("float", ("style", "silhouette", "length"), 1),
    "crepuscular:silhouette:lengthTexels": Attribute(
        "float", ("style", "silhouette", "length_texels"), 0, True
    ),
    "crepuscular:holes:enable": Attribute("bool", ("style", "holes", "enable")),
    "crepuscular:holes:frequency": Attribute("float", ("style", "holes", "frequency"), -1),
    "crepuscular:holes:persistence": Attribute("float", ("style", "holes", "persistence")),
    "crepuscular:holes:octaves": Attribute("int", ("style", "holes", "octaves")),
    "crepuscular:holes:threshold": Attribute("float", ("style", "holes", "threshold")),
    "crepuscular:holes:gridSize": Attribute("int", ("style", "holes", "grid_size")),
    "crepuscular:holes:seed": Attribute("int", ("style", "holes", "seed")),
    "crepuscular:holes:time": Attribute("float", ("style", "holes", "time")),
    "crepuscular:holes:speed": Attribute("float", ("style", "holes", "speed")),
    "crepuscular:holes:warp": Attribute("float", ("style", "holes", "warp")),
    # A stage point: converted with the whole stage-to-renderer transform, not a scale.
    "crepuscular:holes:pivot": Attribute("point3f", ("style", "holes", "pivot")),
    TF_ASSET: Attribute("asset"),
    TF_JSON: Attribute("string"),
}
