"""Meshes of a USD stage as world-space triangles: triangulation, transforms, instancing.

Polygons are fan-triangulated as Hydra does for unrefined meshes, but for quads folded
along their first diagonal and faces that are not convex, which are triangulated as
Blender triangulates them; faces listed in `holeIndices` are left out, faces with fewer
than three vertices are skipped, and `leftHanded` meshes get their winding flipped.
Implicit surfaces (Cube, Sphere, Cylinder, Cone, Capsule, Plane) are tessellated
(`crepuscular_usd.implicit`) and read as meshes.
Meshes bound to a UsdSkel skeleton are posed: blend shapes, then joints
(`crepuscular_usd.skinning`). BasisCurves cast as ribbons of their widths across the sun
and the camera (`crepuscular.strand_ribbons`), Points as spheres of theirs
(`crepuscular.point_spheres`), of which the sun and the camera each get the side their rays
can hit (`crepuscular.point_sphere_visibility`).
Instance proxies and `PointInstancer` prototypes (with the instancers nested in them) share
one triangulation per prototype mesh; every placement is one numpy matrix product, never a
Python loop over vertices.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from pxr import Sdf, Tf, Usd, UsdGeom, UsdLux, UsdSkel, UsdVol

import crepuscular
from crepuscular_usd.attributes import SUBDIVISION_LEVELS, SUBDIVISION_LIMIT
from crepuscular_usd.cutouts import MaskTable, corner_uvs, face_masks
from crepuscular_usd.implicit import (
    ImplicitSurfaceError,
    is_implicit_surface,
    tessellate_implicit,
)
from crepuscular_usd.skinning import SkinnedMeshes, SkinningError
from crepuscular_usd.subdivision import CatmullClark, SubdivisionError

__all__ = ["GeometryCollector", "MeshError", "SceneGeometry", "triangle_corners", "triangulate"]

F64 = npt.NDArray[np.float64]


class MeshError(ValueError):
    """A mesh whose topology cannot be used; the message names the prim."""


def triangulate(
    face_vertex_counts: npt.ArrayLike,
    face_vertex_indices: npt.ArrayLike,
    hole_indices: npt.ArrayLike = (),
    *,
    left_handed: bool = False,
    point_count: int | None = None,
    where: str = "mesh",
    points: npt.ArrayLike | None = None,
) -> npt.NDArray[np.uint32]:
    """(M, 3) triangles of a USD polygon mesh, fan-triangulated per face (with `points`,
    a quad folded along its first diagonal is split along the other, as Blender splits it,
    and a larger face that is not convex is ear-clipped in its plane).

    Faces in `hole_indices` and faces with fewer than 3 vertices produce no triangles.
    Raises `MeshError` naming `where` for inconsistent topology.
    """
    corners, _ = triangle_corners(
        face_vertex_counts,
        face_vertex_indices,
        hole_indices,
        left_handed=left_handed,
        point_count=point_count,
        where=where,
        points=points,
    )
    indices = np.asarray(face_vertex_indices, dtype=np.int64).reshape(-1)
    return indices[corners].astype(np.uint32)


def triangle_corners(
    face_vertex_counts: npt.ArrayLike,
    face_vertex_indices: npt.ArrayLike,
    hole_indices: npt.ArrayLike = (),
    *,
    left_handed: bool = False,
    point_count: int | None = None,
    where: str = "mesh",
    points: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """`triangulate`'s triangles as (M, 3) positions in the face-vertex list (where
    face-varying primvars are), and each triangle's face."""
    counts = np.asarray(face_vertex_counts, dtype=np.int64).reshape(-1)
    indices = np.asarray(face_vertex_indices, dtype=np.int64).reshape(-1)
    if np.any(counts < 0):
        raise MeshError(f"{where}: faceVertexCounts has negative entries")
    if int(counts.sum()) != len(indices):
        raise MeshError(
            f"{where}: faceVertexCounts sum to {int(counts.sum())} but faceVertexIndices "
            f"has {len(indices)} entries"
        )
    if len(indices) and (
        indices.min() < 0 or (point_count is not None and indices.max() >= point_count)
    ):
        raise MeshError(
            f"{where}: faceVertexIndices reach {int(indices.max())} but there are "
            f"{point_count} points"
        )
    keep = counts >= 3
    holes = np.asarray(hole_indices, dtype=np.int64).reshape(-1)
    holes = holes[(holes >= 0) & (holes < len(counts))]
    keep[holes] = False
    per_face = np.where(keep, counts - 2, 0)
    total = int(per_face.sum())
    starts = np.cumsum(counts) - counts
    face = np.repeat(np.arange(len(counts)), per_face)
    corner = np.arange(total) - np.repeat(np.cumsum(per_face) - per_face, per_face)
    base = starts[face]
    first, second, third = base, base + corner + 1, base + corner + 2
    located = None if points is None else np.asarray(points, dtype=np.float64)
    # Faces that index past the points keep the fan (`point_count`, given, names them).
    if located is not None and total and indices.max() < len(located):
        fan = _FanRows(counts[face], corner, first, second, third)
        _split_folded_quads(located, indices, fan)
        _clip_concave_polygons(located, indices, fan)
    if left_handed:
        second, third = third, second
    return np.stack([first, second, third], axis=1), face


def _folded(quads: F64) -> npt.NDArray[np.bool_]:
    """Which of the (Q, 4, 3) quads have fan triangles that face opposite ways."""
    a, b, c, d = (quads[:, k] for k in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), np.cross(d - a, c - a)) > 0.0


@dataclass(frozen=True)
class _FanRows:
    """A fan triangulation, a row per triangle: its face's vertex count, its corner in
    the fan, and its three positions in the face-vertex list, which the fixes below
    rewrite in place."""

    counts: npt.NDArray[np.int64]
    corner: npt.NDArray[np.int64]
    first: npt.NDArray[np.int64]
    second: npt.NDArray[np.int64]
    third: npt.NDArray[np.int64]


def _split_folded_quads(points: F64, indices: npt.NDArray[np.int64], fan: _FanRows) -> None:
    """Quads whose two fan triangles face opposite ways (folded along the diagonal from
    their first corner, or concave there) split along the other diagonal instead, in
    place: Blender's rule (`is_quad_flip_v3_first_third_fast`), which the add-on's
    triangles follow."""
    quads = np.flatnonzero((fan.counts == 4) & (fan.corner == 0))
    if not len(quads):
        return
    folded = _folded(points[indices[fan.first[quads][:, None] + np.arange(4)]])
    if not folded.any():
        return
    rows = quads[folded]
    base = fan.first[rows]
    # (a, b, d) and (b, c, d).
    fan.second[rows], fan.third[rows] = base + 1, base + 3
    fan.first[rows + 1], fan.second[rows + 1], fan.third[rows + 1] = base + 1, base + 2, base + 3


def _clip_concave_polygons(points: F64, indices: npt.NDArray[np.int64], fan: _FanRows) -> None:
    """Faces of five or more points that are not convex in their plane (a wall around a
    window that a Boolean cut, an L-shaped floor), ear-clipped there instead of fanned, in
    place: a fan would cover their notches, where Blender's own triangles (and any
    renderer's that triangulates properly) leave them open. Convex faces keep the fan,
    which covers the same polygon."""
    counts, first, second, third = fan.counts, fan.first, fan.second, fan.third
    rows = np.flatnonzero((counts >= 5) & (fan.corner == 0))
    if not len(rows):
        return
    sizes = counts[rows]
    # Each face's corners, in order, from its first face-vertex (where its fan starts).
    starts = first[rows]
    owner = np.repeat(np.arange(len(rows)), sizes)
    offset = np.repeat(np.cumsum(sizes) - sizes, sizes)
    local = np.arange(int(sizes.sum())) - offset
    at = points[indices[starts[owner] + local]]
    following = at[offset + (local + 1) % sizes[owner]]
    # Newell's normal, and the turn at each corner against it (negative: reflex).
    normal = np.zeros((len(rows), 3))
    np.add.at(normal, owner, np.cross(at, following))
    before = at[offset + (local - 1) % sizes[owner]]
    turn = np.einsum("ij,ij->i", np.cross(at - before, following - at), normal[owner])
    scale = np.einsum("ij,ij->i", normal, normal)[owner]
    reflex = np.zeros(len(rows), dtype=bool)
    np.logical_or.at(reflex, owner, turn < -1e-12 * scale)
    for k in np.flatnonzero(reflex):
        n, start, row = int(sizes[k]), int(starts[k]), int(rows[k])
        polygon = points[indices[start : start + n]]
        for t, (a, b, c) in enumerate(_ear_clipped(polygon, normal[k])):
            first[row + t], second[row + t], third[row + t] = start + a, start + b, start + c


def _ear_clipped(polygon: F64, normal: F64) -> list[tuple[int, int, int]]:
    """The triangles (corner numbers, in the polygon's winding) of a simple polygon, by
    ear clipping in the plane across `normal`: walking around it, each convex corner
    whose triangle holds no reflex corner (only those can lie in it; corners at the same
    place as the triangle's own, as a slit to a hole and back leaves them, excepted) is
    cut off. What cannot be clipped (a polygon that crosses itself) is fanned."""
    u = polygon[1] - polygon[0]
    u = u - normal * (u @ normal) / (normal @ normal)
    if not np.any(u):
        u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    flat = np.stack([polygon @ u, polygon @ np.cross(normal, u)], axis=1)
    flat -= flat.mean(axis=0)
    eps = 1e-12 * float(np.abs(flat).max() ** 2 or 1.0)
    xs, ys = flat[:, 0].tolist(), flat[:, 1].tolist()
    n = len(xs)
    before = [(k - 1) % n for k in range(n)]
    after = [(k + 1) % n for k in range(n)]

    def turn(o: int, a: int, b: int) -> float:
        return (xs[a] - xs[o]) * (ys[b] - ys[o]) - (ys[a] - ys[o]) * (xs[b] - xs[o])

    def convex(k: int) -> bool:
        return turn(before[k], k, after[k]) > eps

    reflex = {k for k in range(n) if not convex(k)}

    def ear(k: int) -> bool:
        if k in reflex:
            return False
        a, c = before[k], after[k]
        places = {(xs[a], ys[a]), (xs[k], ys[k]), (xs[c], ys[c])}
        return not any(
            (xs[r], ys[r]) not in places
            and turn(a, k, r) >= -eps
            and turn(k, c, r) >= -eps
            and turn(c, a, r) >= -eps
            for r in reflex
        )

    triangles: list[tuple[int, int, int]] = []
    left, k, missed = n, 0, 0
    while left > 3 and missed < left:
        if not ear(k):
            k, missed = after[k], missed + 1
            continue
        a, c = before[k], after[k]
        triangles.append((a, k, c))
        after[a], before[c] = c, a
        reflex.discard(k)
        for neighbour in (a, c):
            if neighbour in reflex and convex(neighbour):
                reflex.discard(neighbour)
        left, k, missed = left - 1, c, 0
    rest = [k]
    while len(rest) < left:
        rest.append(after[rest[-1]])
    triangles.extend((rest[0], rest[t], rest[t + 1]) for t in range(1, left - 1))
    return triangles


def row_matrix(matrix: object) -> F64:
    """A Gf.Matrix4d (row vectors, translation in the last row) as a numpy array."""
    return np.array(matrix, dtype=np.float64).reshape(4, 4)


@dataclass
class _LocalMesh:
    points: F64
    triangles: npt.NDArray[np.uint32]
    #: Where faces are cut (`crepuscular_usd.cutouts`): a point per triangle corner, each
    #: with its texture coordinates, the mask index of each triangle (-1: none), and the
    #: corners' points in `unsplit`, the mesh's own (which skinning poses).
    uvs: F64 | None = None
    masks: npt.NDArray[np.int64] | None = None
    corner_points: npt.NDArray[np.int64] | None = None
    unsplit: F64 | None = None
    #: Curves and points: what they are drawn from for the sun and camera of each frame.
    per_view: _Strands | _PointSpheres | None = None
    #: Copies stacked in `points`, one per placement, each its own (the same triangles).
    copies: int = 1
    #: A subdivided mesh: its cage's points (which skinning poses) and their refinement.
    cage: F64 | None = None
    refinement: CatmullClark | None = None
    #: A skinned mesh's quads, whose diagonals are chosen again once it is posed.
    quads: _Quads | None = None
    #: Per triangle, `crepuscular.BLOCKS_SUN`, `SEEN_BY_CAMERA`, both or neither where the
    #: triangles are drawn per view: (T,) for every placement (strand ribbons), or (K, T),
    #: a row per placement (points' spheres, culled as each placement sees them). None: both.
    visibility: npt.NDArray[np.uint8] | None = None


@dataclass(frozen=True)
class _Quads:
    """The quads of a triangulated mesh: each one's first triangle's row and its four
    points, so that a posed mesh can split its quads by Blender's rule again
    (`_split_folded_quads`), as Blender splits the deformed mesh."""

    rows: npt.NDArray[np.int64]
    points: npt.NDArray[np.int64]
    left_handed: bool

    @staticmethod
    def of(
        counts: object,
        indices: npt.NDArray[np.int64],
        triangle_faces: npt.NDArray[np.int64],
        left_handed: bool,
    ) -> _Quads | None:
        sizes = np.asarray(counts, dtype=np.int64).reshape(-1)
        first = np.ones(len(triangle_faces), dtype=bool)
        first[1:] = triangle_faces[1:] != triangle_faces[:-1]
        rows = np.flatnonzero(first & (sizes[triangle_faces] == 4))
        if not len(rows):
            return None
        starts = (np.cumsum(sizes) - sizes)[triangle_faces[rows]]
        return _Quads(rows, indices[starts[:, None] + np.arange(4)], left_handed)

    def split(self, triangles: npt.NDArray[np.uint32], points: F64) -> npt.NDArray[np.uint32]:
        """`triangles` with each quad split by Blender's rule on `points`."""
        folded = _folded(points[self.points])
        p = self.points
        first = np.where(folded[:, None], p[:, [0, 1, 3]], p[:, [0, 1, 2]])
        second = np.where(folded[:, None], p[:, [1, 2, 3]], p[:, [0, 2, 3]])
        if self.left_handed:
            first, second = first[:, [0, 2, 1]], second[:, [0, 2, 1]]
        split = triangles.copy()
        split[self.rows], split[self.rows + 1] = first, second
        return split


@dataclass
class _Strands:
    """The strand inputs of curves (`crepuscular.strand_ribbons`), in their local space."""

    points: F64
    counts: npt.NDArray[np.int64]
    radii: F64
    steps: int

    def tubes(self) -> _LocalMesh:
        """Tubes (`crepuscular.strand_tubes`), for frames without a sun and camera."""
        positions, triangles = crepuscular.strand_tubes(
            self.points, self.counts, self.radii, catmull_rom=self.steps
        )
        return _LocalMesh(positions.astype(np.float64), triangles, per_view=self)

    def for_views(self, seen: _SunAndCamera) -> _LocalMesh:
        """A ribbon across the sun and one across the camera per strand
        (`crepuscular.strand_ribbons`), `seen` in local space: one (3,) each, or K (K, 3)
        for a copy per placement, built in one call (a field of clumps turned at random
        costs one build, not one each)."""
        copies = 1 if seen.sun.ndim == 1 else len(seen.sun)
        strands = len(self.counts)

        def per_strand(value: F64) -> F64:
            return value if value.ndim == 1 else np.repeat(value, strands, axis=0)

        camera = "view" if seen.orthographic else "eye"
        positions, triangles, flags = crepuscular.strand_ribbons(
            np.tile(self.points, (copies, 1)),
            np.tile(self.counts, copies),
            np.tile(self.radii, copies),
            catmull_rom=self.steps,
            sun=per_strand(seen.sun),
            **{camera: per_strand(seen.camera)},
        )
        if copies > 1:
            # The call lays out every copy's sun ribbons, then every copy's camera ribbons;
            # placements want each copy's own block, laid out as one copy's call does.
            half = len(positions) // 2
            by_copy = [positions[:half], positions[half:]]
            positions = np.concatenate(
                [part.reshape(copies, -1, 3) for part in by_copy], axis=1
            ).reshape(-1, 3)
            _, triangles, flags = crepuscular.strand_ribbons(
                self.points,
                self.counts,
                self.radii,
                catmull_rom=self.steps,
                sun=seen.sun[0],
                **{camera: seen.camera[0]},
            )
        return _LocalMesh(
            positions.astype(np.float64),
            triangles,
            per_view=self,
            copies=copies,
            visibility=flags,
        )


@dataclass
class _PointSpheres:
    """The spheres of Points (`crepuscular.point_spheres`), in their local space."""

    centres: F64
    #: One per point, or one for all.
    radii: F64
    _closed: _LocalMesh | None = field(default=None, repr=False, compare=False)

    def closed(self) -> _LocalMesh:
        """Closed spheres, for frames without a sun and camera (built once)."""
        if self._closed is None:
            positions, triangles = crepuscular.point_spheres(self.centres, self.radii)
            self._closed = _LocalMesh(positions.astype(np.float64), triangles, per_view=self)
        return self._closed

    def for_views(self, seen: _SunAndCamera) -> _LocalMesh:
        """The spheres with the side of each that the sun's and the camera's rays can hit
        (`crepuscular.point_sphere_visibility`), `seen` in local space: one (3,) each, or
        K (K, 3), flags for each placement in one call."""
        copies = 1 if seen.sun.ndim == 1 else len(seen.sun)
        camera = "view" if seen.orthographic else "eye"

        def per_point(value: F64) -> F64:
            return value if value.ndim == 1 else np.repeat(value, len(self.centres), axis=0)

        flags = crepuscular.point_sphere_visibility(
            np.tile(self.centres, (copies, 1)),
            np.tile(np.broadcast_to(self.radii, len(self.centres)), copies),
            sun=per_point(seen.sun),
            **{camera: per_point(seen.camera)},
        )
        return replace(self.closed(), visibility=flags.reshape(copies, -1) if copies > 1 else flags)


@dataclass
class _SunAndCamera:
    """The sun's travel direction and the camera (a pinhole's position, or an orthographic
    camera's view direction) in some space, which curves and points are drawn for: one (3,)
    each, or one per placement (K, 3)."""

    sun: F64
    camera: F64
    orthographic: bool

    def placed_by(self, rows: F64) -> _SunAndCamera | None:
        """The same in the local spaces of the (K, 4, 4) row-vector placements `rows`;
        None where one flattens space."""
        linear = np.swapaxes(rows[:, :3, :3], 1, 2)  # a row-vector map d -> d @ L, solved
        count = len(rows)
        camera = self.camera if self.orthographic else self.camera - rows[:, 3, :3]
        try:
            sun = np.linalg.solve(linear, np.broadcast_to(self.sun, (count, 3))[..., None])
            camera = np.linalg.solve(linear, np.broadcast_to(camera, (count, 3))[..., None])
        except np.linalg.LinAlgError:
            return None
        sun, camera = sun[..., 0], camera[..., 0]
        if not (np.isfinite(sun).all() and np.isfinite(camera).all()):
            return None
        return _SunAndCamera(
            sun / np.linalg.norm(sun, axis=1, keepdims=True), camera, self.orthographic
        )


def sun_and_camera(sun: dict[str, Any], camera: dict[str, Any]) -> _SunAndCamera:
    """The sun and camera of a frame (`StageReader.sun` and `.camera` dicts, in the
    renderer's space), which `GeometryCollector.collect` draws curves and points for."""
    world_from_camera = np.array(camera["world_from_camera"], dtype=np.float64).reshape(4, 4).T
    orthographic = camera["projection"]["kind"] == "orthographic"
    return _SunAndCamera(
        np.asarray(sun["direction"], dtype=np.float64),
        -world_from_camera[:3, 2] if orthographic else world_from_camera[:3, 3],
        orthographic,
    )


@dataclass
class _Chunk:
    """One owner's placed triangles, with the cutouts of its `_LocalMesh`es if any."""

    path: Sdf.Path
    points: F64
    triangles: npt.NDArray[np.uint32]
    uvs: F64 | None = None
    masks: npt.NDArray[np.int64] | None = None
    #: Per triangle, the `_LocalMesh`es' visibility flags where some are for one view.
    visibility: npt.NDArray[np.uint8] | None = None


@dataclass
class SceneGeometry:
    """Triangles in the renderer's space, relative to `origin`, with one object id per
    triangle."""

    positions: npt.NDArray[np.float32]
    triangles: npt.NDArray[np.uint32]
    object_ids: npt.NDArray[np.uint32]
    #: Object id of each owner path (a mesh, an instance proxy or a PointInstancer).
    ids_by_path: dict[Sdf.Path, int]
    #: Prototype mesh paths placed by each PointInstancer owner.
    instanced_paths: dict[Sdf.Path, set[Sdf.Path]]
    #: "TypeName" -> number of prims skipped because this step does not render them.
    unsupported: Counter[str] = field(default_factory=Counter)
    invalid: list[str] = field(default_factory=list)
    #: The point `positions` are relative to, in the renderer's space (float64).
    origin: F64 = field(default_factory=lambda: np.zeros(3))
    #: Alpha cutouts where a material cuts: texture coordinates per position, a mask index
    #: per triangle (-1: none) and the masks (`crepuscular_usd.cutouts`).
    uvs: npt.NDArray[np.float32] | None = None
    triangle_masks: npt.NDArray[np.int64] | None = None
    masks: list[crepuscular.AlphaMask] = field(default_factory=list)
    #: Materials whose transparency this step cannot map, named.
    notes: list[str] = field(default_factory=list)
    #: Per triangle, `crepuscular.BLOCKS_SUN` and `SEEN_BY_CAMERA` flags, where the light's
    #: shadow linking leaves some owners out of the shadow map; None where all block.
    visibility: npt.NDArray[np.uint8] | None = None

    def ids_under(self, roots: Iterable[Sdf.Path]) -> list[int]:
        """Object ids of every owner at or below one of `roots`."""
        roots = list(roots)
        ids: set[int] = set()
        for path, object_id in self.ids_by_path.items():
            sources = {path} | self.instanced_paths.get(path, set())
            if any(source.HasPrefix(root) for source in sources for root in roots):
                ids.add(object_id)
        return sorted(ids)


_LIGHT_TYPES = (UsdLux.BoundableLightBase, UsdLux.NonboundableLightBase)


class _Purposes:
    """The purposes of a traversal's prims as USD computes them (`ComputePurpose`): a
    prim's own where authored, else its parent's, so that a `render` prim under a `proxy`
    scope renders. A traversal visits parents first."""

    def __init__(self) -> None:
        self._of: dict[Sdf.Path, str] = {}

    def of(self, prim: Usd.Prim) -> str:
        imageable = UsdGeom.Imageable(prim)
        attribute = imageable.GetPurposeAttr() if imageable else None
        if attribute and attribute.HasAuthoredValue():
            purpose = str(attribute.Get())
        else:
            purpose = self._of.get(prim.GetParent().GetPath(), "")
            if not purpose:
                # The traversal's first prim: what its ancestors give it.
                purpose = str(imageable.ComputePurpose()) if imageable else "default"
        self._of[prim.GetPath()] = purpose
        return purpose


#: The most levels a mesh is refined: each multiplies its faces by four.
MAX_SUBDIVISION_LEVELS = 6


def _cage_note(paths: set[Sdf.Path], cast: str) -> str:
    """That the meshes at `paths` cast as their control cages, naming the first of them."""
    first = min(paths)
    more = f" and {len(paths) - 1} more" if len(paths) > 1 else ""
    return cast.format(meshes=f"{first}{more}")


#: What casting subdivision meshes as their cages means, at the lowest complexity, and
#: for Loop meshes, which are not refined.
CAGES_AT_LOW = (
    "meshes that author a smooth subdivisionScheme ({meshes}) cast as their control cages, "
    "as Storm draws them at its default complexity; give --complexity medium, high or "
    "veryhigh to refine Catmull-Clark meshes 1, 2 or 3 levels onto their limit surface, as "
    "renderers that subdivide (Karma, RenderMan) cast them"
)
LOOP_CAGES = (
    "meshes whose subdivisionScheme is loop ({meshes}) cast as their control cages: only "
    "Catmull-Clark meshes are refined"
)


class GeometryCollector:
    """Reads the renderable meshes of a stage at a time code.

    Local triangulations are cached across time codes when nothing about the mesh is
    time-varying, so a long frame range pays for topology once.
    """

    def __init__(
        self,
        stage: Usd.Stage,
        core_from_stage: F64,
        *,
        skip: Iterable[Sdf.Path] = (),
        purposes: Iterable[str] = ("default", "render"),
        subdivision_levels: int = 0,
    ) -> None:
        if not 0 <= subdivision_levels <= MAX_SUBDIVISION_LEVELS:
            raise MeshError(
                f"subdivision levels must lie in 0..{MAX_SUBDIVISION_LEVELS}, not "
                f"{subdivision_levels}"
            )
        self._stage = stage
        #: How many levels Catmull-Clark meshes without their own are refined (0: cages).
        self._subdivision_levels = subdivision_levels
        #: The purposes that render (a RenderSettings prim's `includedPurposes`).
        self._purposes = frozenset(purposes)
        #: Column-vector 4x4: stage world space -> renderer space (Z-up, metres).
        self._core_from_stage = core_from_stage
        self._skip = set(skip)
        self._cache: dict[Sdf.Path, _LocalMesh] = {}
        self._skinned = SkinnedMeshes(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
        self._masks = MaskTable()
        #: Meshes that author a smooth subdivision scheme, which cast as their cages, and
        #: Loop meshes that would be refined but are not.
        self._subdivided: set[Sdf.Path] = set()
        self._loop: set[Sdf.Path] = set()
        #: Refinements by mesh, with the topology they were built for.
        self._refinements: dict[Sdf.Path, tuple[tuple[object, ...], CatmullClark]] = {}
        #: The sun and camera in the renderer's space, for the frame collecting.
        self._seen: _SunAndCamera | None = None
        #: Curves and points drawn for views, by their local mesh's identity and the sun and
        #: camera in their space (rounded): a still shot draws them once.
        self._drawn_for_views: dict[
            tuple[int, tuple[float, ...]], tuple[_LocalMesh, _LocalMesh]
        ] = {}

    # --- meshes ---------------------------------------------------------------------

    def _local_mesh(self, prim: Usd.Prim, time: Usd.TimeCode) -> _LocalMesh | None:
        """The triangles of a Mesh or an implicit surface in its local space."""
        key = prim.GetPrimInPrototype().GetPath() if prim.IsInstanceProxy() else prim.GetPath()
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        if prim.IsA(UsdGeom.BasisCurves) or prim.IsA(UsdGeom.Points):
            local, varying = (
                _curves_mesh(prim, time)
                if prim.IsA(UsdGeom.BasisCurves)
                else _points_mesh(prim, time)
            )
            if not varying:
                self._cache[key] = local
            return local
        # Meshes first: most surfaces are, and they skip the implicit schemas' tests.
        if not prim.IsA(UsdGeom.Mesh):
            try:
                points, triangles, varying = tessellate_implicit(prim, time)
            except ImplicitSurfaceError as error:
                raise MeshError(str(error)) from error
            local = _LocalMesh(points, triangles)
            if not varying:
                self._cache[key] = local
            return local
        mesh = UsdGeom.Mesh(prim)
        levels, limit = self._levels_of(prim, mesh, time)
        attrs = [
            mesh.GetPointsAttr(),
            mesh.GetFaceVertexCountsAttr(),
            mesh.GetFaceVertexIndicesAttr(),
            mesh.GetHoleIndicesAttr(),
            mesh.GetOrientationAttr(),
        ]
        points_value = attrs[0].Get(time)
        counts = attrs[1].Get(time)
        indices = attrs[2].Get(time)
        if points_value is None or counts is None or indices is None:
            return _LocalMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32))
        points = np.array(points_value, dtype=np.float64).reshape(-1, 3)
        topology = {
            "hole_indices": attrs[3].Get(time) or (),
            "left_handed": attrs[4].Get(time) == UsdGeom.Tokens.leftHanded,
            "point_count": len(points),
            "where": str(prim.GetPath()),
        }
        faces = face_masks(prim, len(counts), self._masks)
        refinement = None
        if levels:
            refinement = self._refinement(
                prim, mesh, time, levels, limit, counts, indices, topology
            )
            cage, points = points, refinement.refine(points)
            counts, indices = refinement.face_vertex_counts, refinement.face_vertex_indices
            topology = {**topology, "hole_indices": (), "point_count": len(points)}
            if faces is not None:
                faces = faces[refinement.faces]
        if faces is None:
            corners, triangle_faces = triangle_corners(counts, indices, **topology, points=points)
            flat = np.asarray(indices, dtype=np.int64).reshape(-1)
            local = _LocalMesh(points, flat[corners].astype(np.uint32))
            if self._skinned.is_skinned(prim):
                local.quads = _Quads.of(counts, flat, triangle_faces, topology["left_handed"])
        else:
            local = self._cut_mesh(prim, time, points, counts, indices, faces, topology, refinement)
        if refinement is not None:
            local = replace(local, cage=cage, refinement=refinement)
        if not any(attr.ValueMightBeTimeVarying() for attr in attrs):
            self._cache[key] = local
        return local

    def _levels_of(
        self, prim: Usd.Prim, mesh: UsdGeom.Mesh, time: Usd.TimeCode
    ) -> tuple[int, bool]:
        """How many levels to refine the mesh, and whether onto its limit surface: its own
        levels (`SUBDIVISION_LEVELS`) where it authors them, else the render's; 0 for
        meshes that are not Catmull-Clark."""
        scheme_attr = mesh.GetSubdivisionSchemeAttr()
        scheme = scheme_attr.Get()
        own = prim.GetAttribute(SUBDIVISION_LEVELS)
        own_levels = own.Get(time) if own and own.HasAuthoredValue() else None
        whole = (
            isinstance(own_levels, int | float)
            and not isinstance(own_levels, bool)
            and bool(np.isfinite(own_levels))
        )
        if own_levels is not None and not (
            whole and own_levels == int(own_levels) and 0 <= own_levels <= MAX_SUBDIVISION_LEVELS
        ):
            raise MeshError(
                f"{prim.GetPath()}.{SUBDIVISION_LEVELS} is {own_levels!r}; give a whole number "
                f"from 0 to {MAX_SUBDIVISION_LEVELS}"
            )
        levels = int(own_levels) if own_levels is not None else self._subdivision_levels
        if scheme == "loop" and levels:
            self._loop.add(prim.GetPath())
            return 0, True
        if scheme != "catmullClark":
            return 0, True
        if not levels:
            if scheme_attr.HasAuthoredValue():
                self._subdivided.add(prim.GetPath())
            return 0, True
        limit_attr = prim.GetAttribute(SUBDIVISION_LIMIT)
        limit = limit_attr.Get(time) if limit_attr and limit_attr.HasAuthoredValue() else None
        return levels, limit is not False

    def _refinement(
        self,
        prim: Usd.Prim,
        mesh: UsdGeom.Mesh,
        time: Usd.TimeCode,
        levels: int,
        limit: bool,
        counts: object,
        indices: object,
        topology: dict[str, Any],
    ) -> CatmullClark:
        """The mesh's refinement at `time`, built once for as long as its topology and
        subdivision tags hold."""
        tags = {
            "hole_indices": topology["hole_indices"],
            "crease_indices": mesh.GetCreaseIndicesAttr().Get(time) or (),
            "crease_lengths": mesh.GetCreaseLengthsAttr().Get(time) or (),
            "crease_sharpnesses": mesh.GetCreaseSharpnessesAttr().Get(time) or (),
            "corner_indices": mesh.GetCornerIndicesAttr().Get(time) or (),
            "corner_sharpnesses": mesh.GetCornerSharpnessesAttr().Get(time) or (),
            "boundary": str(mesh.GetInterpolateBoundaryAttr().Get(time)),
        }
        key = (
            levels,
            limit,
            topology["point_count"],
            np.asarray(counts).tobytes(),
            np.asarray(indices).tobytes(),
            *(np.asarray(value).tobytes() for name, value in tags.items() if name != "boundary"),
            tags["boundary"],
        )
        cached = self._refinements.get(prim.GetPath())
        if cached is not None and cached[0] == key:
            return cached[1]
        # Faces the point count cannot hold are named as unsubdivided meshes name them.
        triangle_corners(counts, indices, **topology)
        try:
            refinement = CatmullClark(
                counts,
                indices,
                topology["point_count"],
                levels,
                limit=limit,
                where=topology["where"],
                **tags,
            )
        except SubdivisionError as error:
            raise MeshError(str(error)) from error
        _check_memory(refinement.point_count, 2 * len(refinement.faces), topology["where"])
        self._refinements[prim.GetPath()] = (key, refinement)
        return refinement

    def _cut_mesh(
        self,
        prim: Usd.Prim,
        time: Usd.TimeCode,
        points: F64,
        counts: object,
        indices: object,
        faces: npt.NDArray[np.int64],
        topology: dict[str, Any],
        refinement: CatmullClark | None = None,
    ) -> _LocalMesh:
        """A mesh some of whose faces are cut: a point per triangle corner, with the
        texture coordinates of the primvar its face's mask reads (on a refined mesh,
        refined with it)."""
        corners, triangle_faces = triangle_corners(counts, indices, **topology, points=points)

        def uvs_at(primvar: str, rows: npt.NDArray[np.bool_]) -> F64 | None:
            if refinement is None:
                return corner_uvs(
                    prim, primvar, time, corners[rows], corner_points[rows], triangle_faces[rows]
                )
            cage = refined_uvs.get(primvar)
            if primvar not in refined_uvs:
                cage = self._refined_uvs(prim, primvar, time, refinement)
                refined_uvs[primvar] = cage
            return None if cage is None else cage[corners[rows]]

        refined_uvs: dict[str, F64 | None] = {}
        corner_points = np.asarray(indices, dtype=np.int64).reshape(-1)[corners]
        masks = faces[triangle_faces]
        uvs = np.zeros((len(corners), 3, 2))
        for mask in np.unique(masks[masks >= 0]):
            rows = masks == mask
            source = self._masks.source(int(mask))
            if source.constant is not None:
                continue  # one opacity everywhere: no coordinates to read
            primvar = source.primvar
            values = uvs_at(primvar, rows)
            if values is None:
                if primvar:
                    fallback = source.st_fallback
                    note = (
                        f"{prim.GetPath()}: primvar '{primvar}' is missing; its mask reads "
                        f"({fallback[0]:g}, {fallback[1]:g}), the reader's fallback"
                    )
                    if note not in self._masks.notes:
                        self._masks.notes.append(note)
                values = np.broadcast_to(source.st_fallback, (int(rows.sum()), 3, 2))
            finite = np.isfinite(values).all(axis=(1, 2))
            if not finite.all():
                note = (
                    f"{prim.GetPath()}: primvar '{primvar}' has NaN or infinite values; the "
                    "triangles that read them cast as opaque"
                )
                if note not in self._masks.notes:
                    self._masks.notes.append(note)
                masks[np.flatnonzero(rows)[~finite]] = -1
                values = np.where(finite[:, None, None], values, 0.0)
            if source.uv_transform is not None:
                matrix = np.array(source.uv_transform, dtype=np.float64).reshape(2, 3)
                values = values @ matrix[:, :2].T + matrix[:, 2]
            # Past the image by more than rounding (coordinates authored as 1 read 1 + 1e-7).
            outside = (values < -1e-6) | (values > 1.0 + 1e-6)
            if source.wrap_unauthored and outside.any():
                note = (
                    f"{prim.GetPath()}: texture {source.file} leaves its wrap to the file "
                    "(wrapS or wrapT useMetadata, the default), so past its edges it reads "
                    "black, USD's fallback, and cuts the mesh away there (Blender's USD "
                    'import repeats it; author wrapS and wrapT "repeat" to tile it)'
                )
                if note not in self._masks.notes:
                    self._masks.notes.append(note)
            uvs[rows] = values
        split = points[corner_points].reshape(-1, 3)
        triangles = np.arange(len(split), dtype=np.uint32).reshape(-1, 3)
        return _LocalMesh(
            split, triangles, uvs.reshape(-1, 2), masks, corner_points.reshape(-1), points
        )

    @staticmethod
    def _refined_uvs(
        prim: Usd.Prim, primvar: str, time: Usd.TimeCode, refinement: CatmullClark
    ) -> F64 | None:
        """A primvar's values at the face-vertices of a mesh's refinement: face-varying
        ones refined as the mesh's `faceVaryingLinearInterpolation` says, vertex ones as
        its points, varying, uniform and constant ones linearly."""
        mesh = UsdGeom.Mesh(prim)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time), dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time), dtype=np.int64)
        corners = np.repeat(np.arange(len(indices))[:, None], 3, axis=1)
        faces = np.repeat(np.arange(len(counts)), counts)
        cage = corner_uvs(prim, primvar, time, corners, indices[corners], faces)
        if cage is None:
            return None
        # As OpenSubdiv refines each kind: face-varying values by the mesh's rule, vertex
        # values as the points (one island, nothing sharpened), the rest linearly.
        kind = UsdGeom.PrimvarsAPI(prim).GetPrimvar(primvar).GetInterpolation()
        if kind == UsdGeom.Tokens.faceVarying:
            interpolation = str(mesh.GetFaceVaryingLinearInterpolationAttr().Get(time))
        else:
            interpolation = "none" if kind == UsdGeom.Tokens.vertex else "all"
        try:
            return refinement.refine_face_varying(cage[:, 0], interpolation)
        except SubdivisionError as error:
            raise MeshError(str(error)) from error

    def _posed(
        self, prim: Usd.Prim, local: _LocalMesh, time: Usd.TimeCode
    ) -> tuple[_LocalMesh, Usd.Prim]:
        """`local` as it renders at `time`, and the prim whose space its points are in:
        skinned in their skeleton's (a subdivided mesh's cage posed, then refined; quads
        split again as they fold once posed), else as it is in the mesh's own."""
        if not self._skinned.is_skinned(prim):
            return local, prim
        rest = local.points if local.unsplit is None else local.unsplit
        if local.cage is not None:
            rest = local.cage
        try:
            posed, space = self._skinned.posed_points(prim, rest, time)
        except SkinningError as error:
            raise MeshError(str(error)) from error
        if local.refinement is not None:
            posed = local.refinement.refine(posed)
        if local.corner_points is not None:
            posed = posed[local.corner_points]
        triangles = local.triangles
        if local.quads is not None:
            triangles = local.quads.split(triangles, posed)
        return _LocalMesh(posed, triangles, local.uvs, local.masks), space

    def _view_groups(
        self, local: _LocalMesh, rows: F64
    ) -> list[tuple[_LocalMesh, npt.NDArray[np.int64]]]:
        """`local` as placed by the (K, 4, 4) row-vector `rows`: curves as ribbons for the
        sun and camera as each placement's space sees them (placements that see them
        alike share them), with the indices of their placements; anything else, or
        without a sun and camera, `local` for all."""
        everything = np.arange(len(rows))
        if local.per_view is None or self._seen is None:
            return [(local, everything)]
        seen = self._seen.placed_by(rows)
        if seen is None:
            return [(local, everything)]
        keys = np.round(np.concatenate([seen.sun, seen.camera], axis=1), 6)
        unique, which = np.unique(keys, axis=0, return_inverse=True)
        if len(unique) > MAX_VIEW_GROUPS:
            return [(local.per_view.for_views(seen), everything)]
        groups = []
        for index, key in enumerate(unique):
            cache_key = (id(local), tuple(float(v) for v in key))
            cached = self._drawn_for_views.get(cache_key)
            if cached is None or cached[0] is not local:
                one = _SunAndCamera(key[:3], key[3:], seen.orthographic)
                cached = (local, local.per_view.for_views(one))
                self._drawn_for_views[cache_key] = cached
            groups.append((cached[1], np.flatnonzero(which.reshape(-1) == index)))
        return groups

    def _add_skel_root(self, prim: Usd.Prim) -> None:
        try:
            self._skinned.add_root(prim)
        except SkinningError as error:
            raise MeshError(str(error)) from error

    # --- traversal ------------------------------------------------------------------

    def collect(
        self,
        time: Usd.TimeCode,
        origin: F64 | None = None,
        seen: _SunAndCamera | None = None,
        shadow_link: Usd.CollectionMembershipQuery | None = None,
    ) -> SceneGeometry:
        """Every visible render-purpose surface at `time`, in the renderer's space, relative to
        `origin` (default the origin): subtracted in float64, a point near the camera keeps
        float32 positions precise however far the stage lies from its origin. Curves
        are drawn as ribbons for the sun and camera `seen` (`sun_and_camera`), so that each
        sees their exact width and ends, as a path tracer draws strands, and points as the
        side of their spheres each view's rays can hit, as Cycles culls them. Owners
        (a mesh, an instance proxy, a PointInstancer) that `shadow_link`, the light's
        shadow-linking collection, leaves out do not block the sun, and still hide the fog
        from the camera."""
        # NaN or infinite points, widths and transforms are named and left out
        # (`_finite_chunks`); numpy's warnings about them on the way add only noise.
        with np.errstate(invalid="ignore", over="ignore"):
            return self._collect(time, origin, seen, shadow_link)

    def _collect(
        self,
        time: Usd.TimeCode,
        origin: F64 | None,
        seen: _SunAndCamera | None,
        shadow_link: Usd.CollectionMembershipQuery | None,
    ) -> SceneGeometry:
        self._seen = seen
        if len(self._drawn_for_views) > 4096:
            self._drawn_for_views.clear()
        xforms = UsdGeom.XformCache(time)
        chunks: list[_Chunk] = []
        instanced: dict[Sdf.Path, set[Sdf.Path]] = {}
        unsupported: Counter[str] = Counter()
        invalid: list[str] = []
        core_row = self._core_from_stage.T
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = iter(Usd.PrimRange(self._stage.GetPseudoRoot(), predicate))
        next(prims)  # the pseudo-root itself
        purposes = _Purposes()
        for prim in prims:
            if not self._renderable(prim, time):
                prims.PruneChildren()
                continue
            if not self._rendered_purpose(prim, purposes):
                if prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer):
                    prims.PruneChildren()
                continue
            if prim.GetPath() in self._skip:
                prims.PruneChildren()
                continue
            if prim.IsA(UsdGeom.PointInstancer):
                prims.PruneChildren()
                try:
                    placed = self._point_instancer(prim, time, xforms, core_row, unsupported)
                except Tf.ErrorException as error:
                    invalid.append(f"{prim.GetPath()}: USD: {tf_message(error)}")
                    continue
                if placed is not None:
                    chunks.append(placed[0])
                    instanced[prim.GetPath()] = placed[1]
                continue
            if _is_surface(prim):
                prims.PruneChildren()
                try:
                    local = self._local_mesh(prim, time)
                    if local is None or len(local.triangles) == 0:
                        continue
                    posed, space = self._posed(prim, local, time)
                except MeshError as error:
                    invalid.append(str(error))
                    continue
                try:
                    world_row = row_matrix(xforms.GetLocalToWorldTransform(space)) @ core_row
                except Tf.ErrorException as error:
                    invalid.append(f"{prim.GetPath()}: its transform: USD: {tf_message(error)}")
                    continue
                [(local, _)] = self._view_groups(local, world_row[None])
                if not local.per_view:
                    local = posed
                chunk = _Chunk(
                    prim.GetPath(),
                    _transform(local.points, world_row),
                    local.triangles,
                    local.uvs,
                    local.masks,
                )
                if local.visibility is not None:
                    chunk.visibility = local.visibility.reshape(-1)
                chunks.append(chunk)
                continue
            if prim.IsA(UsdSkel.Root):
                try:
                    self._add_skel_root(prim)
                except MeshError as error:
                    invalid.append(str(error))
                continue
            self._count_unsupported(prim, unsupported)
        offset = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
        chunks = _finite_chunks(chunks, invalid)
        geometry = _assemble(chunks, instanced, unsupported, invalid, offset)
        geometry.visibility = _visibility(chunks, shadow_link)
        if geometry.triangle_masks is not None:
            geometry.masks = self._masks.masks()
        geometry.notes = list(self._masks.notes)
        if self._subdivided:
            geometry.notes.append(_cage_note(self._subdivided, CAGES_AT_LOW))
        if self._loop:
            geometry.notes.append(_cage_note(self._loop, LOOP_CAGES))
        return geometry

    @staticmethod
    def _renderable(prim: Usd.Prim, time: Usd.TimeCode) -> bool:
        """Whether `prim` and what is under it may render: visibility is inherited
        whatever the descendants say."""
        imageable = UsdGeom.Imageable(prim)
        if not imageable:
            # Typed but not imageable (materials, shaders, render settings) holds no geometry.
            return not prim.GetTypeName()
        return imageable.GetVisibilityAttr().Get(time) != UsdGeom.Tokens.invisible

    def _rendered_purpose(self, prim: Usd.Prim, purposes: _Purposes) -> bool:
        """Whether `prim`'s purpose renders (a RenderSettings prim's `includedPurposes`)."""
        return purposes.of(prim) in self._purposes

    @staticmethod
    def _count_unsupported(prim: Usd.Prim, unsupported: Counter[str]) -> None:
        if prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdVol.Volume):
            unsupported[str(prim.GetTypeName())] += 1
        elif prim.IsA(UsdLux.DistantLight):
            return  # other distant lights: the light in use is chosen explicitly
        elif any(prim.IsA(kind) for kind in _LIGHT_TYPES):
            unsupported[str(prim.GetTypeName())] += 1

    def _prototype_meshes(
        self,
        root: Usd.Prim,
        time: Usd.TimeCode,
        xforms: UsdGeom.XformCache,
        unsupported: Counter[str],
        expanding: tuple[Sdf.Path, ...],
    ) -> list[tuple[Sdf.Path, _LocalMesh, F64]]:
        """Surfaces under a prototype root, each with the (K, 4, 4) rows placing its K copies
        relative to the root's parent: one for a surface of the prototype's own, one per
        instance for a surface of a PointInstancer nested in it (a forest's trees, each
        instancing its leaves). `expanding` holds the prototypes being expanded around it."""
        found: list[tuple[Sdf.Path, _LocalMesh, F64]] = []
        parent = root.GetParent()
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = iter(Usd.PrimRange(root, predicate))
        purposes = _Purposes()
        for prim in prims:
            if not self._renderable(prim, time):
                prims.PruneChildren()
                continue
            if not self._rendered_purpose(prim, purposes):
                if prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer):
                    prims.PruneChildren()
                continue
            if prim.IsA(UsdGeom.PointInstancer):
                prims.PruneChildren()
                nested = self._instanced_meshes(prim, time, xforms, unsupported, expanding)
                if nested:
                    relative = row_matrix(xforms.ComputeRelativeTransform(prim, parent)[0])
                    found.extend((path, local, rows @ relative) for path, local, rows in nested)
                continue
            if _is_surface(prim):
                prims.PruneChildren()
                local = self._local_mesh(prim, time)
                if local is not None and len(local.triangles):
                    local, space = self._posed(prim, local, time)
                    relative, _ = xforms.ComputeRelativeTransform(space, parent)
                    found.append((prim.GetPath(), local, row_matrix(relative)[None]))
                continue
            if prim.IsA(UsdSkel.Root):
                self._add_skel_root(prim)
                continue
            self._count_unsupported(prim, unsupported)
        return found

    def _instanced_meshes(
        self,
        prim: Usd.Prim,
        time: Usd.TimeCode,
        xforms: UsdGeom.XformCache,
        unsupported: Counter[str],
        expanding: tuple[Sdf.Path, ...] = (),
    ) -> list[tuple[Sdf.Path, _LocalMesh, F64]]:
        """The surfaces the PointInstancer `prim` places, each with the (K, 4, 4) rows of its
        copies in the instancer's own space, instance by instance. A prototype that holds an
        instancer of itself, however deep, is expanded once and counted as skipped."""
        instancer = UsdGeom.PointInstancer(prim)
        where = str(prim.GetPath())
        proto_paths = instancer.GetPrototypesRel().GetForwardedTargets()
        proto_indices = instancer.GetProtoIndicesAttr().Get(time)
        if not proto_paths or proto_indices is None or len(proto_indices) == 0:
            return []
        # ExcludeProtoXform: the prototype root's own transform comes with its meshes below.
        transforms = instancer.ComputeInstanceTransformsAtTime(
            time, time, UsdGeom.PointInstancer.ExcludeProtoXform, UsdGeom.PointInstancer.IgnoreMask
        )
        if transforms is None or len(transforms) != len(proto_indices):
            raise MeshError(f"{where}: instance transforms could not be computed at {time}")
        instance_rows = np.array(transforms, dtype=np.float64).reshape(-1, 4, 4)
        indices = np.asarray(proto_indices, dtype=np.int64)
        mask = instancer.ComputeMaskAtTime(time)
        if mask is not None and len(mask):
            keep = np.asarray(mask, dtype=bool)
            indices, instance_rows = indices[keep], instance_rows[keep]
        if len(indices) and (indices.min() < 0 or indices.max() >= len(proto_paths)):
            raise MeshError(
                f"{where}: protoIndices reach {int(indices.max())} but there are "
                f"{len(proto_paths)} prototypes"
            )
        found: list[tuple[Sdf.Path, _LocalMesh, F64]] = []
        for proto_index, proto_path in enumerate(proto_paths):
            placements = instance_rows[indices == proto_index]
            if not len(placements):
                continue
            if proto_path in expanding:
                unsupported["PointInstancer (instancing its own prototype)"] += 1
                continue
            proto = self._stage.GetPrimAtPath(proto_path)
            if not proto:
                raise MeshError(f"{where}: prototype {proto_path} does not exist")
            for mesh_path, local, relative in self._prototype_meshes(
                proto, time, xforms, unsupported, (*expanding, proto_path)
            ):
                # Rows: the surface in its prototype, then the instance; instance-major.
                rows = relative[None, :, :, :] @ placements[:, None, :, :]
                found.append((mesh_path, local, rows.reshape(-1, 4, 4)))
        return found

    def _point_instancer(
        self,
        prim: Usd.Prim,
        time: Usd.TimeCode,
        xforms: UsdGeom.XformCache,
        core_row: F64,
        unsupported: Counter[str],
    ) -> tuple[_Chunk, set[Sdf.Path]] | None:
        found = self._instanced_meshes(prim, time, xforms, unsupported)
        if not found:
            return None
        world_row = row_matrix(xforms.GetLocalToWorldTransform(prim)) @ core_row
        found = [
            (path, drawn, rows[which])
            for path, local, rows in found
            for drawn, which in self._view_groups(local, rows @ world_row)
        ]
        positions: list[F64] = []
        triangles: list[npt.NDArray[np.uint32]] = []
        uvs: list[F64] = []
        masks: list[npt.NDArray[np.int64]] = []
        flags: list[npt.NDArray[np.uint8]] = []
        cut = any(local.masks is not None for _, local, _ in found)
        split = any(local.visibility is not None for _, local, _ in found)
        sources: set[Sdf.Path] = set()
        base = 0
        vertices = sum(len(local.points) // local.copies * len(rows) for _, local, rows in found)
        triangles_placed = sum(len(local.triangles) * len(rows) for _, local, rows in found)
        _check_memory(vertices, triangles_placed, str(prim.GetPath()))
        for mesh_path, local, rows in found:
            sources.add(mesh_path)
            full = rows @ world_row
            homogeneous = np.concatenate([local.points, np.ones((len(local.points), 1))], axis=1)
            if local.copies > 1:  # a copy of its own per placement
                copies = homogeneous.reshape(local.copies, -1, 4)
                placed = np.einsum("knj,kjl->knl", copies, full)[..., :3]
            else:
                placed = np.einsum("nj,kjl->knl", homogeneous, full)[..., :3]
            count = len(local.points) // local.copies
            offsets = (np.arange(len(rows), dtype=np.int64) * count + base)[:, None, None]
            positions.append(placed.reshape(-1, 3))
            triangles.append(
                (local.triangles[None, :, :].astype(np.int64) + offsets).reshape(-1, 3)
            )
            if split:
                own = local.visibility
                if own is None:
                    own = np.full(len(local.triangles), 3, dtype=np.uint8)
                flags.append(own.reshape(-1) if own.ndim == 2 else np.tile(own, len(rows)))
            if cut:
                copies = len(rows)
                if local.masks is None or local.uvs is None:
                    uvs.append(np.zeros((count * copies, 2)))
                    masks.append(np.full(len(local.triangles) * copies, -1, dtype=np.int64))
                else:
                    uvs.append(np.tile(local.uvs, (copies, 1)))
                    masks.append(np.tile(local.masks, copies))
            base += count * len(rows)
        stacked = np.concatenate(triangles).astype(np.uint32)
        chunk = _Chunk(prim.GetPath(), np.concatenate(positions), stacked)
        if split:
            chunk.visibility = np.concatenate(flags)
        if cut:
            chunk.uvs, chunk.masks = np.concatenate(uvs), np.concatenate(masks)
        return chunk, sources


#: Placements of one curves or points prototype that see the sun and camera in more ways
#: than this get a drawing each, built in one call, instead of one build per direction.
MAX_VIEW_GROUPS = 16

#: Bytes the step holds per vertex an instancer places (the einsum's float64 rows and their
#: copies, the float32 positions) and per triangle (int64 indices, the uint32 copy, an id).
BYTES_PER_VERTEX = 4 * 8 + 3 * 8 + 3 * 4
BYTES_PER_TRIANGLE = 3 * 8 * 2 + 3 * 4 + 4


def available_memory() -> int | None:
    """Physical memory available now, in bytes, where the system says (Linux)."""
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_memory(vertices: int, triangles: int, where: str) -> None:
    """A `MeshError` naming `where` if placing `vertices` and `triangles` would need more
    memory than is free: an instancer of a million pebbles is refused with its size rather
    than swapping the farm node or being killed."""
    if vertices < 1_000_000:
        return
    need = vertices * BYTES_PER_VERTEX + triangles * BYTES_PER_TRIANGLE
    free = available_memory()
    if free is not None and need > free:
        raise MeshError(
            f"{where}: too large for memory: it places {vertices} vertices and {triangles} "
            f"triangles, about {need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB are free"
        )


def _is_surface(prim: Usd.Prim) -> bool:
    """Whether `prim` is geometry this step draws: a Mesh, BasisCurves, Points or an
    implicit surface."""
    # One test rules out the Xforms and Scopes that most prims of a large stage are.
    if not prim.IsA(UsdGeom.Gprim):
        return False
    return (
        prim.IsA(UsdGeom.Mesh)
        or prim.IsA(UsdGeom.BasisCurves)
        or prim.IsA(UsdGeom.Points)
        or is_implicit_surface(prim)
    )


def _curves_mesh(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[_LocalMesh, bool]:
    """BasisCurves' strands at half their widths (`_Strands`, drawn per frame), and whether
    that may vary in time: linear curves along their points, Catmull-Rom curves along
    their splines through them (as Blender's exporter writes hair), Bezier and B-spline
    curves along their control polygon; curves with normals (ribbons) round too."""
    curves = UsdGeom.BasisCurves(prim)
    where = str(prim.GetPath())
    attrs = [curves.GetPointsAttr(), curves.GetCurveVertexCountsAttr(), _widths_attr(prim)]
    varying = any(attr.ValueMightBeTimeVarying() for attr in attrs)
    points_value, counts_value = (attr.Get(time) for attr in attrs[:2])
    widths_value = _widths(prim, time)
    if points_value is None or counts_value is None or len(points_value) == 0:
        return _LocalMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32)), varying
    points = np.array(points_value, dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(counts_value, dtype=np.int64)
    if counts.min(initial=0) < 0 or int(counts.sum()) != len(points):
        raise MeshError(
            f"{where}: curveVertexCounts sum to {int(counts.sum())} but there are "
            f"{len(points)} points"
        )
    if widths_value is None or len(widths_value) == 0:
        raise MeshError(f"{where}: the curves have no widths, so no thickness; not drawn")
    widths = np.asarray(widths_value, dtype=np.float64)
    if len(widths) == len(points):
        radii = 0.5 * widths
    elif len(widths) == 1:
        radii = np.full(len(points), 0.5 * widths[0])
    elif len(widths) == len(counts):
        radii = np.repeat(0.5 * widths, counts)
    else:
        raise MeshError(
            f"{where}: {len(widths)} widths match neither its {len(points)} points, its "
            f"{len(counts)} curves nor one (varying widths of cubic curves are not read)"
        )
    cubic = curves.GetTypeAttr().Get(time) == UsdGeom.Tokens.cubic
    catmull_rom = cubic and curves.GetBasisAttr().Get(time) == UsdGeom.Tokens.catmullRom
    steps = crepuscular.CATMULL_ROM_STEPS if catmull_rom else 0
    return _Strands(points, counts, radii, steps).tubes(), varying


def _widths_attr(prim: Usd.Prim) -> Usd.Attribute:
    """The widths of curves or points: `primvars:widths` where it is authored (an indexed
    primvar, as some writers author it), which Hydra takes over the `widths` attribute."""
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("widths")
    if primvar and primvar.HasAuthoredValue():
        return primvar.GetAttr()
    return prim.GetAttribute("widths")


def _widths(prim: Usd.Prim, time: Usd.TimeCode) -> object:
    """The value of `_widths_attr`, flattened through its indices."""
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("widths")
    if primvar and primvar.HasAuthoredValue():
        return primvar.ComputeFlattened(time)
    attr = prim.GetAttribute("widths")
    return attr.Get(time) if attr else None


def _points_mesh(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[_LocalMesh, bool]:
    """Points as spheres of half their widths (`crepuscular.point_spheres`), as Cycles
    draws a point cloud, and whether that may vary in time. Widths are per point or one
    for all; without widths the points have no size and are named, not drawn."""
    points_prim = UsdGeom.Points(prim)
    where = str(prim.GetPath())
    attrs = [points_prim.GetPointsAttr(), _widths_attr(prim)]
    varying = any(attr.ValueMightBeTimeVarying() for attr in attrs)
    points_value, widths_value = attrs[0].Get(time), _widths(prim, time)
    if points_value is None or len(points_value) == 0:
        return _LocalMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32)), varying
    points = np.array(points_value, dtype=np.float64).reshape(-1, 3)
    if widths_value is None or len(widths_value) == 0:
        raise MeshError(f"{where}: the points have no widths, so no size; not drawn")
    widths = np.asarray(widths_value, dtype=np.float64)
    if len(widths) not in (1, len(points)):
        raise MeshError(
            f"{where}: {len(widths)} widths match neither its {len(points)} points nor one"
        )
    try:
        return _PointSpheres(points, 0.5 * widths).closed(), varying
    except ValueError as error:
        raise MeshError(f"{where}: {error}") from error


def _visibility(
    chunks: list[_Chunk], shadow_link: Usd.CollectionMembershipQuery | None
) -> npt.NDArray[np.uint8] | None:
    """Per triangle of `chunks` (in `_assemble`'s order), the visibility flags: the
    chunks' own (strand ribbons), less `BLOCKS_SUN` where the light's shadow-linking
    collection leaves the owner out; None where every triangle has both."""
    if shadow_link is None and all(chunk.visibility is None for chunk in chunks):
        return None
    both = crepuscular.BLOCKS_SUN | crepuscular.SEEN_BY_CAMERA
    parts = []
    for chunk in chunks:
        flags = (
            np.full(len(chunk.triangles), both, dtype=np.uint8)
            if chunk.visibility is None
            else chunk.visibility
        )
        if shadow_link is not None and not shadow_link.IsPathIncluded(chunk.path):
            flags = flags & np.uint8(crepuscular.SEEN_BY_CAMERA)
        parts.append(flags)
    if not parts:
        return None
    flags = np.concatenate(parts)
    return None if (flags == both).all() else flags


def tf_message(error: Exception) -> str:
    """The messages of a Tf.ErrorException without USD's source locations."""
    messages = []
    for arg in error.args or (str(error),):
        text = str(arg).strip()
        # "Error in 'function' at line N in file F : 'message'"
        head, sep, quoted = text.partition(" : '")
        messages.append(" ".join((quoted.rstrip("'").strip() if sep else head).split()))
    return "; ".join(m for m in messages if m) or type(error).__name__


def _finite_chunks(chunks: list[_Chunk], invalid: list[str]) -> list[_Chunk]:
    """The chunks whose placed points are all finite; the others named in `invalid`. NaN or
    infinite points (from points, widths, radii, transforms or instancer attributes) would
    otherwise fail the whole frame without naming their prim."""
    finite = []
    for chunk in chunks:
        bad = int((~np.isfinite(chunk.points).all(axis=1)).sum())
        if bad:
            invalid.append(
                f"{chunk.path}: {bad} of its {len(chunk.points)} placed points are not finite "
                "(NaN or infinite points, widths, radii, transforms or instance attributes)"
            )
        else:
            finite.append(chunk)
    return finite


def _transform(points: F64, world_row: F64) -> F64:
    return points @ world_row[:3, :3] + world_row[3, :3]


def _assemble(
    chunks: list[_Chunk],
    instanced: dict[Sdf.Path, set[Sdf.Path]],
    unsupported: Counter[str],
    invalid: list[str],
    origin: F64,
) -> SceneGeometry:
    ids_by_path: dict[Sdf.Path, int] = {}
    positions: list[F64] = []
    triangles: list[npt.NDArray[np.uint32]] = []
    object_ids: list[npt.NDArray[np.uint32]] = []
    uvs: list[F64] = []
    masks: list[npt.NDArray[np.int64]] = []
    cut = any(chunk.masks is not None for chunk in chunks)
    base = 0
    for chunk in chunks:
        object_id = ids_by_path.setdefault(chunk.path, len(ids_by_path) + 1)
        positions.append(chunk.points)
        triangles.append(chunk.triangles.astype(np.int64) + base)
        object_ids.append(np.full(len(chunk.triangles), object_id, dtype=np.uint32))
        if cut:
            if chunk.masks is None or chunk.uvs is None:
                uvs.append(np.zeros((len(chunk.points), 2)))
                masks.append(np.full(len(chunk.triangles), -1, dtype=np.int64))
            else:
                uvs.append(chunk.uvs)
                masks.append(chunk.masks)
        base += len(chunk.points)
    if base > np.iinfo(np.uint32).max:
        raise MeshError(f"the stage has {base} vertices, more than 32-bit indices address")
    return SceneGeometry(
        positions=(
            (np.concatenate(positions) - origin).astype(np.float32)
            if positions
            else np.zeros((0, 3), dtype=np.float32)
        ),
        triangles=(
            np.concatenate(triangles).astype(np.uint32)
            if triangles
            else np.zeros((0, 3), dtype=np.uint32)
        ),
        object_ids=(np.concatenate(object_ids) if object_ids else np.zeros(0, dtype=np.uint32)),
        ids_by_path=ids_by_path,
        instanced_paths=instanced,
        unsupported=unsupported,
        invalid=invalid,
        origin=origin,
        uvs=np.concatenate(uvs).astype(np.float32) if cut else None,
        triangle_masks=np.concatenate(masks) if cut else None,
    )
