"""Shared by the Blender tests and their subprocesses: installing and enabling the
extension from its zip, running a job of blender_job.py, and building small scenes
(camera, sun, fog box, occluders)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
ADDON_MODULE = "bl_ext.user_default.crepuscular"
JOB = Path(__file__).resolve().parent / "blender_job.py"


def addon_zip() -> Path:
    """The extension zip, built as `make addon` builds it (from the wheel in `dist/`), so
    that the tests always install the current sources."""
    built = subprocess.run(
        [
            sys.executable,
            str(ROOT / "blender_addon" / "build_extension.py"),
            str(ROOT / "dist"),
            str(ROOT / "out" / "addon"),
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    return Path(built.stdout.strip().splitlines()[-1])


def install_addon() -> ModuleType:
    """Installs and enables the zip with Blender's own extension operator."""
    import bpy

    result = bpy.ops.extensions.package_install_files(
        filepath=str(addon_zip()), repo="user_default", enable_on_install=True
    )
    assert result == {"FINISHED"}, result
    return sys.modules[ADDON_MODULE]


def enable_addon() -> ModuleType:
    """Enables the installed extension (after a factory reset disabled it)."""
    import addon_utils

    module = addon_utils.enable(ADDON_MODULE, default_set=True, handle_error=_raise)
    assert module is not None, f"{ADDON_MODULE} did not enable"
    return module


def run_job(out: Path, job: str, **spec: Any) -> float:
    """Runs one job of blender_job.py in a subprocess; returns its wall time in seconds."""
    started = time.perf_counter()
    result = subprocess.run(
        [sys.executable, str(JOB), json.dumps({"job": job, "out": str(out), **spec})],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return time.perf_counter() - started


def _raise(error: BaseException) -> None:
    raise error


def reset() -> ModuleType:
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    return enable_addon()


def look_at(eye: Any, target: Any, up: Any = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world for a camera at `eye` looking at `target`."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = (
        right,
        np.cross(back, right),
        back,
        eye,
    )
    return matrix


def sun_matrix(travel: Any) -> np.ndarray:
    """A sun lamp whose -Z axis is the travel direction."""
    back = -np.asarray(travel, float) / np.linalg.norm(travel)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = right, np.cross(back, right), back
    return matrix


def add_camera(scene: Any, matrix: Any, *, lens: float = 50.0) -> Any:
    import bpy
    from mathutils import Matrix

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    camera.data.lens = lens
    camera.data.sensor_width = 36.0
    camera.data.clip_start = 0.1
    camera.data.clip_end = 100.0
    camera.matrix_world = Matrix(np.asarray(matrix).tolist())
    scene.camera = camera
    return camera


def add_sun(scene: Any, travel: Any, *, strength: float = 3.0, enabled: bool = True) -> Any:
    import bpy
    from mathutils import Matrix

    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", type="SUN"))
    scene.collection.objects.link(sun)
    sun.data.energy = strength
    sun.data.angle = 0.0
    sun.matrix_world = Matrix(sun_matrix(travel).tolist())
    sun.data.crepuscular.enabled = enabled
    return sun


def volume_material(kind: str = "scatter", **inputs: Any) -> Any:
    """A material whose volume output is a Volume Scatter or Principled Volume."""
    import bpy

    material = bpy.data.materials.new(f"Fog {kind}")
    nodes = material.node_tree.nodes
    for node in list(nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            nodes.remove(node)
    node_type = "ShaderNodeVolumeScatter" if kind == "scatter" else "ShaderNodeVolumePrincipled"
    shader = nodes.new(node_type)
    for name, value in inputs.items():
        shader.inputs[name].default_value = value
    output = next(n for n in nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    material.node_tree.links.new(shader.outputs["Volume"], output.inputs["Volume"])
    return material


#: Node types of `volume_graph`'s shaders.
VOLUME_NODES = {
    "scatter": "ShaderNodeVolumeScatter",
    "absorption": "ShaderNodeVolumeAbsorption",
    "principled": "ShaderNodeVolumePrincipled",
    "coefficients": "ShaderNodeVolumeCoefficients",
    "emission": "ShaderNodeEmission",
}


def volume_graph(
    combine: str,
    first: list[tuple[str, dict[str, Any]]],
    second: list[tuple[str, dict[str, Any]]],
    fac: float = 0.5,
) -> Any:
    """A material whose volume output is an Add Shader (`combine` "add") or a Mix Shader
    ("mix", at `fac`) of two shaders, each given as [(kind, inputs)] (`VOLUME_NODES`)."""
    import bpy

    material = bpy.data.materials.new(f"Fog {combine}")
    tree = material.node_tree
    for node in list(tree.nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            tree.nodes.remove(node)
    joint = tree.nodes.new("ShaderNodeAddShader" if combine == "add" else "ShaderNodeMixShader")
    if combine == "mix":
        joint.inputs["Fac"].default_value = fac
    shader_inputs = [socket for socket in joint.inputs if socket.type == "SHADER"]
    for (kind, inputs), socket in zip([*first, *second], shader_inputs, strict=True):
        shader = tree.nodes.new(VOLUME_NODES[kind])
        for name, value in inputs.items():
            shader.inputs[name].default_value = value
        tree.links.new(shader.outputs[0], socket)
    output = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    tree.links.new(joint.outputs[0], output.inputs["Volume"])
    return material


def add_fog_box(scene: Any, matrix: Any, material: Any) -> Any:
    """Blender's default cube (vertices at ±1) placed by `matrix`, with `material`."""
    import bpy
    from mathutils import Matrix

    mesh = bpy.data.meshes.new("Fog")
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh.from_pydata(corners, [], faces)
    fog = bpy.data.objects.new("Fog", mesh)
    scene.collection.objects.link(fog)
    fog.matrix_world = Matrix(np.asarray(matrix).tolist())
    fog.data.materials.append(material)
    scene.crepuscular.medium_source = "fog_object"
    scene.crepuscular.fog_object = fog
    return fog


def black_material(value: float = 0.0) -> Any:
    import bpy

    material = bpy.data.materials.new(f"Grey {value}")
    bsdf = material.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (value, value, value, 1.0)
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    return material


def light_path_material(output: str) -> Any:
    """Black, but a Transparent BSDF to the rays Light Path's `output` ("Is Shadow Ray" or
    "Is Camera Ray") flags: the factor of a Mix Shader from the black surface to it."""
    material = black_material(0.0)
    material.name = f"Black but to {output}"
    nodes, links = material.node_tree.nodes, material.node_tree.links
    light_path = nodes.new("ShaderNodeLightPath")
    transparent = nodes.new("ShaderNodeBsdfTransparent")
    mix = nodes.new("ShaderNodeMixShader")
    links.new(light_path.outputs[output], mix.inputs[0])
    links.new(nodes["Principled BSDF"].outputs[0], mix.inputs[1])
    links.new(transparent.outputs[0], mix.inputs[2])
    links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
    return material


def add_quad(scene: Any, name: str, vertices: Any, material: Any = None) -> Any:
    import bpy

    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in vertices], [], [[0, 1, 2, 3]])
    obj = bpy.data.objects.new(name, mesh)
    if material is not None:
        obj.data.materials.append(material)
    scene.collection.objects.link(obj)
    return obj


def add_mesh(
    scene: Any,
    name: str,
    positions: Any,
    triangles: Any,
    *,
    world_from_object: Any = None,
    material: Any = None,
) -> Any:
    """A triangle mesh object from (N, 3) positions and (M, 3) vertex indices, filled with
    `foreach_set` (no per-vertex Python loops)."""
    import bpy
    from mathutils import Matrix

    positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int32).reshape(-1, 3)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(positions))
    mesh.vertices.foreach_set("co", positions.ravel())
    mesh.loops.add(triangles.size)
    mesh.loops.foreach_set("vertex_index", triangles.ravel())
    mesh.polygons.add(len(triangles))
    mesh.polygons.foreach_set("loop_start", np.arange(0, triangles.size, 3, dtype=np.int32))
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    if world_from_object is not None:
        obj.matrix_world = Matrix(np.asarray(world_from_object).tolist())
    if material is not None:
        obj.data.materials.append(material)
    scene.collection.objects.link(obj)
    return obj


def setup_cycles(scene: Any, *, width: int, height: int, samples: int) -> None:
    import bpy

    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 0
    scene.cycles.volume_bounces = 0
    scene.cycles.seed = 1
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGBA"


def alpha_image(name: str, size: int = 64) -> Any:
    """A float image whose alpha is stripes 8 texels wide, one in two solid, with a round
    hole in a solid stripe; black colour."""
    import bpy

    image = bpy.data.images.new(name, size, size, alpha=True, float_buffer=True)
    y, x = np.mgrid[0:size, 0:size] + 0.5
    alpha = ((x // 8) % 2 == 1).astype(np.float32)
    alpha[(x - 44) ** 2 + (y - 24) ** 2 < 9**2] = 0.0
    rgba = np.zeros((size, size, 4), dtype=np.float32)
    rgba[..., 3] = alpha
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    return image


def add_hair(scene: Any, name: str, strands: Any, radius: float, material: Any = None) -> Any:
    """A hair curves object: one curve through each (K, 3) array of `strands`, every point
    of `radius`."""
    import bpy

    curves = bpy.data.hair_curves.new(name)
    curves.add_curves([len(strand) for strand in strands])
    points = np.concatenate([np.asarray(s, dtype=np.float32) for s in strands])
    curves.points.foreach_set("position", points.ravel())
    attribute = curves.attributes.new("radius", "FLOAT", "POINT")
    attribute.data.foreach_set("value", np.full(len(points), radius, dtype=np.float32))
    if material is not None:
        curves.materials.append(material)
    obj = bpy.data.objects.new(name, curves)
    scene.collection.objects.link(obj)
    return obj


def _vertex_object(scene: Any, name: str, positions: Any) -> Any:
    """A mesh object of loose vertices at (N, 3) `positions`, linked to `scene`."""
    import bpy

    positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(positions))
    mesh.vertices.foreach_set("co", positions.ravel())
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    return obj


def add_points(
    scene: Any, name: str, positions: Any, radii: Any = None, material: Any = None
) -> Any:
    """A point cloud, as geometry nodes make one: an object whose modifier turns its mesh's
    vertices at `positions` into points (Mesh to Points), each of its `radii` (read from a
    vertex attribute), or without a radius attribute where `radii` is None; `material` is
    set on the points."""
    import bpy

    obj = _vertex_object(scene, name, positions)
    if radii is not None:
        attribute = obj.data.attributes.new("point_radius", "FLOAT", "POINT")
        attribute.data.foreach_set("value", np.asarray(radii, dtype=np.float32))
    group = bpy.data.node_groups.new(f"{name} points", "GeometryNodeTree")
    group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    to_points = nodes.new("GeometryNodeMeshToPoints")
    links.new(nodes.new("NodeGroupInput").outputs[0], to_points.inputs["Mesh"])
    geometry = to_points.outputs[0]
    if radii is None:
        remove = nodes.new("GeometryNodeRemoveAttribute")
        remove.inputs["Name"].default_value = "radius"
        links.new(geometry, remove.inputs["Geometry"])
        geometry = remove.outputs[0]
    else:
        radius = nodes.new("GeometryNodeInputNamedAttribute")
        radius.data_type = "FLOAT"
        radius.inputs["Name"].default_value = "point_radius"
        links.new(radius.outputs["Attribute"], to_points.inputs["Radius"])
    if material is not None:
        set_material = nodes.new("GeometryNodeSetMaterial")
        set_material.inputs["Material"].default_value = material
        links.new(geometry, set_material.inputs["Geometry"])
        geometry = set_material.outputs[0]
    links.new(geometry, nodes.new("NodeGroupOutput").inputs[0])
    obj.modifiers.new("points", "NODES").node_group = group
    return obj


def add_point_cloud(scene: Any, name: str, positions: Any, radii: Any, material: Any = None) -> Any:
    """A Point Cloud object (its own data, not a modifier's output, so that Blender's USD
    exporter writes it as Points): vertices at `positions` converted to points, with a
    radius attribute of `radii`."""
    import bpy

    obj = _vertex_object(scene, name, positions)
    for other in bpy.context.selected_objects:
        other.select_set(False)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    assert bpy.ops.object.convert(target="POINTCLOUD") == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    assert obj.type == "POINTCLOUD", obj.type
    radius = obj.data.attributes.new("radius", "FLOAT", "POINT")
    radius.data.foreach_set("value", np.asarray(radii, dtype=np.float32))
    if material is not None:
        obj.data.materials.append(material)
    return obj


def add_particle_hair(
    scene: Any,
    name: str,
    corners: Any,
    count: int,
    length: float,
    *,
    radius_scale: float = 0.01,
    tip_radius: float = 0.0,
    material: Any = None,
) -> Any:
    """A quad emitter whose legacy hair particle system grows `count` straight hairs of
    `length` along its normal, of radius `radius_scale` / 2 at the root tapering to
    `tip_radius` times that at the tip; the emitter itself is not rendered. Returns it."""
    emitter = add_quad(scene, name, corners, material)
    emitter.modifiers.new("hair", "PARTICLE_SYSTEM")
    settings = emitter.particle_systems[0].settings
    settings.type, settings.count, settings.hair_length = "HAIR", count, length
    settings.radius_scale, settings.root_radius, settings.tip_radius = radius_scale, 1.0, tip_radius
    settings.use_close_tip = False
    if material is not None:
        settings.material = 1
    emitter.show_instancer_for_render = False
    emitter.show_instancer_for_viewport = False
    return emitter


def set_blockers(
    collection: Any,
    states: dict[str, str],
    child: Any = None,
    child_state: str | None = None,
) -> None:
    """Makes a light's blocker `collection` hold the objects named in `states`, each with
    its link state ("INCLUDE" or "EXCLUDE"), and `child` with `child_state` if given.
    (`collection_objects` holds the states in the order of `collection.objects`.)"""
    import bpy

    for obj in list(collection.objects):
        collection.objects.unlink(obj)
    for nested in list(collection.children):
        collection.children.unlink(nested)
    for name in states:
        collection.objects.link(bpy.data.objects[name])
    for obj, entry in zip(collection.objects, collection.collection_objects, strict=True):
        entry.light_linking.link_state = states[obj.name]
    if child is not None and child_state is not None:
        collection.children.link(child)
        collection.collection_children[0].light_linking.link_state = child_state


def alpha_png(path: Path) -> Any:
    """`alpha_image` saved as an 8-bit PNG at `path` and loaded back from the file, as an
    artist's leaf texture is (the USD exporter copies such files next to the stage)."""
    import bpy

    image = alpha_image(path.stem)
    image.filepath_raw = str(path)
    image.file_format = "PNG"
    image.save()
    return bpy.data.images.load(str(path))


def cutout_material(image: Any, kind: str) -> Any:
    """Black, cut by `image`'s alpha: into a Principled BSDF's Alpha ("principled"), as the
    factor of a Mix Shader from a Transparent BSDF to it ("mix"), or from it to a
    Transparent BSDF ("inverted", the alpha then being the transparency)."""
    material = black_material(0.0)
    material.name = f"Cutout {kind}"
    nodes, links = material.node_tree.nodes, material.node_tree.links
    texture = nodes.new("ShaderNodeTexImage")
    texture.image = image
    bsdf = nodes["Principled BSDF"]
    if kind == "principled":
        links.new(texture.outputs["Alpha"], bsdf.inputs["Alpha"])
    else:
        transparent = nodes.new("ShaderNodeBsdfTransparent")
        mix = nodes.new("ShaderNodeMixShader")
        links.new(texture.outputs["Alpha"], mix.inputs[0])
        shaders = [transparent.outputs[0], bsdf.outputs[0]]
        if kind == "inverted":
            shaders.reverse()
        links.new(shaders[0], mix.inputs[1])
        links.new(shaders[1], mix.inputs[2])
        links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
    return material


def add_card(
    scene: Any, name: str, corners: Any, material: Any, repeats: float, start: float = 0.0
) -> Any:
    """A quad with a UV map running `start` to `repeats` along its first edge, 0 to 1 along
    the other."""
    card = add_quad(scene, name, corners, material)
    layer = card.data.uv_layers.new(name="UVMap")
    uvs = ((start, 0), (repeats, 0), (repeats, 1), (start, 1))
    for loop, uv in zip(card.data.loops, uvs, strict=True):
        layer.uv[loop.index].vector = uv
    return card


def map_texture(material: Any, texture: Any, chain: list[Any]) -> None:
    """Maps `texture`'s coordinates (the default UV map, a Texture Coordinate node's UV)
    through a chain of Mapping nodes. (Blender's USD exporter renames the default map's
    primvar to "st", but not a UV Map node's reader, which then reads no primvar.)"""
    nodes, links = material.node_tree.nodes, material.node_tree.links
    uv = nodes.new("ShaderNodeTexCoord")
    into = texture.inputs["Vector"]
    for kind, location, rotation, scale in chain:
        mapping = nodes.new("ShaderNodeMapping")
        mapping.vector_type = kind
        if kind != "VECTOR":
            mapping.inputs["Location"].default_value = location
        mapping.inputs["Rotation"].default_value = rotation
        mapping.inputs["Scale"].default_value = scale
        links.new(mapping.outputs["Vector"], into)
        into = mapping.inputs["Vector"]
    links.new(uv.outputs["UV"], into)


#: Node properties that say what a node computes, copied when its graph is rebuilt.
NODE_PROPERTIES = (
    "phase",
    "image",
    "interpolation",
    "extension",
    "projection",
    "uv_map",
    "vector_type",
)


def _socket(sockets: Any, identifier: str) -> Any:
    return next(socket for socket in sockets if socket.identifier == identifier)


def wrap_in_group(material: Any, rng: Any) -> Any:
    """Rebuilds `material`'s shader graph inside a node group, as asset libraries ship
    materials, which Cycles renders alike: the group's outputs feed the material output
    (through a reroute, or a muted Add Shader that passes its first input and drops a
    dense Volume Scatter or a Diffuse BSDF at its second); about half of the graph's
    unlinked value and colour inputs are exposed on the group and given there by the
    group node's own socket, a Value or RGB node, through a reroute or not (a grey colour
    sometimes as a value, which Blender converts). `rng` is a `random.Random`. Returns
    the group."""
    import bpy

    tree = material.node_tree
    output = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    originals = [node for node in tree.nodes if node != output]
    group = bpy.data.node_groups.new(f"{material.name} group", "ShaderNodeTree")
    group_in = group.nodes.new("NodeGroupInput")
    group_out = group.nodes.new("NodeGroupOutput")
    copies = {}
    for node in originals:
        copy = group.nodes.new(node.bl_idname)
        for name in NODE_PROPERTIES:
            if hasattr(node, name):
                setattr(copy, name, getattr(node, name))
        for socket in node.inputs:
            if hasattr(socket, "default_value"):
                _socket(copy.inputs, socket.identifier).default_value = socket.default_value
        copies[node.name] = copy
    outputs = []
    for link in tree.links:
        source = _socket(copies[link.from_node.name].outputs, link.from_socket.identifier)
        if link.to_node == output:
            outputs.append((link.to_socket.name, source))
        else:
            target = _socket(copies[link.to_node.name].inputs, link.to_socket.identifier)
            group.links.new(source, target)
    for name, source in outputs:
        group.interface.new_socket(name, in_out="OUTPUT", socket_type="NodeSocketShader")
        group.links.new(source, group_out.inputs[name])
    exposed = []
    for copy in copies.values():
        for socket in copy.inputs:
            kind = socket.type
            if socket.is_linked or not socket.enabled or kind not in ("VALUE", "RGBA"):
                continue
            if rng.random() < 0.5:
                continue
            value = socket.default_value if kind == "VALUE" else tuple(socket.default_value)
            if kind == "RGBA" and value[0] == value[1] == value[2] and rng.random() < 0.5:
                kind, value = "VALUE", value[0]
            name = f"{copy.name} {socket.identifier}"
            interface = "NodeSocketFloat" if kind == "VALUE" else "NodeSocketColor"
            group.interface.new_socket(name, in_out="INPUT", socket_type=interface)
            group.links.new(group_in.outputs[name], socket)
            exposed.append((name, kind, value))
    for node in originals:
        tree.nodes.remove(node)
    wrapper = tree.nodes.new("ShaderNodeGroup")
    wrapper.node_tree = group
    for name, kind, value in exposed:
        socket = wrapper.inputs[name]
        choice = rng.choice(["socket", "node", "node via reroute"])
        if choice == "socket":
            socket.default_value = value
            continue
        constant = tree.nodes.new("ShaderNodeValue" if kind == "VALUE" else "ShaderNodeRGB")
        constant.outputs[0].default_value = value
        source = constant.outputs[0]
        if choice == "node via reroute":
            reroute = tree.nodes.new("NodeReroute")
            tree.links.new(source, reroute.inputs[0])
            source = reroute.outputs[0]
        tree.links.new(source, socket)
    for name, _ in outputs:
        source = wrapper.outputs[name]
        if rng.random() < 0.5:
            reroute = tree.nodes.new("NodeReroute")
            tree.links.new(source, reroute.inputs[0])
            source = reroute.outputs[0]
        else:
            passing = tree.nodes.new("ShaderNodeAddShader")
            dropped = tree.nodes.new(
                "ShaderNodeVolumeScatter" if name == "Volume" else "ShaderNodeBsdfDiffuse"
            )
            if name == "Volume":
                dropped.inputs["Density"].default_value = 10.0
            tree.links.new(source, passing.inputs[0])
            tree.links.new(dropped.outputs[0], passing.inputs[1])
            passing.mute = True
            source = passing.outputs[0]
        tree.links.new(source, output.inputs[name])
    return group
