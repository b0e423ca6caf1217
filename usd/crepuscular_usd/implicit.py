"""UsdGeom's implicit surfaces (Cube, Sphere, Cylinder, Cone, Capsule, Plane) as triangles.

Hydra tessellates these gprims before it draws them, and so does this step, so that a stage
blocked out with a Cube or a Sphere casts the shadows it shows in any USD viewer. Surfaces of
revolution are tessellated finer than Hydra's defaults: a shadow map resolves the facets of a
coarse sphere, and what the stage describes is the round surface. Every surface comes out in
its prim's local space, fronts facing out (reversed for `leftHanded` prims, as meshes are).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
from pxr import Usd, UsdGeom

__all__ = [
    "IMPLICIT_TYPES",
    "RADIAL_SEGMENTS",
    "ImplicitSurfaceError",
    "is_implicit_surface",
    "tessellate_implicit",
]

F64 = npt.NDArray[np.float64]
Triangles = npt.NDArray[np.uint32]

#: Segments around a surface of revolution: its silhouette lies within 0.21% of the radius
#: of the true surface (Hydra's 10 are within 4.9%, a visible polygon in a sharp shadow).
RADIAL_SEGMENTS = 48

#: Segments along a half circle (a sphere's profile, or a capsule's two caps together).
ARC_SEGMENTS = RADIAL_SEGMENTS // 2


class ImplicitSurfaceError(ValueError):
    """An implicit surface whose size cannot be tessellated; the message names the prim."""


def _revolve(profile: F64, where: str) -> tuple[F64, Triangles]:
    """The surface swept by `profile`, (N, 2) points (radius, z) from the bottom pole to the
    top one, around the z axis: a point of zero radius stays one vertex, a pole or an apex."""
    radii, heights = profile[:, 0], profile[:, 1]
    if not (np.all(np.isfinite(profile)) and np.all(radii >= 0)):
        raise ImplicitSurfaceError(f"{where}: its radius and height must be finite, radius ≥ 0")
    angles = 2.0 * np.pi * np.arange(RADIAL_SEGMENTS) / RADIAL_SEGMENTS
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    points: list[F64] = []
    # Per profile point: the index of its first vertex and whether it is a whole ring.
    rings: list[tuple[int, bool]] = []
    start = 0
    for radius, height in zip(radii, heights, strict=True):
        if radius == 0.0:
            points.append(np.array([[0.0, 0.0, height]]))
        else:
            points.append(np.column_stack([radius * ring, np.full(RADIAL_SEGMENTS, height)]))
        rings.append((start, radius != 0.0))
        start += len(points[-1])
    k = np.arange(RADIAL_SEGMENTS)
    following = (k + 1) % RADIAL_SEGMENTS
    triangles: list[npt.NDArray[np.int64]] = []
    for (below, below_ring), (above, above_ring) in itertools.pairwise(rings):
        # Counter-clockwise seen from outside: around +z, with z rising from below to above.
        if below_ring and above_ring:
            triangles.append(np.stack([below + k, below + following, above + following], axis=1))
            triangles.append(np.stack([below + k, above + following, above + k], axis=1))
        elif above_ring:
            triangles.append(
                np.stack([np.full_like(k, below), above + following, above + k], axis=1)
            )
        elif below_ring:
            triangles.append(
                np.stack([below + k, below + following, np.full_like(k, above)], axis=1)
            )
    if not triangles:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32)
    return np.concatenate(points), np.concatenate(triangles).astype(np.uint32)


def _arc(centre: float, radius: float, start: float, end: float, segments: int) -> F64:
    """(segments + 1, 2) points (radius, z) of a circle about (0, `centre`) from angle `start`
    to `end` (radians above the horizontal)."""
    angles = np.linspace(start, end, segments + 1)
    return np.column_stack([radius * np.cos(angles), centre + radius * np.sin(angles)])


def _along_axis(points: F64, axis: str, where: str) -> F64:
    """Points built around z turned so that z runs along `axis`: cyclic permutations of the
    coordinates, which keep the winding."""
    if axis == "Z":
        return points
    if axis == "X":
        return points[:, [2, 0, 1]]
    if axis == "Y":
        return points[:, [1, 2, 0]]
    raise ImplicitSurfaceError(f"{where}: axis is {axis!r}; it must be X, Y or Z")


def _value(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> float:
    attribute = prim.GetAttribute(name)
    value = attribute.Get(time) if attribute else None
    if value is None:
        raise ImplicitSurfaceError(f"{prim.GetPath()}: {name} has no value at {time}")
    return float(value)


def _axis(prim: Usd.Prim, time: Usd.TimeCode) -> str:
    attribute = prim.GetAttribute("axis")
    value = attribute.Get(time) if attribute else None
    return str(value) if value is not None else "Z"


def _cube(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    size = _value(prim, "size", time)
    if not (math.isfinite(size) and size >= 0):
        raise ImplicitSurfaceError(f"{where}: size is {size}; it must be finite and ≥ 0")
    corners = (
        0.5
        * size
        * np.array([[x, y, z] for z in (-1.0, 1.0) for y in (-1.0, 1.0) for x in (-1.0, 1.0)])
    )
    # Corner index = x + 2y + 4z (each 0 or 1); each face's quad counter-clockwise from outside.
    quads = [
        (0, 2, 3, 1),  # -z
        (4, 5, 7, 6),  # +z
        (0, 1, 5, 4),  # -y
        (2, 6, 7, 3),  # +y
        (0, 4, 6, 2),  # -x
        (1, 3, 7, 5),  # +x
    ]
    triangles = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return corners, np.array(triangles, dtype=np.uint32)


def _sphere(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    radius = _value(prim, "radius", time)
    profile = _arc(0.0, radius, -0.5 * np.pi, 0.5 * np.pi, ARC_SEGMENTS)
    profile[[0, -1], 0] = 0.0
    return _revolve(profile, where)


def _radii(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[float, float]:
    """(bottom, top) radii: `radiusBottom` and `radiusTop` where the schema has them
    (Cylinder_1, Capsule_1), else `radius` for both."""
    if prim.GetAttribute("radiusBottom"):
        return _value(prim, "radiusBottom", time), _value(prim, "radiusTop", time)
    radius = _value(prim, "radius", time)
    return radius, radius


def _cylinder(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    bottom, top = _radii(prim, time)
    half = 0.5 * _value(prim, "height", time)
    profile = np.array([[0.0, -half], [bottom, -half], [top, half], [0.0, half]])
    points, triangles = _revolve(profile, where)
    return _along_axis(points, _axis(prim, time), where), triangles


def _cone(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    radius = _value(prim, "radius", time)
    half = 0.5 * _value(prim, "height", time)
    points, triangles = _revolve(np.array([[0.0, -half], [radius, -half], [0.0, half]]), where)
    return _along_axis(points, _axis(prim, time), where), triangles


def _capsule(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    """Two spherical caps whose centres lie `height` apart, joined by the cone tangent to both
    (a cylinder where the radii are equal)."""
    bottom, top = _radii(prim, time)
    half = 0.5 * _value(prim, "height", time)
    if not (half > 0.0 and abs(bottom - top) < 2.0 * half):
        if not all(map(math.isfinite, (bottom, top, half))):
            raise ImplicitSurfaceError(f"{where}: its radius and height must be finite")
        # One cap holds the other (or there is no spine): the larger sphere is the surface.
        centre, radius = (-half, bottom) if bottom >= top else (half, top)
        profile = _arc(centre, radius, -0.5 * np.pi, 0.5 * np.pi, ARC_SEGMENTS)
    else:
        # The side's outward normal leans up by `lean` where the bottom cap is the larger.
        lean = math.asin((bottom - top) / (2.0 * half))
        profile = np.concatenate(
            [
                _arc(-half, bottom, -0.5 * np.pi, lean, ARC_SEGMENTS // 2),
                _arc(half, top, lean, 0.5 * np.pi, ARC_SEGMENTS // 2),
            ]
        )
    profile[[0, -1], 0] = 0.0
    points, triangles = _revolve(profile, where)
    return _along_axis(points, _axis(prim, time), where), triangles


def _plane(prim: Usd.Prim, time: Usd.TimeCode, where: str) -> tuple[F64, Triangles]:
    """A rectangle facing +axis: `width` along x and `length` along y for axis Z, `width`
    along z and `length` along y for X, `width` along x and `length` along z for Y."""
    width, length = _value(prim, "width", time), _value(prim, "length", time)
    if not all(math.isfinite(v) and v >= 0 for v in (width, length)):
        raise ImplicitSurfaceError(f"{where}: width and length must be finite and ≥ 0")
    u, v = 0.5 * width, 0.5 * length
    square = np.array([[-u, -v, 0.0], [u, -v, 0.0], [u, v, 0.0], [-u, v, 0.0]])
    axis = _axis(prim, time)
    if axis == "X":
        # Width along z, length along y, facing +x: (z, y) runs clockwise seen from +x.
        points = np.column_stack([square[:, 2], square[:, 1], square[:, 0]])
        triangles = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)
    elif axis == "Y":
        # Width along x, length along z, facing +y: (x, z) runs clockwise seen from +y.
        points = np.column_stack([square[:, 0], square[:, 2], square[:, 1]])
        triangles = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)
    elif axis == "Z":
        points = square
        triangles = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
    else:
        raise ImplicitSurfaceError(f"{where}: axis is {axis!r}; it must be X, Y or Z")
    return points, triangles


_Builder = Callable[[Usd.Prim, Usd.TimeCode, str], tuple[F64, Triangles]]

#: Each implicit schema this step tessellates, with its builder; `Cylinder_1` and
#: `Capsule_1` where the USD build has them.
IMPLICIT_TYPES: tuple[tuple[type, _Builder], ...] = tuple(
    (schema, builder)
    for schema, builder in (
        (UsdGeom.Cube, _cube),
        (UsdGeom.Sphere, _sphere),
        (UsdGeom.Cylinder, _cylinder),
        (getattr(UsdGeom, "Cylinder_1", None), _cylinder),
        (UsdGeom.Cone, _cone),
        (UsdGeom.Capsule, _capsule),
        (getattr(UsdGeom, "Capsule_1", None), _capsule),
        (getattr(UsdGeom, "Plane", None), _plane),
    )
    if schema is not None
)

#: The attributes a surface's tessellation reads, for knowing when it may be cached.
SHAPE_ATTRIBUTES = (
    "size",
    "radius",
    "radiusTop",
    "radiusBottom",
    "height",
    "axis",
    "width",
    "length",
    "orientation",
)


def is_implicit_surface(prim: Usd.Prim) -> bool:
    return any(prim.IsA(schema) for schema, _ in IMPLICIT_TYPES)


def tessellate_implicit(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[F64, Triangles, bool]:
    """The local-space points and triangles of the implicit surface `prim` at `time`, and
    whether any attribute they come from may vary in time. Raises `ImplicitSurfaceError`
    naming the prim for a size that cannot be tessellated."""
    where = str(prim.GetPath())
    builder = next(builder for schema, builder in IMPLICIT_TYPES if prim.IsA(schema))
    points, triangles = builder(prim, time, where)
    if UsdGeom.Gprim(prim).GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        triangles = triangles[:, [0, 2, 1]]
    varying = any(
        attribute.ValueMightBeTimeVarying()
        for attribute in (prim.GetAttribute(name) for name in SHAPE_ATTRIBUTES)
        if attribute
    )
    return points, np.ascontiguousarray(triangles, dtype=np.uint32), varying
