"""The evaluated depsgraph to the core's inputs: world-space triangles with object ids,
camera, sun, medium, render settings and style, ready for `crepuscular.render_arrays`.

Geometry comes from `depsgraph.object_instances`, so modifiers, geometry-nodes output,
collection and particle instances, curves and text (as their evaluated meshes) all count.
Vertices and triangles are read with `foreach_get` into numpy. Object-space triangles of
static meshes (no modifiers, no shape keys) are cached across frames, keyed by the mesh, and
only their matrices are applied again; `GeometryCache.invalidate` drops what changed.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import bpy
import numpy as np

import crepuscular

from . import node_links
from .cutouts import MaskTable

#: Object types whose evaluated mesh occludes the sun. Curves, surfaces and text reach the
#: depsgraph's instances as their evaluated meshes (type MESH, instanced by the curve).
#: Hair curves (CURVES) are drawn as ribbons of their radius (`curves_arrays`), point clouds
#: (POINTCLOUD, such as geometry nodes' points) as spheres of theirs (`pointcloud_arrays`).
GEOMETRY_TYPES = {"MESH", "META", "CURVES", "POINTCLOUD"}
#: Both visibility flags: a triangle that blocks the sun and that the camera sees.
BOTH = crepuscular.BLOCKS_SUN | crepuscular.SEEN_BY_CAMERA
#: Object types without texture coordinates, which no alpha mask cuts.
UNCUT_TYPES = {"CURVES", "POINTCLOUD"}
#: Object types drawn for the sun and camera as each instance's space sees them.
SEEN_TYPES = {"CURVES", "POINTCLOUD"}
#: The radius Blender gives a point cloud's points without a radius attribute; Cycles
#: draws them at it (a render of such a point measured 0.00996).
DEFAULT_POINT_RADIUS = 0.01
#: The volume shader nodes a fog object's closures are read from (`_volume_closures`).
VOLUME_SHADERS = {
    "ShaderNodeVolumeScatter",
    "ShaderNodeVolumeAbsorption",
    "ShaderNodeVolumePrincipled",
    "ShaderNodeVolumeCoefficients",
}
#: Directions over a wide sun's disc in the viewport preview (renders take
#: `crepuscular.SUN_DISC_SAMPLES`): its penumbrae in four steps, at a quarter of the cost.
PREVIEW_DISC_SAMPLES = 4
LUMINANCE = node_links.LUMINANCE


class ExportError(ValueError):
    """The scene cannot be exported; the message names the object or setting at fault."""


class NonFiniteGeometry(ValueError):
    """Strand or point positions or radii that are NaN or infinite: the object is left out
    of the frame and named in a note, as an object with NaN vertices is."""


@dataclass
class MeshArrays:
    """Object-space vertices (N, 3) float32 and triangles (M, 3) uint32 of one mesh. For a
    mesh with cut materials (`cutouts`), a vertex per triangle corner, with its texture
    coordinates (N, 2) and each triangle's material slot (M,)."""

    positions: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray | None = None
    slots: np.ndarray | None = None
    #: Per triangle, `crepuscular.BLOCKS_SUN`, `SEEN_BY_CAMERA`, both or neither where the
    #: arrays are drawn per view (strand ribbons, points' spheres); None: both.
    visibility: np.ndarray | None = None


@dataclass
class GeometryCache:
    """Object-space triangles of static meshes, and the alpha of cutout masks, reused across
    frames."""

    meshes: dict[str, MeshArrays] = field(default_factory=dict)
    #: By `MaskSource.pixels`, whose first item is the image's name.
    masks: dict[tuple[str, str, bool, float | None], np.ndarray] = field(default_factory=dict)
    hits: int = 0
    misses: int = 0

    def invalidate(self, names: set[str] | None = None) -> None:
        """Drops the entries of these mesh names, or everything when `names` is None."""
        if names is None:
            self.meshes.clear()
            self.masks.clear()
        else:
            for key in [k for k in self.meshes if k.split(_CUT_KEY)[0] in names]:
                del self.meshes[key]

    def invalidate_images(self, names: set[str]) -> None:
        """Drops the masks read from these images."""
        for pixels in [key for key in self.masks if key[0] in names]:
            del self.masks[pixels]


#: Separates a mesh's name from the UV maps of its loop-split arrays in cache keys.
_CUT_KEY = "\x00"


@dataclass
class Geometry:
    #: Relative to `origin`.
    positions: np.ndarray
    triangles: np.ndarray
    object_ids: np.ndarray
    #: Object ids that take noise holes.
    hole_ids: list[int]
    #: Object id -> original object name, for messages and tests.
    names: dict[int, str]
    #: The world point the positions are relative to (float64).
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: Alpha cutouts, where a material cuts: texture coordinates per position, a mask
    #: index per triangle (-1: none) and the masks.
    uvs: np.ndarray | None = None
    triangle_masks: np.ndarray | None = None
    masks: list[crepuscular.AlphaMask] = field(default_factory=list)
    #: Per triangle, whether it blocks the sun and whether the camera sees it
    #: (`crepuscular.BLOCKS_SUN`, `crepuscular.SEEN_BY_CAMERA`); None where all do both.
    visibility: np.ndarray | None = None
    #: What the export could not map (transparency of other kinds).
    notes: list[str] = field(default_factory=list)


@dataclass
class FrameInputs:
    """Everything one `render_arrays` call takes, plus what to tell the user."""

    kwargs: dict[str, Any]
    sun: str
    notes: list[str]
    geometry: Geometry
    #: What in Blender feeds each part of the scene description ("medium", "render" ...),
    #: for the renderer's errors: `source_of`.
    sources: dict[str, str] = field(default_factory=dict)

    def source_of(self, field_path: str) -> str | None:
        """The Blender data behind the renderer's scene field `field_path` (as its
        invalid-input errors name it), or None."""
        head = field_path.split(".")[0].split("[")[0]
        return self.sources.get(head)


def mesh_arrays(mesh: bpy.types.Mesh) -> MeshArrays:
    """A mesh's vertices and loop triangles, read with `foreach_get`."""
    positions = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", positions)
    triangles = np.empty(len(mesh.loop_triangles) * 3, dtype=np.uint32)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    return MeshArrays(positions.reshape(-1, 3), triangles.reshape(-1, 3))


def _static_key(obj: bpy.types.Object) -> str | None:
    """The cache key of an evaluated object whose mesh is its original data, else None."""
    original = obj.original
    if obj.type != "MESH" or original.type != "MESH" or len(original.modifiers) > 0:
        return None
    data = original.data
    if data.shape_keys is not None or data.animation_data is not None:
        return None
    return data.name_full


def curves_arrays(curves: bpy.types.Curves, seen: SunAndCamera | None = None) -> MeshArrays:
    """A hair curves datablock along the Catmull-Rom splines of its strands (the hair
    curves' default type) at each point's radius; without a radius attribute, nothing, as
    Cycles draws nothing. With `seen` (the sun and camera in the object's space), as a
    ribbon facing each (`crepuscular.strand_ribbons`): each view sees the strand's exact
    width and ends, as Cycles draws it; without, as tubes (`crepuscular.strand_tubes`)."""
    count = len(curves.points)
    if count == 0 or "radius" not in curves.attributes:
        return MeshArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    points = np.empty(count * 3, dtype=np.float32)
    curves.points.foreach_get("position", points)
    radius = np.empty(count, dtype=np.float32)
    curves.attributes["radius"].data.foreach_get("value", radius)
    offsets = np.empty(len(curves.curves) + 1, dtype=np.int64)
    curves.curve_offset_data.foreach_get("value", offsets)
    return _strand_arrays(points.reshape(-1, 3), np.diff(offsets), radius, seen)


def _strand_arrays(
    points: np.ndarray, counts: np.ndarray, radii: np.ndarray, seen: SunAndCamera | None
) -> MeshArrays:
    """Strands as ribbons for the sun and camera of `seen`, or as tubes without."""
    if not (np.isfinite(points).all() and np.isfinite(radii).all()):
        raise NonFiniteGeometry("NaN or infinite strand points or radii")
    steps = crepuscular.CATMULL_ROM_STEPS
    if seen is None:
        return MeshArrays(*crepuscular.strand_tubes(points, counts, radii, catmull_rom=steps))
    positions, triangles, flags = crepuscular.strand_ribbons(
        points, counts, radii, catmull_rom=steps, **seen.view_arguments()
    )
    return MeshArrays(positions, triangles, visibility=flags)


def pointcloud_arrays(
    pointcloud: bpy.types.PointCloud, seen: SunAndCamera | None = None
) -> MeshArrays:
    """A point cloud as a sphere around each point (`crepuscular.point_spheres`), of the
    point's radius, or Blender's default radius where there is no radius attribute. With
    `seen` (the sun and camera in the object's space), each view gets the side of each
    sphere Cycles' rays can hit (`crepuscular.point_sphere_visibility`)."""
    count = len(pointcloud.points)
    positions = np.empty(count * 3, dtype=np.float32)
    if count:
        pointcloud.attributes["position"].data.foreach_get("vector", positions)
    radius = pointcloud.attributes.get("radius")
    if radius is None:
        radii = np.full(count, DEFAULT_POINT_RADIUS, dtype=np.float32)
    else:
        radii = np.empty(count, dtype=np.float32)
        radius.data.foreach_get("value", radii)
    centres = positions.reshape(-1, 3)
    if not (np.isfinite(centres).all() and np.isfinite(radii).all()):
        raise NonFiniteGeometry("NaN or infinite point positions or radii")
    spheres = MeshArrays(*crepuscular.point_spheres(centres, radii))
    if seen is not None:
        spheres.visibility = crepuscular.point_sphere_visibility(
            centres, radii, **seen.view_arguments()
        )
    return spheres


def particle_hair_arrays(
    obj: bpy.types.Object, render: bool, seen: SunAndCamera | None = None
) -> MeshArrays:
    """The legacy particle hair of an evaluated emitter (`particle_hair_strands`) as
    Catmull-Rom strands, drawn for `seen` (see `curves_arrays`): the ribbons 2 triangles a
    piece per view."""
    strands = particle_hair_strands(obj, render)
    if strands is None:
        return MeshArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    return _strand_arrays(*strands, seen)


def particle_hair_strands(
    obj: bpy.types.Object, render: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The legacy particle hair of an evaluated emitter, in its object space, as Cycles
    draws it, as points, points per strand and radii; None where it has none: each hair
    system (rendered as paths) whose modifier shows in this kind of render gives its
    children, or its parents where it has none, as Catmull-Rom strands through
    `co_hair`'s keys (2^steps + 1 of them, the render or the viewport steps); radii from
    the root to the tip radius, shaped by `shape` along the strand's length and scaled by
    half the radius scale, with a closed tip at 0. Each key is one Python call (0.5 µs;
    100,000 strands of 9 keys read in about 0.5 s)."""
    try:
        inverse = np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
    except np.linalg.LinAlgError:
        # An emitter scaled to nothing flattens its hair with it, and Cycles draws none.
        return None
    points: list[np.ndarray] = []
    counts: list[np.ndarray] = []
    radii: list[np.ndarray] = []
    for modifier in obj.modifiers:
        shown = modifier.show_render if render else modifier.show_viewport
        if modifier.type != "PARTICLE_SYSTEM" or not shown:
            continue
        system = modifier.particle_system
        settings = system.settings
        if settings.type != "HAIR" or settings.render_type != "PATH":
            continue
        parents, children = len(system.particles), len(system.child_particles)
        if not render:
            children = int(children * settings.display_percentage / 100)
        first = parents if settings.child_type != "NONE" and children > 0 else 0
        keys = (1 << (settings.render_step if render else settings.display_step)) + 1
        if settings.kink == "SPIRAL":
            keys += settings.kink_extra_steps
        strands = parents + children - first
        if strands <= 0:
            continue
        co_hair = system.co_hair
        world = np.fromiter(
            (
                value
                for number in range(first, parents + children)
                for step in range(keys)
                for value in co_hair(obj, particle_no=number, step=step)
            ),
            dtype=np.float64,
            count=strands * keys * 3,
        ).reshape(strands, keys, 3)
        local = world @ inverse[:3, :3].T + inverse[:3, 3]
        steps = np.linalg.norm(np.diff(local, axis=1), axis=2)
        along = np.concatenate([np.zeros((strands, 1)), np.cumsum(steps, axis=1)], axis=1)
        lengths = along[:, -1:]
        time = np.divide(along, lengths, out=np.zeros_like(along), where=lengths > 0)
        scale = 0.5 * settings.radius_scale
        radius = _hair_shape(
            settings.shape, scale * settings.root_radius, scale * settings.tip_radius, time
        )
        if settings.use_close_tip:
            radius[:, -1] = 0.0
        points.append(local.reshape(-1, 3))
        counts.append(np.full(strands, keys))
        radii.append(radius.ravel())
    if not points:
        return None
    return np.concatenate(points), np.concatenate(counts), np.concatenate(radii)


def _hair_shape(shape: float, root: float, tip: float, time: np.ndarray) -> np.ndarray:
    """Cycles' radius of particle hair at `time` (0 at the root, 1 at the tip, by length):
    from `root` to `tip`, bent by `shape` in [-1, 1]."""
    falling = 1.0 - time
    if shape < 0.0:
        falling = falling ** (1.0 + shape)
    elif shape > 0.0:
        # At 1 the exponent is infinite: full radius at the root only, as Cycles' powf.
        falling = falling ** (1.0 / (1.0 - shape) if shape < 1.0 else np.inf)
    return falling * (root - tip) + tip


def cut_mesh_arrays(mesh: bpy.types.Mesh, slot_uv_maps: tuple[str, ...]) -> MeshArrays:
    """`mesh_arrays` with a vertex per triangle corner, each with the texture coordinates
    of the UV map its triangle's slot reads (`slot_uv_maps`, "" for the default map)."""
    loops = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    slots = np.empty(len(mesh.loop_triangles), dtype=np.int64)
    mesh.loop_triangles.foreach_get("material_index", slots)
    # Cycles takes a slot index past the last slot as the last.
    slots = np.clip(slots, 0, max(len(slot_uv_maps) - 1, 0))
    loop_vertices = np.empty(len(mesh.loops), dtype=np.int64)
    mesh.loops.foreach_get("vertex_index", loop_vertices)
    coordinates = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", coordinates)
    corners = loops.reshape(-1, 3)
    positions = coordinates.reshape(-1, 3)[loop_vertices[corners]].reshape(-1, 3)
    uvs = np.zeros((len(corners), 3, 2), dtype=np.float32)
    for name in set(slot_uv_maps):
        layer = mesh.uv_layers.get(name) if name else None
        if layer is None:
            layer = next((uv for uv in mesh.uv_layers if uv.active_render), None)
        if layer is None:
            continue  # no UV map: Cycles reads the texture at (0, 0) too
        loop_uvs = np.empty(len(mesh.loops) * 2, dtype=np.float32)
        layer.uv.foreach_get("vector", loop_uvs)
        rows = np.isin(slots, [k for k, uv in enumerate(slot_uv_maps) if uv == name])
        uvs[rows] = loop_uvs.reshape(-1, 2)[corners[rows]]
    triangles = np.arange(len(positions), dtype=np.uint32).reshape(-1, 3)
    return MeshArrays(positions, triangles, uvs.reshape(-1, 2), slots)


def _object_arrays(
    obj: bpy.types.Object,
    cache: GeometryCache | None,
    slot_uv_maps: tuple[str, ...] | None = None,
    seen: SunAndCamera | None = None,
) -> MeshArrays | None:
    """The object's mesh arrays; loop-split with texture coordinates where `slot_uv_maps`
    (the UV map of each material slot) is given; hair curves and point clouds drawn for
    `seen` (the sun and camera in the object's space, `curves_arrays`,
    `pointcloud_arrays`)."""
    key = _static_key(obj) if cache is not None else None
    if key is not None and slot_uv_maps is not None:
        key = key + _CUT_KEY + "|".join(slot_uv_maps)
    if key is not None and cache is not None:
        cached = cache.meshes.get(key)
        valid = cached is not None and (
            len(cached.positions) == len(obj.data.vertices)
            if slot_uv_maps is None
            else len(cached.triangles) == len(obj.data.loop_triangles)
        )
        if cached is not None and valid:
            cache.hits += 1
            return cached

    def read(mesh: bpy.types.Mesh) -> MeshArrays:
        if slot_uv_maps is None:
            return mesh_arrays(mesh)
        return cut_mesh_arrays(mesh, slot_uv_maps)

    if obj.type == "MESH":
        arrays = read(obj.data)
    elif obj.type == "CURVES":
        arrays = curves_arrays(obj.data, seen)
    elif obj.type == "POINTCLOUD":
        arrays = pointcloud_arrays(obj.data, seen)
    else:
        mesh = obj.to_mesh()
        try:
            arrays = None if mesh is None else read(mesh)
        finally:
            obj.to_mesh_clear()
    if key is not None and cache is not None and arrays is not None:
        cache.misses += 1
        cache.meshes[key] = arrays
    return arrays


#: Geometry shared by instances: the object's data (or the object, for hair curves and its
#: particle hair), which of its geometry ("data" or particle "hair"), the UV maps its cut
#: slots read, and the sun and camera in its space (strands and points only).
_MeshKey = tuple[int, str, tuple[str, ...] | None, tuple[float, ...] | None]


@dataclass(frozen=True)
class SunAndCamera:
    """The sun's travel direction and the camera (a pinhole's position, or an orthographic
    camera's view direction), which strands are drawn for (`crepuscular.strand_ribbons`)
    and points are culled for (`crepuscular.point_sphere_visibility`)."""

    sun: np.ndarray
    camera: np.ndarray
    orthographic: bool

    def in_space_of(self, matrix_world: np.ndarray) -> SunAndCamera | None:
        """The same in an object's space; None where its matrix flattens space."""
        linear, offset = matrix_world[:3, :3], matrix_world[:3, 3]
        try:
            sun = np.linalg.solve(linear, self.sun)
            camera = np.linalg.solve(
                linear, self.camera if self.orthographic else self.camera - offset
            )
        except np.linalg.LinAlgError:
            return None
        if not (np.isfinite(sun).all() and np.isfinite(camera).all()):
            return None
        return SunAndCamera(sun, camera, self.orthographic)

    def key(self) -> tuple[float, ...]:
        """Rounded, for sharing one build between instances that see alike."""
        sun = self.sun / np.linalg.norm(self.sun)
        return (*np.round(sun, 6), *np.round(self.camera, 6), float(self.orthographic))

    def view_arguments(self) -> dict[str, np.ndarray]:
        """`crepuscular.strand_ribbons` and `point_sphere_visibility` keywords."""
        return {"sun": self.sun, "view" if self.orthographic else "eye": self.camera}


#: The core's vertex indices are 32-bit.
MAX_VERTICES = 2**32 - 1
#: Bytes the export and the core hold per vertex and per triangle, about (world positions,
#: a copy while concatenating, indices and object ids, and the core's own copies).
BYTES_PER_VERTEX = 3 * 4 * 3
BYTES_PER_TRIANGLE = (3 * 4 + 4) * 3


def available_memory() -> int | None:
    """Physical memory available now, in bytes, where the system says (Linux)."""
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_memory(vertices: int, triangles: int, name: str) -> None:
    if vertices < 1_000_000:
        return
    need = vertices * BYTES_PER_VERTEX + triangles * BYTES_PER_TRIANGLE
    free = available_memory()
    if free is not None and need > free:
        raise ExportError(
            f"geometry too large for memory: {vertices} vertices and {triangles} triangles "
            f"so far (at object '{name}') need about {need / 2**30:.1f} GiB, "
            f"{free / 2**30:.1f} GiB are free"
        )


def _hidden_in_render(obj: bpy.types.Object) -> bool:
    """Render visibility for a viewport depsgraph: the object or a collection hides it."""
    if obj.hide_render:
        return True
    return bool(obj.users_collection) and all(c.hide_render for c in obj.users_collection)


@dataclass(frozen=True)
class LightLinking:
    """The objects a light's linking collection (blockers: shadow linking; receivers:
    light linking) includes and excludes, by original name: with any included, only those
    take part, less the excluded; with only excluded, everything else does (Blender's
    rules). A child collection's state applies to every object in it."""

    included: frozenset[str]
    excluded: frozenset[str]
    #: Whether no object takes part: the blockers of a light that casts no shadows.
    takes_none: bool = False

    @classmethod
    def of_blockers(cls, light: bpy.types.Object) -> LightLinking | None:
        """The light object's blocker collection, or None where it has none (all block);
        none block where the light casts no shadows (its Cast Shadow off)."""
        if not light.original.data.use_shadow:
            return cls(frozenset(), frozenset(), takes_none=True)
        return cls._of(light.original.light_linking.blocker_collection)

    @classmethod
    def of_receivers(cls, light: bpy.types.Object) -> LightLinking | None:
        """The light object's receiver collection, or None where it has none (all receive)."""
        return cls._of(light.original.light_linking.receiver_collection)

    @classmethod
    def _of(cls, collection: bpy.types.Collection | None) -> LightLinking | None:
        if collection is None:
            return None
        included: set[str] = set()
        excluded: set[str] = set()
        # collection_objects and collection_children hold the link states of objects and
        # children, in their order.
        for obj, entry in zip(collection.objects, collection.collection_objects, strict=True):
            state = entry.light_linking.link_state
            (included if state == "INCLUDE" else excluded).add(obj.name_full)
        children = zip(collection.children, collection.collection_children, strict=True)
        for child, entry in children:
            names = {o.name_full for o in child.all_objects}
            (included if entry.light_linking.link_state == "INCLUDE" else excluded).update(names)
        return cls(frozenset(included), frozenset(excluded))

    def contains(self, chain: list[bpy.types.Object]) -> bool:
        """Whether an instance (its object, and its instancer if any) takes part."""
        names = {o.original.name_full for o in chain}
        if self.takes_none or names & self.excluded:
            return False
        return not self.included or bool(names & self.included)


def blocks_sun(chain: list[bpy.types.Object], blockers: LightLinking | None) -> bool:
    """Whether an instance (its object, and its instancer if any) blocks the sun: Casts
    Shafts Off on either, no; On on either, yes; else by Shadow ray visibility of both and
    the sun's shadow linking."""
    choices = [_casts(o) for o in chain]
    if False in choices:
        return False
    if True in choices:
        return True
    linked = blockers is None or blockers.contains(chain)
    return linked and all(o.visible_shadow for o in chain)


def _casts(obj: bpy.types.Object) -> bool | None:
    """The object's own choice: True/False when forced, None to follow ray visibility."""
    mode = obj.original.crepuscular.casts_shafts
    return None if mode == "auto" else mode == "on"


def export_geometry(
    depsgraph: bpy.types.Depsgraph,
    *,
    cache: GeometryCache | None = None,
    exclude: set[str] | frozenset[str] = frozenset(),
    origin: np.ndarray | None = None,
    seen: SunAndCamera | None = None,
    blockers: LightLinking | None = None,
) -> Geometry:
    """Triangles of everything that casts shafts in `depsgraph`, relative to the world point
    `origin` (default the world's origin): the camera's position keeps float32 positions
    precise however far the scene lies from the world's origin.

    An instance casts unless it or its instancer is set to Off; set to Auto, it follows
    Blender's Shadow ray visibility of both, and the sun's shadow linking (`blockers`).
    With a viewport depsgraph, objects hidden in renders are left out too. `exclude` holds
    original object names (the fog box).
    `seen`, the sun and camera in world space, is what hair strands and point clouds are
    drawn for (`curves_arrays`, `pointcloud_arrays`).
    """
    render_mode = depsgraph.mode == "RENDER"
    offset = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    names: dict[str, int] = {}
    holes: set[int] = set()
    # Decisions per (object, instancer) and meshes per evaluated mesh, so that thousands
    # of particle or geometry-nodes instances of one mesh cost one lookup each; their
    # matrices are then applied in one batch per mesh.
    decisions: dict[tuple[str, str | None], tuple[int, int] | None] = {}
    # Per object, its slots' mask indices and UV maps where a material cuts.
    table = MaskTable(kept=cache.masks if cache is not None else {})
    cuts: dict[str, _SlotCuts | None] = {}
    meshes: dict[_MeshKey, MeshArrays | None] = {}
    groups: dict[tuple[_MeshKey, int, int, _SlotCuts | None], list[Any]] = {}
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type == "VOLUME" and (render_mode or not _hidden_in_render(obj.original)):
            note = (
                f"object '{obj.name}' is a Volume object: its grids are not rendered (the "
                "medium is the scene's Medium setting)"
            )
            if note not in table.notes:
                table.notes.append(note)
        if obj.type not in GEOMETRY_TYPES:
            continue
        parent = instance.parent if instance.is_instance else None
        key = (obj.original.name_full, None if parent is None else parent.original.name_full)
        if key not in decisions:
            decisions[key] = _decide(obj, parent, render_mode, exclude, names, holes, blockers)
        decided = decisions[key]
        if decided is None:
            continue
        object_id, flags = decided
        hair = instance.show_particles and len(obj.particle_systems) > 0
        if not (instance.show_self or hair):
            continue  # an emitter or instancer that Cycles does not render either
        local_seen = None
        if (obj.type in SEEN_TYPES or hair) and seen is not None:
            local_seen = seen.in_space_of(np.array(instance.matrix_world, dtype=np.float64))
        seen_key = None if local_seen is None else local_seen.key()
        if hair:
            hair_key: _MeshKey = (obj.as_pointer(), "hair", None, seen_key)
            if hair_key not in meshes:
                meshes[hair_key] = _finite_or_named(
                    f"the particle hair of object '{obj.name}'",
                    table.notes,
                    particle_hair_arrays,
                    obj,
                    render_mode,
                    local_seen,
                )
            hair_arrays = meshes[hair_key]
            if hair_arrays is not None and len(hair_arrays.triangles):
                groups.setdefault((hair_key, object_id, flags, None), []).append(
                    instance.matrix_world.copy()
                )
        if not instance.show_self:
            continue
        if obj.name_full not in cuts:
            cuts[obj.name_full] = None if obj.type in UNCUT_TYPES else _slot_cuts(obj, table)
        cut = cuts[obj.name_full]
        pointer = obj.data.as_pointer() if obj.type == "MESH" else obj.as_pointer()
        mesh_key = (
            pointer,
            "data",
            None if cut is None else cut.uv_maps,
            seen_key if obj.type in SEEN_TYPES else None,
        )
        if mesh_key not in meshes:
            meshes[mesh_key] = _finite_or_named(
                f"object '{obj.name}'",
                table.notes,
                _object_arrays,
                obj,
                cache,
                mesh_key[2],
                local_seen,
            )
        arrays = meshes[mesh_key]
        if arrays is None or len(arrays.triangles) == 0:
            continue
        groups.setdefault((mesh_key, object_id, flags, cut), []).append(
            instance.matrix_world.copy()
        )
    positions: list[np.ndarray] = []
    triangles: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    triangle_masks: list[np.ndarray] = []
    visibility: list[np.ndarray] = []
    any_cut = any(cut is not None for _, _, _, cut in groups)
    base = 0
    triangle_total = 0
    for (mesh_key, object_id, flags, cut), matrices in groups.items():
        arrays = meshes[mesh_key]
        if arrays is None:  # never grouped; keeps the type checker informed
            continue
        count, vertices = len(matrices), len(arrays.positions)
        if base + count * vertices > MAX_VERTICES:
            raise ExportError(
                f"geometry too large: more than {MAX_VERTICES} vertices by object "
                f"'{_name_of(names, object_id)}' (the core indexes vertices with 32 bits)"
            )
        triangle_total += count * len(arrays.triangles)
        _check_memory(base + count * vertices, triangle_total, _name_of(names, object_id))
        stack = np.array(matrices, dtype=np.float64).reshape(count, 4, 4)
        world = np.einsum("kij,nj->kni", stack[:, :3, :3], arrays.positions.astype(np.float64))
        world += stack[:, None, :3, 3] - offset
        # NaN or infinite vertices or transforms would fail the whole frame, naming no
        # object: those placements are left out and named.
        finite = np.isfinite(world).all(axis=(1, 2))
        if not finite.all():
            table.notes.append(
                f"object '{_name_of(names, object_id)}': {int((~finite).sum())} of its {count} "
                "placements have NaN or infinite points or transforms; left out"
            )
            world, count = world[finite], int(finite.sum())
            if count == 0:
                continue
        offsets = base + vertices * np.arange(count, dtype=np.uint32)
        positions.append(world.reshape(-1, 3).astype(np.float32))
        triangles.append((arrays.triangles[None] + offsets[:, None, None]).reshape(-1, 3))
        ids.append(np.full(count * len(arrays.triangles), object_id, dtype=np.uint32))
        own = flags if arrays.visibility is None else arrays.visibility & flags
        if cut is not None and arrays.slots is not None and any(r != BOTH for r in cut.rays):
            # Materials that Light Path shows to some rays only.
            own = np.asarray(cut.rays, dtype=np.uint8)[arrays.slots] & own
        visibility.append(
            np.broadcast_to(own, (count, len(arrays.triangles))).reshape(-1).astype(np.uint8)
        )
        if any_cut:
            if cut is None or arrays.uvs is None or arrays.slots is None:
                uvs.append(np.zeros((count * vertices, 2), dtype=np.float32))
                triangle_masks.append(np.full(count * len(arrays.triangles), -1, np.int64))
            else:
                per_slot = np.asarray(cut.masks, dtype=np.int64)
                masks_here = per_slot[arrays.slots]
                uvs_here = _mapped_uvs(arrays.uvs, arrays.slots, cut.uv_transforms)
                # NaN texture coordinates would fail the frame, naming no object: the
                # triangles that read them cast as opaque instead, and are named.
                finite = np.isfinite(uvs_here.reshape(-1, 3, 2)).all(axis=(1, 2))
                if not finite.all():
                    note = (
                        f"object '{_name_of(names, object_id)}': NaN or infinite texture "
                        "coordinates; the triangles with them cast as opaque"
                    )
                    if note not in table.notes:
                        table.notes.append(note)
                    masks_here = np.where(finite, masks_here, -1)
                    uvs_here = np.where(np.repeat(finite, 3)[:, None], uvs_here, 0.0)
                uvs.append(np.tile(uvs_here.astype(np.float32), (count, 1)))
                triangle_masks.append(np.tile(masks_here, count))
        base += count * vertices
    if not positions:
        return Geometry(
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.uint32),
            np.zeros(0, np.uint32),
            [],
            {},
            offset,
            notes=table.notes,
        )
    geometry = Geometry(
        np.ascontiguousarray(np.concatenate(positions)),
        np.ascontiguousarray(np.concatenate(triangles), dtype=np.uint32),
        np.ascontiguousarray(np.concatenate(ids)),
        sorted(holes),
        {v: k for k, v in names.items()},
        offset,
        notes=table.notes,
    )
    flags_all = np.concatenate(visibility)
    if (flags_all != BOTH).any():
        geometry.visibility = flags_all
    if any_cut:
        geometry.uvs = np.concatenate(uvs)
        geometry.triangle_masks = np.concatenate(triangle_masks)
        try:
            geometry.masks = table.masks()
        except ValueError as error:
            raise ExportError(f"alpha cutout: {error}") from error
    return geometry


def _finite_or_named(
    what: str, notes: list[str], build: Callable[..., MeshArrays | None], *args: Any
) -> MeshArrays | None:
    """`build(*args)`'s arrays, or None with a note naming `what` where its strands or
    points are not finite."""
    try:
        return build(*args)
    except NonFiniteGeometry as error:
        note = f"{what}: {error}; left out"
        if note not in notes:
            notes.append(note)
        return None


@dataclass(frozen=True)
class _SlotCuts:
    """Per material slot of an object, its mask index in the export (-1: none) and the UV
    map the mask reads ("" for the default)."""

    masks: tuple[int, ...]
    uv_maps: tuple[str, ...]
    #: The affine map of the coordinates each slot's texture reads through Mapping nodes
    #: (`MaskSource.uv_transform`), or None.
    uv_transforms: tuple[tuple[float, ...] | None, ...]
    #: Which rays see each slot's surface (`MaskSource.rays`).
    rays: tuple[int, ...]


def _slot_cuts(obj: bpy.types.Object, table: MaskTable) -> _SlotCuts | None:
    """The object's slots' masks, or None where no material of it cuts."""
    found = [table.add(slot.material) for slot in obj.material_slots]
    if all(index < 0 for index, _ in found):
        return None
    sources = [table.sources[i] if i >= 0 else None for i, _ in found]
    return _SlotCuts(
        tuple(i for i, _ in found),
        tuple(uv for _, uv in found),
        tuple(source.uv_transform if source else None for source in sources),
        tuple(source.rays if source else BOTH for source in sources),
    )


def _mapped_uvs(
    uvs: np.ndarray, slots: np.ndarray, transforms: tuple[tuple[float, ...] | None, ...]
) -> np.ndarray:
    """`uvs` (three rows a triangle) mapped per triangle by its slot's transform; `uvs`
    itself, which a cache may hold, where no slot maps them."""
    if all(transform is None for transform in transforms):
        return uvs
    mapped = uvs.astype(np.float64).reshape(-1, 3, 2)
    for slot, transform in enumerate(transforms):
        if transform is None:
            continue
        rows = slots == slot
        matrix = np.array(transform, dtype=np.float64).reshape(2, 3)
        mapped[rows] = mapped[rows] @ matrix[:, :2].T + matrix[:, 2]
    return mapped.reshape(-1, 2)


def _name_of(names: dict[str, int], object_id: int) -> str:
    return next((name for name, i in names.items() if i == object_id), "?")


def _decide(
    obj: bpy.types.Object,
    parent: bpy.types.Object | None,
    render_mode: bool,
    exclude: set[str] | frozenset[str],
    names: dict[str, int],
    holes: set[int],
    blockers: LightLinking | None = None,
) -> tuple[int, int] | None:
    """The object id of an (object, instancer) pair and its visibility flags (whether it
    blocks the sun, whether the camera sees it), or None when it does neither."""
    if obj.original.name_full in exclude:
        return None
    chain = [obj] if parent is None else [obj, parent]
    if not render_mode and any(_hidden_in_render(o.original) for o in chain):
        return None
    blocks = blocks_sun(chain, blockers)
    seen = all(o.visible_camera for o in chain)
    flags = crepuscular.BLOCKS_SUN * blocks + crepuscular.SEEN_BY_CAMERA * seen
    if flags == 0:
        return None
    owner = chain[-1].original
    object_id = names.setdefault(owner.name_full, len(names) + 1)
    if blocks and any(o.original.crepuscular.takes_holes for o in chain):
        holes.add(object_id)
    return object_id, flags


def column_major(matrix: Any) -> list[float]:
    return [float(v) for v in np.array(matrix, dtype=np.float64).T.ravel()]


def render_size(scene: bpy.types.Scene, divisor: int = 1) -> tuple[int, int]:
    """The render's whole frame in pixels, as Blender computes it, divided for previews."""
    render = scene.render
    width = render.resolution_x * render.resolution_percentage // 100
    height = render.resolution_y * render.resolution_percentage // 100
    return max(1, width // divisor), max(1, height // divisor)


@dataclass(frozen=True)
class Region:
    """The render region (*Render Region*) in the frame's pixels, from its top-left corner,
    and whether the render is cropped to it (else the frame keeps its size around it)."""

    x: int
    y: int
    width: int
    height: int
    cropped: bool


def render_region(scene: bpy.types.Scene) -> Region | None:
    """The render region F12 renders, None for the whole frame. Its pixels are Blender's:
    the border's fractions of the frame, truncated (y from the bottom)."""
    render = scene.render
    corners = (render.border_min_x, render.border_min_y, render.border_max_x, render.border_max_y)
    if not render.use_border or corners == (0.0, 0.0, 1.0, 1.0):
        return None
    width, height = render_size(scene)
    left, right = int(corners[0] * width), int(corners[2] * width)
    bottom, top = int(corners[1] * height), int(corners[3] * height)
    if right <= left or top <= bottom:
        raise ExportError(
            f"scene.render.border_min/max: the render region is empty at {width}x{height} pixels"
        )
    return Region(left, height - top, right - left, top - bottom, render.use_crop_to_border)


def output_size(scene: bpy.types.Scene) -> tuple[int, int]:
    """The size of what F12 renders: the region where the render is cropped to it."""
    region = render_region(scene)
    if region is not None and region.cropped:
        return region.width, region.height
    return render_size(scene)


def camera_dict(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    divisor: int = 1,
    region: Region | None = None,
) -> dict[str, Any]:
    """The scene camera in the core's terms (sensor fit, shift, clip, orthographic, pixel
    aspect), its window the frame's `region` where given."""
    if scene.camera is None:
        raise ExportError(f"scene '{scene.name}' has no camera (scene.camera)")
    obj = scene.camera.evaluated_get(depsgraph)
    if obj.type != "CAMERA":
        raise ExportError(f"scene.camera: '{obj.name}' is a {obj.type}, not a camera")
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    # Blender renders with the camera matrix normalized: scale does not change the view.
    for axis in range(3):
        length = np.linalg.norm(matrix[:3, axis])
        if length == 0 or not np.isfinite(length):
            raise ExportError(f"camera '{obj.name}': its matrix has a zero or non-finite axis")
        matrix[:3, axis] /= length
    data = obj.data
    fit = data.sensor_fit.lower()
    if data.type == "PERSP":
        projection: dict[str, Any] = {
            "kind": "perspective",
            "focal_length": float(data.lens),
            "sensor_width": float(data.sensor_width),
            "sensor_height": float(data.sensor_height),
            "sensor_fit": fit,
            "shift_x": float(data.shift_x),
            "shift_y": float(data.shift_y),
        }
    elif data.type == "ORTHO":
        projection = {
            "kind": "orthographic",
            "ortho_scale": float(data.ortho_scale),
            "sensor_fit": fit,
            "shift_x": float(data.shift_x),
            "shift_y": float(data.shift_y),
        }
    else:
        raise ExportError(
            f"camera '{data.name}': {data.type.lower()} cameras are not supported "
            "(perspective or orthographic only)"
        )
    width, height = render_size(scene, divisor)
    camera = {
        "world_from_camera": column_major(matrix),
        "projection": projection,
        "clip_start": float(data.clip_start),
        "clip_end": float(data.clip_end),
        "width": width,
        "height": height,
        "pixel_aspect": float(scene.render.pixel_aspect_x / scene.render.pixel_aspect_y),
    }
    if region is not None:
        camera["window"] = {
            "x": region.x,
            "y": region.y,
            "width": region.width,
            "height": region.height,
        }
    return camera


def shaft_suns(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """Sun lamps in the scene with shafts enabled, by name."""
    suns = [
        obj
        for obj in scene.objects
        if obj.type == "LIGHT" and obj.data.type == "SUN" and obj.data.crepuscular.enabled
    ]
    return sorted(suns, key=lambda obj: obj.name)


def sun_dict(sun: bpy.types.Object) -> dict[str, Any]:
    """Direction (the lamp's -Z), colour, strength and angle of an evaluated sun, and whether
    the fog dims its light, as Cycles lights with it: strength x 2^exposure, colour x
    blackbody colour when Temperature is on, undimmed when its Cast Shadow is off."""
    matrix = np.array(sun.matrix_world, dtype=np.float64)
    direction = -matrix[:3, 2]
    norm = np.linalg.norm(direction)
    if norm == 0 or not np.isfinite(norm):
        raise ExportError(f"sun '{sun.name}': its matrix has no usable -Z axis")
    light = sun.data
    color = np.array(light.color, dtype=np.float64)
    if light.use_temperature:
        color *= np.array(light.temperature_color, dtype=np.float64)
    return {
        "direction": (direction / norm).tolist(),
        "color": color.tolist(),
        "strength": float(light.energy) * 2.0 ** float(light.exposure),
        "angular_diameter": float(light.angle),
        # Cycles traces no shadow rays for a light whose Cast Shadow is off, through the
        # fog no more than through surfaces.
        "attenuated_by_medium": bool(light.use_shadow),
    }


def _constant(
    node: bpy.types.Node, name: str, groups: tuple[bpy.types.Node, ...], where: str
) -> Any:
    try:
        return node_links.constant(node, name, groups, where)
    except node_links.NodeLinkError as error:
        raise ExportError(str(error)) from error


def _density(node: bpy.types.Node, groups: tuple[bpy.types.Node, ...], where: str) -> float:
    """A volume shader's Density, which must be one value: the core's fog is homogeneous."""
    try:
        return float(node_links.constant(node, "Density", groups, where))
    except node_links.NodeLinkError as error:
        raise ExportError(
            f"{error}. The shafts' fog is homogeneous, one density throughout, so a texture's "
            "variation cannot be rendered: unlink Density, or set the scene's Stylized Shafts "
            "Medium to Custom and give its extinction there"
        ) from error


@dataclass
class _VolumeClosure:
    """One volume closure of a shader, already weighted: σs and σt per channel, and the
    anisotropy of its Henyey-Greenstein phase (0 where it only absorbs)."""

    scattering: np.ndarray
    extinction: np.ndarray
    anisotropy: float = 0.0


def _volume_closures(
    socket: bpy.types.NodeSocket,
    weight: float,
    where: str,
    notes: list[str],
    groups: tuple[bpy.types.Node, ...] = (),
) -> list[_VolumeClosure]:
    """The closures reaching the shader input `socket` (of a node nested in the group
    nodes `groups`), scaled by `weight`, as Cycles builds them: Volume Scatter σs = σt =
    color·density; Volume Absorption σt = (1 − color)·density; Principled Volume σs =
    color·density and σt = (color + (1 − color)(1 − √absorption))·density; Volume
    Coefficients σs = its scatter coefficients and σt = those plus its absorption
    coefficients; Add Shader sums its inputs, Mix Shader weights them by 1 − Fac and Fac;
    emission is left out with a note. Links are followed through reroutes, muted nodes and
    node groups (`node_links`). Other nodes, and inputs fed by other than constants, are
    named."""
    source = node_links.traced(socket, groups)
    if not source.is_linked or weight == 0:
        return []
    node, groups = source.node, source.groups
    kind = node.bl_idname
    if kind == "ShaderNodeAddShader":
        return [
            closure
            for shader in node.inputs[:2]
            for closure in _volume_closures(shader, weight, where, notes, groups)
        ]
    if kind == "ShaderNodeMixShader":
        fac = min(max(float(_constant(node, "Fac", groups, where)), 0.0), 1.0)
        first = _volume_closures(node.inputs[1], weight * (1 - fac), where, notes, groups)
        return first + _volume_closures(node.inputs[2], weight * fac, where, notes, groups)
    if kind == "ShaderNodeEmission":
        notes.append(f"'{node.name}' is ignored: shafts have no emission")
        return []
    if kind not in VOLUME_SHADERS:
        raise ExportError(
            f"{where}: the volume shader '{node.name}' is a {kind}; use Volume Scatter, "
            "Volume Absorption, Principled Volume or Volume Coefficients, or Add and Mix "
            "Shaders of them"
        )
    phase = getattr(node, "phase", "HENYEY_GREENSTEIN")
    if phase != "HENYEY_GREENSTEIN":
        raise ExportError(f"{where}: phase '{phase}' is not supported (Henyey-Greenstein)")
    if kind == "ShaderNodeVolumeCoefficients":
        absorbing = np.array(
            _constant(node, "Absorption Coefficients", groups, where), dtype=np.float64
        )
        scattering = np.maximum(np.array(_constant(node, "Scatter Coefficients", groups, where)), 0)
        if np.any(np.array(_constant(node, "Emission Coefficients", groups, where)) != 0):
            notes.append(f"the emission of '{node.name}' is ignored: shafts have no emission")
        scattering = scattering * weight
        extinction = scattering + np.maximum(absorbing, 0) * weight
        return [
            _VolumeClosure(
                scattering, extinction, float(_constant(node, "Anisotropy", groups, where))
            )
        ]
    color = np.maximum(np.array(_constant(node, "Color", groups, where)[:3], dtype=np.float64), 0)
    density = max(_density(node, groups, where), 0.0) * weight
    if kind == "ShaderNodeVolumeAbsorption":
        return [_VolumeClosure(np.zeros(3), np.maximum(1 - color, 0) * density)]
    anisotropy = float(_constant(node, "Anisotropy", groups, where))
    if kind == "ShaderNodeVolumeScatter":
        return [_VolumeClosure(color * density, color * density, anisotropy)]
    absorption = np.array(_constant(node, "Absorption Color", groups, where)[:3], dtype=np.float64)
    absorbed = np.maximum(1 - color, 0) * np.maximum(1 - np.sqrt(np.maximum(absorption, 0)), 0)
    for name in ("Emission Strength", "Blackbody Intensity"):
        if float(_constant(node, name, groups, where)) != 0:
            notes.append(f"{name} of '{node.name}' is ignored: shafts have no emission")
    return [_VolumeClosure(color * density, (color + absorbed) * density, anisotropy)]


def _mean_anisotropy(closures: list[_VolumeClosure], where: str, notes: list[str]) -> float:
    """The one Henyey-Greenstein anisotropy of the closures that scatter: theirs where they
    agree; else their mean weighted by scattering (luminance), with a note, since Cycles
    scatters by each lobe in proportion to its σs, which one lobe only approximates."""
    lobes = [c for c in closures if float(LUMINANCE @ c.scattering) > 0]
    if not lobes:
        return 0.0
    values = np.array([lobe.anisotropy for lobe in lobes])
    if np.allclose(values, values[0], rtol=0, atol=1e-6):
        return float(values[0])
    weights = np.array([float(LUMINANCE @ lobe.scattering) for lobe in lobes])
    mean = float(weights @ values / weights.sum())
    notes.append(
        f"{where}: scattering lobes of anisotropy {', '.join(f'{v:g}' for v in values)} are "
        f"rendered as one of {mean:.3g}, their mean weighted by scattering"
    )
    return mean


def fog_medium(fog: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> tuple[dict, list[str]]:
    """The medium of a fog object: a box mesh whose volume shader is a Volume Scatter,
    Volume Absorption or Principled Volume, or Add and Mix Shaders of them.

    The box is the object's matrix times its bounds. Coefficients are read as Cycles reads
    them (`_volume_closures`) and summed over the shader's closures, as Cycles sums them.
    Where σt is coloured it goes to the core per channel (`channel_extinction`, a pass per
    distinct value, and a note says so), with `extinction` its Rec. 709 luminance.
    """
    where = f"fog object '{fog.name}'"
    evaluated = fog.evaluated_get(depsgraph)
    if evaluated.type != "MESH":
        raise ExportError(f"{where}: must be a mesh box, not a {evaluated.type}")
    arrays = mesh_arrays(evaluated.data)
    if len(arrays.positions) == 0:
        raise ExportError(f"{where}: the mesh is empty")
    low, high = arrays.positions.min(axis=0), arrays.positions.max(axis=0)
    span = np.maximum(high - low, 1e-12)
    relative = (arrays.positions - low) / span
    if np.any(np.minimum(relative, 1 - relative) > 1e-4):
        raise ExportError(
            f"{where}: must be a box (every vertex on a corner of its bounds); "
            "other shapes cannot be mapped exactly"
        )
    if np.any(high - low <= 0):
        raise ExportError(f"{where}: the box is flat")
    cube = np.diag([*((high - low) / 2), 1.0])
    cube[:3, 3] = (high + low) / 2
    world_from_cube = np.array(evaluated.matrix_world, dtype=np.float64) @ cube
    material = evaluated.active_material
    if material is None or material.node_tree is None:
        raise ExportError(f"{where}: needs a material with a volume shader")
    output = material.node_tree.get_output_node("CYCLES")
    if output is None or not node_links.traced(output.inputs["Volume"]).is_linked:
        raise ExportError(f"{where}: material '{material.name}' has no Volume output link")
    where = f"{where}, material '{material.name}'"
    notes: list[str] = []
    closures = _volume_closures(output.inputs["Volume"], 1.0, where, notes)
    scattering = sum((closure.scattering for closure in closures), np.zeros(3))
    extinction = sum((closure.extinction for closure in closures), np.zeros(3))
    anisotropy = _mean_anisotropy(closures, where, notes)
    sigma_t = float(LUMINANCE @ extinction)
    medium: dict[str, Any] = {"extinction": sigma_t}
    if np.allclose(extinction, extinction[0], rtol=1e-6, atol=0):
        albedo = scattering / sigma_t if sigma_t > 0 else np.zeros(3)
    else:
        # σs = albedo·σt per channel, each channel scattered at its own σt.
        albedo = np.divide(scattering, extinction, out=np.zeros(3), where=extinction > 0)
        medium["channel_extinction"] = extinction.tolist()
        distinct = len(set(extinction.tolist()))
        notes.append(
            "Cycles' extinction here is coloured "
            f"({', '.join(f'{v:.4g}' for v in extinction)}): the shafts are scattered once "
            f"per channel value, {distinct} times"
        )
    return {
        **medium,
        "albedo": albedo.tolist(),
        "anisotropy": anisotropy,
        "extent": {"kind": "box", "world_from_cube": column_major(world_from_cube)},
    }, notes


def _unblurred_notes(scene: bpy.types.Scene) -> list[str]:
    """Notes for what Cycles blurs and the layers do not: the camera's depth of field and
    motion blur, which leave shafts sharp over a blurred beauty."""
    notes = []
    camera = scene.camera
    if camera is not None and camera.type == "CAMERA" and camera.data.dof.use_dof:
        notes.append(
            f"camera '{camera.name}' has depth of field: the layers are in focus throughout "
            "(defocus them by their depth layer to match the beauty)"
        )
    if scene.render.use_motion_blur:
        notes.append("motion blur is on: the layers are rendered at the frame's instant")
    return notes


def medium_dict(
    scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph
) -> tuple[dict[str, Any], list[str]]:
    settings = scene.crepuscular
    if settings.medium_source == "fog_object":
        if settings.fog_object is None:
            raise ExportError(
                "scene.crepuscular.fog_object: the medium comes from a fog object, but none is set"
            )
        return fog_medium(settings.fog_object, depsgraph)
    return {
        "extinction": float(settings.extinction),
        "albedo": [float(v) for v in settings.albedo],
        "anisotropy": float(settings.anisotropy),
    }, []


def settings_dict(light: Any, *, preview: bool = False) -> dict[str, Any]:
    downsample = int(light.downsample)
    return {
        "method": light.method,
        "shadow_map_size": int(light.shadow_map_size),
        "bases": int(light.bases),
        "exact_ray_ends": light.exact_ray_ends,
        "steps": int(light.steps),
        "max_distance": float(light.max_distance),
        "downsample": 1 if preview else downsample,
        "adaptive_tolerance": float(light.adaptive_tolerance),
        # The core upsamples a downsampled frame along full-size depth edges instead.
        "supersampling": 1 if preview or downsample > 1 else int(light.edge_samples),
    }


def frame_inputs(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    *,
    sun: bpy.types.Object | None = None,
    cache: GeometryCache | None = None,
    divisor: int = 1,
    preview: bool = False,
) -> FrameInputs:
    """The `render_arrays` arguments of one sun (default: the first with shafts, by name)
    for the scene's current frame in `depsgraph`."""
    from .style import style_from_light

    if sun is None:
        suns = shaft_suns(scene)
        if not suns:
            raise ExportError(
                "no sun lamp has Stylized Shafts enabled (light.crepuscular.enabled on a SUN)"
            )
        sun = suns[0]
    notes: list[str] = []
    evaluated = sun.evaluated_get(depsgraph)
    # The viewport's preview shows the whole frame; F12 renders its region.
    region = None if preview or divisor != 1 else render_region(scene)
    camera = camera_dict(scene, depsgraph, divisor, region)
    notes += _unblurred_notes(scene)
    medium, medium_notes = medium_dict(scene, depsgraph)
    notes += medium_notes
    fog = scene.crepuscular.fog_object if scene.crepuscular.medium_source == "fog_object" else None
    exclude = {fog.name_full} if fog is not None else set()
    eye = np.asarray(camera["world_from_camera"][12:15], dtype=np.float64)
    blockers = LightLinking.of_blockers(sun)
    receivers = LightLinking.of_receivers(sun)
    if blockers is not None and blockers.takes_none:
        notes.append(
            f"'{sun.name}' casts no shadows (its Cast Shadow is off): nothing casts shafts "
            "but objects whose Casts Shafts is On, and the fog is lit everywhere, its light "
            "not fading through the fog towards the sun (Cycles traces no shadow rays for it)"
        )
    if not sun.original.visible_volume_scatter:
        notes.append(
            f"'{sun.name}' has its Volume Scatter ray visibility off: Cycles then lights no "
            "fog with it; the shafts are rendered as if it were on"
        )
    for linking, kind, collection in (
        (blockers, "shadow linking", "blocker"),
        (receivers, "light linking", "receiver"),
    ):
        if linking is None or linking.takes_none:
            continue
        if fog is not None and not linking.contains([fog]):
            notes.append(
                f"the {kind} of '{sun.name}' leaves the fog object '{fog.name}' out: "
                "Cycles then lights no fog with it; the shafts are rendered as if it were "
                f"in (include the fog object in the {collection} collection to match)"
            )
    world_from_camera = np.array(camera["world_from_camera"], dtype=np.float64).reshape(4, 4).T
    orthographic = camera["projection"]["kind"] == "orthographic"
    seen = SunAndCamera(
        np.array(sun_dict(evaluated)["direction"]),
        -world_from_camera[:3, 2] if orthographic else eye,
        orthographic,
    )
    geometry = export_geometry(
        depsgraph,
        cache=cache,
        exclude=exclude,
        origin=eye,
        seen=seen,
        blockers=blockers,
    )
    settings = evaluated.data.crepuscular
    fps = scene.render.fps / scene.render.fps_base
    style = style_from_light(
        settings,
        time=depsgraph.scene.frame_current / fps,
        hole_objects=geometry.hole_ids,
        name=f"bpy.data.lights['{evaluated.data.original.name}']",
    )
    sun_desc = sun_dict(evaluated)
    disc = sun_desc["angular_diameter"]
    disc_samples = crepuscular.sun_disc_samples(disc)
    if preview:
        disc_samples = min(disc_samples, PREVIEW_DISC_SAMPLES)
    if disc_samples > 1:
        notes.append(
            f"the {math.degrees(disc):.1f}° disc of '{sun.name}' softens the shafts: "
            f"{disc_samples} directions over it, each a frame's scattering"
        )
    if "holes" in style and not style["holes"]["objects"]:
        notes.append(
            f"hole creation is on for '{sun.name}', but no rendered object has Takes Holes "
            "enabled: no holes are made"
        )
    kwargs = {
        "positions": geometry.positions,
        "triangles": geometry.triangles,
        "object_ids": geometry.object_ids,
        "camera": camera,
        "sun": sun_desc,
        "medium": medium,
        "settings": settings_dict(settings, preview=preview) | {"sun_disc_samples": disc_samples},
        "style": style,
        "origin": geometry.origin,
    }
    if geometry.visibility is not None:
        kwargs["triangle_visibility"] = geometry.visibility
    if geometry.uvs is not None:
        kwargs |= {
            "uvs": geometry.uvs,
            "triangle_masks": geometry.triangle_masks,
            "masks": geometry.masks,
        }
    notes += geometry.notes
    lamp = f"the Stylized Shafts settings of '{sun.name}'"
    sources = {
        "camera": f"camera '{scene.camera.name}'",
        "sun": f"sun '{sun.name}'",
        "medium": (
            f"fog object '{fog.name}' (its volume shader and box)"
            if fog is not None
            else "the scene's Stylized Shafts medium"
        ),
        "render": lamp,
        "style": lamp,
    }
    return FrameInputs(kwargs, sun.name, notes, geometry, sources)


def all_frame_inputs(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph,
    *,
    cache: GeometryCache | None = None,
    divisor: int = 1,
    preview: bool = False,
) -> list[FrameInputs]:
    """`frame_inputs` of every sun with shafts, by name; an error names the missing sun."""
    suns = shaft_suns(scene)
    if not suns:
        raise ExportError(
            "no sun lamp has Stylized Shafts enabled (light.crepuscular.enabled on a SUN)"
        )
    return [
        frame_inputs(scene, depsgraph, sun=sun, cache=cache, divisor=divisor, preview=preview)
        for sun in suns
    ]


def render_suns(
    inputs: list[FrameInputs], progress: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renders every sun's layers and sums their in-scattered light.

    The volume's alpha (1 − transmittance to the first surface) and the depth do not depend
    on the light, so they are the first sun's; `visibility` is the first sun's too.
    Returns (volume, visibility, depth).
    """
    import crepuscular

    if not inputs:
        raise ExportError("no sun lamp has Stylized Shafts enabled")

    def render(index: int) -> crepuscular.Layers:
        def scaled(fraction: float) -> object:
            return progress((index + fraction) / len(inputs))

        try:
            return crepuscular.render_arrays(
                **inputs[index].kwargs, progress=None if progress is None else scaled
            )
        except crepuscular.InvalidInputError as error:
            field_path = getattr(error, "field", None)
            source = inputs[index].source_of(field_path) if field_path else None
            if source is None:
                raise
            raise ExportError(f"{source}: {error}") from error

    first = render(0)
    volume = np.array(first.volume, dtype=np.float32)
    for index in range(1, len(inputs)):
        volume[..., :3] += render(index).volume[..., :3]
    return volume, first.visibility, first.depth
