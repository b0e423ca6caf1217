"""A scene of every kind the add-on reads (a fog box, a roof, hair, a point cloud, a
camera and a sun), mutated one thing at a time as artists' scenes go wrong: zero, NaN and
huge transforms, NaN or negative shader inputs (the fog's, and a NaN alpha, mix factor or
transparency on the roof's material, NaN texture coordinates or mappings on a cut card,
Light Path materials of transparent or missing sides), emptied or
missing data, modifiers that break the fog box or multiply the roof, an emitter of
particle hair scaled to nothing, extreme cameras and resolutions. Each frame must render
to finite layers, or fail with one of the add-on's own errors that names the Blender data
to fix. Any other exception would reach the artist as a traceback. Objects with NaN or
infinite geometry are left out, and a note names them."""

from __future__ import annotations

import math
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import blender_scenes  # noqa: E402

NAN = math.nan


def _rich_scene() -> dict[str, Any]:
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 32, 18
    scene.render.resolution_percentage = 100
    camera = blender_scenes.add_camera(
        scene, blender_scenes.look_at((0, -12, 3), (0, 0, 2)), lens=35
    )
    sun = blender_scenes.add_sun(scene, (0.2, 0.3, -1.0))
    sun.data.crepuscular.shadow_map_size = 128
    sun.data.crepuscular.edge_samples = 1
    roof = blender_scenes.add_quad(scene, "Roof", [(-4, -4, 6), (4, -4, 6), (4, 4, 6), (-4, 4, 6)])
    fog_material = blender_scenes.volume_material(
        "principled", Density=0.2, Color=(0.8, 0.8, 0.8, 1.0), Anisotropy=0.3
    )
    fog = blender_scenes.add_fog_box(scene, np.diag([5.0, 5.0, 4.0, 1.0]), fog_material)
    fog.location = (0.0, 0.0, 3.0)
    strands = [np.array([(x, 1.0, 2.0), (x, 1.5, 3.0), (x, 2.0, 3.5)]) for x in (-1, 0, 1)]
    hair = blender_scenes.add_hair(scene, "Hair", strands, 0.05)
    dust = blender_scenes.add_point_cloud(
        scene, "Dust", [(-1.0, 0.0, 2.0), (1.0, 0.5, 3.0)], [0.2, 0.3]
    )
    return {
        "scene": scene,
        "camera": camera,
        "sun": sun,
        "roof": roof,
        "fog": fog,
        "fog_shader": fog_material.node_tree.nodes["Principled Volume"],
        "hair": hair,
        "dust": dust,
    }


def _set_attribute(obj: Any, name: str, index: int, value: Any) -> None:
    obj.data.attributes[name].data[index].value = value


def _modifier(obj: Any, kind: str, **settings: Any) -> None:
    modifier = obj.modifiers.new(kind.title(), kind)
    for name, value in settings.items():
        setattr(modifier, name, value)


def _points_modifier(obj: Any) -> None:
    """A geometry-nodes modifier that turns the roof's vertices into points."""
    group = bpy.data.node_groups.new("To Points", "GeometryNodeTree")
    group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    to_points = nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = 0.5
    links.new(nodes.new("NodeGroupInput").outputs[0], to_points.inputs["Mesh"])
    links.new(to_points.outputs["Points"], nodes.new("NodeGroupOutput").inputs[0])
    modifier = obj.modifiers.new("To Points", "NODES")
    modifier.node_group = group


def _roof_shader(things: dict[str, Any], kind: str) -> Any:
    """A new material 'Leaf' on the roof whose surface is a node of `kind` (a Principled
    BSDF, a Transparent BSDF, or a Mix Shader of a Transparent BSDF and a Principled BSDF,
    in that order); returns that node."""
    material = bpy.data.materials.new("Leaf")
    things["roof"].data.materials.append(material)
    tree = material.node_tree
    principled = tree.nodes["Principled BSDF"]
    if kind == "ShaderNodeBsdfPrincipled":
        return principled
    node = tree.nodes.new(kind)
    if kind == "ShaderNodeMixShader":
        transparent = tree.nodes.new("ShaderNodeBsdfTransparent")
        tree.links.new(transparent.outputs[0], node.inputs[1])
        tree.links.new(principled.outputs[0], node.inputs[2])
    tree.links.new(node.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return node


def _particle_hair(things: dict[str, Any]) -> Any:
    """A quad emitter of 20 particle hairs beside the roof; returns it."""
    corners = [(-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]
    return blender_scenes.add_particle_hair(things["scene"], "Fur", corners, 20, 0.5)


def _nan_uv_card(things: dict[str, Any]) -> None:
    """A leaf card cut by an image's alpha, one of whose UV coordinates is NaN."""
    image = blender_scenes.alpha_image("Stripes", size=16)
    material = blender_scenes.cutout_material(image, "principled")
    corners = [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)]
    card = blender_scenes.add_card(things["scene"], "Card", corners, material, 3.0)
    card.data.uv_layers["UVMap"].uv[0].vector = (NAN, NAN)


def _mapped_card(things: dict[str, Any], kind: str = "POINT", **inputs: Any) -> Any:
    """A leaf card cut by an image's alpha, clipped past its edges, whose coordinates a
    Mapping node of `kind` maps with `inputs`; returns the node."""
    image = blender_scenes.alpha_image("Stripes", size=16)
    material = blender_scenes.cutout_material(image, "principled")
    texture = material.node_tree.nodes["Image Texture"]
    texture.extension = "CLIP"
    blender_scenes.map_texture(material, texture, [(kind, (0, 0, 0), (0, 0, 0), (1, 1, 1))])
    mapping = next(n for n in material.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    for name, value in inputs.items():
        mapping.inputs[name].default_value = value
    corners = [(0, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)]
    blender_scenes.add_card(things["scene"], "Card", corners, material, 3.0)
    return mapping


def _noise_mapped_card(things: dict[str, Any]) -> None:
    mapping = _mapped_card(things)
    tree = mapping.id_data
    tree.links.new(
        tree.nodes.new("ShaderNodeTexNoise").outputs["Color"], mapping.inputs["Rotation"]
    )


def _light_path_roof(things: dict[str, Any], output: str, sides: tuple[str, str]) -> None:
    """The roof's material a Mix Shader of `sides` (node types, or "" for unlinked) by
    Light Path's `output`."""
    material = blender_scenes.light_path_material(output)
    tree = material.node_tree
    mix = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeMixShader")
    for slot, kind in zip((1, 2), sides, strict=True):
        for link in mix.inputs[slot].links:
            tree.links.remove(link)
        if kind:
            tree.links.new(tree.nodes.new(kind).outputs[0], mix.inputs[slot])
    things["roof"].data.materials.append(material)


MUTATIONS: dict[str, Callable[[dict[str, Any]], None]] = {
    "fog scaled to zero": lambda s: setattr(s["fog"], "scale", (0.0, 0.0, 0.0)),
    "fog scaled by 1e30": lambda s: setattr(s["fog"], "scale", (1e30, 1e30, 1e30)),
    "fog at NaN": lambda s: setattr(s["fog"], "location", (NAN, NAN, NAN)),
    "fog 1e30 m away": lambda s: setattr(s["fog"], "location", (1e30, 0.0, 0.0)),
    "fog density NaN": lambda s: setattr(s["fog_shader"].inputs["Density"], "default_value", NAN),
    "fog density infinite": lambda s: setattr(
        s["fog_shader"].inputs["Density"], "default_value", math.inf
    ),
    "fog density negative": lambda s: setattr(
        s["fog_shader"].inputs["Density"], "default_value", -1.0
    ),
    "fog anisotropy 1": lambda s: setattr(
        s["fog_shader"].inputs["Anisotropy"], "default_value", 1.0
    ),
    "fog colour NaN": lambda s: setattr(
        s["fog_shader"].inputs["Color"], "default_value", (NAN, NAN, NAN, 1.0)
    ),
    "fog without material": lambda s: s["fog"].data.materials.clear(),
    "fog mesh emptied": lambda s: s["fog"].data.clear_geometry(),
    "fog arrayed": lambda s: _modifier(s["fog"], "ARRAY", count=3),
    "fog removed": lambda s: bpy.data.objects.remove(s["fog"]),
    "roof vertex NaN": lambda s: setattr(s["roof"].data.vertices[0], "co", (NAN, 0.0, 6.0)),
    "roof scaled to zero": lambda s: setattr(s["roof"], "scale", (0.0, 0.0, 0.0)),
    "roof arrayed and subdivided": lambda s: (
        _modifier(s["roof"], "ARRAY", count=40),
        _modifier(s["roof"], "SUBSURF", levels=2, render_levels=2),
    ),
    "roof solidified": lambda s: _modifier(s["roof"], "SOLIDIFY", thickness=0.3),
    "roof as geometry-nodes points": lambda s: _points_modifier(s["roof"]),
    "roof alpha NaN": lambda s: setattr(
        _roof_shader(s, "ShaderNodeBsdfPrincipled").inputs["Alpha"], "default_value", NAN
    ),
    "roof mix factor NaN": lambda s: setattr(
        _roof_shader(s, "ShaderNodeMixShader").inputs[0], "default_value", NAN
    ),
    "card texture coordinates NaN": lambda s: _nan_uv_card(s),
    "card mapped to NaN": lambda s: _mapped_card(s, Location=(NAN, 0.0, 0.0)),
    "card mapped by 1e30": lambda s: _mapped_card(s, Scale=(1e30, 1e30, 1.0)),
    "card mapped by a zero scale, inverted": lambda s: _mapped_card(s, "TEXTURE", Scale=(0, 0, 0)),
    "card mapped by a noise texture's rotation": lambda s: _noise_mapped_card(s),
    "roof transparent to every ray by Light Path": lambda s: _light_path_roof(
        s, "Is Shadow Ray", ("ShaderNodeBsdfTransparent", "ShaderNodeBsdfTransparent")
    ),
    "roof of no closure to shadow rays by Light Path": lambda s: _light_path_roof(
        s, "Is Shadow Ray", ("ShaderNodeBsdfTransparent", "")
    ),
    "roof of no closure at all by Light Path": lambda s: _light_path_roof(
        s, "Is Camera Ray", ("", "")
    ),
    "particle hair on an emitter scaled to zero": lambda s: setattr(
        _particle_hair(s), "scale", (1.0, 1.0, 0.0)
    ),
    "roof transparency NaN": lambda s: setattr(
        _roof_shader(s, "ShaderNodeBsdfTransparent").inputs["Color"],
        "default_value",
        (NAN, NAN, NAN, 1.0),
    ),
    "hair point NaN": lambda s: setattr(s["hair"].data.points[0], "position", (NAN, 0, 0)),
    "hair radius infinite": lambda s: _set_attribute(s["hair"], "radius", 0, math.inf),
    "dust radius NaN": lambda s: _set_attribute(s["dust"], "radius", 0, NAN),
    "dust radius zero": lambda s: _set_attribute(s["dust"], "radius", 1, 0.0),
    "camera at NaN": lambda s: setattr(s["camera"], "location", (NAN, NAN, NAN)),
    "camera lens 1 mm": lambda s: setattr(s["camera"].data, "lens", 1.0),
    "camera shifted by 10": lambda s: setattr(s["camera"].data, "shift_x", 10.0),
    "camera clipping 1e-6 to 1e6": lambda s: (
        setattr(s["camera"].data, "clip_start", 1e-6),
        setattr(s["camera"].data, "clip_end", 1e6),
    ),
    "camera orthographic 1e-6 wide": lambda s: (
        setattr(s["camera"].data, "type", "ORTHO"),
        setattr(s["camera"].data, "ortho_scale", 1e-6),
    ),
    "camera inside the roof's plane": lambda s: setattr(s["camera"], "location", (0, 0, 6)),
    "sun strength infinite": lambda s: setattr(s["sun"].data, "energy", math.inf),
    "sun rotated by NaN": lambda s: setattr(s["sun"], "rotation_euler", (NAN, 0.0, 0.0)),
    "sun disc of 180°": lambda s: setattr(s["sun"].data, "angle", math.pi),
    "sun pointing up": lambda s: setattr(s["sun"], "rotation_euler", (math.pi, 0.0, 0.0)),
    "resolution 1 by 1": lambda s: (
        setattr(s["scene"].render, "resolution_x", 1),
        setattr(s["scene"].render, "resolution_y", 1),
    ),
    "resolution at 1%": lambda s: setattr(s["scene"].render, "resolution_percentage", 1),
}

#: What an error may name as the data to fix: objects and data by name, or a setting.
NAMED = ("'Fog'", "'Roof'", "'Hair'", "'Dust'", "'Camera'", "'Sun'", "fog_object", "render.")

#: Mutations that leave an object out of the frame, and how its note begins.
LEFT_OUT = {
    "roof vertex NaN": "object 'Roof'",
    "hair point NaN": "object 'Hair': NaN or infinite strand points or radii",
    "hair radius infinite": "object 'Hair': NaN or infinite strand points or radii",
    "dust radius NaN": "object 'Dust': NaN or infinite point positions or radii",
}

#: Mutations of materials and texture coordinates that render, with the note that says
#: how: a NaN alpha or mix factor as Cycles saturates it (to 0), a closure of NaN weight
#: dropped as Cycles drops it, triangles of NaN coordinates opaque.
NOTED = {
    "roof alpha NaN": "material 'Leaf': its alpha or mix factor is NaN, which Cycles reads "
    "as 0: it neither casts nor hides the fog",
    "roof mix factor NaN": "material 'Leaf': its alpha or mix factor is NaN, which Cycles "
    "reads as 0: it neither casts nor hides the fog",
    "roof transparency NaN": "material 'Leaf': its Transparent BSDF's Color is not finite; "
    "it casts as opaque",
    "card texture coordinates NaN": "object 'Card': NaN or infinite texture coordinates; the "
    "triangles with them cast as opaque",
    "card mapped to NaN": "material 'Cutout principled': image 'Stripes' is mapped by values "
    "that are not finite; it casts as opaque",
    "card mapped by a noise texture's rotation": "material 'Cutout principled': input "
    "'Rotation' of 'Mapping' must be a constant (its own value, a group input's, or a Value "
    "or RGB node's), not linked from 'Noise Texture'; it casts as opaque",
}


@pytest.mark.parametrize("mutation", MUTATIONS)
def test_a_mutated_scene_renders_or_names_what_is_wrong(addon: ModuleType, mutation: str) -> None:
    things = _rich_scene()
    MUTATIONS[mutation](things)
    scene = things["scene"]
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        layers, inputs = addon.render.render_layers(scene, depsgraph)
    except addon.render.USER_ERRORS as error:
        message = str(error)
        assert any(name in message for name in NAMED), f"{mutation}: names nothing: {message}"
        assert mutation not in LEFT_OUT.keys() | NOTED.keys(), f"{mutation}: failed: {message}"
        return
    for name in ("volume", "visibility", "depth"):
        assert np.isfinite(np.asarray(getattr(layers, name))).all(), f"{mutation}: {name}"
    if mutation in LEFT_OUT:
        assert any(note.startswith(LEFT_OUT[mutation]) for note in inputs.notes), inputs.notes
    if mutation in NOTED:
        assert NOTED[mutation] in inputs.notes, inputs.notes
