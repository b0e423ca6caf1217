"""The extension under real Blender, in this process: install from the zip, symmetric
unregister, settings, presets, depsgraph export, the fog-object mapping, the scripting
operator, bad input, and the viewport preview's update logic."""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest

import crepuscular

bpy = pytest.importorskip("bpy")

import blender_scenes  # noqa: E402
from mathutils import Matrix, Vector  # noqa: E402

PRESETS = blender_scenes.ROOT / "examples" / "presets"


def _basic_scene(width: int = 64, height: int = 36) -> bpy.types.Scene:
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    blender_scenes.add_camera(scene, blender_scenes.look_at((0, -12, 3), (0, 0, 2)), lens=35)
    sun = blender_scenes.add_sun(scene, (0.2, 0.3, -1.0))
    sun.data.crepuscular.shadow_map_size = 256
    sun.data.crepuscular.edge_samples = 1
    mesh = bpy.data.meshes.new("Roof")
    mesh.from_pydata([(-4, -4, 6), (4, -4, 6), (4, 4, 6), (-4, 4, 6)], [], [[0, 1, 2, 3]])
    roof = bpy.data.objects.new("Roof", mesh)
    scene.collection.objects.link(roof)
    scene.crepuscular.extinction = 0.1
    return scene


# Packaging ------------------------------------------------------------------------------


def test_installed_from_the_zip_with_its_bundled_wheel(installed: ModuleType) -> None:
    extensions = Path(bpy.utils.user_resource("EXTENSIONS"))
    assert Path(installed.__file__).is_relative_to(extensions / "user_default" / "crepuscular")
    assert str(extensions).startswith(os.environ["CREPUSCULAR_TEST_BLENDER_USER"])
    cores = list((extensions / ".local").glob("lib/python*/site-packages/crepuscular/_core*.so"))
    assert len(cores) == 1, "the manifest's wheel was not installed"
    site = cores[0].parent.parent
    # The installed wheel imports on its own, ahead of any other copy.
    found = subprocess.run(
        [
            sys.executable,
            "-c",
            f"import sys; sys.path.insert(0, {str(site)!r}); import crepuscular; "
            "print(crepuscular.__file__, crepuscular.__version__)",
        ],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    assert Path(found[0]).is_relative_to(site)
    assert found[1] == crepuscular.__version__
    assert bpy.ops.crepuscular.render_layers.get_rna_type().identifier


def _registered(owner: type, name: str) -> bool:
    return owner.bl_rna_get_subclass_py(name) is not None


def test_unregister_leaves_nothing_behind(addon: ModuleType, tmp_path: Path) -> None:
    import addon_utils

    preview, render = addon.preview, addon.render
    handler_lists = [name for name, _ in render.HANDLERS]
    ours = [
        h
        for name in handler_lists
        for h in getattr(bpy.app.handlers, name)
        if h.__module__.startswith(blender_scenes.ADDON_MODULE)
    ]
    assert len(ours) == len(render.HANDLERS)
    assert bpy.app.timers.is_registered(preview._tick)
    scene = _basic_scene()  # enabling shafts wires the compositor group
    node = scene.compositing_node_group.nodes[render.NODE_NAME]
    assert not node.mute
    classes = [
        cls.__name__
        for module in (addon.properties, addon.render, addon.ui)
        for cls in module.CLASSES
    ]
    (hook,) = addon.usd_hook.CLASSES
    assert hook.is_registered
    # A layer file still being written when the add-on goes is finished, not lost.
    pending = tmp_path / "pending.exr"
    zeros = np.zeros((2, 4), np.float32)
    layers = crepuscular.Layers(4, 2, np.zeros((2, 4, 4)), zeros, zeros)
    render.WRITER.submit(str(pending), layers, "zip")
    addon_utils.disable(blender_scenes.ADDON_MODULE, default_set=True)
    try:
        for name in dir(bpy.app.handlers):
            handlers = getattr(bpy.app.handlers, name)
            if isinstance(handlers, list):
                leftover = [
                    h
                    for h in handlers
                    if getattr(h, "__module__", "").startswith(blender_scenes.ADDON_MODULE)
                ]
                assert not leftover, (name, leftover)
        assert not bpy.app.timers.is_registered(preview._tick)
        assert preview._DRAW_HANDLE == []
        assert preview.CONTROLLER.result is None
        assert not preview.CONTROLLER.busy
        for owner in (bpy.types.Light, bpy.types.Object, bpy.types.Scene):
            assert "crepuscular" not in owner.bl_rna.properties
            assert not hasattr(owner, "crepuscular")
        for name in classes:
            for base in (
                bpy.types.PropertyGroup,
                bpy.types.Operator,
                bpy.types.Panel,
                bpy.types.UIList,
            ):
                assert not _registered(base, name), name
        assert not hasattr(bpy.types, "CREPUSCULAR_OT_render_layers")
        assert not hook.is_registered  # the USD export hook
        assert crepuscular.read_exr(pending)["depth"].shape == (2, 4)
        assert render.WRITER._executor is None
        # The group stays (it is the user's data) but composites nothing stale.
        assert node.mute
    finally:
        enabled = blender_scenes.enable_addon()
    assert _registered(bpy.types.Operator, "CREPUSCULAR_OT_render_layers")
    assert all(cls.is_registered for cls in enabled.usd_hook.CLASSES)


# Settings and presets -------------------------------------------------------------------


def test_settings_are_saved_in_the_blend_and_animatable(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    light = scene.objects["Sun"].data
    settings = light.crepuscular
    settings.use_closing = True
    for frame, radius in ((1, 0.2), (11, 2.2)):
        settings.closing_radius = radius
        settings.keyframe_insert("closing_radius", frame=frame)
    settings.method = "reference"
    layer = settings.tf_layers.add()
    layer.kind, layer.color = "solid", (1.0, 0.5, 0.25, 1.0)
    scene.objects["Roof"].crepuscular.takes_holes = True
    scene.crepuscular.extinction = 0.123
    path = tmp_path / "saved.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    blender_scenes.reset()
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    light = bpy.data.lights["Sun"]
    assert light.crepuscular.method == "reference"
    assert light.crepuscular.tf_layers[0].color[:] == pytest.approx((1.0, 0.5, 0.25, 1.0))
    assert bpy.data.objects["Roof"].crepuscular.takes_holes
    assert scene.crepuscular.extinction == pytest.approx(0.123)
    assert bpy.data.objects["Camera"].crepuscular.casts_shafts == "auto"
    assert light.animation_data is not None
    assert light.animation_data.action is not None
    scene.frame_set(1)
    assert light.crepuscular.closing_radius == pytest.approx(0.2)
    scene.frame_set(11)
    assert light.crepuscular.closing_radius == pytest.approx(2.2)
    scene.frame_set(6)
    assert 0.2 < light.crepuscular.closing_radius < 2.2


@pytest.mark.parametrize(
    "name",
    ["alarm.json", "hole-filled-torus.json", "holes-in-tree.json", "extruded-colonnade.json"],
)
def test_presets_load_and_save_in_the_preset_format(
    addon: ModuleType, tmp_path: Path, name: str
) -> None:
    scene = _basic_scene()
    light = scene.objects["Sun"].data
    addon.style.apply_preset(light.crepuscular, PRESETS / name)
    saved = tmp_path / name
    addon.style.save_preset(light.crepuscular, saved)
    original = crepuscular.load_style(PRESETS / name)
    again = crepuscular.load_style(saved)
    for style in (original, again):
        if "holes" in style:
            style["holes"].pop("objects")  # in Blender, objects are marked instead
    assert json.dumps(again, sort_keys=True) == json.dumps(original, sort_keys=True)


def test_tf_bakes_into_an_image_to_paint_on(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    light = scene.objects["Sun"].data
    settings = light.crepuscular
    with (
        bpy.context.temp_override(light=light),
        pytest.raises(RuntimeError, match="use_tf"),
    ):
        bpy.ops.crepuscular.bake_tf()
    addon.style.apply_preset(settings, PRESETS / "alarm.json")
    with bpy.context.temp_override(light=light):
        assert bpy.ops.crepuscular.bake_tf() == {"FINISHED"}
    image = settings.tf_image
    assert tuple(image.size) == (256, 256)
    pixels = np.empty(256 * 256 * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    expected = crepuscular.bake_tf(PRESETS / "alarm.json")
    np.testing.assert_allclose(pixels.reshape(256, 256, 4), expected, atol=1e-6)
    # Painted pixels come back as an image layer of the stack.
    pixels.reshape(256, 256, 4)[:, :128] = [0.0, 0.0, 1.0, 1.0]
    image.pixels.foreach_set(pixels)
    layer = settings.tf_layers.add()
    layer.kind, layer.image = "image", image
    style = addon.style.style_from_light(settings, time=0.0, hole_objects=[])
    repainted = crepuscular.bake_tf(style)
    assert repainted[100, 20, 2] == pytest.approx(1.0)  # painted blue over the left half
    assert repainted[100, 20, 0] == pytest.approx(0.0)
    np.testing.assert_allclose(repainted[:, 200], expected[:, 200], atol=1e-3)


def test_tf_stack_operators_edit_the_stack(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    light = scene.objects["Sun"].data
    settings = light.crepuscular
    with bpy.context.temp_override(light=light):
        assert not bpy.ops.crepuscular.tf_layer_remove.poll()
        for kind in ("solid", "gradient", "diffusion"):
            assert bpy.ops.crepuscular.tf_layer_add(kind=kind) == {"FINISHED"}
        assert [layer.kind for layer in settings.tf_layers] == ["solid", "gradient", "diffusion"]
        assert len(settings.tf_layers[1].stops) == 2  # a new gradient runs black to white
        assert settings.active_tf_layer == 2
        assert bpy.ops.crepuscular.tf_item_add() == {"FINISHED"}
        assert len(settings.tf_layers[2].constraints) == 1
        assert bpy.ops.crepuscular.tf_layer_move(direction="DOWN") == {"FINISHED"}
        assert [layer.kind for layer in settings.tf_layers] == ["solid", "diffusion", "gradient"]
        assert settings.active_tf_layer == 1
        assert bpy.ops.crepuscular.tf_item_remove() == {"FINISHED"}
        assert len(settings.tf_layers[1].constraints) == 0
        assert bpy.ops.crepuscular.tf_item_remove() == {"CANCELLED"}
        assert bpy.ops.crepuscular.tf_layer_remove() == {"FINISHED"}
        assert [layer.kind for layer in settings.tf_layers] == ["solid", "gradient"]
        settings.use_tf = True
        path = tmp_path / "stack.json"
        assert bpy.ops.crepuscular.save_preset(filepath=str(path)) == {"FINISHED"}
    saved = crepuscular.load_style(path)
    assert [layer["kind"] for layer in saved["tf"]["layers"]] == ["solid", "gradient"]


def test_bad_presets_name_the_field(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    settings = scene.objects["Sun"].data.crepuscular
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"version": 1, "closing": {"radius": -1.0}}))
    with pytest.raises(crepuscular.InvalidInputError, match=r"style\.closing\.radius"):
        addon.style.apply_preset(settings, bad)
    bad.write_text(json.dumps({"version": 1, "closing": {"radios": 1.0}}))
    with pytest.raises(crepuscular.CrepuscularError, match="radios"):
        addon.style.apply_preset(settings, bad)
    with (
        bpy.context.temp_override(light=settings.id_data),
        pytest.raises(RuntimeError, match="radios"),
    ):
        bpy.ops.crepuscular.load_preset(filepath=str(bad))


def test_a_presets_tf_image_is_found_beside_it(
    addon: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    looks = tmp_path / "looks"
    looks.mkdir()
    ramp = np.array([[0.0, 1.0]], dtype=np.float32)
    crepuscular.write_exr_channels(looks / "ramp.exr", {"R": ramp, "G": ramp, "B": 1.0 - ramp})
    preset = looks / "ramp-look.json"
    image_layer = {"kind": "image", "image": {"kind": "file", "path": "ramp.exr"}}
    tf = {"mode": "color", "depth_range": {"near": 0.0, "far": 50.0}, "layers": [image_layer]}
    preset.write_text(json.dumps({"version": 1, "tf": tf}))
    elsewhere = tmp_path / "session"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    settings = _basic_scene().objects["Sun"].data.crepuscular
    addon.style.apply_preset(settings, preset)
    image = settings.tf_layers[0].image
    assert Path(bpy.path.abspath(image.filepath)) == looks / "ramp.exr"
    assert tuple(image.size) == (2, 1)
    pixels = np.array(image.pixels[:], dtype=np.float32).reshape(2, 4)
    assert pixels[0, 2] > 0.9, "the ramp's blue end"
    assert pixels[1, 0] > 0.9, "the ramp's red end"


# Export ---------------------------------------------------------------------------------


def _geometry_nodes_instancer(scene: bpy.types.Scene) -> bpy.types.Object:
    """A geometry-nodes object: 4 points on a line, a cube instanced on each."""
    tree = bpy.data.node_groups.new("Instancer", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    line = tree.nodes.new("GeometryNodeMeshLine")
    line.inputs["Count"].default_value = 4
    cube = tree.nodes.new("GeometryNodeMeshCube")
    cube.inputs["Size"].default_value = (0.5, 0.5, 0.5)
    instance = tree.nodes.new("GeometryNodeInstanceOnPoints")
    output = tree.nodes.new("NodeGroupOutput")
    tree.links.new(line.outputs["Mesh"], instance.inputs["Points"])
    tree.links.new(cube.outputs["Mesh"], instance.inputs["Instance"])
    tree.links.new(instance.outputs["Instances"], output.inputs[0])
    obj = bpy.data.objects.new("GN", bpy.data.meshes.new("GN"))
    scene.collection.objects.link(obj)
    obj.modifiers.new("Nodes", "NODES").node_group = tree
    obj.location = (5, 0, 0)
    return obj


def _particle_emitter(scene: bpy.types.Scene, leaf: bpy.types.Object) -> bpy.types.Object:
    bpy.ops.mesh.primitive_plane_add(size=4, location=(0, 5, 0))
    emitter = bpy.context.active_object
    emitter.modifiers.new("Leaves", "PARTICLE_SYSTEM")
    particles = emitter.particle_systems[0].settings
    particles.type = "HAIR"
    particles.count = 5
    particles.render_type = "OBJECT"
    particles.instance_object = leaf
    emitter.show_instancer_for_render = True
    return emitter


def _instance_bounds(depsgraph: bpy.types.Depsgraph, names: set[str]) -> np.ndarray:
    """World bounds of Blender's evaluated instances, from their bounding boxes."""
    corners = []
    for instance in depsgraph.object_instances:
        if instance.object.original.name in names:
            matrix = instance.matrix_world
            corners += [matrix @ Vector(c) for c in instance.object.bound_box]
    points = np.array(corners)
    return np.stack([points.min(axis=0), points.max(axis=0)])


def test_export_matches_blenders_evaluated_meshes(addon: ModuleType) -> None:
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_cube_add(size=1, location=(-5, 0, 0))
    arrayed = bpy.context.active_object
    arrayed.modifiers.new("Array", "ARRAY").count = 3  # 3 cubes: 36 triangles
    gn = _geometry_nodes_instancer(scene)  # 4 instanced cubes: 48 triangles
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, radius=0.2, location=(0, 0, 8))
    leaf = bpy.context.active_object  # 20 triangles, and 5 particle copies
    emitter = _particle_emitter(scene, leaf)  # 2 triangles of the plane itself
    text = bpy.data.objects.new("Text", bpy.data.curves.new("Text", "FONT"))
    text.data.body = "Hi"
    text.data.extrude = 0.1
    scene.collection.objects.link(text)
    hidden = bpy.data.objects.new("Hidden", bpy.data.meshes.new("Hidden"))
    hidden.data.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [[0, 1, 2]])
    hidden.hide_render = True
    scene.collection.objects.link(hidden)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    text_mesh = text.evaluated_get(depsgraph).to_mesh()
    text_triangles = len(text_mesh.loop_triangles)
    text.evaluated_get(depsgraph).to_mesh_clear()
    assert text_triangles > 20

    geometry = addon.export.export_geometry(depsgraph)
    per_object = {
        name: int(np.sum(geometry.object_ids == object_id))
        for object_id, name in geometry.names.items()
    }
    # Instances count under their instancer: the emitter holds its plane and 5 leaves.
    assert per_object == {
        arrayed.name: 36,
        gn.name: 48,
        leaf.name: 20,
        emitter.name: 2 + 5 * 20,
        text.name: text_triangles,
    }
    names = {arrayed.name, gn.name, leaf.name, emitter.name, text.name}
    expected = _instance_bounds(depsgraph, names)
    ours = np.stack([geometry.positions.min(axis=0), geometry.positions.max(axis=0)])
    np.testing.assert_allclose(ours, expected, atol=1e-4)
    assert geometry.triangles.max() < len(geometry.positions)

    # Shadow ray visibility decides on Auto; On and Off override it. What does not block
    # the sun still hides the fog from the camera, where the camera sees it.
    assert geometry.visibility is None
    arrayed.visible_shadow = False
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert _names_by_flag(addon.export.export_geometry(depsgraph)) == (
        names - {arrayed.name},
        names,
    )
    arrayed.crepuscular.casts_shafts = "on"
    text.crepuscular.casts_shafts = "off"
    text.visible_camera = False
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert _names_by_flag(addon.export.export_geometry(depsgraph)) == (
        names - {text.name},
        names - {text.name},
    )


def test_shadow_linking_decides_what_blocks_the_sun(addon: ModuleType) -> None:
    """The sun's blocker collection, as Blender's light linking defines it: only excluded
    objects, all but those block; any included, only those (objects of an included child
    collection too) less the excluded; an instance blocks by its object or its instancer.
    What does not block the sun still hides the fog from the camera."""
    scene = bpy.context.scene
    sun = blender_scenes.add_sun(scene, (0.2, 0.1, -1.0))
    quads = {}
    for index, name in enumerate(("a", "b", "c")):
        x = 2.0 * index
        corners = [(x, 0, 1), (x + 1, 0, 1), (x + 1, 1, 1), (x, 1, 1)]
        quads[name] = blender_scenes.add_quad(scene, name, corners)
    source = bpy.data.collections.new("source")
    source.objects.link(quads["c"])
    scene.collection.objects.unlink(quads["c"])
    instancer = bpy.data.objects.new("instancer", None)
    instancer.instance_type, instancer.instance_collection = "COLLECTION", source
    scene.collection.objects.link(instancer)
    blockers = bpy.data.collections.new("blockers")
    sun.light_linking.blocker_collection = blockers
    child = bpy.data.collections.new("child")

    def blocking(states: dict[str, str], child_state: str | None = None) -> set[str]:
        blender_scenes.set_blockers(blockers, states, child, child_state)
        linking = addon.export.LightLinking.of_blockers(sun)
        geometry = addon.export.export_geometry(
            bpy.context.evaluated_depsgraph_get(), blockers=linking
        )
        blocks, seen = _names_by_flag(geometry)
        assert seen == {"a", "b", "instancer"}
        return blocks

    assert blocking({}) == {"a", "b", "instancer"}
    assert blocking({"a": "EXCLUDE"}) == {"b", "instancer"}
    assert blocking({"a": "INCLUDE"}) == {"a"}
    assert blocking({"a": "INCLUDE", "instancer": "INCLUDE"}) == {"a", "instancer"}
    assert blocking({"c": "INCLUDE"}) == {"instancer"}
    assert blocking({"instancer": "EXCLUDE"}) == {"a", "b"}
    child.objects.link(quads["b"])
    assert blocking({"a": "INCLUDE"}, "INCLUDE") == {"a", "b"}
    assert blocking({}, "EXCLUDE") == {"a", "instancer"}
    sun.light_linking.blocker_collection = None
    assert addon.export.LightLinking.of_blockers(sun) is None


def _names_by_flag(geometry: Any) -> tuple[set[str], set[str]]:
    """The objects with triangles that block the sun, and with triangles the camera sees."""
    flags = (
        np.full(len(geometry.triangles), 3) if geometry.visibility is None else geometry.visibility
    )
    found = []
    for flag in (crepuscular.BLOCKS_SUN, crepuscular.SEEN_BY_CAMERA):
        ids = set(geometry.object_ids[(flags & flag) != 0].tolist())
        found.append({geometry.names[k] for k in ids})
    return found[0], found[1]


def test_static_geometry_is_cached_and_invalidated(addon: ModuleType) -> None:
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_cube_add(size=2)
    cube = bpy.context.active_object
    cache = addon.export.GeometryCache()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    first = addon.export.export_geometry(depsgraph, cache=cache)
    assert (cache.misses, cache.hits) == (1, 0)
    cube.location.x = 3.0  # moves: the cached object-space mesh is reused
    scene.frame_set(scene.frame_current)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    moved = addon.export.export_geometry(depsgraph, cache=cache)
    assert (cache.misses, cache.hits) == (1, 1)
    np.testing.assert_allclose(
        moved.positions, first.positions + np.array([3.0, 0.0, 0.0]), atol=1e-6
    )
    # An edit reaches the depsgraph handler, which drops the entry.
    addon.render.CACHE.meshes.update(cache.meshes)
    cube.data.vertices[0].co.z = 5.0
    cube.data.update()
    bpy.context.evaluated_depsgraph_get().update()
    assert cube.data.name_full not in addon.render.CACHE.meshes
    cache.invalidate({cube.data.name_full})
    edited = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get(), cache=cache)
    assert edited.positions[:, 2].max() == pytest.approx(5.0)


def test_cut_materials_export_their_masks(addon: ModuleType) -> None:
    """A card whose material cuts by an image's alpha exports a vertex per triangle corner
    with the UV map its texture reads, a mask index per triangle and the image's alpha
    (rows from the bottom), read past its edges and filtered as the texture's extension and
    interpolation say; a Mix Shader towards a Transparent BSDF cuts by one minus the
    factor; other geometry keeps no mask; transparency of other kinds is named in a note."""
    scene = bpy.context.scene
    image = blender_scenes.alpha_image("Stripes", size=16)
    material = blender_scenes.cutout_material(image, "principled")
    card = blender_scenes.add_card(
        scene, "Card", [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)], material, 3.0
    )
    # A second map, which the texture reads through a UV Map node.
    leaf = card.data.uv_layers.new(name="Leaf")
    for loop in card.data.loops:
        leaf.uv[loop.index].vector = card.data.uv_layers["UVMap"].uv[loop.index].vector * 0.5
    nodes, links = material.node_tree.nodes, material.node_tree.links
    uv_node = nodes.new("ShaderNodeUVMap")
    uv_node.uv_map = "Leaf"
    links.new(uv_node.outputs["UV"], nodes["Image Texture"].inputs["Vector"])
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(5, 0, 0))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    geometry = addon.export.export_geometry(depsgraph)
    card_id = next(i for i, name in geometry.names.items() if name == "Card")
    cut = geometry.object_ids == card_id
    assert cut.sum() == 2
    assert (geometry.triangle_masks[cut] == 0).all()
    assert (geometry.triangle_masks[~cut] == -1).all()
    corners = geometry.triangles[cut].ravel()
    assert len(np.unique(corners)) == 6  # a vertex per corner
    # Each corner's coordinates are the Leaf map's at its position: half the UVMap's.
    xy = geometry.positions[corners][:, :2]
    np.testing.assert_allclose(geometry.uvs[corners], xy * [1.5 / 2, 0.5], atol=1e-6)
    assert len(geometry.masks) == 1
    pixels = np.array(image.pixels[:], dtype=np.float32).reshape(16, 16, 4)
    np.testing.assert_array_equal(np.asarray(geometry.masks[0].alpha), pixels[..., 3])
    assert geometry.masks[0].threshold == 0.5
    assert geometry.notes == []

    # The Mix Shader's factor is the alpha where the Transparent BSDF is its first input,
    # and the transparency where it is the second.
    mixed = blender_scenes.cutout_material(image, "mix")
    card.data.materials[0] = mixed
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    np.testing.assert_array_equal(np.asarray(geometry.masks[0].alpha), pixels[..., 3])
    mix = mixed.node_tree.nodes["Mix Shader"]
    first, second = mix.inputs[1].links[0].from_socket, mix.inputs[2].links[0].from_socket
    mixed.node_tree.links.new(second, mix.inputs[1])
    mixed.node_tree.links.new(first, mix.inputs[2])
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    np.testing.assert_array_equal(np.asarray(geometry.masks[0].alpha), 1.0 - pixels[..., 3])
    assert (geometry.masks[0].wrap, geometry.masks[0].filter) == ("repeat", "linear")
    # The texture's extension and interpolation; clipped, an inverted factor reads 1 past
    # the image (Cycles reads the factor 0 there: the opaque first input).
    mixed_texture = mixed.node_tree.nodes["Image Texture"]
    for extension, wrap in (("EXTEND", "extend"), ("MIRROR", "mirror"), ("CLIP", "clip")):
        mixed_texture.extension, mixed_texture.interpolation = extension, "Closest"
        geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
        mask = geometry.masks[0]
        assert (mask.wrap, mask.filter, mask.border) == (wrap, "closest", 1.0), extension
    mixed_texture.interpolation = "Cubic"
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.masks[0].filter == "linear"

    # A Mapping node between the UV map and the texture: the coordinates it gives.
    texture = material.node_tree.nodes["Image Texture"]
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Location"].default_value = (0.5, -1.0, 0.0)
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.pi / 2)
    mapping.inputs["Scale"].default_value = (2.0, 3.0, 1.0)
    links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
    links.new(uv_node.outputs["UV"], mapping.inputs["Vector"])
    card.data.materials[0] = material
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    leaf_uvs = xy * [1.5 / 2, 0.5]
    # Point: scaled, turned a quarter about z, moved: (u, v) to (0.5 - 3v, 2u - 1).
    expected = np.c_[0.5 - 3 * leaf_uvs[:, 1], 2 * leaf_uvs[:, 0] - 1]
    np.testing.assert_allclose(geometry.uvs[corners], expected, atol=1e-5)
    assert geometry.notes == []
    # Texture undoes the Point mapping.
    mapping.vector_type = "TEXTURE"
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    expected = np.c_[(leaf_uvs[:, 1] + 1) / 2, (0.5 - leaf_uvs[:, 0]) / 3]
    np.testing.assert_allclose(geometry.uvs[corners], expected, atol=1e-5)

    # Mappings the export cannot follow, and a constant alpha: opaque, with a note.
    mapping.vector_type = "NORMAL"
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.uvs is None
    assert "maps normals, which is not affine" in geometry.notes[0]
    mapping.vector_type = "POINT"
    links.remove(mapping.inputs["Vector"].links[0])
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.uvs is None
    assert len(geometry.notes) == 1
    assert "mapped from no coordinates" in geometry.notes[0]
    coordinates = nodes.new("ShaderNodeTexCoord")
    links.new(coordinates.outputs["Object"], mapping.inputs["Vector"])
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert "mapped by 'Texture Coordinate', not a UV map" in geometry.notes[0]
    links.remove(nodes["Principled BSDF"].inputs["Alpha"].links[0])
    nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.5
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.uvs is None
    assert "alpha 0.50 is clipped at 0.5: it casts as opaque" in geometry.notes[0]
    # One alpha everywhere below the threshold: a 1x1 mask that cuts the whole card, from
    # a constant Alpha, a Mix Shader's constant factor, or a Transparent BSDF alone.
    nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.2
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert len(geometry.masks) == 1
    np.testing.assert_allclose(np.asarray(geometry.masks[0].alpha), [[0.2]])
    assert "neither casts nor hides the fog (Cycles lets 80% of the light" in geometry.notes[0]
    mixed.node_tree.links.remove(mix.inputs[0].links[0])
    mix.inputs[0].default_value = 0.75  # towards the second input, now the Transparent BSDF
    card.data.materials[0] = mixed
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    np.testing.assert_allclose(np.asarray(geometry.masks[0].alpha), [[0.25]])
    clear = bpy.data.materials.new("Clear")
    tree = clear.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    transparent = tree.nodes.new("ShaderNodeBsdfTransparent")
    tree.links.new(transparent.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    card.data.materials[0] = clear
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert [np.asarray(mask.alpha).tolist() for mask in geometry.masks] == [[[0.0]]]
    assert geometry.notes == []


def test_masks_read_an_images_colour_and_alpha_as_cycles_does(addon: ModuleType) -> None:
    """An 8-bit sRGB image's Color, which `Image.pixels` gives sRGB-encoded, cuts by its
    scene-linear luminance, as Cycles reads it (an Emission of a grey of 0.6 renders 0.318
    there); a Non-Color image's as stored. An image whose alpha is ignored (alpha mode
    None) has an Alpha of 1."""
    scene = bpy.context.scene
    image = bpy.data.images.new("Grey", 4, 4, alpha=True)
    # Bytes of exactly 0.6 (153) and 0.2 (51).
    rgba = np.tile(np.array([0.6, 0.6, 0.6, 0.2], dtype=np.float32), 16)
    image.pixels.foreach_set(rgba)
    assert not image.is_float
    assert image.colorspace_settings.name == "sRGB"
    material = blender_scenes.cutout_material(image, "principled")
    nodes, links = material.node_tree.nodes, material.node_tree.links
    corners = [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)]
    blender_scenes.add_card(scene, "Card", corners, material, 1.0)

    def mask() -> np.ndarray:
        geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
        return np.asarray(geometry.masks[0].alpha)

    np.testing.assert_allclose(mask(), 0.2, atol=1e-6)
    image.alpha_mode = "NONE"
    np.testing.assert_array_equal(mask(), 1.0)
    links.new(nodes["Image Texture"].outputs["Color"], nodes["Principled BSDF"].inputs["Alpha"])
    np.testing.assert_allclose(mask(), ((0.6 + 0.055) / 1.055) ** 2.4, rtol=1e-5)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(rgba)  # a generated image is generated again on that change
    np.testing.assert_allclose(mask(), 0.6, rtol=1e-6)


def test_value_nodes_on_the_alpha_move_the_cut(addon: ModuleType) -> None:
    """Math, Map Range, Invert and Color Ramp nodes between the image and the alpha: where
    the texture values whose alpha reaches one half are one interval from 0 or to 1, the
    mask cuts the raw value there (inverted for a falling chain); a chain that cuts several
    bands, an operation this does not map, or a tiled image, is named and casts as
    opaque."""
    image = blender_scenes.alpha_image("Stripes", size=16)
    material = blender_scenes.cutout_material(image, "principled")
    nodes, links = material.node_tree.nodes, material.node_tree.links
    corners = [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)]
    blender_scenes.add_card(bpy.context.scene, "Card", corners, material, 1.0)
    texture, alpha = nodes["Image Texture"], nodes["Principled BSDF"].inputs["Alpha"]
    math_node = nodes.new("ShaderNodeMath")
    links.new(texture.outputs["Alpha"], math_node.inputs[0])
    links.new(math_node.outputs[0], alpha)

    def cut(operation: str, operand: float) -> tuple[Any, list[str]]:
        math_node.operation, math_node.inputs[1].default_value = operation, operand
        geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
        return geometry.masks, geometry.notes

    masks, notes = cut("GREATER_THAN", 0.3)
    assert notes == []
    assert masks[0].threshold == pytest.approx(0.3, abs=1e-3)
    masks, _ = cut("MULTIPLY", 2.0)
    assert masks[0].threshold == pytest.approx(0.25, abs=1e-3)
    # Falling: solid where 0.7 - v reaches one half, v up to 0.2; the mask holds 1 - v.
    math_node.inputs[0].default_value = 0.7
    links.remove(math_node.inputs[0].links[0])
    links.new(texture.outputs["Alpha"], math_node.inputs[1])
    masks, _ = cut("SUBTRACT", 0.0)
    pixels = np.array(image.pixels[:], dtype=np.float32).reshape(16, 16, 4)
    np.testing.assert_allclose(np.asarray(masks[0].alpha), 1.0 - pixels[..., 3])
    assert masks[0].threshold == pytest.approx(0.8, abs=1e-3)
    links.remove(math_node.inputs[1].links[0])
    links.new(texture.outputs["Alpha"], math_node.inputs[0])
    # Every value solid, or none: opaque, or a card of no surface.
    masks, notes = cut("LESS_THAN", 2.0)
    assert (masks, notes) == ([], [])
    masks, _ = cut("GREATER_THAN", 2.0)
    assert np.asarray(masks[0].alpha).tolist() == [[0.0]]
    masks, notes = cut("SINE", 0.0)
    assert masks == []
    assert "Math node 'Math' on its alpha is SINE" in notes[0]
    # |v - 0.5| + 0.25 reaches one half at both ends: two bands.
    subtract = nodes.new("ShaderNodeMath")
    subtract.operation, subtract.inputs[1].default_value = "SUBTRACT", 0.5
    links.new(texture.outputs["Alpha"], subtract.inputs[0])
    links.new(subtract.outputs[0], math_node.inputs[0])
    absolute = nodes.new("ShaderNodeMath")
    absolute.operation = "ABSOLUTE"
    links.new(subtract.outputs[0], absolute.inputs[0])
    links.new(absolute.outputs[0], math_node.inputs[0])
    masks, notes = cut("ADD", 0.25)
    assert "cut the texture in more than one band" in notes[0]
    # A Map Range from [0.2, 0.8] to [0, 1], and an Invert before it: falling, at 0.5.
    remap = nodes.new("ShaderNodeMapRange")
    remap.inputs["From Min"].default_value, remap.inputs["From Max"].default_value = 0.2, 0.8
    invert = nodes.new("ShaderNodeInvert")
    links.new(texture.outputs["Alpha"], invert.inputs["Color"])
    links.new(invert.outputs["Color"], remap.inputs["Value"])
    links.new(remap.outputs["Result"], alpha)
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.masks[0].threshold == pytest.approx(0.5, abs=1e-3)
    np.testing.assert_allclose(np.asarray(geometry.masks[0].alpha), 1.0 - pixels[..., 3])
    # A tiled image, of which `Image.pixels` holds the first tile only.
    image.source = "TILED"
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert geometry.masks == []
    assert "image 'Stripes' is tiled (UDIM); it casts as opaque" in geometry.notes[0]


def test_a_sun_that_casts_no_shadows_is_blocked_by_nothing(addon: ModuleType) -> None:
    """A sun whose Cast Shadow is off: no triangle blocks it but one whose Casts Shafts
    is On, every one still hides the fog from the camera, the fog does not dim its light
    (Cycles traces no shadow rays for it), and a note says so; a sun whose Volume Scatter
    ray visibility is off is named."""
    scene = bpy.context.scene
    blender_scenes.add_camera(scene, blender_scenes.look_at((0, -10, 2), (0, 0, 2)))
    sun = blender_scenes.add_sun(scene, (0.2, 0.3, -1.0))
    for x in (0, 3):
        bpy.ops.mesh.primitive_cube_add(size=1.0, location=(x, 0, 2))
    forced = bpy.context.object
    sun.data.use_shadow = False
    inputs = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get(), sun=sun)
    flags = inputs.geometry.visibility
    ids = inputs.geometry.object_ids
    assert set(flags.tolist()) == {crepuscular.SEEN_BY_CAMERA}
    assert "casts no shadows (its Cast Shadow is off)" in " ".join(inputs.notes)
    assert inputs.kwargs["sun"]["attenuated_by_medium"] is False
    forced.crepuscular.casts_shafts = "on"
    inputs = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get(), sun=sun)
    forced_id = next(i for i, name in inputs.geometry.names.items() if name == forced.name)
    flags, ids = inputs.geometry.visibility, inputs.geometry.object_ids
    assert set(flags[ids == forced_id].tolist()) == {3}
    assert set(flags[ids != forced_id].tolist()) == {crepuscular.SEEN_BY_CAMERA}
    sun.visible_volume_scatter = False
    inputs = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get(), sun=sun)
    assert "Volume Scatter ray visibility off" in " ".join(inputs.notes)


def test_light_path_materials_hide_a_surface_from_some_rays(addon: ModuleType) -> None:
    """A Mix Shader whose factor is Light Path's Is Shadow Ray or Is Camera Ray, towards a
    Transparent BSDF, shows the surface only to the other rays: its triangles' visibility
    flags say which, and the seen side keeps its own cut. Other Light Path outputs, and
    different cuts for the two kinds of ray, are named and cast as opaque."""
    scene = bpy.context.scene
    corners = [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)]
    card = blender_scenes.add_card(scene, "Card", corners, None, 1.0)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(5, 0, 0))

    def exported(material: bpy.types.Material) -> tuple[Any, Any]:
        card.data.materials.clear()
        card.data.materials.append(material)
        geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
        card_id = next(i for i, name in geometry.names.items() if name == "Card")
        rows = geometry.object_ids == card_id
        flags = None if geometry.visibility is None else geometry.visibility[rows]
        return geometry, flags

    _, flags = exported(blender_scenes.light_path_material("Is Shadow Ray"))
    assert (flags == crepuscular.SEEN_BY_CAMERA).all()
    geometry, flags = exported(blender_scenes.light_path_material("Is Camera Ray"))
    assert (flags == crepuscular.BLOCKS_SUN).all()
    assert geometry.notes == []
    # The cube keeps both.
    cube_id = next(i for i, name in geometry.names.items() if name == "Cube")
    assert (geometry.visibility[geometry.object_ids == cube_id] == 3).all()
    # A leaf the camera sees cut by its image, and shadow rays not at all.
    image = blender_scenes.alpha_image("Stripes", size=16)
    leaf = blender_scenes.cutout_material(image, "principled")
    nodes, links = leaf.node_tree.nodes, leaf.node_tree.links
    light_path = nodes.new("ShaderNodeLightPath")
    mix = nodes.new("ShaderNodeMixShader")
    links.new(light_path.outputs["Is Shadow Ray"], mix.inputs[0])
    links.new(nodes["Principled BSDF"].outputs[0], mix.inputs[1])
    links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[2])
    links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
    geometry, flags = exported(leaf)
    assert (flags == crepuscular.SEEN_BY_CAMERA).all()
    pixels = np.array(image.pixels[:], dtype=np.float32).reshape(16, 16, 4)
    np.testing.assert_array_equal(np.asarray(geometry.masks[0].alpha), pixels[..., 3])
    # Shadow rays see a plain black surface, the camera the leaf: cuts that differ.
    links.new(nodes.new("ShaderNodeBsdfDiffuse").outputs[0], mix.inputs[2])
    geometry, flags = exported(leaf)
    assert flags is None or (flags == 3).all()
    assert "see different cutouts through Light Path" in geometry.notes[0]
    links.new(light_path.outputs["Is Diffuse Ray"], mix.inputs[0])
    links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[2])
    geometry, _ = exported(leaf)
    assert "mix factor is Light Path's 'Is Diffuse Ray'" in geometry.notes[0]


def test_cut_materials_inside_node_groups_export_their_masks(addon: ModuleType) -> None:
    """A leaf material as asset libraries wrap it: the Principled BSDF inside a node
    group whose Alpha input is exposed and fed by the Image Texture outside, through a
    reroute. It cuts with the image's alpha, as the same material without the group does;
    a Value node into the exposed Alpha is one alpha everywhere."""
    scene = bpy.context.scene
    image = blender_scenes.alpha_image("Stripes", size=16)
    group = _node_group("Leaf Shader", {"Alpha": "NodeSocketFloat"}, "BSDF")
    bsdf = group.nodes.new("ShaderNodeBsdfPrincipled")
    group.links.new(group.nodes["Group Input"].outputs["Alpha"], bsdf.inputs["Alpha"])
    group.links.new(bsdf.outputs[0], group.nodes["Group Output"].inputs["BSDF"])
    material = bpy.data.materials.new("Grouped Leaf")
    tree = material.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    shader = tree.nodes.new("ShaderNodeGroup")
    shader.node_tree = group
    texture = tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    reroute = tree.nodes.new("NodeReroute")
    tree.links.new(texture.outputs["Alpha"], reroute.inputs[0])
    tree.links.new(reroute.outputs[0], shader.inputs["Alpha"])
    tree.links.new(shader.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    blender_scenes.add_card(
        scene, "Card", [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)], material, 3.0
    )
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    pixels = np.array(image.pixels[:], dtype=np.float32).reshape(16, 16, 4)
    assert len(geometry.masks) == 1
    np.testing.assert_array_equal(np.asarray(geometry.masks[0].alpha), pixels[..., 3])
    assert geometry.notes == []
    value = tree.nodes.new("ShaderNodeValue")
    value.outputs[0].default_value = 0.2
    tree.links.new(value.outputs[0], shader.inputs["Alpha"])
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    np.testing.assert_allclose(np.asarray(geometry.masks[0].alpha), [[0.2]])


def _grounded_scene(tmp_path: Path) -> tuple[Any, Callable[[str], dict[str, np.ndarray]]]:
    """`_basic_scene` over a black ground, and a function that renders its layers through
    the operator under a name and reads them back."""
    scene = _basic_scene()
    ground = [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)]
    blender_scenes.add_quad(scene, "Ground", ground, blender_scenes.black_material(0.0))

    def layers(name: str) -> dict[str, np.ndarray]:
        path = tmp_path / f"{name}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        return crepuscular.read_exr(path)

    return scene, layers


def test_a_clear_card_neither_casts_nor_hides_the_fog(addon: ModuleType, tmp_path: Path) -> None:
    """A card whose surface is a Transparent BSDF alone (no UV map) renders as if it were
    not there, as in Cycles; made half opaque (alpha 0.6) it casts as an opaque card."""
    scene, layers = _grounded_scene(tmp_path)
    bare = layers("bare")
    clear = bpy.data.materials.new("Clear")
    tree = clear.node_tree
    principled = tree.nodes["Principled BSDF"]
    tree.nodes.remove(principled)
    transparent = tree.nodes.new("ShaderNodeBsdfTransparent")
    tree.links.new(transparent.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    corners = [(-3, -2, 3), (3, -2, 3), (3, -2, 5), (-3, -2, 5)]
    card = blender_scenes.add_quad(scene, "Card", corners, clear)
    for name, channel in layers("clear").items():
        np.testing.assert_array_equal(channel, bare[name], err_msg=name)
    opaque = blender_scenes.black_material(0.0)
    card.data.materials[0] = opaque
    solid = layers("solid")
    assert np.abs(solid["depth"] - bare["depth"]).max() > 1.0
    opaque.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.6
    for name, channel in layers("partial").items():
        np.testing.assert_array_equal(channel, solid[name], err_msg=name)


def test_a_volume_only_object_is_no_surface(addon: ModuleType, tmp_path: Path) -> None:
    """A box whose material has a Volume shader and no Surface one (a second fog box, a
    smoke domain) is no surface in Cycles: the camera sees into it and the sun shines
    through it, as through the fog object. Left in the scene while the medium is the
    Custom one, it renders as if it were not there, with a note, as does a Volume object;
    a material with neither shader is an opaque black surface in Cycles, and casts."""
    scene, layers = _grounded_scene(tmp_path)
    bare = layers("bare")
    smoke = bpy.data.materials.new("Smoke")
    tree = smoke.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    volume = tree.nodes.new("ShaderNodeVolumePrincipled")
    tree.links.new(volume.outputs[0], tree.nodes["Material Output"].inputs["Volume"])
    placed = np.diag([3.0, 3.0, 2.0, 1.0])
    placed[2, 3] = 3.0
    blender_scenes.add_fog_box(scene, placed, smoke)
    scene.crepuscular.medium_source = "custom"
    for name, channel in layers("volume only").items():
        np.testing.assert_array_equal(channel, bare[name], err_msg=name)
    # A Volume object (an OpenVDB grid), which Cycles renders, is named as left out.
    bpy.ops.object.volume_add(location=(0.0, 6.0, 2.0))
    bpy.context.active_object.name = "Cloud"
    inputs = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get())
    assert any("material 'Smoke': only a volume shader" in note for note in inputs.notes)
    assert any("object 'Cloud' is a Volume object" in note for note in inputs.notes)
    tree.links.remove(tree.nodes["Material Output"].inputs["Volume"].links[0])
    empty = layers("no shader")
    assert np.abs(empty["depth"] - bare["depth"]).max() > 1.0


def test_depth_of_field_and_motion_blur_are_named(addon: ModuleType) -> None:
    """Cycles blurs the beauty by the camera's depth of field and by motion blur; the
    layers stay sharp, and a note says which, so that an artist defocuses or blurs them in
    compositing. Neither is on in a new scene, which gets no such note."""
    scene = _basic_scene()

    def notes() -> list[str]:
        return addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get()).notes

    assert notes() == []
    scene.camera.data.dof.use_dof = True
    scene.render.use_motion_blur = True
    assert notes() == [
        "camera 'Camera' has depth of field: the layers are in focus throughout (defocus "
        "them by their depth layer to match the beauty)",
        "motion blur is on: the layers are rendered at the frame's instant",
    ]


def _turned_and_seen(addon: ModuleType, obj: Any) -> tuple[np.ndarray, np.ndarray, Any]:
    """Turns and scales `obj`; returns a sun direction, a pinhole's eye and the add-on's
    `SunAndCamera` of both."""
    obj.rotation_euler = (0.3, 0.0, 0.8)
    obj.scale = (1.5, 1.5, 1.5)
    bpy.context.view_layer.update()
    sun = np.array([0.4, -0.3, -1.0]) / np.linalg.norm([0.4, -0.3, -1.0])
    eye = np.array([-6.0, -8.0, 5.0])
    return sun, eye, addon.export.SunAndCamera(sun, eye, orthographic=False)


def test_hair_curves_export_as_tubes_of_their_radius(addon: ModuleType) -> None:
    """Hair curves (Curves objects) cast as open tubes around their points' polyline, each
    ring of the point's radius (scaled so that the tube's mean width is the strand's);
    curves without a radius attribute cast nothing, as Cycles draws nothing."""
    scene = bpy.context.scene
    y = np.linspace(0.0, 3.0, 4)
    strands = [np.c_[np.full_like(y, x), y, np.full_like(y, 2.0)] for x in (0.0, 1.0, 2.0)]
    hair = blender_scenes.add_hair(scene, "hair", strands, 0.1)
    assert addon.ui.CREPUSCULAR_PT_object.poll(SimpleNamespace(object=hair))
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    sides = crepuscular.TUBE_SIDES
    # Hair curves are Catmull-Rom: each of a strand's 3 segments cut into pieces.
    assert len(geometry.triangles) == 3 * 3 * crepuscular.CATMULL_ROM_STEPS * sides * 2
    radius = 0.1 * crepuscular._strands.TUBE_RADIUS
    low, high = geometry.positions.min(axis=0), geometry.positions.max(axis=0)
    np.testing.assert_allclose(low, [-radius, 0.0, 2.0 - radius], atol=1e-5)
    np.testing.assert_allclose(high, [2.0 + radius, 3.0, 2.0 + radius], atol=1e-5)
    # Every vertex lies at the ring's radius from its strand's axis (x = 0, 1 or 2; z = 2).
    x, z = geometry.positions[:, 0], geometry.positions[:, 2]
    distance = np.hypot(x - np.round(x), z - 2.0)
    np.testing.assert_allclose(distance, radius, rtol=1e-5)
    # Seen by a sun and a camera (through a turned, scaled object), each strand is a
    # ribbon across each view, of the strand's width as it sees it: the sun's in the
    # shadow map only, two radii past the strand along the sun, the camera's in its depth
    # only, at the axis.
    sun, eye, seen = _turned_and_seen(addon, hair)
    ribbons = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get(), seen=seen)
    flags = ribbons.visibility
    assert set(flags.tolist()) == {crepuscular.BLOCKS_SUN, crepuscular.SEEN_BY_CAMERA}
    matrix = np.array(hair.matrix_world)
    width = 0.1 * 1.5
    for flag in (crepuscular.BLOCKS_SUN, crepuscular.SEEN_BY_CAMERA):
        corners = ribbons.positions[ribbons.triangles[flags == flag]].astype(np.float64)
        edges = corners.reshape(-1, 3)
        if flag == crepuscular.BLOCKS_SUN:
            edges = edges - crepuscular.STRAND_SHADOW_GAP * width * sun
        # Strands run along y through x = 0, 1, 2 at z = 2 (object space): each edge vertex
        # is `width` from its strand's axis, across the strand and across the view.
        local = (edges - matrix[:3, 3]) @ np.linalg.inv(matrix[:3, :3]).T
        strand = np.round(local[:, 0]).clip(0, 2)
        axis_point = np.c_[strand, local[:, 1], np.full(len(local), 2.0)]
        centre = axis_point @ matrix[:3, :3].T + matrix[:3, 3]
        offset = edges - centre
        np.testing.assert_allclose(np.linalg.norm(offset, axis=1), width, rtol=1e-4)
        along = matrix[:3, :3] @ np.array([0.0, 1.0, 0.0])
        np.testing.assert_allclose(offset @ along, 0.0, atol=1e-4)
        toward = sun if flag == crepuscular.BLOCKS_SUN else centre - eye
        toward = toward / np.linalg.norm(toward, axis=-1, keepdims=True)
        np.testing.assert_allclose(
            np.einsum("ij,ij->i", offset, np.broadcast_to(toward, offset.shape)), 0.0, atol=1e-4
        )
    hair.data.attributes.remove(hair.data.attributes["radius"])
    hair.data.update_tag()
    bare = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert len(bare.triangles) == 0


def test_particle_hair_exports_as_tubes_along_its_paths(addon: ModuleType) -> None:
    """Legacy particle hair casts as Cycles draws it: a tube along each path's keys
    (co_hair, 2^steps + 1 of them), its radius half the radius scale times the root radius
    at the root, falling to the tip radius (times the same) by length, bent by the shape;
    children in place of their parents; the emitter left out where it is not rendered,
    and nothing where the particle system's modifier is off."""
    scene = bpy.context.scene
    corners = [(-1, -1, 2), (1, -1, 2), (1, 1, 2), (-1, 1, 2)]
    emitter = blender_scenes.add_particle_hair(
        scene, "fur", corners, 6, 1.5, radius_scale=0.2, tip_radius=0.25
    )
    settings = emitter.particle_systems[0].settings
    settings.shape = 0.5
    depsgraph = bpy.context.evaluated_depsgraph_get()
    geometry = addon.export.export_geometry(depsgraph)
    keys = (1 << settings.display_step) + 1
    rings = geometry.positions.astype(np.float64).reshape(6, -1, crepuscular.TUBE_SIDES, 3)
    assert rings.shape[1] == (keys - 1) * crepuscular.CATMULL_ROM_STEPS + 1
    centres = rings.mean(axis=2)
    evaluated = emitter.evaluated_get(depsgraph)
    system = evaluated.particle_systems[0]
    for number in range(6):
        path = np.array(
            [system.co_hair(evaluated, particle_no=number, step=k) for k in range(keys)]
        )
        np.testing.assert_allclose(
            centres[number, :: crepuscular.CATMULL_ROM_STEPS], path, atol=1e-5
        )
        # Hairs grow straight up 1.5: the radius at each key by its height (between keys,
        # the tubes interpolate it linearly).
        at_keys = rings[number, :: crepuscular.CATMULL_ROM_STEPS]
        time = (path[:, 2] - 2.0) / 1.5
        expected = 0.1 * ((1 - time) ** 2 * (1.0 - 0.25) + 0.25)
        distance = np.linalg.norm(at_keys - path[:, None], axis=2)
        np.testing.assert_allclose(
            distance, np.outer(crepuscular._strands.TUBE_RADIUS * expected, np.ones(16)), rtol=1e-4
        )
    # The emitter is not rendered: none of its quad.
    assert np.abs(geometry.positions[:, 2] - 2.0).min() > 1e-4 or len(geometry.positions) == len(
        rings.reshape(-1, 3)
    )
    settings.child_type = "SIMPLE"
    settings.child_percent = 3
    children = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert len(children.triangles) == 3 * len(geometry.triangles)
    emitter.show_instancer_for_viewport = True
    emitter.modifiers["hair"].show_viewport = False
    bare = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert len(bare.triangles) == 2


def test_point_clouds_export_as_spheres_of_their_radius(addon: ModuleType) -> None:
    """A point cloud (geometry nodes' Mesh to Points) casts a sphere around each point, of
    the point's radius; without a radius attribute, of Blender's default 0.01, the size
    Cycles draws such points at."""
    scene = bpy.context.scene
    centres = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0, 3.0, 2.0]])
    radii = np.array([0.1, 0.25, 0.5])
    points = blender_scenes.add_points(scene, "dust", centres, radii)
    points.location = (1.0, 0.0, 0.0)
    geometry = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert len(geometry.triangles) == 3 * crepuscular.SPHERE_TRIANGLES
    spheres = geometry.positions.reshape(3, -1, 3)
    np.testing.assert_allclose(spheres.mean(axis=1), centres + np.array([1.0, 0.0, 0.0]), atol=1e-5)
    extent = spheres.max(axis=1) - spheres.min(axis=1)
    np.testing.assert_allclose(extent / (2 * radii[:, None]), 1.0, atol=0.06)
    assert set(geometry.names.values()) == {"dust"}
    # Seen by a sun and a camera (through a turned, scaled object), each view gets the
    # side of each sphere that Cycles' rays can hit: the camera the triangles facing it,
    # the sun's shadow map those facing away from the sun.
    sun, eye, seen = _turned_and_seen(addon, points)
    culled = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get(), seen=seen)
    np.testing.assert_array_equal(culled.triangles, geometry.triangles)
    corners = culled.positions.astype(np.float64)[culled.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing_eye = np.einsum("ij,ij->i", normals, corners[:, 0] - eye) < 0
    np.testing.assert_array_equal((culled.visibility & crepuscular.SEEN_BY_CAMERA) > 0, facing_eye)
    np.testing.assert_array_equal(
        (culled.visibility & crepuscular.BLOCKS_SUN) > 0, normals @ sun > 0
    )
    # An artist can switch a point cloud off, or follow its Shadow ray visibility, from the
    # object panel, as for a mesh.
    panel = addon.ui.CREPUSCULAR_PT_object
    assert panel.poll(SimpleNamespace(object=points))
    points.crepuscular.casts_shafts = "off"
    off = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    assert (off.visibility == crepuscular.SEEN_BY_CAMERA).all()
    points.crepuscular.casts_shafts = "auto"
    points.visible_shadow = False
    points.visible_camera = False
    assert len(addon.export.export_geometry(bpy.context.evaluated_depsgraph_get()).triangles) == 0
    bpy.data.objects.remove(points)
    blender_scenes.add_points(scene, "plain", centres)
    plain = addon.export.export_geometry(bpy.context.evaluated_depsgraph_get())
    extent = np.ptp(plain.positions.reshape(3, -1, 3), axis=1)
    np.testing.assert_allclose(extent / 0.02, 1.0, atol=0.06)


def _plane_distance(
    camera: bpy.types.Object, scene: bpy.types.Scene, x: float, y: float, plane_y: float
) -> float:
    """Blender's own view ray through image point (x, y) in [0, 1]² (y up), intersected
    with the plane Y = plane_y; returns the distance along the ray."""
    frame = camera.data.view_frame(scene=scene)  # top right, bottom right, bottom left, top left
    bottom_left, bottom_right, top_left = frame[2], frame[1], frame[3]
    local = bottom_left + (bottom_right - bottom_left) * x + (top_left - bottom_left) * y
    matrix = camera.matrix_world.normalized()
    if camera.data.type == "ORTHO":
        origin = matrix @ Vector((local.x, local.y, 0.0))
        direction = (matrix.to_3x3() @ Vector((0, 0, -1))).normalized()
    else:
        origin = matrix.translation
        direction = ((matrix @ local) - origin).normalized()
    t = (plane_y - origin.y) / direction.y
    return float(t)


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_camera_matches_blenders_projection(addon: ModuleType, kind: str) -> None:
    scene = bpy.context.scene
    width, height = 40, 30
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    camera = blender_scenes.add_camera(scene, np.eye(4))
    camera.matrix_world = (
        Matrix.Translation((0.3, -10.0, 0.5))
        @ Matrix.Rotation(np.radians(92.0), 4, "X")
        @ Matrix.Rotation(np.radians(4.0), 4, "Y")
        @ Matrix.Scale(2.0, 4)
    )
    camera.data.sensor_fit = "VERTICAL"
    camera.data.sensor_height = 20.0
    camera.data.shift_x, camera.data.shift_y = 0.1, -0.05
    if kind == "orthographic":
        camera.data.type = "ORTHO"
        camera.data.ortho_scale = 6.0
    blender_scenes.add_sun(scene, (0.0, 0.2, -1.0))
    wall = bpy.data.meshes.new("Wall")
    wall.from_pydata([(-50, 5, -50), (50, 5, -50), (50, 5, 50), (-50, 5, 50)], [], [[0, 1, 2, 3]])
    scene.collection.objects.link(bpy.data.objects.new("Wall", wall))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    inputs = addon.export.frame_inputs(scene, depsgraph)
    inputs.kwargs["settings"].update(steps=4, supersampling=1, max_distance=200.0)
    layers = crepuscular.render_arrays(**inputs.kwargs)
    assert layers.depth.shape == (height, width)
    for row, column in ((0, 0), (height - 1, width - 1), (7, 31), (22, 3)):
        x, y = (column + 0.5) / width, 1.0 - (row + 0.5) / height
        expected = _plane_distance(camera, scene, x, y, 5.0)
        assert layers.depth[row, column] == pytest.approx(expected, rel=2e-4), (row, column)


def test_sun_is_lit_as_cycles_lights_it(addon: ModuleType) -> None:
    """Cycles: colour x blackbody colour (Temperature on) x strength x 2^exposure."""
    sun = blender_scenes.add_sun(bpy.context.scene, (0.0, 0.0, -1.0), strength=3.0)
    sun.data.color = (1.0, 0.5, 0.25)
    plain = addon.export.sun_dict(sun)
    assert plain["strength"] == pytest.approx(3.0)
    assert plain["color"] == pytest.approx([1.0, 0.5, 0.25])
    sun.data.exposure = 1.5
    sun.data.use_temperature, sun.data.temperature = True, 4000.0
    lit = addon.export.sun_dict(sun)
    assert lit["strength"] == pytest.approx(3.0 * 2**1.5)
    blackbody = np.array(sun.data.temperature_color)
    assert blackbody[0] > 1.2 * blackbody[2]  # warm
    assert lit["color"] == pytest.approx(np.array([1.0, 0.5, 0.25]) * blackbody)


def test_fog_object_maps_as_cycles_reads_it(addon: ModuleType) -> None:
    scene = bpy.context.scene
    matrix = (
        Matrix.Translation((1, 2, 3)) @ Matrix.Rotation(0.4, 4, "Z") @ Matrix.Diagonal((4, 3, 2, 1))
    )
    scatter = blender_scenes.volume_material(
        "scatter", Color=(0.5, 0.5, 0.5, 1.0), Density=0.8, Anisotropy=0.3
    )
    fog = blender_scenes.add_fog_box(scene, matrix, scatter)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    medium, notes = addon.export.medium_dict(scene, depsgraph)
    assert medium["extinction"] == pytest.approx(0.4)  # sigma_t = color * density
    assert medium["albedo"] == pytest.approx([1.0, 1.0, 1.0])  # sigma_s = sigma_t
    assert medium["anisotropy"] == pytest.approx(0.3)
    world = np.array(medium["extent"]["world_from_cube"]).reshape(4, 4).T
    np.testing.assert_allclose(world, np.array(matrix), atol=1e-6)
    assert notes == []
    # Bounds that are not the unit cube move into the matrix.
    for vertex in fog.data.vertices:
        vertex.co = vertex.co * 0.5 + Vector((1.0, 0.0, 0.0))
    fog.data.update()
    medium, _ = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    world = np.array(medium["extent"]["world_from_cube"]).reshape(4, 4).T
    expected = np.array(matrix @ Matrix.Translation((1, 0, 0)) @ Matrix.Scale(0.5, 4))
    np.testing.assert_allclose(world, expected, atol=1e-6)

    # Principled Volume defaults: colour 0.5, no absorption colour, so sigma_t = density.
    fog.data.materials[0] = blender_scenes.volume_material("principled", Density=2.0)
    medium, _ = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    assert medium["extinction"] == pytest.approx(2.0)
    assert medium["albedo"] == pytest.approx([0.5, 0.5, 0.5])

    # Coloured extinction: per channel, with its luminance as the grey value, and a note.
    fog.data.materials[0] = blender_scenes.volume_material(
        "scatter", Color=(1.0, 0.5, 0.25, 1.0), Density=2.0
    )
    medium, notes = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    luminance = 0.2126 * 1.0 + 0.7152 * 0.5 + 0.0722 * 0.25
    assert medium["extinction"] == pytest.approx(2.0 * luminance)
    assert medium["channel_extinction"] == pytest.approx([2.0, 1.0, 0.5])
    assert medium["albedo"] == pytest.approx([1.0, 1.0, 1.0])  # sigma_s = sigma_t per channel
    assert any("3 times" in note for note in notes)
    # Principled Volume with a coloured absorption: sigma_s / sigma_t per channel.
    fog.data.materials[0] = blender_scenes.volume_material(
        "principled", Density=1.0, **{"Absorption Color": (0.0, 0.25, 1.0, 1.0)}
    )
    medium, _ = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    extinction = 0.5 + 0.5 * (1 - np.sqrt([0.0, 0.25, 1.0]))
    assert medium["channel_extinction"] == pytest.approx(extinction)
    assert medium["albedo"] == pytest.approx(0.5 / extinction)


def test_fog_shaders_of_several_closures_sum_as_cycles_sums_them(addon: ModuleType) -> None:
    """Add Shader sums its volume closures' coefficients, Mix Shader weights them by
    1 - Fac and Fac, Volume Absorption only absorbs, Volume Coefficients gives them
    outright, and emission is left out with a note; lobes of different anisotropy are
    rendered as their mean weighted by scattering, with a note."""
    scene = bpy.context.scene
    material = blender_scenes.volume_graph(
        "add",
        [("scatter", {"Color": (0.8, 0.8, 0.8, 1.0), "Density": 0.5, "Anisotropy": 0.3})],
        [("absorption", {"Color": (0.2, 0.4, 0.6, 1.0), "Density": 0.3})],
    )
    blender_scenes.add_fog_box(scene, np.eye(4), material)

    def medium() -> tuple[dict[str, Any], list[str]]:
        return addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())

    found, notes = medium()
    extinction = 0.4 + 0.3 * np.array([0.8, 0.6, 0.4])
    assert found["channel_extinction"] == pytest.approx(extinction)
    assert found["albedo"] == pytest.approx(0.4 / extinction)
    assert found["anisotropy"] == pytest.approx(0.3)
    assert not any("anisotropy" in note for note in notes)
    # A quarter of a Principled Volume of the other anisotropy, three quarters scatter.
    material = blender_scenes.volume_graph(
        "mix",
        [("scatter", {"Color": (1.0, 1.0, 1.0, 1.0), "Density": 0.4, "Anisotropy": 0.5})],
        [("principled", {"Density": 0.8, "Anisotropy": -0.1})],
        fac=0.25,
    )
    scene.crepuscular.fog_object.data.materials[0] = material
    found, notes = medium()
    assert found["extinction"] == pytest.approx(0.75 * 0.4 + 0.25 * 0.8)
    assert found["albedo"] == pytest.approx([(0.3 + 0.25 * 0.4) / 0.5] * 3)
    assert found["anisotropy"] == pytest.approx((0.3 * 0.5 + 0.1 * -0.1) / 0.4)
    assert any("rendered as one of" in note for note in notes)
    material = blender_scenes.volume_graph(
        "add",
        [
            (
                "coefficients",
                {
                    "Absorption Coefficients": (0.1, 0.2, 0.3),
                    "Scatter Coefficients": (0.4, 0.4, 0.4),
                    "Anisotropy": 0.2,
                },
            )
        ],
        [("emission", {"Strength": 2.0})],
    )
    scene.crepuscular.fog_object.data.materials[0] = material
    found, notes = medium()
    assert found["channel_extinction"] == pytest.approx([0.5, 0.6, 0.7])
    assert found["albedo"] == pytest.approx(0.4 / np.array([0.5, 0.6, 0.7]))
    assert any("is ignored" in note for note in notes)
    nodes = material.node_tree.nodes
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    add = next(node for node in nodes if node.bl_idname == "ShaderNodeAddShader")
    material.node_tree.links.new(diffuse.outputs[0], add.inputs[1])
    with pytest.raises(addon.export.ExportError, match="ShaderNodeBsdfDiffuse"):
        medium()


def _node_group(name: str, inputs: dict[str, str], output: str) -> bpy.types.NodeTree:
    """A shader node group with the interface `inputs` (name: socket type) and one output,
    its Group Input and Group Output nodes made."""
    group = bpy.data.node_groups.new(name, "ShaderNodeTree")
    group.nodes.new("NodeGroupInput")
    group.nodes.new("NodeGroupOutput")
    for socket, kind in inputs.items():
        group.interface.new_socket(socket, in_out="INPUT", socket_type=kind)
    group.interface.new_socket(output, in_out="OUTPUT", socket_type="NodeSocketShader")
    return group


def test_fog_shaders_are_followed_through_groups_reroutes_and_muted_nodes(
    addon: ModuleType,
) -> None:
    """A fog preset as asset libraries ship it: a Principled Volume inside a node group
    inside another, its Density and Color exposed, the density driven by a Value node and
    the colour from the outer group's own socket; reached through a reroute and a muted
    Add Shader (which passes its first input), beside a muted Volume Scatter (which adds
    nothing). It maps exactly as the same Principled Volume alone does, as Cycles compiles
    it. An RGB node feeding the density is converted to its luminance, as Blender does."""
    scene = bpy.context.scene
    plain = blender_scenes.volume_material(
        "principled",
        Density=0.7,
        Color=(0.8, 0.6, 0.4, 1.0),
        Anisotropy=0.25,
        **{"Absorption Color": (0.2, 0.3, 0.9, 1.0)},
    )
    blender_scenes.add_fog_box(scene, np.eye(4), plain)

    def medium() -> tuple[dict[str, Any], list[str]]:
        return addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())

    expected, expected_notes = medium()
    inner = _node_group(
        "Fog Core", {"Density": "NodeSocketFloat", "Tint": "NodeSocketColor"}, "Volume"
    )
    principled = inner.nodes.new("ShaderNodeVolumePrincipled")
    principled.inputs["Anisotropy"].default_value = 0.25
    principled.inputs["Absorption Color"].default_value = (0.2, 0.3, 0.9, 1.0)
    core_in, core_out = inner.nodes["Group Input"], inner.nodes["Group Output"]
    inner.links.new(core_in.outputs["Density"], principled.inputs["Density"])
    inner.links.new(core_in.outputs["Tint"], principled.inputs["Color"])
    inner.links.new(principled.outputs[0], core_out.inputs["Volume"])
    outer = _node_group(
        "Fog Preset", {"Density": "NodeSocketFloat", "Tint": "NodeSocketColor"}, "Volume"
    )
    core = outer.nodes.new("ShaderNodeGroup")
    core.node_tree = inner
    preset_in, preset_out = outer.nodes["Group Input"], outer.nodes["Group Output"]
    outer.links.new(preset_in.outputs["Density"], core.inputs["Density"])
    outer.links.new(preset_in.outputs["Tint"], core.inputs["Tint"])
    outer.links.new(core.outputs[0], preset_out.inputs["Volume"])

    material = bpy.data.materials.new("Fog Preset")
    tree = material.node_tree
    for node in list(tree.nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            tree.nodes.remove(node)
    preset = tree.nodes.new("ShaderNodeGroup")
    preset.node_tree = outer
    preset.inputs["Tint"].default_value = (0.8, 0.6, 0.4, 1.0)
    density = tree.nodes.new("ShaderNodeValue")
    density.outputs[0].default_value = 0.7
    tree.links.new(density.outputs[0], preset.inputs["Density"])
    muted_add = tree.nodes.new("ShaderNodeAddShader")
    muted_add.mute = True
    ignored = tree.nodes.new("ShaderNodeVolumeScatter")
    ignored.mute = True
    ignored.inputs["Density"].default_value = 5.0
    tree.links.new(preset.outputs[0], muted_add.inputs[0])
    tree.links.new(ignored.outputs[0], muted_add.inputs[1])
    reroute = tree.nodes.new("NodeReroute")
    tree.links.new(muted_add.outputs[0], reroute.inputs[0])
    output = tree.nodes["Material Output"]
    tree.links.new(reroute.outputs[0], output.inputs["Volume"])
    scene.crepuscular.fog_object.data.materials[0] = material
    found, notes = medium()
    assert found.keys() == expected.keys()
    for key, value in expected.items():
        assert found[key] == (value if key == "extent" else pytest.approx(value)), key
    assert notes == expected_notes

    # The muted Add Shader passes its first input alone; unmuted, it sums the scatter's
    # closure (sigma_t 0.8 x 5 more in every channel) too.
    ignored.mute = False
    assert medium()[0]["extinction"] == pytest.approx(expected["extinction"])
    muted_add.mute = False
    assert medium()[0]["extinction"] == pytest.approx(expected["extinction"] + 4.0)
    muted_add.mute = True
    # A muted link is no link: the fog has no closure and the material no volume.
    tree.links.remove(output.inputs["Volume"].links[0])
    link = tree.links.new(reroute.outputs[0], output.inputs["Volume"])
    link.is_muted = True
    with pytest.raises(addon.export.ExportError, match="no Volume output link"):
        medium()
    link.is_muted = False
    # An RGB node into the float socket reads as its luminance.
    rgb = tree.nodes.new("ShaderNodeRGB")
    rgb.outputs[0].default_value = (0.5, 1.0, 0.0, 1.0)
    tree.links.new(rgb.outputs[0], preset.inputs["Density"])
    found, _ = medium()
    luminance = 0.2126 * 0.5 + 0.7152 * 1.0
    assert found["extinction"] == pytest.approx(expected["extinction"] / 0.7 * luminance)
    # A texture is not a constant: named, with the node that feeds it, and what to do.
    noise = tree.nodes.new("ShaderNodeTexNoise")
    tree.links.new(noise.outputs["Fac"], preset.inputs["Density"])
    with pytest.raises(addon.export.ExportError, match=r"'Density'.*'Noise Texture'") as info:
        medium()
    assert "fog is homogeneous" in str(info.value)
    assert "Medium to Custom" in str(info.value)


@pytest.mark.parametrize("seed", range(4))
def test_materials_rebuilt_inside_node_groups_map_as_before(addon: ModuleType, seed: int) -> None:
    """Fog materials of one or several closures and cutout materials, rebuilt inside node
    groups with random inputs exposed and given outside (`wrap_in_group`), map exactly as
    before: the same medium, and the same mask."""
    rng = random.Random(seed)
    scene = bpy.context.scene
    fogs = [
        blender_scenes.volume_material(
            "principled",
            Density=0.4,
            Color=(0.7, 0.7, 0.7, 1.0),
            Anisotropy=0.3,
            **{"Absorption Color": (0.5, 0.5, 0.5, 1.0)},
        ),
        blender_scenes.volume_graph(
            "mix",
            [("scatter", {"Color": (0.9, 0.6, 0.3, 1.0), "Density": 0.5, "Anisotropy": 0.2})],
            [("absorption", {"Color": (0.4, 0.4, 0.4, 1.0), "Density": 0.3})],
            fac=0.3,
        ),
        blender_scenes.volume_graph(
            "add",
            [("coefficients", {"Scatter Coefficients": (0.2, 0.3, 0.4), "Anisotropy": 0.5})],
            [("emission", {"Strength": 0.0})],
        ),
    ]
    fog = blender_scenes.add_fog_box(scene, np.eye(4), fogs[0])
    for material in fogs:
        fog.data.materials[0] = material
        before = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
        blender_scenes.wrap_in_group(material, rng)
        after = addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
        assert after[1] == before[1], material.name
        for key, value in before[0].items():
            expected = value if key == "extent" else pytest.approx(value, rel=1e-6)
            assert after[0][key] == expected, (material.name, key)
    image = blender_scenes.alpha_image("Stripes", size=16)
    for kind in ("principled", "mix"):
        material = blender_scenes.cutout_material(image, kind)
        before = addon.cutouts.material_mask(material)
        blender_scenes.wrap_in_group(material, rng)
        assert addon.cutouts.material_mask(material) == before, kind


def test_a_fog_object_no_view_ray_reaches_is_named(addon: ModuleType) -> None:
    scene = _basic_scene()
    material = blender_scenes.volume_material("scatter", Density=0.2)
    fog = blender_scenes.add_fog_box(scene, np.diag([4.0, 4.0, 4.0, 1.0]), material)
    scene.crepuscular.medium_source = "fog_object"
    scene.crepuscular.fog_object = fog
    note = "no view ray reaches fog object 'Fog': the frame has no fog"
    for location, named in (((0.0, 0.0, 2.0), False), ((0.0, 1e4, 2.0), True)):
        fog.location = location
        depsgraph = bpy.context.evaluated_depsgraph_get()
        layers, inputs = addon.render.render_layers(scene, depsgraph)
        assert (layers.volume[..., 3].max() == 0) == named
        assert any(n.startswith(note) for n in inputs.notes) == named, inputs.notes


def test_fog_objects_that_cannot_map_are_named(addon: ModuleType) -> None:
    scene = bpy.context.scene
    material = blender_scenes.volume_material("scatter", Density=1.0)
    fog = blender_scenes.add_fog_box(scene, np.eye(4), material)
    texture = material.node_tree.nodes.new("ShaderNodeTexNoise")
    scatter = material.node_tree.nodes["Volume Scatter"]
    link = material.node_tree.links.new(texture.outputs["Fac"], scatter.inputs["Density"])
    depsgraph = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(addon.export.ExportError, match=r"'Density'.*constant"):
        addon.export.medium_dict(scene, depsgraph)
    material.node_tree.links.remove(link)
    bpy.ops.mesh.primitive_uv_sphere_add()
    scene.crepuscular.fog_object = bpy.context.active_object
    bpy.context.active_object.data.materials.append(material)
    with pytest.raises(addon.export.ExportError, match="must be a box"):
        addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    scene.crepuscular.fog_object = None
    with pytest.raises(addon.export.ExportError, match="fog_object"):
        addon.export.medium_dict(scene, bpy.context.evaluated_depsgraph_get())
    del fog


# The scripting contract -----------------------------------------------------------------


def test_render_layers_operator_writes_the_layers(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    path = tmp_path / "layers.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
    channels = crepuscular.read_exr(path)
    assert sorted(channels) == [
        "depth",
        "visibility",
        "volume.A",
        "volume.B",
        "volume.G",
        "volume.R",
    ]
    assert channels["volume.A"].shape == (36, 64)
    lit = channels["visibility"]
    assert 0.05 < lit.mean() < 0.95  # the roof shadows part of the fog, not all of it
    # A style setting changes the shafts; the depth layer never changes.
    settings = scene.objects["Sun"].data.crepuscular
    settings.use_tf = True
    layer = settings.tf_layers.add()
    layer.kind, layer.color = "solid", (0.2, 0.2, 0.2, 1.0)
    styled = tmp_path / "styled.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(styled)) == {"FINISHED"}
    again = crepuscular.read_exr(styled)
    np.testing.assert_array_equal(again["depth"], channels["depth"])
    assert again["volume.R"].mean() < 0.5 * channels["volume.R"].mean()


def test_render_layers_renders_what_is_hidden_only_in_the_viewport(
    addon: ModuleType, tmp_path: Path
) -> None:
    """The operator renders what F12 renders: a roof hidden in the viewport (the eye, the
    monitor, or its collection's) still casts, one hidden from renders does not, and the
    viewport's hiding is as it was afterwards."""
    scene = _basic_scene()
    roof = scene.objects["Roof"]
    ground = [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)]
    blender_scenes.add_quad(scene, "Ground", ground, blender_scenes.black_material(0.0))
    shown = tmp_path / "shown.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(shown)) == {"FINISHED"}
    expected = crepuscular.read_exr(shown)
    folder = bpy.data.collections.new("Roofs")
    scene.collection.children.link(folder)
    scene.collection.objects.unlink(roof)
    folder.objects.link(roof)
    layer = bpy.context.view_layer.layer_collection.children["Roofs"]

    def hide_eye(hidden: bool) -> None:
        roof.hide_set(hidden)

    def hide_monitor(hidden: bool) -> None:
        roof.hide_viewport = hidden

    def hide_collection(hidden: bool) -> None:
        folder.hide_viewport = hidden

    def hide_layer(hidden: bool) -> None:
        layer.hide_viewport = hidden

    for hide in (hide_eye, hide_monitor, hide_collection, hide_layer):
        hide(True)
        path = tmp_path / f"{hide.__name__}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        found = crepuscular.read_exr(path)
        for name, channel in found.items():
            np.testing.assert_array_equal(channel, expected[name], err_msg=hide.__name__)
        hidden = (roof.hide_get(), roof.hide_viewport, folder.hide_viewport, layer.hide_viewport)
        assert sum(hidden) == 1, hide.__name__
        hide(False)
    roof.hide_render = True
    bare = tmp_path / "bare.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(bare)) == {"FINISHED"}
    assert crepuscular.read_exr(bare)["visibility"].mean() > expected["visibility"].mean() + 0.05


def test_render_layers_evaluates_modifiers_and_particles_as_rendered(
    addon: ModuleType, tmp_path: Path
) -> None:
    """The operator evaluates modifiers, subdivision levels and particle amounts as F12
    does: its layers are those of the scene with each viewport setting set to its render
    setting by hand (and not those of the viewport's own settings), and every viewport
    setting is as it was afterwards."""
    scene = _basic_scene()
    roof = scene.objects["Roof"]
    ground = [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)]
    blender_scenes.add_quad(scene, "Ground", ground, blender_scenes.black_material(0.0))
    array = roof.modifiers.new("Array", "ARRAY")
    array.relative_offset_displace = (1.2, 0.0, 0.0)
    array.show_viewport = False
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(-3.0, 0.0, 4.0))
    block = bpy.context.active_object
    subdivision = block.modifiers.new("Subdivision", "SUBSURF")
    subdivision.levels, subdivision.render_levels = 0, 3
    corners = [(-2, -2, 5), (2, -2, 5), (2, 2, 5), (-2, 2, 5)]
    emitter = blender_scenes.add_particle_hair(scene, "fur", corners, 20, 1.0, radius_scale=0.2)
    particles = emitter.particle_systems[0].settings
    particles.child_type = "SIMPLE"
    particles.child_percent, particles.rendered_child_count = 1, 10
    particles.display_step, particles.render_step = 2, 4
    viewport = (array.show_viewport, subdivision.levels, particles.child_percent, 2)

    def operator_layers(name: str) -> dict[str, np.ndarray]:
        path = tmp_path / f"{name}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        return crepuscular.read_exr(path)

    array.show_viewport, subdivision.levels = True, 3
    particles.child_percent, particles.display_step = 10, 4
    by_hand = operator_layers("by_hand")
    array.show_viewport, subdivision.levels = viewport[0], viewport[1]
    particles.child_percent, particles.display_step = viewport[2], viewport[3]
    found = operator_layers("found")
    for name, channel in found.items():
        np.testing.assert_array_equal(channel, by_hand[name], err_msg=name)
    now = (array.show_viewport, subdivision.levels, particles.child_percent)
    assert (*now, particles.display_step) == viewport
    layers, _ = addon.render.render_layers(scene, bpy.context.evaluated_depsgraph_get())
    in_viewport = np.asarray(layers.visibility)
    assert np.abs(in_viewport - by_hand["visibility"]).mean() > 0.004


def test_adaptive_tolerance_reaches_the_renderer(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    settings = scene.objects["Sun"].data.crepuscular
    assert settings.method == "prefiltered"
    assert addon.export.settings_dict(settings)["adaptive_tolerance"] == pytest.approx(0.01)
    layers = {}
    for tolerance in (0.0, 1.0):
        settings.adaptive_tolerance = tolerance
        path = tmp_path / f"tolerance-{tolerance}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        layers[tolerance] = crepuscular.read_exr(path)
    # Shading every pixel and interpolating wherever the surfaces allow give different
    # layers over the same depth.
    np.testing.assert_array_equal(layers[0.0]["depth"], layers[1.0]["depth"])
    assert not np.array_equal(layers[0.0]["volume.R"], layers[1.0]["volume.R"])


def test_a_scene_far_from_the_origin_renders_as_near_it(addon: ModuleType, tmp_path: Path) -> None:
    # The export hands positions over relative to the camera: 100 km out, float32 world
    # positions would lie 8 mm apart. The roof's corners are off any float32 grid there;
    # the objects' locations are on it, as Blender's float32 matrices hold them.
    scene = _basic_scene()
    for vertex in scene.objects["Roof"].data.vertices:
        vertex.co = (1.03717 * vertex.co.x, 1.03717 * vertex.co.y, vertex.co.z + 0.01139)
    layers = []
    for step in range(2):
        if step == 1:
            for obj in scene.objects:
                obj.location += Vector((1e5, -7e4, 32.0))
        path = tmp_path / f"placed-{step}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        layers.append(crepuscular.read_exr(path))
    for name in ("volume.R", "visibility", "depth"):
        near, far = layers[0][name], layers[1][name]
        assert np.abs(far - near).max() <= 1e-5 * np.abs(near).max(), name


def test_exact_ray_ends_reach_the_renderer_and_auto_follows_the_medium(
    addon: ModuleType, tmp_path: Path
) -> None:
    scene = _basic_scene()
    ground = [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)]
    blender_scenes.add_quad(scene, "Ground", ground)
    settings = scene.objects["Sun"].data.crepuscular
    assert settings.exact_ray_ends == "auto"
    assert addon.export.settings_dict(settings)["exact_ray_ends"] == "auto"
    # At 256² every ray crosses so few texels that it is walked exactly whichever setting.
    settings.shadow_map_size = 1024

    def volume(setting: str) -> np.ndarray:
        settings.exact_ray_ends = setting
        path = tmp_path / f"{scene.crepuscular.medium_source}-{setting}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        return crepuscular.read_exr(path)["volume.R"]

    # Open fog: auto is off. In a fog box around the roof and the ground it is on, and
    # rays that end on the ground in the box differ.
    np.testing.assert_array_equal(volume("auto"), volume("off"))
    box = Matrix.Translation((0, 0, 3.5)) @ Matrix.Diagonal((12, 12, 4, 1))
    blender_scenes.add_fog_box(scene, box, blender_scenes.volume_material("scatter", Density=0.1))
    boxed = {setting: volume(setting) for setting in ("auto", "on", "off")}
    np.testing.assert_array_equal(boxed["auto"], boxed["on"])
    assert not np.array_equal(boxed["on"], boxed["off"])


def test_world_constraints_follow_the_frame(addon: ModuleType, tmp_path: Path) -> None:
    """A 3D TF constraint (what 'pick in viewport' adds) takes V̄ and depth from the pixel
    where its point appears; a point the camera cannot see is an error naming it."""
    scene = _basic_scene()
    settings = scene.objects["Sun"].data.crepuscular
    settings.tf_mode = "color"
    blender_scenes.add_quad(scene, "Wall", [(-9, 5, -3), (9, 5, -3), (9, 5, 9), (-9, 5, 9)])
    plain = tmp_path / "plain.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(plain)) == {"FINISHED"}
    constraint = addon.ui.add_world_constraint(settings, (0.0, 5.0, 2.0))  # on the wall
    constraint.color = (1.0, 0.0, 0.0, 1.0)
    assert settings.use_tf
    assert settings.tf_layers[settings.active_tf_layer].kind == "diffusion"
    red = tmp_path / "red.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(red)) == {"FINISHED"}
    before, after = crepuscular.read_exr(plain), crepuscular.read_exr(red)
    assert after["volume.G"].mean() < 0.2 * before["volume.G"].mean()  # all red now
    constraint.world_point = (0.0, -30.0, 3.0)  # behind the camera
    with pytest.raises(RuntimeError, match=r"world_point"):
        bpy.ops.crepuscular.render_layers(filepath=str(red))


def test_several_suns_add_their_light(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    second = blender_scenes.add_sun(scene, (-0.4, 0.1, -1.0), strength=1.5)
    second.name = "Sun.2"
    second.data.crepuscular.shadow_map_size = 256
    second.data.crepuscular.edge_samples = 1
    first = scene.objects["Sun"]
    paths = {}
    for name, enabled in (
        ("both", (True, True)),
        ("first", (True, False)),
        ("second", (False, True)),
    ):
        first.data.crepuscular.enabled, second.data.crepuscular.enabled = enabled
        paths[name] = tmp_path / f"{name}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(paths[name])) == {"FINISHED"}
    both, one, two = (volume_of(paths[n]) for n in ("both", "first", "second"))
    np.testing.assert_allclose(both[..., :3], one[..., :3] + two[..., :3], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(both[..., 3], one[..., 3])  # transmittance is the medium's
    assert two[..., :3].mean() > 0.1 * one[..., :3].mean()


def volume_of(path: Path) -> np.ndarray:
    channels = crepuscular.read_exr(path)
    return np.stack([channels[f"volume.{c}"] for c in "RGBA"], axis=-1)


def test_bad_input_is_reported_by_name(addon: ModuleType, tmp_path: Path) -> None:
    path = str(tmp_path / "x.exr")
    scene = bpy.context.scene
    blender_scenes.add_sun(scene, (0, 0, -1))
    with pytest.raises(RuntimeError, match="no camera"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    assert "no camera" in scene.crepuscular.last_error
    scene = _basic_scene()
    for obj in [o for o in scene.objects if o.type == "LIGHT"]:
        obj.data.crepuscular.enabled = False
    with pytest.raises(RuntimeError, match="no sun lamp has Stylized Shafts"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    sun = scene.objects["Sun"].data.crepuscular
    sun.enabled = True
    sun.method, sun.bases = "prefiltered", 5
    # The renderer's checks are named by the Blender data that fed them.
    with pytest.raises(RuntimeError, match=r"Stylized Shafts settings of 'Sun': .*render\.bases"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    sun.method = "minmax"
    scene.objects["Sun"].data.energy = math.nan
    with pytest.raises(RuntimeError, match=r"sun 'Sun': invalid sun\.strength: nan"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    scene.objects["Sun"].data.energy = 3.0
    scene.camera.data.clip_start, scene.camera.data.clip_end = 50.0, 1.0
    with pytest.raises(RuntimeError, match=r"camera 'Camera': invalid camera\.clip_end"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    scene.camera.data.clip_start, scene.camera.data.clip_end = 0.1, 100.0
    scene.crepuscular.extinction = math.nan
    with pytest.raises(RuntimeError, match=r"the scene's Stylized Shafts medium: .*extinction"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    scene.crepuscular.extinction = 0.1
    sun.method = "minmax"
    scene.render.resolution_x = 20000
    with pytest.raises(RuntimeError, match=r"camera\.width"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    scene.render.resolution_x = 64
    scene.render.use_border = True
    scene.render.border_min_x = scene.render.border_max_x = 0.5
    with pytest.raises(RuntimeError, match=r"the render region is empty at 64x"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    scene.render.use_border = False
    scene.camera.data.type = "PANO"
    with pytest.raises(RuntimeError, match="pano"):
        bpy.ops.crepuscular.render_layers(filepath=path)
    assert not os.path.exists(path)


def test_objects_with_nan_or_infinite_points_are_left_out_and_named(
    addon: ModuleType, tmp_path: Path
) -> None:
    """A NaN vertex or location failed the whole frame as `positions[k]`, naming no
    object: such placements are left out with a note, and the rest renders."""
    scene = _basic_scene()
    clean = tmp_path / "clean.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(clean)) == {"FINISHED"}
    mesh = bpy.data.meshes.new("Broken")
    mesh.from_pydata([(0, 0, 1), (1, 0, 1), (0, 1, 1)], [], [[0, 1, 2]])
    mesh.vertices[0].co = (math.nan, 0.0, 1.0)
    scene.collection.objects.link(bpy.data.objects.new("Broken", mesh))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    notes = addon.export.frame_inputs(scene, depsgraph).notes
    assert (
        "object 'Broken': 1 of its 1 placements have NaN or infinite points or transforms; "
        "left out" in notes
    )
    broken = tmp_path / "broken.exr"
    assert bpy.ops.crepuscular.render_layers(filepath=str(broken)) == {"FINISHED"}
    np.testing.assert_array_equal(volume_of(broken), volume_of(clean))


def test_hole_creation_without_objects_that_take_holes_says_so(addon: ModuleType) -> None:
    scene = _basic_scene()
    scene.objects["Sun"].data.crepuscular.use_holes = True
    depsgraph = bpy.context.evaluated_depsgraph_get()
    (note,) = [n for n in addon.export.frame_inputs(scene, depsgraph).notes if "holes" in n]
    assert note.endswith("but no rendered object has Takes Holes enabled: no holes are made")
    scene.objects["Roof"].crepuscular.takes_holes = True
    depsgraph = bpy.context.evaluated_depsgraph_get()
    inputs = addon.export.frame_inputs(scene, depsgraph)
    assert not [n for n in inputs.notes if "holes" in n]
    assert inputs.kwargs["style"]["holes"]["objects"]


def test_a_fog_object_left_out_of_light_linking_is_named(addon: ModuleType) -> None:
    """Cycles lights no fog that the sun's shadow linking or light linking leaves out
    (measured: the fog renders 0.0); the shafts still render, with a note that names the
    fog object and the fix."""
    scene = _basic_scene()
    fog = np.diag([4.0, 4.0, 2.0, 1.0])
    fog[:3, 3] = [0.0, 0.0, 2.0]
    box = blender_scenes.add_fog_box(scene, fog, blender_scenes.volume_material("scatter"))
    sun = scene.objects["Sun"]
    blockers = bpy.data.collections.new("blockers")
    sun.light_linking.blocker_collection = blockers
    blockers.objects.link(scene.objects["Roof"])  # included: only it blocks
    notes = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get()).notes
    (note,) = [n for n in notes if "shadow linking" in n]
    assert f"leaves the fog object '{box.name}' out" in note
    blockers.objects.link(box)
    notes = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get()).notes
    assert not [n for n in notes if "shadow linking" in n]
    # So with light linking: a fog object that does not receive the sun gets no light.
    receivers = bpy.data.collections.new("receivers")
    sun.light_linking.receiver_collection = receivers
    blender_scenes.set_blockers(receivers, {box.name: "EXCLUDE"})
    notes = addon.export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get()).notes
    (note,) = [n for n in notes if "light linking" in n]
    assert "include the fog object in the receiver collection" in note


def test_a_sun_disc_wider_than_the_sun_s_softens_the_shafts(addon: ModuleType) -> None:
    """Blender's default sun (0.526°) renders as a point; a wider disc takes
    `crepuscular.SUN_DISC_SAMPLES` directions over it (the preview fewer), with a note."""
    scene = _basic_scene()
    sun = scene.objects["Sun"]
    sun.data.angle = bpy.types.SunLight.bl_rna.properties["angle"].default
    depsgraph = bpy.context.evaluated_depsgraph_get()
    inputs = addon.export.frame_inputs(scene, depsgraph)
    assert not [n for n in inputs.notes if "disc" in n]
    assert inputs.kwargs["settings"]["sun_disc_samples"] == 1
    sun.data.angle = math.radians(4.0)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    inputs = addon.export.frame_inputs(scene, depsgraph)
    (note,) = [n for n in inputs.notes if "disc" in n]
    assert note.startswith("the 4.0° disc of 'Sun' softens the shafts: 16 directions")
    assert inputs.kwargs["settings"]["sun_disc_samples"] == crepuscular.SUN_DISC_SAMPLES
    preview = addon.export.frame_inputs(scene, depsgraph, preview=True)
    assert preview.kwargs["settings"]["sun_disc_samples"] == addon.export.PREVIEW_DISC_SAMPLES


def test_layer_files_take_the_scenes_exr_codec(addon: ModuleType, tmp_path: Path) -> None:
    scene = _basic_scene()
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    codec_byte = b"compression\0compression\0\x01\0\0\0"
    for blender_codec, ours, code in [("PIZ", "piz", 4), ("ZIPS", "zips", 2), ("DWAA", "zip", 3)]:
        settings.exr_codec = blender_codec
        assert addon.render.layers_compression(scene) == ours
        path = tmp_path / f"{blender_codec}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
        assert codec_byte + bytes([code]) in path.read_bytes(), blender_codec
    # A scene that renders to PNG keeps its EXR codec setting, which does not apply.
    settings.exr_codec = "PIZ"
    settings.file_format = "PNG"
    assert addon.render.layers_compression(scene) == "zip"


def test_layers_are_named_next_to_the_render_output(addon: ModuleType) -> None:
    scene = bpy.context.scene
    scene.render.filepath = "//renders/shot_"
    path = addon.render.layers_path(scene, 12)
    assert path.endswith(os.path.join("renders", "shot_crepuscular_0012.exr"))
    scene.render.filepath = "/tmp/frames/"
    assert addon.render.layers_path(scene, 3) == "/tmp/frames/crepuscular_0003.exr"
    scene.render.filepath = "/tmp/frames/still.png"
    assert addon.render.layers_path(scene, 3) == "/tmp/frames/still_crepuscular_0003.exr"


def test_enabling_shafts_wires_the_compositor(addon: ModuleType) -> None:
    scene = _basic_scene()
    tree = scene.compositing_node_group
    assert tree is not None
    node = tree.nodes[addon.render.NODE_NAME]
    assert node.node_tree.name == "Crepuscular Composite"
    assert not node.mute
    output = next(n for n in tree.nodes if n.bl_idname == "NodeGroupOutput")
    assert output.inputs[0].links[0].from_node == node
    assert node.inputs[0].links[0].from_node.bl_idname == "CompositorNodeRLayers"
    scene.objects["Sun"].data.crepuscular.enabled = False
    assert node.mute
    scene.objects["Sun"].data.crepuscular.enabled = True
    assert not node.mute
    assert len([n for n in tree.nodes if n.name.startswith(addon.render.NODE_NAME)]) == 1


def test_the_group_goes_in_front_of_an_existing_compositor_output(addon: ModuleType) -> None:
    scene = bpy.context.scene
    tree = bpy.data.node_groups.new("Artist Comp", "CompositorNodeTree")
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    layers = tree.nodes.new("CompositorNodeRLayers")
    glare = tree.nodes.new("CompositorNodeGlare")
    output = tree.nodes.new("NodeGroupOutput")
    tree.links.new(layers.outputs["Image"], glare.inputs["Image"])
    tree.links.new(glare.outputs["Image"], output.inputs[0])
    scene.compositing_node_group = tree
    _basic_scene()
    node = tree.nodes[addon.render.NODE_NAME]
    assert node.inputs[0].links[0].from_node == glare  # the artist's work stays upstream
    assert output.inputs[0].links[0].from_node == node
    # A tree with no output to composite in front of: a report, no exception.
    broken = bpy.data.node_groups.new("No Output", "CompositorNodeTree")
    scene.compositing_node_group = broken
    sun = scene.objects["Sun"].data.crepuscular
    sun.enabled = False
    sun.enabled = True
    assert "No Output" in scene.crepuscular.last_error


# Viewport preview -----------------------------------------------------------------------


def test_preview_updates_debounced_off_the_main_thread(addon: ModuleType) -> None:
    scene = _basic_scene(64, 36)
    scene.crepuscular.preview = True
    controller = addon.preview.PreviewController(debounce=0.2)
    controller.mark_dirty()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert not controller.step(scene, depsgraph, now=controller.last_change + 0.1)
    assert controller.step(scene, depsgraph, now=controller.last_change + 0.3)
    controller.wait()
    assert controller.result is not None
    assert controller.error == ""
    assert controller.result.volume.shape == (18, 32, 4)  # half resolution
    assert controller.result.display.shape == (18, 32, 4)
    first = controller.result
    assert not controller.step(scene, depsgraph)  # nothing changed
    # A setting change reaches the shared controller through the property update.
    addon.preview.CONTROLLER.dirty = False
    scene.objects["Sun"].data.crepuscular.closing_radius = 1.0
    assert addon.preview.CONTROLLER.dirty
    scene.crepuscular.preview_scale = "4"
    controller.mark_dirty()
    assert controller.step(scene, depsgraph, now=time.monotonic() + 1.0)
    controller.wait()
    assert controller.result.generation > first.generation
    assert controller.result.volume.shape == (9, 16, 4)
    # Preview off: nothing runs.
    scene.crepuscular.preview = False
    controller.mark_dirty()
    assert not controller.step(scene, depsgraph, now=time.monotonic() + 1.0)


def test_preview_timer_follows_frame_changes(addon: ModuleType) -> None:
    """The registered timer callback and the frame handler, driven by hand (timers do not
    run in background mode)."""
    scene = _basic_scene(64, 36)
    scene.crepuscular.preview = True
    controller = addon.preview.CONTROLLER
    controller.dirty = False
    scene.frame_set(5)  # the viewport depsgraph's frame change marks it
    assert controller.dirty
    controller.last_change -= 1.0  # as if the debounce time had passed
    assert addon.preview._tick() == addon.preview.TICK
    controller.wait()
    assert controller.result is not None
    assert controller.result.volume.shape == (18, 32, 4)


def test_preview_cancels_superseded_work(addon: ModuleType) -> None:
    scene = _basic_scene(1280, 720)
    scene.crepuscular.preview = True
    scene.crepuscular.preview_scale = "2"
    sun = scene.objects["Sun"].data.crepuscular
    sun.method, sun.steps = "reference", 3000
    controller = addon.preview.PreviewController(debounce=0.0)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    controller.mark_dirty()
    assert controller.step(scene, depsgraph)
    time.sleep(0.2)
    assert controller.busy  # a slow update is running in the background
    assert controller.progress < 0.5
    sun.steps = 8
    controller.mark_dirty()
    started = time.monotonic()
    controller.cancel()  # what a newer request does first
    assert time.monotonic() - started < 3.0
    assert controller.cancelled == 1
    assert controller.result is None
    controller.mark_dirty()
    assert controller.step(bpy.context.scene, bpy.context.evaluated_depsgraph_get())
    controller.wait()
    assert controller.result is not None


def test_preview_reports_errors_without_raising(addon: ModuleType) -> None:
    scene = bpy.context.scene
    scene.crepuscular.preview = True
    controller = addon.preview.PreviewController(debounce=0.0)
    controller.mark_dirty()
    assert not controller.step(scene, bpy.context.evaluated_depsgraph_get())
    assert "no sun lamp" in controller.error
