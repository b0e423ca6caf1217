"""Rendering the layers: the scripting operator, and compositing during F12/animation.

Mechanism. Blender calls `frame_change_post` once per rendered frame with the render
pipeline's own depsgraph (mode 'RENDER', evaluated at that frame, with render visibility
and render modifier settings), after `render_pre` and before the engine and the compositor
run. There the add-on exports the frame, renders the layers with the core, writes them into
the float Image datablock "Crepuscular Volume" (premultiplied, scene-linear) and, when asked,
into a multi-layer EXR next to the render output. The EXR is compressed and written on a
worker thread while the engine renders the beauty; the next frame, the end of the render
(`render_complete`, `render_cancel`) and unregistering wait for it and report a failure.
The compositor node group "Crepuscular Composite", wired into
`scene.compositing_node_group` in front of its output, reads that image and puts it over
the beauty with a premultiplied Alpha Over, in scene-linear before the view transform.
The user can open and tweak both node trees.

The fog object, when it supplies the medium, is made invisible to every ray type for the
duration of a render (and restored after), so the beauty does not count the medium twice.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import bpy
import numpy as np

import crepuscular

from . import export
from .style import StyleError

GROUP_NAME = "Crepuscular Composite"
IMAGE_NAME = "Crepuscular Volume"
NODE_NAME = "Crepuscular Composite"
#: Ray visibility flags switched off on the fog object during renders.
RAY_FLAGS = (
    "visible_camera",
    "visible_diffuse",
    "visible_glossy",
    "visible_transmission",
    "visible_volume_scatter",
    "visible_shadow",
)
#: Errors that come from the scene or its settings: they are reported, not raised further.
USER_ERRORS = (export.ExportError, StyleError, crepuscular.CrepuscularError, OSError)

CACHE = export.GeometryCache()
#: Original ray flags of fog objects hidden for the current render, by object name.
_HIDDEN_FOG: dict[str, dict[str, bool]] = {}


def log(message: str) -> None:
    print(f"crepuscular: {message}", file=sys.stderr, flush=True)


def pixel_filter_width(scene: bpy.types.Scene) -> float:
    """The beauty's pixel filter width in pixels (Cycles' or the render setting)."""
    if scene.render.engine == "CYCLES":
        return float(scene.cycles.filter_width)
    return float(scene.render.filter_size)


def match_pixel_filter(volume: np.ndarray, filter_width: float, samples: int) -> np.ndarray:
    """Widens the volume layer's pixel filter to the beauty's, so that edges line up.

    The core box-averages `samples`² depth samples per pixel, a filter of variance
    (1 − 1/samples²)/12. The beauty is filtered with a Blackman-Harris window 2·width wide
    (Cycles doubles it), whose standard deviation is 0.1385 of its support. A separable
    3-tap kernel [a, 1 − 2a, a] adds the missing variance 2a. Only the volume layer is
    filtered: depth and visibility stay exact.
    """
    target = (0.1385 * 2.0 * filter_width) ** 2
    extra = target - (1.0 - 1.0 / samples**2) / 12.0
    a = min(max(extra / 2.0, 0.0), 1.0 / 3.0)
    if a <= 0.0 or min(volume.shape[:2]) < 2:
        return volume
    result = np.array(volume, dtype=np.float32)
    for axis in (0, 1):
        padded = np.concatenate(
            [np.take(result, [0], axis), result, np.take(result, [-1], axis)], axis=axis
        )
        n = result.shape[axis]
        before = np.take(padded, range(0, n), axis)
        after = np.take(padded, range(2, n + 2), axis)
        result = (a * (before + after) + (1.0 - 2.0 * a) * result).astype(np.float32)
    return result


def render_layers(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    *,
    progress: crepuscular.ProgressCallback | None = None,
) -> tuple[crepuscular.Layers, export.FrameInputs]:
    """Exports the frame in `depsgraph` and renders its layers at the render's size (its
    render region's, in the frame or cropped to it, as F12 renders it), with the volume
    layer filtered like the beauty's pixels. Several suns with shafts add their
    light (see `export.render_suns`); the first one's inputs are returned, with every
    sun's notes."""
    inputs = export.all_frame_inputs(scene, depsgraph, cache=CACHE)
    volume, visibility, depth = export.render_suns(inputs, progress)
    settings = inputs[0].kwargs["settings"]
    volume = match_pixel_filter(volume, pixel_filter_width(scene), settings["supersampling"])
    height, width = depth.shape
    for entry in inputs[1:]:
        inputs[0].notes.extend(note for note in entry.notes if note not in inputs[0].notes)
    fog = scene.crepuscular.fog_object
    if fog is not None and crepuscular.fog_box_unreached(inputs[0].kwargs["medium"], volume):
        inputs[0].notes.append(
            f"no view ray reaches fog object '{fog.name}': the frame has no fog (is it out of "
            "view, behind a surface or past Max Distance?)"
        )
    camera = inputs[0].kwargs["camera"]
    layers = crepuscular.Layers(width, height, volume, visibility, depth, camera["pixel_aspect"])
    region = export.render_region(scene)
    if region is not None and not region.cropped:
        # The frame keeps its size, as Blender uncrops the beauty.
        layers = layers.in_frame(camera)
    return layers, inputs[0]


@contextlib.contextmanager
def evaluated_as_rendered(view_layer: bpy.types.ViewLayer) -> Iterator[None]:
    """Within it, the viewport's depsgraph evaluates the view layer as a render does, so
    that the operator, which renders from that depsgraph, renders what F12 renders:

    - objects and collections hidden only in the viewport (the eye, the monitor, or a
      collection's) are shown;
    - modifiers are on or off as for renders, subdivision and multires at their render
      levels, particle systems at their render steps and children's render amount, with
      every particle and their emitters shown as rendered;
    - curves, surfaces, text and metaballs at their render resolutions.

    Everything is set back afterwards, whatever happens. Linked data, which cannot be
    changed, keeps its library's settings."""
    restore: list[Callable[[], None]] = []

    def put(target: Any, name: str, value: Any) -> None:
        # Linked data is evaluated as the library has it.
        if not target.id_data.is_editable:
            return
        old = getattr(target, name)
        if old != value:
            setattr(target, name, value)
            restore.append(functools.partial(setattr, target, name, old))

    try:
        for layer_collection in _layer_collections(view_layer.layer_collection):
            collection = layer_collection.collection
            if layer_collection.exclude or collection.hide_render:
                continue
            put(layer_collection, "hide_viewport", False)
            put(collection, "hide_viewport", False)
        for obj in view_layer.objects:
            if obj.hide_render:
                continue
            put(obj, "hide_viewport", False)
            if obj.hide_get(view_layer=view_layer):  # the view layer's own state
                obj.hide_set(False, view_layer=view_layer)
                restore.append(functools.partial(obj.hide_set, True, view_layer=view_layer))
            put(obj, "show_instancer_for_viewport", obj.show_instancer_for_render)
            for modifier in obj.modifiers:
                put(modifier, "show_viewport", modifier.show_render)
                if modifier.type in {"SUBSURF", "MULTIRES"}:
                    put(modifier, "levels", modifier.render_levels)
            for system in obj.particle_systems:
                settings = system.settings
                put(settings, "display_step", settings.render_step)
                put(settings, "child_percent", settings.rendered_child_count)
                put(settings, "display_percentage", 100)
            data = obj.data
            if isinstance(data, bpy.types.Curve):
                if data.render_resolution_u > 0:
                    put(data, "resolution_u", data.render_resolution_u)
                if isinstance(data, bpy.types.SurfaceCurve) and data.render_resolution_v > 0:
                    put(data, "resolution_v", data.render_resolution_v)
            elif isinstance(data, bpy.types.MetaBall) and data.render_resolution > 0:
                put(data, "resolution", data.render_resolution)
        yield
    finally:
        for undo in reversed(restore):
            undo()


def _layer_collections(root: bpy.types.LayerCollection) -> Iterator[bpy.types.LayerCollection]:
    yield root
    for child in root.children:
        yield from _layer_collections(child)


def layers_path(scene: bpy.types.Scene, frame: int) -> str:
    """The layers' EXR next to the rendered frame: `<output>crepuscular_<frame>.exr`.

    `//renders/shot_` gives `renders/shot_crepuscular_0012.exr`, `/tmp/x.png` gives
    `/tmp/x_crepuscular_0012.exr` and a bare folder `/tmp/` gives `/tmp/crepuscular_0012.exr`.
    """
    output = bpy.path.abspath(scene.render.filepath)
    directory = os.path.dirname(scene.render.frame_path(frame=frame))
    stem = os.path.basename(output).replace("#", "")
    root, extension = os.path.splitext(stem)
    if extension.lower() in bpy.path.extensions_image:
        stem = root
    if stem and stem[-1] not in "_-.":
        stem += "_"
    return os.path.join(directory, f"{stem}crepuscular_{frame:04d}.exr")


def layers_compression(scene: bpy.types.Scene) -> str:
    """The layer EXRs' codec: the scene's own where it renders to OpenEXR with a codec the
    core writes, else ZIP (the lossy B44, B44A, DWAA and DWAB are not among those)."""
    settings = scene.render.image_settings
    codec = settings.exr_codec.lower()
    if settings.file_format == "OPEN_EXR" and codec in crepuscular.EXR_COMPRESSIONS:
        return codec
    return "zip"


class LayerWriter:
    """Writes layer EXRs on one worker thread, at most one file in flight: compressing a
    1080p frame takes about as long as rendering its layers, and the core releases the GIL
    while it writes, so the write overlaps the beauty render instead of adding to it."""

    def __init__(self) -> None:
        self._executor: ThreadPoolExecutor | None = None
        self._pending: tuple[str, Future[None]] | None = None

    def submit(self, path: str, layers: crepuscular.Layers, compression: str) -> None:
        """Starts writing `layers` to `path` with the EXR codec `compression` once the
        previous file is done; raises the previous file's error, if it failed."""
        self.wait()
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="crepuscular")
        write = functools.partial(crepuscular.write_exr, compression=compression)
        self._pending = (path, self._executor.submit(write, path, layers))

    def wait(self) -> None:
        """Blocks until the file in flight is written; raises its error, if it failed."""
        if self._pending is None:
            return
        path, future = self._pending
        self._pending = None
        future.result()
        log(f"wrote layers to {path}")

    def close(self) -> None:
        """Waits for the file in flight and stops the worker."""
        try:
            self.wait()
        finally:
            if self._executor is not None:
                self._executor.shutdown()
                self._executor = None


WRITER = LayerWriter()


def finish_layer_files(scene: bpy.types.Scene) -> None:
    """Waits for the layer file in flight; a failure is reported on the scene and raised."""
    try:
        WRITER.wait()
    except USER_ERRORS as error:
        scene.crepuscular.last_error = f"writing layers: {error}"
        log(scene.crepuscular.last_error)
        raise


# Compositor -----------------------------------------------------------------------------


def _scene_linear_name() -> str:
    items = bpy.types.ColorManagedInputColorspaceSettings.bl_rna.properties["name"].enum_items
    names = [item.identifier for item in items]
    for name in ("Linear Rec.709", "Linear CIE-XYZ E", "Linear"):
        if name in names:
            return name
    return names[0]


def volume_image(width: int, height: int) -> bpy.types.Image:
    """The float image the compositor reads: premultiplied, scene-linear."""
    image = bpy.data.images.get(IMAGE_NAME)
    if image is None:
        image = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True, float_buffer=True)
        # Generated pixels are not saved: a file opened without the add-on regenerates them
        # transparent, and the composite is the plain beauty.
        image.generated_color = (0.0, 0.0, 0.0, 0.0)
        image.colorspace_settings.name = _scene_linear_name()
        image.alpha_mode = "PREMUL"
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    return image


def set_volume_image(volume: np.ndarray) -> bpy.types.Image:
    """Stores the (H, W, 4) premultiplied volume layer in the compositor's image."""
    height, width = volume.shape[:2]
    image = volume_image(width, height)
    image.pixels.foreach_set(np.ascontiguousarray(volume[::-1], dtype=np.float32).ravel())
    image.update()
    return image


def composite_group() -> bpy.types.NodeTree:
    """The node group: Image in, the volume image over it (premultiplied), Image out."""
    group = bpy.data.node_groups.get(GROUP_NAME)
    if group is not None:
        return group
    group = bpy.data.node_groups.new(GROUP_NAME, "CompositorNodeTree")
    group.interface.new_socket("Image", in_out="INPUT", socket_type="NodeSocketColor")
    group.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    nodes, links = group.nodes, group.links
    source = nodes.new("NodeGroupInput")
    source.location = (-400, 0)
    volume = nodes.new("CompositorNodeImage")
    volume.name = volume.label = "Volume Layer"
    # Any size: each render resizes the image to its own.
    volume.image = volume_image(64, 64)
    volume.location = (-400, -200)
    over = nodes.new("CompositorNodeAlphaOver")
    over.name = over.label = "Premultiplied Over"
    over.inputs["Straight Alpha"].default_value = False
    over.location = (0, 0)
    sink = nodes.new("NodeGroupOutput")
    sink.location = (300, 0)
    links.new(source.outputs[0], over.inputs["Background"])
    links.new(volume.outputs["Image"], over.inputs["Foreground"])
    links.new(over.outputs["Image"], sink.inputs[0])
    return group


def wire_compositor(scene: bpy.types.Scene) -> bpy.types.Node:
    """Puts the group in front of the output of `scene.compositing_node_group`, creating
    a Render Layers -> group -> output tree when the scene has none. Idempotent."""
    group = composite_group()
    tree = scene.compositing_node_group
    if tree is None:
        tree = bpy.data.node_groups.new(f"{scene.name} Compositing", "CompositorNodeTree")
        tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        layers = tree.nodes.new("CompositorNodeRLayers")
        layers.scene = scene
        layers.location = (-400, 0)
        output = tree.nodes.new("NodeGroupOutput")
        output.location = (300, 0)
        tree.links.new(layers.outputs["Image"], output.inputs[0])
        scene.compositing_node_group = tree
    node = tree.nodes.get(NODE_NAME)
    if node is not None:
        return node
    outputs = [n for n in tree.nodes if n.bl_idname == "NodeGroupOutput"]
    if not outputs:
        raise export.ExportError(
            f"compositor tree '{tree.name}' has no Group Output to composite in front of"
        )
    output = next((n for n in outputs if n.is_active_output), outputs[0])
    node = tree.nodes.new("CompositorNodeGroup")
    node.node_tree = group
    node.name = node.label = NODE_NAME
    node.location = (output.location.x - 200, output.location.y)
    sink = output.inputs[0]
    if sink.is_linked:
        upstream = sink.links[0].from_socket
        tree.links.new(upstream, node.inputs[0])
    tree.links.new(node.outputs[0], sink)
    return node


def sync_scene(scene: bpy.types.Scene) -> None:
    """Keeps the compositor in step with the settings: wired and active while a sun has
    shafts and compositing is on, muted otherwise."""
    active = bool(export.shaft_suns(scene)) and scene.crepuscular.composite
    tree = scene.compositing_node_group
    node = tree.nodes.get(NODE_NAME) if tree is not None else None
    if active:
        node = wire_compositor(scene)
        # The handlers change data during the render; lock the UI so nothing races them.
        scene.render.use_lock_interface = True
    if node is not None:
        node.mute = not active


# Handlers -------------------------------------------------------------------------------


def _fog_object(scene: bpy.types.Scene) -> bpy.types.Object | None:
    settings = scene.crepuscular
    if settings.medium_source != "fog_object" or not export.shaft_suns(scene):
        return None
    return settings.fog_object


@bpy.app.handlers.persistent
def on_render_init(scene: bpy.types.Scene, _depsgraph: Any = None) -> None:
    sync_scene(scene)
    fog = _fog_object(scene)
    if fog is not None and fog.name_full not in _HIDDEN_FOG:
        _HIDDEN_FOG[fog.name_full] = {flag: getattr(fog, flag) for flag in RAY_FLAGS}
        for flag in RAY_FLAGS:
            setattr(fog, flag, False)
        log(
            f"fog object '{fog.name}' is hidden from the beauty during this render: "
            "the shafts replace its medium"
        )


@bpy.app.handlers.persistent
def on_render_done(scene: bpy.types.Scene, _depsgraph: Any = None) -> None:
    for name, flags in list(_HIDDEN_FOG.items()):
        fog = bpy.data.objects.get(name)
        if fog is not None:
            for flag, value in flags.items():
                setattr(fog, flag, value)
        del _HIDDEN_FOG[name]
    finish_layer_files(scene)


@bpy.app.handlers.persistent
def on_frame_change_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph) -> None:
    if depsgraph is None or depsgraph.mode != "RENDER":
        from . import preview

        preview.CONTROLLER.mark_dirty()
        return
    settings = scene.crepuscular
    if not export.shaft_suns(scene) or not (settings.composite or settings.write_layers):
        return
    frame = depsgraph.scene.frame_current
    try:
        layers, inputs = render_layers(scene, depsgraph)
    except USER_ERRORS as error:
        settings.last_error = f"frame {frame}: {error}"
        # A transparent layer: the render shows the plain beauty, never a stale frame.
        try:
            width, height = export.output_size(scene)
        except export.ExportError:
            width, height = export.render_size(scene)
        set_volume_image(np.zeros((height, width, 4), np.float32))
        log(settings.last_error)
        raise
    settings.last_error = ""
    for note in inputs.notes:
        log(note)
    if settings.composite:
        set_volume_image(layers.volume)
    if settings.write_layers:
        path = layers_path(scene, frame)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        finish_layer_files(scene)
        WRITER.submit(path, layers, layers_compression(scene))


@bpy.app.handlers.persistent
def on_depsgraph_update_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph) -> None:
    changed = {
        update.id.original.name_full
        for update in depsgraph.updates
        if update.is_updated_geometry and isinstance(update.id, bpy.types.Mesh)
    }
    if changed:
        CACHE.invalidate(changed)
    images = {
        update.id.original.name_full
        for update in depsgraph.updates
        if isinstance(update.id, bpy.types.Image)
    }
    if images:
        CACHE.invalidate_images(images)
    from . import preview

    preview.CONTROLLER.mark_dirty()


@bpy.app.handlers.persistent
def on_load_post(*_args: Any) -> None:
    CACHE.invalidate()
    _HIDDEN_FOG.clear()


HANDLERS = (
    ("render_init", on_render_init),
    ("render_complete", on_render_done),
    ("render_cancel", on_render_done),
    ("frame_change_post", on_frame_change_post),
    ("depsgraph_update_post", on_depsgraph_update_post),
    ("load_post", on_load_post),
)


# Operator -------------------------------------------------------------------------------


class CREPUSCULAR_OT_render_layers(bpy.types.Operator):
    """Render the shafts' layers of the current frame for the scene camera and write them as
    a multi-layer EXR (volume.R/G/B/A, visibility, depth), without rendering the beauty"""

    bl_idname = "crepuscular.render_layers"
    bl_label = "Render Shaft Layers"
    bl_options = {"REGISTER"}

    filepath: bpy.props.StringProperty(
        name="File Path",
        subtype="FILE_PATH",
        description="The EXR to write; empty: next to the render output, named by frame",
    )

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        wm = context.window_manager
        wm.progress_begin(0.0, 1.0)
        try:
            with evaluated_as_rendered(context.view_layer):
                depsgraph = context.evaluated_depsgraph_get()
                layers, inputs = render_layers(scene, depsgraph, progress=wm.progress_update)
            path = (
                bpy.path.abspath(self.filepath)
                if self.filepath
                else layers_path(scene, scene.frame_current)
            )
            directory = os.path.dirname(path)
            if directory:
                os.makedirs(directory, exist_ok=True)
            crepuscular.write_exr(path, layers, compression=layers_compression(scene))
        except USER_ERRORS as error:
            scene.crepuscular.last_error = str(error)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        scene.crepuscular.last_error = ""
        for note in inputs.notes:
            self.report({"WARNING"}, note)
        self.report({"INFO"}, f"wrote {path}")
        return {"FINISHED"}


CLASSES = (CREPUSCULAR_OT_render_layers,)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for name, handler in HANDLERS:
        getattr(bpy.app.handlers, name).append(handler)


def mute_compositor_nodes() -> None:
    """Mutes the group in every scene, so that nothing composites a stale layer while the
    add-on is off (registration turns it back on at the next render)."""
    if not isinstance(bpy.data, bpy.types.BlendData):
        return  # restricted while Blender loads or resets; nothing to reach then
    for scene in bpy.data.scenes:
        tree = scene.compositing_node_group
        node = tree.nodes.get(NODE_NAME) if tree is not None else None
        if node is not None:
            node.mute = True


def unregister() -> None:
    WRITER.close()
    mute_compositor_nodes()
    for name, handler in reversed(HANDLERS):
        handlers = getattr(bpy.app.handlers, name)
        while handler in handlers:
            handlers.remove(handler)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
    CACHE.invalidate()
