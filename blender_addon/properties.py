"""Settings as PropertyGroups: per sun lamp (`Light.crepuscular`), per object
(`Object.crepuscular`) and per scene (`Scene.crepuscular`: the medium and the output).

Every value is a plain Blender property, so it is saved in the .blend and can be keyframed.
Lengths use Blender's LENGTH unit: they are stored in scene units and shown with the
scene's unit scale, as the core expects (kernel sizes in scene units, not texels).
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)
from bpy.types import PropertyGroup

METHODS = [
    ("reference", "Reference", "Brute-force ray marching: exact, slowest"),
    ("minmax", "Min-max", "1D min-max mipmaps on the rectified shadow map"),
    ("prefiltered", "Prefiltered", "Fourier-basis prefiltering (work in progress in the core)"),
]
BLENDS = [
    ("alpha", "Alpha", "Porter-Duff over"),
    ("add", "Add", "Add to the layers below"),
    ("multiply", "Multiply", "Multiply the layers below"),
]
TF_KINDS = [
    ("solid", "Solid", "One colour"),
    ("gradient", "Gradient", "Linear or radial gradient with colour stops"),
    ("image", "Image", "An Image datablock, V̄ left to right and depth bottom to top"),
    ("diffusion", "Diffusion", "Colour constraints diffused smoothly over the TF"),
]


def _tag_preview(self: PropertyGroup, context: bpy.types.Context) -> None:
    """Any setting change asks the viewport preview to update (debounced)."""
    from . import preview

    preview.CONTROLLER.mark_dirty()


def _lights_update(self: PropertyGroup, context: bpy.types.Context) -> None:
    from . import render

    if context is not None and context.scene is not None:
        from . import export

        try:
            render.sync_scene(context.scene)
        except export.ExportError as error:
            # Shown in the panels and logged; the next render tries again.
            context.scene.crepuscular.last_error = str(error)
            render.log(str(error))
    _tag_preview(self, context)


class CrepuscularTfStop(PropertyGroup):
    position: FloatProperty(name="Position", min=0.0, max=1.0, update=_tag_preview)
    color: FloatVectorProperty(
        name="Color",
        subtype="COLOR",
        size=4,
        min=0.0,
        soft_max=1.0,
        default=(1.0, 1.0, 1.0, 1.0),
        update=_tag_preview,
    )


class CrepuscularTfConstraint(PropertyGroup):
    position: FloatVectorProperty(
        name="Position",
        description="TF-space position (V̄, normalized depth)",
        size=2,
        min=0.0,
        max=1.0,
        default=(0.5, 0.5),
        update=_tag_preview,
    )
    color: FloatVectorProperty(
        name="Color",
        subtype="COLOR",
        size=4,
        min=0.0,
        soft_max=1.0,
        default=(1.0, 1.0, 1.0, 1.0),
        update=_tag_preview,
    )
    use_world_point: BoolProperty(
        name="3D Constraint",
        description="Take the position each frame from the pixel where the world point appears",
        update=_tag_preview,
    )
    world_point: FloatVectorProperty(
        name="World Point", subtype="TRANSLATION", unit="LENGTH", size=3, update=_tag_preview
    )


class CrepuscularTfLayer(PropertyGroup):
    name: StringProperty(name="Name", default="Layer")
    kind: EnumProperty(name="Kind", items=TF_KINDS, default="solid", update=_tag_preview)
    blend: EnumProperty(name="Blend", items=BLENDS, default="alpha", update=_tag_preview)
    opacity: FloatProperty(name="Opacity", min=0.0, max=1.0, default=1.0, update=_tag_preview)
    color: FloatVectorProperty(
        name="Color",
        subtype="COLOR",
        size=4,
        min=0.0,
        soft_max=1.0,
        default=(1.0, 1.0, 1.0, 1.0),
        update=_tag_preview,
    )
    shape: EnumProperty(
        name="Shape",
        items=[("linear", "Linear", ""), ("radial", "Radial", "")],
        default="linear",
        update=_tag_preview,
    )
    start: FloatVectorProperty(
        name="From",
        description="Gradient start (V̄, depth)",
        size=2,
        default=(0.0, 0.0),
        update=_tag_preview,
    )
    end: FloatVectorProperty(
        name="To",
        description="Gradient end (V̄, depth)",
        size=2,
        default=(1.0, 0.0),
        update=_tag_preview,
    )
    center: FloatVectorProperty(name="Center", size=2, default=(0.5, 0.5), update=_tag_preview)
    radius: FloatProperty(name="Radius", min=0.0, default=0.5, update=_tag_preview)
    stops: CollectionProperty(type=CrepuscularTfStop)
    active_stop: IntProperty(default=0)
    image: PointerProperty(name="Image", type=bpy.types.Image, update=_tag_preview)
    constraints: CollectionProperty(type=CrepuscularTfConstraint)
    active_constraint: IntProperty(default=0)


class CrepuscularLight(PropertyGroup):
    """Shafts of one sun lamp: quality and style (`light.crepuscular`)."""

    enabled: BoolProperty(
        name="Stylized Shafts",
        description="Render volumetric shafts of this sun and composite them over renders",
        update=_lights_update,
    )
    method: EnumProperty(name="Method", items=METHODS, default="prefiltered", update=_tag_preview)
    shadow_map_size: IntProperty(
        name="Shadow Map",
        description="Side of the sun's shadow map, in texels",
        min=16,
        max=16384,
        soft_max=4096,
        default=1024,
        update=_tag_preview,
    )
    bases: IntProperty(
        name="Bases",
        description="Fourier bases of the prefiltered method (even)",
        min=4,
        max=64,
        default=32,
        step=2,
        update=_tag_preview,
    )
    exact_ray_ends: EnumProperty(
        name="Exact Ray Ends",
        description="Prefiltered method: integrate exactly where a ray closes in on the surface "
        "it ends on (ground it grazes, views near the sun's direction, surfaces that nearly "
        "shadow themselves)",
        # Numbered so that files saved while this was a checkbox read off and on as before.
        items=[
            (
                "auto",
                "Auto",
                "In a fog box, where it costs little, and under a sun below the horizon "
                "(otherwise off in open fog)",
                2,
            ),
            ("on", "On", "Always; in open fog frames take up to 60% longer", 1),
            ("off", "Off", "Never; a fog box may glow where surfaces shadow themselves", 0),
        ],
        default="auto",
        update=_tag_preview,
    )
    downsample: EnumProperty(
        name="Downsample",
        items=[("1", "1/1", ""), ("2", "1/2", ""), ("4", "1/4", "")],
        default="1",
        update=_tag_preview,
        description="Evaluate scattering at reduced resolution and upsample along depth edges",
    )
    adaptive_tolerance: FloatProperty(
        name="Adaptive Tolerance",
        description="Fast methods: shade a sparse grid of pixels, and the pixels between only "
        "where their neighbours differ by more than this fraction or lie on another surface; "
        "0 shades every pixel",
        min=0.0,
        max=1.0,
        soft_max=0.1,
        default=0.01,
        precision=3,
        step=0.1,
        update=_tag_preview,
    )
    steps: IntProperty(
        name="Steps",
        description="Ray-march steps of the reference method",
        min=1,
        max=1 << 20,
        soft_max=4096,
        default=256,
        update=_tag_preview,
    )
    edge_samples: IntProperty(
        name="Edge Samples",
        description="Depth samples per pixel along each axis, so that the layers' edges "
        "match the beauty's antialiasing (no halo at silhouettes)",
        min=1,
        max=8,
        default=2,
        update=_tag_preview,
    )
    max_distance: FloatProperty(
        name="Max Distance",
        description="Distance integrated for background pixels",
        unit="LENGTH",
        min=1e-3,
        default=100.0,
        update=_tag_preview,
    )
    # Style: occluder manipulation (papers 000/001 section 4.1).
    use_closing: BoolProperty(name="Hole Filling", update=_tag_preview)
    closing_operation: EnumProperty(
        name="Operation",
        items=[
            ("close", "Close", "Fill holes smaller than the kernel"),
            ("dilate", "Dilate", ""),
            ("erode", "Erode", ""),
            ("open", "Open", ""),
        ],
        default="close",
        update=_tag_preview,
    )
    closing_kernel: EnumProperty(
        name="Kernel",
        items=[("disk", "Disk", ""), ("box", "Box", "")],
        default="disk",
        update=_tag_preview,
    )
    closing_radius: FloatProperty(
        name="Radius", unit="LENGTH", min=0.0, default=0.5, update=_tag_preview
    )
    use_silhouette: BoolProperty(name="Silhouette", update=_tag_preview)
    silhouette_operation: EnumProperty(
        name="Operation",
        items=[
            ("dilate", "Dilate", "Extrude away from the camera"),
            ("close", "Close", "Extrude, then erode back what the camera would not see"),
        ],
        default="dilate",
        update=_tag_preview,
    )
    silhouette_length: FloatProperty(
        name="Length", unit="LENGTH", min=0.0, default=0.3, update=_tag_preview
    )
    use_holes: BoolProperty(
        name="Holes",
        description="Noise holes in the objects marked 'Takes Holes'",
        update=_tag_preview,
    )
    holes_frequency: FloatProperty(
        name="Frequency",
        description="Noise grid repeats per scene unit",
        min=0.0,
        default=1.0 / 32.0,
        precision=4,
        update=_tag_preview,
    )
    holes_persistence: FloatProperty(
        name="Persistence", min=1e-3, max=1.0, default=0.5, update=_tag_preview
    )
    holes_octaves: IntProperty(name="Octaves", min=1, max=16, default=4, update=_tag_preview)
    holes_threshold: FloatProperty(
        name="Threshold", min=0.0, max=1.0, default=0.5, update=_tag_preview
    )
    holes_grid_size: IntProperty(name="Grid Size", min=1, max=4096, default=64, update=_tag_preview)
    holes_seed: IntProperty(name="Seed", min=0, default=0, update=_tag_preview)
    holes_speed: FloatProperty(name="Speed", default=0.02, update=_tag_preview)
    holes_warp: FloatProperty(name="Warp", min=0.0, max=64.0, default=0.5, update=_tag_preview)
    holes_pivot: FloatVectorProperty(
        name="Pivot", subtype="TRANSLATION", unit="LENGTH", size=3, update=_tag_preview
    )
    # Style: the 2D transfer function.
    use_tf: BoolProperty(name="Transfer Function", update=_tag_preview)
    tf_mode: EnumProperty(
        name="Mode",
        items=[
            ("monochrome", "Monochrome", "The TF's luminance scales the physical light"),
            ("color", "Color", "The TF colour replaces the light's colour"),
        ],
        default="monochrome",
        update=_tag_preview,
    )
    tf_depth_near: FloatProperty(
        name="Depth Near", unit="LENGTH", min=0.0, default=0.0, update=_tag_preview
    )
    tf_depth_far: FloatProperty(
        name="Depth Far", unit="LENGTH", min=0.0, default=60.0, update=_tag_preview
    )
    tf_resolution: IntProperty(name="Resolution", min=2, max=4096, default=256, update=_tag_preview)
    tf_layers: CollectionProperty(type=CrepuscularTfLayer)
    active_tf_layer: IntProperty(default=0)
    tf_image: PointerProperty(
        name="Baked TF",
        type=bpy.types.Image,
        description="The TF baked by 'Bake TF to Image': V̄ left to right, depth bottom to "
        "top, premultiplied. Paint on it in the Image Editor and use it as an Image layer",
    )


CASTS = [
    ("auto", "Auto", "Follow the object's Shadow ray visibility"),
    ("on", "On", "Always in the sun's shadow map"),
    ("off", "Off", "Never in the sun's shadow map"),
]


class CrepuscularObject(PropertyGroup):
    """Per object (`object.crepuscular`)."""

    casts_shafts: EnumProperty(
        name="Casts Shafts",
        items=CASTS,
        default="auto",
        update=_tag_preview,
        description="Whether the object occludes the sun in the shafts' shadow map",
    )
    takes_holes: BoolProperty(
        name="Takes Holes",
        description="Noise holes of the sun's style open in this object",
        update=_tag_preview,
    )


def _poll_fog(self: PropertyGroup, obj: bpy.types.Object) -> bool:
    return obj.type == "MESH"


class CrepuscularScene(PropertyGroup):
    """The medium and the outputs (`scene.crepuscular`)."""

    medium_source: EnumProperty(
        name="Medium",
        items=[
            ("custom", "Custom", "Set the medium here"),
            ("fog_object", "Fog Object", "Read it from a box with a volume material"),
        ],
        default="custom",
        update=_tag_preview,
    )
    fog_object: PointerProperty(
        name="Fog Object",
        type=bpy.types.Object,
        poll=_poll_fog,
        update=_tag_preview,
        description="A box mesh whose material's volume is a Volume Scatter, Volume "
        "Absorption, Principled Volume or Volume Coefficients, or Add and Mix Shaders of "
        "them. It is hidden from the beauty while shafts replace it",
    )
    extinction: FloatProperty(
        name="Extinction",
        description="σt per scene unit",
        min=0.0,
        soft_max=2.0,
        default=0.05,
        precision=4,
        update=_tag_preview,
    )
    albedo: FloatVectorProperty(
        name="Albedo",
        subtype="COLOR",
        size=3,
        min=0.0,
        soft_max=1.0,
        default=(1.0, 1.0, 1.0),
        update=_tag_preview,
    )
    anisotropy: FloatProperty(
        name="Anisotropy", min=-0.99, max=0.99, default=0.3, update=_tag_preview
    )
    composite: BoolProperty(
        name="Composite Renders",
        default=True,
        description="Composite the shafts over F12 and animation renders",
    )
    write_layers: BoolProperty(
        name="Write Layers",
        default=True,
        description="Write volume, visibility and depth as a multi-layer EXR next to each "
        "rendered frame",
    )
    preview: BoolProperty(
        name="Viewport Preview",
        update=_tag_preview,
        description="Draw the volume layer over the viewport in camera view",
    )
    preview_scale: EnumProperty(
        name="Preview Scale",
        items=[("2", "1/2", ""), ("4", "1/4", ""), ("8", "1/8", "")],
        default="2",
        update=_tag_preview,
    )
    last_error: StringProperty(
        name="Last Error", description="The last error of a render, empty when it worked"
    )


CLASSES = (
    CrepuscularTfStop,
    CrepuscularTfConstraint,
    CrepuscularTfLayer,
    CrepuscularLight,
    CrepuscularObject,
    CrepuscularScene,
)

#: (type, attribute, group): the pointers this module adds to Blender's types.
POINTERS = (
    (bpy.types.Light, "crepuscular", CrepuscularLight),
    (bpy.types.Object, "crepuscular", CrepuscularObject),
    (bpy.types.Scene, "crepuscular", CrepuscularScene),
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for owner, name, group in POINTERS:
        setattr(owner, name, PointerProperty(type=group))


def unregister() -> None:
    for owner, name, _group in reversed(POINTERS):
        delattr(owner, name)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
