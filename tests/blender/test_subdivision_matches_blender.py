"""The USD step's Catmull-Clark refinement (`crepuscular_usd.subdivision`) against Blender
5.0's own Subdivision Surface modifier, whose cages Blender's USD exporter writes: the
evaluated mesh's vertices and its texture coordinates under each *UV Smooth* (which the
exporter writes as `faceVaryingLinearInterpolation`), on meshes with seams, junctions of
islands, n-gons, open boundaries and creases.

Tolerance. Both evaluate the same limit surface in single precision on Blender's side:
measured, points within 4·10⁻⁷ and coordinates within 3·10⁻⁷ of Blender's (on shapes a
unit or two across); the bounds are 2·10⁻⁶. Refined linearly in each face, as the USD
step did before, the coordinates are 0.6 to 8 % of the image off where Blender smooths
them, so the bounds are far below any rule applied wrongly. *Quality* 10 keeps Blender's
own approximations near creases out of the comparison.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from crepuscular_usd.subdivision import CatmullClark  # noqa: E402

#: Blender's *UV Smooth* and what its USD exporter writes for it.
UV_SMOOTH = {
    "NONE": "all",
    "PRESERVE_CORNERS": "cornersOnly",
    "PRESERVE_CORNERS_AND_JUNCTIONS": "cornersPlus1",
    "PRESERVE_CORNERS_JUNCTIONS_AND_CONCAVE": "cornersPlus2",
    "PRESERVE_BOUNDARIES": "boundaries",
    "SMOOTH_ALL": "none",
}
#: Blender's *Boundary Smooth* and the `interpolateBoundary` its exporter writes.
BOUNDARY_SMOOTH = {"ALL": "edgeOnly", "PRESERVE_CORNERS": "edgeAndCorner"}
BOUND = 2e-6


def _shape(kind: str) -> Any:
    """A mesh with UV islands: a cube's cross, a sphere's seam and poles, Suzanne cut into
    islands by Smart UV Project, a cylinder's seven-sided caps, an open grid whose
    coordinates are bent, and a cube creased around a face and at a corner."""
    if kind in ("cube", "creased"):
        bpy.ops.mesh.primitive_cube_add()
    elif kind == "sphere":
        bpy.ops.mesh.primitive_uv_sphere_add(segments=9, ring_count=6)
    elif kind == "cylinder":
        bpy.ops.mesh.primitive_cylinder_add(vertices=7)
    elif kind == "grid":
        bpy.ops.mesh.primitive_grid_add(x_subdivisions=4, y_subdivisions=3)
    elif kind == "suzanne":
        bpy.ops.mesh.primitive_monkey_add()
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.smart_project()
        bpy.ops.object.mode_set(mode="OBJECT")
    shape = bpy.context.active_object
    mesh = shape.data
    if kind == "grid":
        for loop in mesh.uv_layers.active.data:
            u, v = loop.uv
            loop.uv = (u + 0.2 * v * v, v + 0.1 * u * u)
    if kind == "creased":
        # A closed loop of creases (where one ends, a dart, Blender's points are 2·10⁻⁵
        # off the limit even at Quality 10), and a corner off it.
        creases = mesh.attributes.new("crease_edge", "FLOAT", "EDGE")
        loop = {frozenset(key) for key in mesh.polygons[0].edge_keys}
        for edge in mesh.edges:
            creases.data[edge.index].value = float(frozenset(edge.vertices) in loop)
        corner = next(i for i in range(len(mesh.vertices)) if i not in mesh.polygons[0].vertices)
        mesh.attributes.new("crease_vert", "FLOAT", "POINT").data[corner].value = 1.0
    return shape


def _cage(shape: Any) -> dict[str, Any]:
    """The cage as Blender's exporter writes it: points, faces, coordinates per
    face-vertex, and creases and corners of sharpness 10 (creases of 1)."""
    mesh = shape.data
    loops = np.array([loop.vertex_index for loop in mesh.loops])
    tags: dict[str, Any] = {}
    if "crease_edge" in mesh.attributes:
        creased = [e for e in mesh.edges if mesh.attributes["crease_edge"].data[e.index].value]
        tags["crease_indices"] = [v for e in creased for v in e.vertices]
        tags["crease_lengths"] = [2] * len(creased)
        tags["crease_sharpnesses"] = [10.0] * len(creased)
    if "crease_vert" in mesh.attributes:
        values = mesh.attributes["crease_vert"].data
        tags["corner_indices"] = [i for i in range(len(values)) if values[i].value]
        tags["corner_sharpnesses"] = [10.0] * len(tags["corner_indices"])
    return {
        "points": np.array([v.co for v in mesh.vertices], dtype=np.float64),
        "counts": np.array([p.loop_total for p in mesh.polygons]),
        "indices": loops,
        "uvs": np.array([d.uv for d in mesh.uv_layers.active.data], dtype=np.float64),
        "tags": tags,
    }


def _evaluated(shape: Any) -> tuple[np.ndarray, dict[frozenset, list[int]], np.ndarray, Any]:
    """Blender's refined points, its faces by their set of points (their loops), and the
    coordinates per loop."""
    evaluated = shape.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    points = np.array([v.co for v in evaluated.vertices], dtype=np.float64)
    loop_points = np.array([loop.vertex_index for loop in evaluated.loops])
    faces = {
        frozenset(loop_points[list(p.loop_indices)].tolist()): list(p.loop_indices)
        for p in evaluated.polygons
    }
    uvs = np.array([d.uv for d in evaluated.uv_layers.active.data], dtype=np.float64)
    return points, faces, uvs, loop_points


def _nearest(ours: np.ndarray, theirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of our points' nearest of Blender's, and the distance."""
    nearest = np.empty(len(ours), dtype=np.int64)
    distance = np.empty(len(ours))
    for start in range(0, len(ours), 512):
        block = ours[start : start + 512]
        squared = ((block[:, None, :] - theirs[None, :, :]) ** 2).sum(axis=2)
        nearest[start : start + 512] = squared.argmin(axis=1)
        distance[start : start + 512] = np.sqrt(squared.min(axis=1))
    return nearest, distance


def _compare(shape: Any, levels: int, limit: bool, boundary_smooth: str, uv_smooth: str) -> dict:
    modifier = shape.modifiers.get("Subdivision") or shape.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels = modifier.render_levels = levels
    modifier.quality, modifier.use_limit_surface = 10, limit
    modifier.boundary_smooth, modifier.uv_smooth = boundary_smooth, uv_smooth
    cage = _cage(shape)
    refinement = CatmullClark(
        cage["counts"],
        cage["indices"],
        len(cage["points"]),
        levels,
        boundary=BOUNDARY_SMOOTH[boundary_smooth],
        limit=limit,
        **cage["tags"],
    )
    points = refinement.refine(cage["points"])
    uvs = refinement.refine_face_varying(cage["uvs"], UV_SMOOTH[uv_smooth])
    linear = refinement.refine_face_varying(cage["uvs"], "all")
    their_points, their_faces, their_uvs, loop_points = _evaluated(shape)
    assert len(their_points) == len(points)
    nearest, distance = _nearest(points, their_points)
    quads = nearest[refinement.face_vertex_indices].reshape(-1, 4)
    assert len(their_faces) == len(quads)
    loops = []
    for quad in quads:
        by_point = {int(loop_points[i]): i for i in their_faces[frozenset(quad.tolist())]}
        loops.extend(by_point[int(point)] for point in quad)
    return {
        "points": float(distance.max()),
        "uvs": float(np.abs(uvs - their_uvs[loops]).max()),
        "linear": float(np.abs(linear - their_uvs[loops]).max()),
    }


@pytest.mark.parametrize("kind", ["cube", "sphere", "cylinder", "grid", "suzanne", "creased"])
def test_points_and_texture_coordinates_match_blenders(addon: ModuleType, kind: str) -> None:
    shape = _shape(kind)
    smoothed = []
    for uv_smooth in UV_SMOOTH:
        errors = _compare(shape, 2, True, "PRESERVE_CORNERS", uv_smooth)
        print(kind, uv_smooth, errors)
        assert errors["points"] < BOUND, (uv_smooth, errors)
        assert errors["uvs"] < BOUND, (uv_smooth, errors)
        smoothed.append(errors["linear"])
    # Smoothing the coordinates moves them off the linear ones (but on the cube, whose
    # islands have no value inside them, where every rule but the smoothest is linear).
    assert max(smoothed) > 5e-3
    # Off the limit surface, one level, and with the boundary's corners smoothed too.
    errors = _compare(shape, 1, False, "ALL", "SMOOTH_ALL")
    assert errors["points"] < BOUND, errors
    assert errors["uvs"] < BOUND, errors
    errors = _compare(shape, 3, True, "ALL", "PRESERVE_BOUNDARIES")
    assert errors["points"] < BOUND, errors
    assert errors["uvs"] < BOUND, errors
