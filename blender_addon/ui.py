"""Panels and small operators: sun lamp shafts and style (with the TF layer stack and
presets), per-object flags, and the scene's medium and outputs."""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

import crepuscular

from . import preview
from .cutouts import material_mask
from .properties import TF_KINDS
from .style import StyleError, apply_preset, bake_tf_image, save_preset


def _sun_settings(context: bpy.types.Context):
    light = getattr(context, "light", None)
    return None if light is None else light.crepuscular


def _active_tf_items(context: bpy.types.Context):
    """The stops (gradient) or constraints (other kinds) of the active TF layer, if any."""
    settings = _sun_settings(context)
    if settings is None or not 0 <= settings.active_tf_layer < len(settings.tf_layers):
        return None
    layer = settings.tf_layers[settings.active_tf_layer]
    return layer.stops if layer.kind == "gradient" else layer.constraints


# Operators ------------------------------------------------------------------------------


class CREPUSCULAR_OT_load_preset(bpy.types.Operator, ImportHelper):
    """Load a style preset (JSON) into this sun's settings"""

    bl_idname = "crepuscular.load_preset"
    bl_label = "Load Style Preset"
    bl_options = {"REGISTER", "UNDO"}
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _sun_settings(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            apply_preset(context.light.crepuscular, bpy.path.abspath(self.filepath))
        except (StyleError, crepuscular.CrepuscularError, OSError) as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return {"FINISHED"}


class CREPUSCULAR_OT_save_preset(bpy.types.Operator, ExportHelper):
    """Save this sun's style as a preset (JSON)"""

    bl_idname = "crepuscular.save_preset"
    bl_label = "Save Style Preset"
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _sun_settings(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        light = context.light
        try:
            save_preset(light.crepuscular, bpy.path.abspath(self.filepath), name=light.name)
        except (StyleError, crepuscular.CrepuscularError, OSError) as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return {"FINISHED"}


class CREPUSCULAR_OT_bake_tf(bpy.types.Operator):
    """Bake this sun's TF stack at the current frame into an Image datablock, to view it
    and paint on it in the Image Editor"""

    bl_idname = "crepuscular.bake_tf"
    bl_label = "Bake TF to Image"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _sun_settings(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        light, scene = context.light, context.scene
        fps = scene.render.fps / scene.render.fps_base
        try:
            image = bake_tf_image(
                light.crepuscular, time=scene.frame_current / fps, name=light.name
            )
        except (StyleError, crepuscular.CrepuscularError) as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        self.report({"INFO"}, f"baked the TF into image '{image.name}'")
        return {"FINISHED"}


class CREPUSCULAR_OT_tf_layer_add(bpy.types.Operator):
    """Add a layer on top of the TF stack"""

    bl_idname = "crepuscular.tf_layer_add"
    bl_label = "Add TF Layer"
    bl_options = {"REGISTER", "UNDO"}
    kind: EnumProperty(items=TF_KINDS, default="solid")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _sun_settings(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        settings = context.light.crepuscular
        layer = settings.tf_layers.add()
        layer.kind = self.kind
        layer.name = f"{self.kind.title()} {len(settings.tf_layers)}"
        if self.kind == "gradient":
            for position, value in ((0.0, 0.0), (1.0, 1.0)):
                stop = layer.stops.add()
                stop.position, stop.color = position, (value, value, value, 1.0)
        settings.active_tf_layer = len(settings.tf_layers) - 1
        preview.CONTROLLER.mark_dirty()
        return {"FINISHED"}


class CREPUSCULAR_OT_tf_layer_remove(bpy.types.Operator):
    """Remove the active TF layer"""

    bl_idname = "crepuscular.tf_layer_remove"
    bl_label = "Remove TF Layer"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        settings = _sun_settings(context)
        return settings is not None and len(settings.tf_layers) > 0

    def execute(self, context: bpy.types.Context) -> set[str]:
        settings = context.light.crepuscular
        settings.tf_layers.remove(settings.active_tf_layer)
        settings.active_tf_layer = max(
            0, min(settings.active_tf_layer, len(settings.tf_layers) - 1)
        )
        preview.CONTROLLER.mark_dirty()
        return {"FINISHED"}


class CREPUSCULAR_OT_tf_layer_move(bpy.types.Operator):
    """Move the active TF layer up or down the stack"""

    bl_idname = "crepuscular.tf_layer_move"
    bl_label = "Move TF Layer"
    bl_options = {"REGISTER", "UNDO"}
    direction: EnumProperty(items=[("UP", "Up", ""), ("DOWN", "Down", "")])

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        settings = _sun_settings(context)
        return settings is not None and len(settings.tf_layers) > 1

    def execute(self, context: bpy.types.Context) -> set[str]:
        settings = context.light.crepuscular
        index = settings.active_tf_layer
        target = index + (1 if self.direction == "UP" else -1)
        if not 0 <= target < len(settings.tf_layers):
            return {"CANCELLED"}
        settings.tf_layers.move(index, target)
        settings.active_tf_layer = target
        preview.CONTROLLER.mark_dirty()
        return {"FINISHED"}


class CREPUSCULAR_OT_tf_item_add(bpy.types.Operator):
    """Add a gradient stop or a diffusion constraint to the active TF layer"""

    bl_idname = "crepuscular.tf_item_add"
    bl_label = "Add Stop or Constraint"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _active_tf_items(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        items = _active_tf_items(context)
        items.add()
        preview.CONTROLLER.mark_dirty()
        return {"FINISHED"}


class CREPUSCULAR_OT_tf_item_remove(bpy.types.Operator):
    """Remove the last gradient stop or diffusion constraint of the active TF layer"""

    bl_idname = "crepuscular.tf_item_remove"
    bl_label = "Remove Stop or Constraint"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _active_tf_items(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        items = _active_tf_items(context)
        if len(items) == 0:
            return {"CANCELLED"}
        items.remove(len(items) - 1)
        preview.CONTROLLER.mark_dirty()
        return {"FINISHED"}


def add_world_constraint(settings, point) -> bpy.types.PropertyGroup:
    """Adds a 3D TF constraint at world `point` to the active TF layer, or to a new
    diffusion layer on top when the active layer is not one. Each frame, the core moves it
    to the (V̄, depth) of the pixel where the point appears."""
    layers = settings.tf_layers
    active = settings.active_tf_layer
    if not 0 <= active < len(layers) or layers[active].kind != "diffusion":
        layer = layers.add()
        layer.kind, layer.name = "diffusion", f"Diffusion {len(layers)}"
        settings.active_tf_layer = len(layers) - 1
    layer = layers[settings.active_tf_layer]
    constraint = layer.constraints.add()
    constraint.use_world_point = True
    constraint.world_point = point
    settings.use_tf = True
    preview.CONTROLLER.mark_dirty()
    return constraint


class CREPUSCULAR_OT_pick_constraint(bpy.types.Operator):
    """Click on a surface in the 3D viewport to add a 3D TF constraint there"""

    bl_idname = "crepuscular.pick_constraint"
    bl_label = "Pick TF Constraint in Viewport"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.area is not None and context.area.type == "VIEW_3D"

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        from . import export

        if not export.shaft_suns(context.scene):
            self.report({"ERROR"}, "no sun lamp has Stylized Shafts enabled")
            return {"CANCELLED"}
        context.window.cursor_modal_set("EYEDROPPER")
        context.window_manager.modal_handler_add(self)
        self.report({"INFO"}, "Click a surface to add a constraint; Esc or right-click cancels")
        return {"RUNNING_MODAL"}

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        from bpy_extras import view3d_utils

        from . import export

        if event.type in {"ESC", "RIGHTMOUSE"}:
            context.window.cursor_modal_restore()
            return {"CANCELLED"}
        if event.type != "LEFTMOUSE" or event.value != "PRESS":
            return {"RUNNING_MODAL"}
        context.window.cursor_modal_restore()
        region, view = context.region, context.region_data
        mouse = (event.mouse_region_x, event.mouse_region_y)
        origin = view3d_utils.region_2d_to_origin_3d(region, view, mouse)
        direction = view3d_utils.region_2d_to_vector_3d(region, view, mouse)
        hit, location, *_ = context.scene.ray_cast(
            context.evaluated_depsgraph_get(), origin, direction
        )
        if not hit:
            self.report({"WARNING"}, "no surface under the cursor")
            return {"CANCELLED"}
        sun = export.shaft_suns(context.scene)[0]
        add_world_constraint(sun.data.crepuscular, location)
        self.report({"INFO"}, f"3D constraint at {tuple(round(v, 3) for v in location)}")
        return {"FINISHED"}


# Panels ---------------------------------------------------------------------------------


class CREPUSCULAR_UL_tf_layers(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_prop, index=0):
        row = layout.row(align=True)
        row.prop(item, "name", text="", emboss=False)
        row.label(text=item.kind.title())
        row.prop(item, "blend", text="")


class SunPanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "data"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        light = getattr(context, "light", None)
        return light is not None and light.type == "SUN"


class CREPUSCULAR_PT_sun(SunPanel, bpy.types.Panel):
    bl_label = "Stylized Shafts"

    def draw_header(self, context: bpy.types.Context) -> None:
        self.layout.prop(context.light.crepuscular, "enabled", text="")

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        settings = context.light.crepuscular
        layout.active = settings.enabled
        layout.prop(settings, "method")
        layout.prop(settings, "shadow_map_size")
        if settings.method == "prefiltered":
            layout.prop(settings, "bases")
            layout.prop(settings, "exact_ray_ends")
        if settings.method == "reference":
            layout.prop(settings, "steps")
        else:
            layout.prop(settings, "adaptive_tolerance")
        layout.prop(settings, "downsample")
        layout.prop(settings, "edge_samples")
        layout.prop(settings, "max_distance")
        row = layout.row(align=True)
        row.operator(CREPUSCULAR_OT_load_preset.bl_idname, icon="IMPORT")
        row.operator(CREPUSCULAR_OT_save_preset.bl_idname, icon="EXPORT")
        error = context.scene.crepuscular.last_error
        if error:
            layout.label(text=error, icon="ERROR")


class CREPUSCULAR_PT_sun_occluders(SunPanel, bpy.types.Panel):
    bl_label = "Occluders"
    bl_parent_id = "CREPUSCULAR_PT_sun"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        settings = context.light.crepuscular
        for flag, names in (
            ("use_closing", ("closing_operation", "closing_kernel", "closing_radius")),
            ("use_silhouette", ("silhouette_operation", "silhouette_length")),
            (
                "use_holes",
                (
                    "holes_frequency",
                    "holes_threshold",
                    "holes_octaves",
                    "holes_persistence",
                    "holes_grid_size",
                    "holes_seed",
                    "holes_speed",
                    "holes_warp",
                    "holes_pivot",
                ),
            ),
        ):
            layout.prop(settings, flag)
            column = layout.column()
            column.active = getattr(settings, flag)
            for name in names:
                column.prop(settings, name)


class CREPUSCULAR_PT_sun_tf(SunPanel, bpy.types.Panel):
    bl_label = "Transfer Function"
    bl_parent_id = "CREPUSCULAR_PT_sun"

    def draw_header(self, context: bpy.types.Context) -> None:
        self.layout.prop(context.light.crepuscular, "use_tf", text="")

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.light.crepuscular
        layout.active = settings.use_tf
        column = layout.column()
        column.use_property_split = True
        column.prop(settings, "tf_mode")
        column.prop(settings, "tf_depth_near")
        column.prop(settings, "tf_depth_far")
        column.prop(settings, "tf_resolution")
        row = layout.row()
        row.template_list(
            "CREPUSCULAR_UL_tf_layers", "", settings, "tf_layers", settings, "active_tf_layer"
        )
        buttons = row.column(align=True)
        buttons.operator_menu_enum(
            CREPUSCULAR_OT_tf_layer_add.bl_idname, "kind", text="", icon="ADD"
        )
        buttons.operator(CREPUSCULAR_OT_tf_layer_remove.bl_idname, text="", icon="REMOVE")
        buttons.operator(
            CREPUSCULAR_OT_tf_layer_move.bl_idname, text="", icon="TRIA_UP"
        ).direction = "UP"
        buttons.operator(
            CREPUSCULAR_OT_tf_layer_move.bl_idname, text="", icon="TRIA_DOWN"
        ).direction = "DOWN"
        row = layout.row(align=True)
        row.operator(CREPUSCULAR_OT_bake_tf.bl_idname, icon="IMAGE_DATA")
        if settings.tf_image is not None:
            row.label(text=settings.tf_image.name)
        if not 0 <= settings.active_tf_layer < len(settings.tf_layers):
            return
        layer = settings.tf_layers[settings.active_tf_layer]
        column = layout.column()
        column.use_property_split = True
        column.prop(layer, "kind")
        column.prop(layer, "blend")
        column.prop(layer, "opacity")
        if layer.kind == "solid":
            column.prop(layer, "color")
        elif layer.kind == "gradient":
            column.prop(layer, "shape")
            if layer.shape == "linear":
                column.prop(layer, "start")
                column.prop(layer, "end")
            else:
                column.prop(layer, "center")
                column.prop(layer, "radius")
            for stop in layer.stops:
                row = column.row(align=True)
                row.prop(stop, "position", text="")
                row.prop(stop, "color", text="")
        elif layer.kind == "image":
            column.template_ID(layer, "image", open="image.open", new="image.new")
        else:
            for constraint in layer.constraints:
                box = column.box()
                box.prop(constraint, "color")
                box.prop(constraint, "use_world_point")
                box.prop(constraint, "world_point" if constraint.use_world_point else "position")
        if layer.kind == "diffusion":
            column.operator(CREPUSCULAR_OT_pick_constraint.bl_idname, icon="EYEDROPPER")
        if layer.kind in {"gradient", "diffusion"}:
            row = column.row(align=True)
            row.operator(CREPUSCULAR_OT_tf_item_add.bl_idname, icon="ADD")
            row.operator(CREPUSCULAR_OT_tf_item_remove.bl_idname, icon="REMOVE")


#: Objects that cast shafts themselves (meshes, and what evaluates to them, hair curves and
#: point clouds) or through what they instance (empties).
PANEL_OBJECT_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META", "CURVES", "POINTCLOUD", "EMPTY"}


class CREPUSCULAR_PT_object(bpy.types.Panel):
    bl_label = "Stylized Shafts"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = context.object
        return obj is not None and obj.type in PANEL_OBJECT_TYPES

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        settings = context.object.crepuscular
        layout.prop(settings, "casts_shafts")
        if settings.casts_shafts == "auto":
            state = "casts" if context.object.visible_shadow else "does not cast"
            layout.label(text=f"Follows Shadow ray visibility: {state}")
        layout.prop(settings, "takes_holes")
        # What each material's transparency does to the shafts (`cutouts.py`).
        for slot in context.object.material_slots:
            source, note = material_mask(slot.material)
            if source is not None:
                uv = source.uv_map or "the default UV map"
                layout.label(text=f"'{slot.material.name}' cuts by '{source.image}' ({uv})")
            elif note is not None:
                layout.label(text=note, icon="ERROR")


class CREPUSCULAR_PT_scene(bpy.types.Panel):
    bl_label = "Stylized Shafts"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        settings = context.scene.crepuscular
        layout.prop(settings, "medium_source")
        if settings.medium_source == "fog_object":
            layout.prop(settings, "fog_object")
            box = layout.box()
            box.label(text="The fog object is hidden from the beauty", icon="INFO")
            box.label(text="during renders: the shafts replace its medium.")
            box.label(text="Coloured extinction: one pass per channel value.")
        else:
            layout.prop(settings, "extinction")
            layout.prop(settings, "albedo")
            layout.prop(settings, "anisotropy")
        layout.separator()
        layout.prop(settings, "composite")
        if settings.composite and not context.scene.render.use_compositing:
            layout.label(text="Compositing is off in Post Processing: no composite", icon="ERROR")
        layout.prop(settings, "write_layers")
        layout.prop(settings, "preview")
        row = layout.row()
        row.active = settings.preview
        row.prop(settings, "preview_scale")
        layout.operator("crepuscular.render_layers", icon="RENDER_STILL")
        if preview.CONTROLLER.error:
            layout.label(text=f"Preview: {preview.CONTROLLER.error}", icon="ERROR")
        if settings.last_error:
            layout.label(text=settings.last_error, icon="ERROR")


CLASSES = (
    CREPUSCULAR_OT_load_preset,
    CREPUSCULAR_OT_bake_tf,
    CREPUSCULAR_OT_save_preset,
    CREPUSCULAR_OT_tf_layer_add,
    CREPUSCULAR_OT_tf_layer_remove,
    CREPUSCULAR_OT_tf_layer_move,
    CREPUSCULAR_OT_tf_item_add,
    CREPUSCULAR_OT_tf_item_remove,
    CREPUSCULAR_OT_pick_constraint,
    CREPUSCULAR_UL_tf_layers,
    CREPUSCULAR_PT_sun,
    CREPUSCULAR_PT_sun_occluders,
    CREPUSCULAR_PT_sun_tf,
    CREPUSCULAR_PT_object,
    CREPUSCULAR_PT_scene,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
