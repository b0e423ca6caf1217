"""Points (dust, spray, scanned or simulated particles) as triangles: a small polyhedron
around each point, which casts the shadow of a round sphere from any direction within
1.2%."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

#: Times the icosahedron's faces are split in four for a point's sphere: once gives 42
#: vertices and 80 triangles, whose shadow's area is within 1.2% of the round sphere's from
#: any direction (none gives 20 triangles and 4.5%; twice, 320 triangles and 0.3%).
SPHERE_SUBDIVISIONS = 1


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


def _unit_sphere() -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """The icosphere scaled so that its mean shadow is a unit disc's: by Cauchy, a convex
    body's shadow averaged over directions is a quarter of its surface, so the surface is
    made 4π."""
    vertices, faces = _icosphere(SPHERE_SUBDIVISIONS)
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    surface = 0.5 * np.linalg.norm(normals, axis=1).sum()
    return vertices * math.sqrt(4 * math.pi / surface), faces


_SPHERE_VERTICES, _SPHERE_FACES = _unit_sphere()
#: Vertices and triangles of one point's sphere.
SPHERE_VERTICES = len(_SPHERE_VERTICES)
SPHERE_TRIANGLES = len(_SPHERE_FACES)


def point_spheres(
    positions: npt.ArrayLike, radii: npt.ArrayLike
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Spheres around points, as Cycles draws a point cloud: `positions` (P, 3), `radii`
    (P,) or one radius for all. Returns (P * SPHERE_VERTICES, 3) float32 positions and
    (P * SPHERE_TRIANGLES, 3) uint32 triangles, one closed polyhedron a point; a point of
    radius 0 or less makes none."""
    centres = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    sizes = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(sizes) == 1:
        sizes = np.full(len(centres), sizes[0])
    if len(sizes) != len(centres):
        raise ValueError(f"{len(centres)} points but {len(sizes)} radii")
    if not (np.isfinite(centres).all() and np.isfinite(sizes).all()):
        raise ValueError("point positions and radii must be finite")
    keep = sizes > 0
    centres, sizes = centres[keep], sizes[keep]
    spheres = centres[:, None] + sizes[:, None, None] * _SPHERE_VERTICES[None]
    offsets = SPHERE_VERTICES * np.arange(len(centres), dtype=np.int64)
    triangles = _SPHERE_FACES[None] + offsets[:, None, None]
    return (
        spheres.reshape(-1, 3).astype(np.float32),
        triangles.reshape(-1, 3).astype(np.uint32),
    )
