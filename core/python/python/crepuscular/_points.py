"""Points (dust, spray, scanned or simulated particles) as triangles: a small polyhedron
around each point, which casts the shadow of a round sphere from any direction within
1.2%, and which of its triangles each view sees as Cycles sees a point."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from crepuscular._strands import BLOCKS_SUN, SEEN_BY_CAMERA, _directions, _points

#: How far, in metres, a point's outline may lie from the round sphere's: a point's
#: icosahedron is split in four once (80 triangles, outline within 3.8% of the radius, up to
#: 0.53 m), and more often for larger points (320, 1280, then 5120 triangles, within 0.06%).
#: A point of 8 m around the camera read 3.7% off Cycles per pixel with 80 triangles, and
#: 0.45% with 1280.
SPHERE_OUTLINE_TOLERANCE = 0.02
#: The splits of the finest sphere.
MOST_SUBDIVISIONS = 4


def _icosphere(subdivisions: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Unit vertices and outward-wound triangles of an icosahedron split `subdivisions`
    times."""
    t = (1 + math.sqrt(5)) / 2
    vertices = [
        (-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0),
        (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
        (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1),
    ]  # fmt: skip
    faces = [
        (0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
        (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
        (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
        (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1),
    ]  # fmt: skip
    points = [np.array(v, dtype=np.float64) / math.hypot(*v) for v in vertices]
    for _ in range(subdivisions):
        midpoints: dict[tuple[int, int], int] = {}
        split = []
        for face in faces:
            middle = []
            for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
                key = (min(a, b), max(a, b))
                if key not in midpoints:
                    point = points[a] + points[b]
                    points.append(point / np.linalg.norm(point))
                    midpoints[key] = len(points) - 1
                middle.append(midpoints[key])
            ab, bc, ca = middle
            a, b, c = face
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    return np.array(points), np.array(faces, dtype=np.int64)


@dataclass(frozen=True)
class _UnitSphere:
    """An icosphere scaled so that its mean shadow is a unit disc's (by Cauchy, a convex
    body's shadow averaged over directions is a quarter of its surface, so the surface is
    made 4π), with its triangles' outward normals n, n . v for a corner v of each (how far
    along its normal each triangle's plane lies), and how far its outline strays from the
    unit circle's at most (between its in- and circumradius)."""

    vertices: npt.NDArray[np.float64]
    faces: npt.NDArray[np.int64]
    normals: npt.NDArray[np.float64]
    reach: npt.NDArray[np.float64]
    outline_error: float

    @classmethod
    def split(cls, subdivisions: int) -> _UnitSphere:
        vertices, faces = _icosphere(subdivisions)
        corners = vertices[faces]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        surface = 0.5 * np.linalg.norm(normals, axis=1).sum()
        vertices = vertices * math.sqrt(4 * math.pi / surface)
        corners = vertices[faces]
        reach = np.einsum("ij,ij->i", normals, corners[:, 0])
        inradius = (reach / np.linalg.norm(normals, axis=1)).min()
        circumradius = np.linalg.norm(vertices, axis=1).max()
        return cls(vertices, faces, normals, reach, max(circumradius - 1, 1 - inradius))


_SPHERES = [_UnitSphere.split(k) for k in range(1, MOST_SUBDIVISIONS + 1)]
#: Vertices and triangles of the sphere of a point up to `SPHERE_OUTLINE_TOLERANCE` over
#: its outline error (0.53 m); larger points have 4, 16 or 64 times as many.
SPHERE_VERTICES = len(_SPHERES[0].vertices)
SPHERE_TRIANGLES = len(_SPHERES[0].faces)


@dataclass
class _Layout:
    """Which sphere each drawn point gets (`_SPHERES` index), and where its vertices and
    triangles start in the output, in the points' order."""

    levels: npt.NDArray[np.int64]
    first_vertex: npt.NDArray[np.int64]
    first_triangle: npt.NDArray[np.int64]
    vertices: int
    triangles: int

    @classmethod
    def of(cls, sizes: npt.NDArray[np.float64]) -> _Layout:
        errors = np.array([sphere.outline_error for sphere in _SPHERES])
        fine_enough = sizes[:, None] * errors[None] <= SPHERE_OUTLINE_TOLERANCE
        levels = np.where(fine_enough.any(axis=1), fine_enough.argmax(axis=1), len(_SPHERES) - 1)
        vertex_counts = np.array([len(sphere.vertices) for sphere in _SPHERES])[levels]
        triangle_counts = np.array([len(sphere.faces) for sphere in _SPHERES])[levels]
        return cls(
            levels,
            np.cumsum(vertex_counts) - vertex_counts,
            np.cumsum(triangle_counts) - triangle_counts,
            int(vertex_counts.sum()),
            int(triangle_counts.sum()),
        )

    def by_level(self) -> list[tuple[_UnitSphere, npt.NDArray[np.int64]]]:
        """Per sphere in use: it, and its points."""
        return [
            (_SPHERES[level], np.flatnonzero(self.levels == level))
            for level in np.unique(self.levels)
        ]


def _rows(
    starts: npt.NDArray[np.int64], points: npt.NDArray[np.int64], count: int
) -> slice | npt.NDArray[np.int64]:
    """The output rows of `points`' `count` items each, from their `starts`: every row,
    in order, where the points are all the points (one sphere for all)."""
    if len(points) == len(starts):
        return slice(None)
    return (starts[points, None] + np.arange(count)).reshape(-1)


def point_spheres(
    positions: npt.ArrayLike, radii: npt.ArrayLike
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Spheres around points, as Cycles draws a point cloud: `positions` (P, 3), `radii`
    (P,) or one radius for all. Returns float32 positions (N, 3) and uint32 triangles
    (M, 3), one closed polyhedron a point, in the points' order: `SPHERE_VERTICES` and
    `SPHERE_TRIANGLES` each for points up to 0.53 m, more for larger ones, so that every
    outline lies within `SPHERE_OUTLINE_TOLERANCE` of the round sphere's (or within 0.06%
    of the radius). A point of radius 0 or less makes none."""
    centres, sizes, _ = _drawn_points(positions, radii)
    layout = _Layout.of(sizes)
    spheres = np.empty((layout.vertices, 3), dtype=np.float32)
    triangles = np.empty((layout.triangles, 3), dtype=np.uint32)
    for sphere, points in layout.by_level():
        placed = centres[points, None] + sizes[points, None, None] * sphere.vertices[None]
        faces = sphere.faces[None] + layout.first_vertex[points, None, None]
        spheres[_rows(layout.first_vertex, points, len(sphere.vertices))] = placed.reshape(-1, 3)
        triangles[_rows(layout.first_triangle, points, len(sphere.faces))] = faces.reshape(-1, 3)
    return spheres, triangles


def point_sphere_visibility(
    positions: npt.ArrayLike,
    radii: npt.ArrayLike,
    *,
    sun: npt.ArrayLike,
    eye: npt.ArrayLike | None = None,
    view: npt.ArrayLike | None = None,
) -> npt.NDArray[np.uint8]:
    """`render_arrays` visibility flags for the triangles of `point_spheres(positions,
    radii)`, as Cycles sees a point: it culls a point's back side for every ray.

    The camera sees the triangles that face it (`SEEN_BY_CAMERA`), so that a camera inside
    a point, or whose near clip cuts into one, sees out of it. The sun's shadow map holds
    those that face away from the sun (`BLOCKS_SUN`): a shadow ray from the fog beyond a
    point enters it there, and one from inside leaves it unblocked, so the fog inside a
    point is lit. A triangle facing neither gets 0. Each view still sees each point's
    whole outline.

    `sun` is the sun's travel direction; the camera is `eye`, a pinhole's position, or
    `view`, an orthographic camera's direction. Each may be one (3,) or one per point
    (P, 3); a point of radius 0 or less is skipped with its directions."""
    if (eye is None) == (view is None):
        raise ValueError("give the camera as eye (a position) or view (a direction): one of them")
    centres, sizes, keep = _drawn_points(positions, radii)
    count = len(keep)
    suns = _directions(sun, count, "sun", each="point")[keep]
    views = None if view is None else _directions(view, count, "view", each="point")[keep]
    eyes = None if eye is None else _points(eye, count, "eye", each="point")[keep]
    layout = _Layout.of(sizes)
    flags = np.empty(layout.triangles, dtype=np.uint8)
    for sphere, points in layout.by_level():
        normals = sphere.normals.T
        blocks = suns[points] @ normals > 0
        if views is not None:
            seen = views[points] @ normals < 0
        else:
            # Triangle k of point i lies in the plane n_k . (x - c_i - s_i v_k) = 0.
            offsets = (centres[points] - eyes[points]) @ normals
            seen = offsets + sizes[points, None] * sphere.reach[None] < 0
        both = np.where(blocks, BLOCKS_SUN, 0) | np.where(seen, SEEN_BY_CAMERA, 0)
        flags[_rows(layout.first_triangle, points, len(sphere.faces))] = both.reshape(-1)
    return flags


def _drawn_points(
    positions: npt.ArrayLike, radii: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """The centres and radii of the points drawn (radius above 0), and which those are;
    bad input named."""
    centres = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    sizes = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(sizes) == 1:
        sizes = np.full(len(centres), sizes[0])
    if len(sizes) != len(centres):
        raise ValueError(f"{len(centres)} points but {len(sizes)} radii")
    if not (np.isfinite(centres).all() and np.isfinite(sizes).all()):
        raise ValueError("point positions and radii must be finite")
    keep = sizes > 0
    return centres[keep], sizes[keep], keep
