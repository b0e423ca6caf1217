"""Catmull-Clark subdivision of USD meshes, for stages whose meshes author it.

A mesh whose `subdivisionScheme` is `catmullClark` (USD's fallback) describes the smooth
surface its faces are the control cage of. This refines such a cage uniformly a number
of levels by the rules OpenSubdiv applies to UsdGeomMesh: semi-sharp and infinitely sharp
creases (`creaseIndices`, `creaseLengths`, `creaseSharpnesses`) and corners
(`cornerIndices`, `cornerSharpnesses`) by the uniform crease method, non-manifold edges
as infinitely sharp, `interpolateBoundary`, and `holeIndices` (hole faces shape their
neighbours but are not drawn). The refined points are then moved to their limit
positions, where the smooth surface passes (as Blender's Subdivision Surface modifier
places them under its default *Use Limit Surface*): smooth points, creases and corners
by their limit rules, and points whose rule would still change (darts, semi-sharp
creases) by refining the faces around each of them further on their own (`_Rings`).

The refinement is built once per topology (`CatmullClark`) and applied to any points
on it, so that animated or skinned meshes pose their cage and refine it each frame.
Face-varying values (texture coordinates) refine as their own mesh, smooth or linear where
`faceVaryingLinearInterpolation` says, as OpenSubdiv refines them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Sharpness at or above which USD (and OpenSubdiv) take an edge or corner as sharp at
#: every level.
INFINITELY_SHARP = 10.0

#: `interpolateBoundary` values.
BOUNDARIES = ("none", "edgeOnly", "edgeAndCorner")

#: `faceVaryingLinearInterpolation` values, from smooth everywhere to linear everywhere
#: (USD's fallback is `cornersPlus1`; Blender writes its modifier's *UV Smooth*, by
#: default *Keep Boundaries*, `boundaries`).
FACE_VARYING_INTERPOLATIONS = (
    "none",
    "cornersOnly",
    "cornersPlus1",
    "cornersPlus2",
    "boundaries",
    "all",
)

SMOOTH, CREASE, CORNER = 0, 1, 2


class SubdivisionError(ValueError):
    """Subdivision tags that do not fit the mesh; the message names the mesh."""


def _sum_by(index: I64, values: F64, length: int) -> F64:
    """Rows of `values` summed into `length` rows by `index` (one bincount a column)."""
    summed = np.empty((length, values.shape[1]))
    for k in range(values.shape[1]):
        summed[:, k] = np.bincount(index, weights=values[:, k], minlength=length)
    return summed


def _decremented(sharpness: F64) -> F64:
    """The sharpness of an edge's or vertex's children (the uniform crease method)."""
    return np.where(sharpness >= INFINITELY_SHARP, sharpness, np.maximum(sharpness - 1.0, 0.0))


def _edge_keys(first: I64, second: I64) -> I64:
    low, high = np.minimum(first, second), np.maximum(first, second)
    return (low << 32) | high


@dataclass(frozen=True)
class _Topology:
    """One level's faces and what its refinement reads of them."""

    point_count: int
    sizes: I64
    #: Per face-vertex: its face, its point, the next and previous face-vertex in its face,
    #: and the edge from it to the next.
    corner_face: I64
    corner_point: I64
    corner_next: I64
    corner_previous: I64
    corner_edge: I64
    #: Per edge: its two points, and how many faces it bounds.
    edge_ends: I64
    edge_faces: I64
    edge_sharpness: F64
    vertex_sharpness: F64
    #: Per point: how many edges and faces meet there, and whether an edge of one face.
    valence: I64
    face_count: I64
    on_boundary: npt.NDArray[np.bool_]

    @property
    def face_total(self) -> int:
        return len(self.sizes)

    @property
    def edge_total(self) -> int:
        return len(self.edge_ends)

    def rules(self, edge_sharpness: F64, vertex_sharpness: F64) -> I64:
        """Each point's rule for the given sharpness: a corner where it is sharp or more
        than two sharp edges meet, a crease where two do, else smooth (one, a dart, is
        smooth too)."""
        sharp = edge_sharpness > 0.0
        ends = self.edge_ends[sharp].reshape(-1)
        count = np.bincount(ends, minlength=self.point_count)
        rule = np.full(self.point_count, SMOOTH, dtype=np.int64)
        rule[count == 2] = CREASE
        rule[(count > 2) | (vertex_sharpness > 0.0)] = CORNER
        # A point no face uses stays where it is.
        rule[self.face_count == 0] = CORNER
        return rule

    def crease_neighbours(self, edge_sharpness: F64, points: F64) -> F64:
        """Per point, the sum of the far ends of its sharp edges."""
        sharp = self.edge_ends[edge_sharpness > 0.0]
        return _sum_by(sharp[:, 0], points[sharp[:, 1]], self.point_count) + _sum_by(
            sharp[:, 1], points[sharp[:, 0]], self.point_count
        )


def _topology(
    sizes: I64,
    indices: I64,
    point_count: int,
    sharp_keys: I64,
    sharp_values: F64,
    vertex_sharpness: F64,
    boundary: str,
) -> _Topology:
    starts = np.cumsum(sizes) - sizes
    corner_face = np.repeat(np.arange(len(sizes)), sizes)
    position = np.arange(len(indices)) - starts[corner_face]
    corner_next = starts[corner_face] + (position + 1) % sizes[corner_face]
    corner_previous = starts[corner_face] + (position - 1) % sizes[corner_face]
    keys = _edge_keys(indices, indices[corner_next])
    unique, corner_edge = np.unique(keys, return_inverse=True)
    corner_edge = corner_edge.reshape(-1)
    edge_ends = np.stack([unique >> 32, unique & 0xFFFFFFFF], axis=1)
    edge_faces = np.bincount(corner_edge, minlength=len(unique))
    edge_sharpness = np.zeros(len(unique))
    if len(sharp_keys):
        found = np.searchsorted(unique, sharp_keys)
        found = np.minimum(found, max(len(unique) - 1, 0))
        hit = (unique[found] == sharp_keys) if len(unique) else np.zeros(0, dtype=bool)
        np.maximum.at(edge_sharpness, found[hit], sharp_values[hit])
    # Boundary and non-manifold edges are infinitely sharp (with boundary "none" too:
    # the faces there are dropped, and this keeps their neighbours' rules defined).
    edge_sharpness[edge_faces != 2] = INFINITELY_SHARP
    valence = np.bincount(edge_ends.reshape(-1), minlength=point_count)
    face_count = np.bincount(indices, minlength=point_count)
    vertex_sharpness = vertex_sharpness.copy()
    on_boundary = np.zeros(point_count, dtype=bool)
    on_boundary[edge_ends[edge_faces == 1].reshape(-1)] = True
    if boundary == "edgeAndCorner":
        vertex_sharpness[on_boundary & (face_count == 1)] = INFINITELY_SHARP
    return _Topology(
        point_count=point_count,
        sizes=sizes,
        corner_face=corner_face,
        corner_point=indices,
        corner_next=corner_next,
        corner_previous=corner_previous,
        corner_edge=corner_edge,
        edge_ends=edge_ends,
        edge_faces=edge_faces,
        edge_sharpness=edge_sharpness,
        vertex_sharpness=vertex_sharpness,
        valence=valence,
        face_count=face_count,
        on_boundary=on_boundary,
    )


@dataclass(frozen=True)
class _Step:
    """One level of refinement, as weights precomputed from its topology."""

    topology: _Topology
    #: Per edge, how much of its point is the edge's midpoint rather than the smooth rule.
    edge_sharp_weight: F64
    #: Per point, the weights of its smooth, crease and corner rules (rows sum to 1), and
    #: the sharpness that selects each crease rule's neighbours (parent's, child's).
    rule_weights: F64
    parent_sharpness: F64
    child_sharpness: F64
    #: Per point, whether its crease rule is the parent's (else the child's).
    parent_creases: npt.NDArray[np.bool_]

    def points(self, points: F64) -> F64:
        top = self.topology
        e0, e1 = top.edge_ends[:, 0], top.edge_ends[:, 1]
        face_points = _sum_by(top.corner_face, points[top.corner_point], top.face_total)
        face_points /= top.sizes[:, None]
        midpoints = 0.5 * (points[e0] + points[e1])
        around = _sum_by(top.corner_edge, face_points[top.corner_face], top.edge_total)
        smooth_edges = (points[e0] + points[e1] + around) / (2 + top.edge_faces)[:, None]
        w = self.edge_sharp_weight[:, None]
        edge_points = w * midpoints + (1.0 - w) * smooth_edges
        n = np.maximum(top.valence, 1)[:, None].astype(np.float64)
        faces_mean = _sum_by(top.corner_point, face_points[top.corner_face], top.point_count)
        faces_mean /= np.maximum(top.face_count, 1)[:, None]
        edges_mean = _sum_by(e0, midpoints, top.point_count) + _sum_by(
            e1, midpoints, top.point_count
        )
        edges_mean /= n
        smooth = (faces_mean + 2.0 * edges_mean + (n - 3.0) * points) / n
        weights = self.rule_weights
        vertex_points = weights[:, SMOOTH, None] * smooth + weights[:, CORNER, None] * points
        creasing = weights[:, CREASE] > 0.0
        if creasing.any():
            # The crease rule reads the edges sharp in whichever of parent and child takes it.
            ends = top.crease_neighbours(self.parent_sharpness, points)
            from_child = creasing & ~self.parent_creases
            if from_child.any():
                ends[from_child] = top.crease_neighbours(self.child_sharpness, points)[from_child]
            crease = (ends + 6.0 * points) / 8.0
            vertex_points += weights[:, CREASE, None] * crease
        return np.concatenate([vertex_points, edge_points, face_points])


def _fraction(
    top: _Topology, child_edges: F64, child_vertices: F64, parent_rule: I64, child_rule: I64
) -> F64:
    """Per point, the weight of the parent's rule where it differs from the child's: as
    OpenSubdiv blends them, the mean sharpness of the edges and corner that turn smooth
    (at most 1)."""
    parent_edges, parent_vertices = top.edge_sharpness, top.vertex_sharpness
    transitions = (parent_edges > 0.0) & (child_edges <= 0.0)
    ends = top.edge_ends[transitions].reshape(-1)
    total = np.bincount(
        ends, weights=np.repeat(parent_edges[transitions], 2), minlength=top.point_count
    ).astype(np.float64)
    count = np.bincount(ends, minlength=top.point_count).astype(np.float64)
    turning = (parent_vertices > 0.0) & (child_vertices <= 0.0)
    total += np.where(turning, parent_vertices, 0.0)
    count += turning
    fraction = np.minimum(np.divide(total, count, out=np.zeros_like(total), where=count > 0), 1.0)
    return np.where(parent_rule == child_rule, 1.0, fraction)


def _step(top: _Topology) -> _Step:
    parent_edges = top.edge_sharpness
    child_edges = _decremented(parent_edges)
    parent_vertices = top.vertex_sharpness
    child_vertices = _decremented(parent_vertices)
    parent_rule = top.rules(parent_edges, parent_vertices)
    child_rule = top.rules(child_edges, child_vertices)
    fraction = _fraction(top, child_edges, child_vertices, parent_rule, child_rule)
    weights = np.zeros((top.point_count, 3))
    rows = np.arange(top.point_count)
    weights[rows, parent_rule] += fraction
    weights[rows, child_rule] += 1.0 - fraction
    return _Step(
        topology=top,
        edge_sharp_weight=np.minimum(parent_edges, 1.0),
        rule_weights=weights,
        parent_sharpness=parent_edges,
        child_sharpness=child_edges,
        parent_creases=parent_rule == CREASE,
    )


def _child_order(top: _Topology) -> I64:
    """Where each refined face's corners come from among (its parent face-vertex's point,
    the edge after it, the face, the edge before it), as positions in that list of four
    per face-vertex. A quad's children keep its orientation, so that each quad of the
    cage refines to a grid whose diagonals all run alike, as Blender's do: the child at
    corner k starts at its corner nearest the quad's first (a face of another size starts
    each child at its own corner)."""
    starts = np.cumsum(top.sizes) - top.sizes
    position = np.arange(len(top.corner_point)) - starts[top.corner_face]
    turn = np.where(top.sizes[top.corner_face] == 4, (4 - position) % 4, 0)
    return (4 * np.arange(len(turn))[:, None] + (np.arange(4) + turn[:, None]) % 4).reshape(-1)


def _child_points(top: _Topology, order: I64 | None = None) -> I64:
    """The points of one level's refined faces: a quad per face-vertex, in face-vertex
    order, its corners as `_child_order` turns them (points numbered vertices, then
    edges, then faces)."""
    p, e = top.point_count, top.edge_total
    return np.stack(
        [
            top.corner_point,
            p + top.corner_edge,
            p + e + top.corner_face,
            p + top.corner_edge[top.corner_previous],
        ],
        axis=1,
    ).reshape(-1)[_child_order(top) if order is None else order]


def _children(top: _Topology) -> tuple[I64, I64, F64, F64]:
    """One level's refined faces (`_child_points`), the sharp edges among them as keys
    with their sharpness, and every refined point's own sharpness: for a ring
    (`_Rings`), whose faces are renumbered each level and so found by their keys."""
    p, e = top.point_count, top.edge_total
    indices = _child_points(top)
    # Each edge's halves keep its sharpness, less a level.
    child = _decremented(top.edge_sharpness)
    sharp = np.flatnonzero(child > 0.0)
    ends = top.edge_ends[sharp]
    keys = np.concatenate([_edge_keys(ends[:, 0], p + sharp), _edge_keys(ends[:, 1], p + sharp)])
    sharpness = np.concatenate([child[sharp], child[sharp]])
    vertex_sharpness = np.concatenate(
        [_decremented(top.vertex_sharpness), np.zeros(e + top.face_total)]
    )
    return indices, keys, sharpness, vertex_sharpness


def _child_topology(top: _Topology, boundary: str) -> _Topology:
    """The topology of `_children`'s faces, numbered from the parent's rather than found
    by sorting: the halves of parent edge e are edges 2e (at its first point) and 2e + 1,
    and the edge from face-vertex c's edge point to its face point is 2E + c."""
    p, e, f = top.point_count, top.edge_total, top.face_total
    count = len(top.corner_point)
    order = _child_order(top)
    indices = _child_points(top, order)
    after, before = top.corner_edge, top.corner_edge[top.corner_previous]
    half_after = 2 * after + (top.edge_ends[after, 0] != top.corner_point)
    half_before = 2 * before + (top.edge_ends[before, 0] != top.corner_point)
    corners = np.arange(count)
    corner_edge = np.stack(
        [half_after, 2 * e + corners, 2 * e + top.corner_previous, half_before], axis=1
    ).reshape(-1)[order]
    middles = p + np.arange(e)
    halves = np.stack(
        [np.stack([top.edge_ends[:, 0], middles], 1), np.stack([top.edge_ends[:, 1], middles], 1)],
        axis=1,
    ).reshape(-1, 2)
    inner = np.stack([p + top.corner_edge, p + e + top.corner_face], axis=1)
    edge_faces = np.concatenate([np.repeat(top.edge_faces, 2), np.full(count, 2)])
    edge_sharpness = np.concatenate(
        [np.repeat(_decremented(top.edge_sharpness), 2), np.zeros(count)]
    )
    edge_sharpness[edge_faces != 2] = INFINITELY_SHARP
    face_count = np.concatenate([top.face_count, 2 * top.edge_faces, top.sizes])
    on_boundary = np.concatenate([top.on_boundary, top.edge_faces == 1, np.zeros(f, bool)])
    vertex_sharpness = np.concatenate([_decremented(top.vertex_sharpness), np.zeros(e + f)])
    if boundary == "edgeAndCorner":
        vertex_sharpness[on_boundary & (face_count == 1)] = INFINITELY_SHARP
    position = np.arange(4 * count) % 4
    base = 4 * (np.arange(4 * count) // 4)
    return _Topology(
        point_count=p + e + f,
        sizes=np.full(count, 4, dtype=np.int64),
        corner_face=np.arange(4 * count) // 4,
        corner_point=indices,
        corner_next=base + (position + 1) % 4,
        corner_previous=base + (position + 3) % 4,
        corner_edge=corner_edge,
        edge_ends=np.concatenate([halves, inner]),
        edge_faces=edge_faces,
        edge_sharpness=edge_sharpness,
        vertex_sharpness=vertex_sharpness,
        valence=np.concatenate([top.valence, 2 + top.edge_faces, top.sizes]),
        face_count=face_count,
        on_boundary=on_boundary,
    )


#: Levels past a mesh's own over which a dart (a point where a single sharp edge ends)
#: is followed to its limit: the smooth rule's limit position is not its own, and what
#: is left of the difference halves about every level (1.5·10⁻⁷ of a cube of side 2 after
#: these).
DART_LEVELS = 14


def _inexact(top: _Topology) -> npt.NDArray[np.bool_]:
    """The points whose limit the smooth, crease or corner positions do not give: darts,
    and points whose own or edges' sharpness is semi-sharp (not 0 nor infinite), unless
    they stay corners at every level."""
    sharp = top.edge_sharpness > 0.0
    infinite = top.edge_sharpness >= INFINITELY_SHARP
    count = np.bincount(top.edge_ends[sharp].reshape(-1), minlength=top.point_count)
    finite = np.bincount(top.edge_ends[sharp & ~infinite].reshape(-1), minlength=top.point_count)
    vertex = top.vertex_sharpness
    smooth = (count == 0) & (vertex <= 0.0)
    corner = (vertex >= INFINITELY_SHARP) | ((count - finite) > 2)
    crease = (count == 2) & (finite == 0) & (vertex <= 0.0)
    return ~(smooth | corner | crease) & (top.face_count > 0)


@dataclass(frozen=True)
class _Rings:
    """How to follow chosen points to their limits, built once per topology: each point
    refined on its own with the faces around it (a point's ring of faces at one level
    refines to its ring at the next, so each level keeps only the child faces at the
    point's own corners)."""

    #: The mesh's point behind each ring point, and per level its step and the refined
    #: ring points it keeps; the last level's topology and the chosen points' places.
    sources: I64
    steps: list[tuple[_Step, I64]]
    final: _Topology
    centres: I64

    @staticmethod
    def around(top: _Topology, chosen: I64, boundary: str) -> _Rings:
        corners = np.flatnonzero(np.isin(top.corner_point, chosen))
        owner = np.searchsorted(chosen, top.corner_point[corners])
        # The ring faces' points, a copy per chosen point: (owner, point) numbered anew.
        face_corners = top.corner_face[corners]
        starts = np.cumsum(top.sizes) - top.sizes
        quads = top.corner_point[starts[face_corners][:, None] + np.arange(4)]
        # Each ring face starts at its owner's corner, so that its child there comes first.
        turn = (corners - starts[face_corners])[:, None]
        quads = np.take_along_axis(quads, (np.arange(4) + turn) % 4, axis=1)
        unique, local = np.unique(owner[:, None] * top.point_count + quads, return_inverse=True)
        local = local.reshape(-1, 4)
        centre = np.searchsorted(unique, np.arange(len(chosen)) * top.point_count + chosen)
        edge_keys = _edge_keys(top.edge_ends[:, 0], top.edge_ends[:, 1])
        by_key = np.argsort(edge_keys)
        ends = unique[local] % top.point_count, unique[np.roll(local, -1, axis=1)] % top.point_count
        found = np.searchsorted(edge_keys[by_key], _edge_keys(*ends).reshape(-1))
        sharpness = top.edge_sharpness[by_key[found]]
        keys = _edge_keys(local, np.roll(local, -1, axis=1)).reshape(-1)
        vertex_sharpness = np.zeros(len(unique))
        vertex_sharpness[centre] = top.vertex_sharpness[chosen]
        finite = sharpness[(sharpness > 0.0) & (sharpness < INFINITELY_SHARP)]
        indices = local.reshape(-1)
        count = len(unique)
        steps: list[tuple[_Step, I64]] = []
        levels = DART_LEVELS + int(np.ceil(finite.max(initial=0.0)))
        while len(steps) < levels:
            before = (indices, keys, sharpness, vertex_sharpness, centre)
            sizes = np.full(len(indices) // 4, 4, dtype=np.int64)
            ring = _topology(sizes, indices, count, keys, sharpness, vertex_sharpness, boundary)
            children, keys, sharpness, vertex_sharpness = _children(ring)
            # The child at each face's first corner, the owner's, and its points.
            kept = children.reshape(-1, 4)[_first_corners(ring)]
            used, indices = np.unique(kept, return_inverse=True)
            indices = indices.reshape(-1)
            steps.append((_step(ring), used))
            renumber = np.full(ring.point_count + ring.edge_total + ring.face_total, -1)
            renumber[used] = np.arange(len(used))
            mapped = renumber[np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1)]
            keep = (mapped >= 0).all(axis=1)
            keys, sharpness = _edge_keys(mapped[keep, 0], mapped[keep, 1]), sharpness[keep]
            vertex_sharpness, centre, count = vertex_sharpness[used], renumber[centre], len(used)
            after = (indices, keys, sharpness, vertex_sharpness, centre)
            if all(np.array_equal(a, b) for a, b in zip(before, after, strict=True)):
                # Once no sharpness is left to wear off, a level refines the rings to
                # themselves, numbered alike: every level left is this one.
                steps.extend([steps[-1]] * (levels - len(steps)))
        sizes = np.full(len(indices) // 4, 4, dtype=np.int64)
        final = _topology(sizes, indices, count, keys, sharpness, vertex_sharpness, boundary)
        return _Rings(unique % top.point_count, steps, final, centre)

    def limits(self, points: F64) -> F64:
        """The chosen points' limit positions, from the points of the mesh around them."""
        ring = points[self.sources]
        for step, used in self.steps:
            ring = step.points(ring)[used]
        return _limit(self.final, ring)[self.centres]


def _first_corners(top: _Topology) -> npt.NDArray[np.bool_]:
    """Each face's first face-vertex."""
    first = np.zeros(len(top.corner_point), dtype=bool)
    first[np.cumsum(top.sizes) - top.sizes] = True
    return first


def _limit(top: _Topology, points: F64) -> F64:
    """The limit positions of the points of an all-quad mesh (one refined at least once),
    by the rule each point's sharpness gives it: exact where it keeps that rule at every
    level (`_inexact` says where not)."""
    quads = top.corner_point.reshape(-1, 4)
    diagonal = quads[:, [2, 3, 0, 1]].reshape(-1)
    e0, e1 = top.edge_ends[:, 0], top.edge_ends[:, 1]
    neighbours = _sum_by(e0, points[e1], top.point_count) + _sum_by(e1, points[e0], top.point_count)
    across = _sum_by(top.corner_point, points[diagonal], top.point_count)
    n = np.maximum(top.valence, 1)[:, None].astype(np.float64)
    limits = (n * n * points + 4.0 * neighbours + across) / (n * (n + 5.0))
    rule = top.rules(top.edge_sharpness, top.vertex_sharpness)
    crease = rule == CREASE
    if crease.any():
        ends = top.crease_neighbours(top.edge_sharpness, points)
        limits[crease] = (ends[crease] + 4.0 * points[crease]) / 6.0
    corner = rule == CORNER
    limits[corner] = points[corner]
    return limits


def _tags(
    point_count: int,
    crease_indices: Sequence[int] | npt.ArrayLike,
    crease_lengths: Sequence[int] | npt.ArrayLike,
    crease_sharpnesses: Sequence[float] | npt.ArrayLike,
    corner_indices: Sequence[int] | npt.ArrayLike,
    corner_sharpnesses: Sequence[float] | npt.ArrayLike,
    where: str,
) -> tuple[I64, F64, F64]:
    """The creases as edge keys with their sharpness, and each point's corner sharpness."""
    chain = np.asarray(crease_indices, dtype=np.int64).reshape(-1)
    lengths = np.asarray(crease_lengths, dtype=np.int64).reshape(-1)
    sharpness = np.asarray(crease_sharpnesses, dtype=np.float64).reshape(-1)
    if np.any(lengths < 2) or int(lengths.sum()) != len(chain):
        raise SubdivisionError(
            f"{where}: creaseLengths ({lengths.tolist()[:8]}) must each be 2 or more and sum "
            f"to the {len(chain)} creaseIndices"
        )
    edges_per_crease = lengths - 1
    if len(sharpness) == len(lengths):
        sharpness = np.repeat(sharpness, edges_per_crease)
    elif len(sharpness) != int(edges_per_crease.sum()):
        raise SubdivisionError(
            f"{where}: creaseSharpnesses has {len(sharpness)} values; give one per crease "
            f"({len(lengths)}) or one per crease edge ({int(edges_per_crease.sum())})"
        )
    if len(chain) and (chain.min() < 0 or chain.max() >= point_count):
        raise SubdivisionError(f"{where}: creaseIndices reach past the {point_count} points")
    last = np.cumsum(lengths) - 1
    starts = np.ones(len(chain), dtype=bool)
    starts[last] = False
    first = np.flatnonzero(starts)
    keys = _edge_keys(chain[first], chain[first + 1]) if len(chain) else np.zeros(0, np.int64)
    vertex_sharpness = np.zeros(point_count)
    corners = np.asarray(corner_indices, dtype=np.int64).reshape(-1)
    corner_values = np.asarray(corner_sharpnesses, dtype=np.float64).reshape(-1)
    if len(corners) != len(corner_values):
        raise SubdivisionError(
            f"{where}: {len(corners)} cornerIndices but {len(corner_values)} cornerSharpnesses"
        )
    if len(corners) and (corners.min() < 0 or corners.max() >= point_count):
        raise SubdivisionError(f"{where}: cornerIndices reach past the {point_count} points")
    np.maximum.at(vertex_sharpness, corners, np.nan_to_num(corner_values))
    return keys, np.nan_to_num(sharpness), vertex_sharpness


def _weld(corner_point: I64, values: F64) -> tuple[I64, F64]:
    """Each face-vertex's value numbered as one with the values equal to it at its point,
    and the table of those as rows of (point, value...)."""
    rows = np.column_stack([corner_point.astype(np.float64), values + 0.0])
    table, ids = np.unique(rows, axis=0, return_inverse=True)
    return ids.reshape(-1), table


def _manifold(top: _Topology) -> npt.NDArray[np.bool_]:
    """Per point, whether its faces form one fan: closed, or open between two boundary
    edges."""
    ends = top.edge_ends
    open_edges = np.bincount(ends[top.edge_faces == 1].reshape(-1), minlength=top.point_count)
    shared = np.bincount(ends[top.edge_faces > 2].reshape(-1), minlength=top.point_count)
    closed = (open_edges == 0) & (top.valence == top.face_count)
    fan = (open_edges == 2) & (top.valence == top.face_count + 1)
    return (shared == 0) & (closed | fan)


def _face_varying_topology(cage: _Topology, ids: I64, value_point: I64) -> _Topology:
    """The values' own mesh: the cage's faces on the values, with the cage's creases and
    corners (where values differ across an edge, the edge is two boundary edges)."""
    corners = np.flatnonzero(cage.edge_sharpness[cage.corner_edge] > 0.0)
    keys = _edge_keys(ids[corners], ids[cage.corner_next[corners]])
    return _topology(
        cage.sizes,
        ids,
        len(value_point),
        keys,
        cage.edge_sharpness[cage.corner_edge[corners]],
        cage.vertex_sharpness[value_point],
        "edgeOnly",
    )


def _sharpened(top: _Topology, cage: _Topology, value_point: I64, interpolation: str) -> _Topology:
    """The values' mesh with the corners `interpolation` makes sharp, as OpenSubdiv
    decides them at the points where values differ (or that it treats so): every value
    there for `boundaries` (which takes in the cage's boundary too), at junctions of
    three or more values (`cornersPlus1` and `cornersPlus2`), at the ends of seams inside
    the mesh (`cornersPlus2`), at both values where one is a corner (`cornersPlus2`); and
    else each value that is a corner (one face) or whose faces are not one fan."""
    linear = interpolation == "boundaries"
    corners_sharp = interpolation != "none"
    dependent = interpolation in ("cornersPlus1", "cornersPlus2")
    darts = interpolation in ("cornersPlus2", "boundaries")
    count = cage.point_count
    values_at = np.bincount(value_point, minlength=count)
    pairs = np.unique(np.stack([cage.corner_edge, top.corner_edge], axis=1), axis=0)
    seams = np.bincount(pairs[:, 0], minlength=cage.edge_total) > 1
    seam_ends = np.zeros(count, dtype=bool)
    seam_ends[cage.edge_ends[seams].reshape(-1)] = True
    mismatched = (values_at > 1) | seam_ends
    if linear:
        mismatched |= cage.on_boundary & (cage.face_count > 0)
    elif corners_sharp:
        mismatched |= cage.on_boundary & (cage.face_count == 1)
    every = (
        linear
        | (cage.vertex_sharpness >= INFINITELY_SHARP)
        | ~_manifold(cage)
        | (dependent & (values_at > 2))
        | (darts & (values_at == 1) & ~cage.on_boundary)
    )
    disjoint = ~_manifold(top)
    corner = top.face_count == 1
    if dependent:
        either = disjoint | corner if interpolation == "cornersPlus2" else disjoint
        every |= (values_at == 2) & (np.bincount(value_point[either], minlength=count) > 0)
    own = disjoint | (corner & corners_sharp)
    sharp = mismatched[value_point] & (every[value_point] | own)
    vertex_sharpness = top.vertex_sharpness.copy()
    vertex_sharpness[sharp] = INFINITELY_SHARP
    return replace(top, vertex_sharpness=vertex_sharpness)


@dataclass(frozen=True)
class _Levels:
    """A topology refined some levels: each level's step and, for the limit, the last
    level's topology and the points followed further to theirs."""

    steps: list[_Step]
    last: _Topology
    limit: bool
    inexact: I64
    rings: _Rings | None

    @staticmethod
    def of(top: _Topology, levels: int, boundary: str, limit: bool) -> _Levels:
        steps = []
        for _ in range(levels):
            steps.append(_step(top))
            top = _child_topology(top, boundary)
        inexact = np.flatnonzero(_inexact(top)) if limit else np.zeros(0, dtype=np.int64)
        rings = _Rings.around(top, inexact, boundary) if len(inexact) else None
        return _Levels(steps, top, limit, inexact, rings)

    def refine(self, points: F64) -> F64:
        for step in self.steps:
            points = step.points(points)
        if not self.limit:
            return points
        limits = _limit(self.last, points)
        if self.rings is not None:
            limits[self.inexact] = self.rings.limits(points)
        return limits


class CatmullClark:
    """A cage's topology refined `levels` times: the refined faces (all quads, holes and
    faces of fewer than three points left out), each one's face in the cage, and the
    means to refine points and face-varying values on it."""

    def __init__(
        self,
        face_vertex_counts: npt.ArrayLike,
        face_vertex_indices: npt.ArrayLike,
        point_count: int,
        levels: int,
        *,
        hole_indices: npt.ArrayLike = (),
        crease_indices: npt.ArrayLike = (),
        crease_lengths: npt.ArrayLike = (),
        crease_sharpnesses: npt.ArrayLike = (),
        corner_indices: npt.ArrayLike = (),
        corner_sharpnesses: npt.ArrayLike = (),
        boundary: str = "edgeAndCorner",
        limit: bool = True,
        where: str = "mesh",
    ) -> None:
        if levels < 1:
            raise SubdivisionError(f"{where}: refine at least one level, not {levels}")
        if boundary not in BOUNDARIES:
            raise SubdivisionError(
                f"{where}: interpolateBoundary '{boundary}' is not one of {', '.join(BOUNDARIES)}"
            )
        counts = np.asarray(face_vertex_counts, dtype=np.int64).reshape(-1)
        indices = np.asarray(face_vertex_indices, dtype=np.int64).reshape(-1)
        if np.any(counts < 0) or int(counts.sum()) != len(indices):
            raise SubdivisionError(
                f"{where}: faceVertexCounts sum to {int(counts.sum())} but faceVertexIndices "
                f"has {len(indices)} entries"
            )
        if len(indices) and (indices.min() < 0 or indices.max() >= point_count):
            raise SubdivisionError(
                f"{where}: faceVertexIndices reach past the {point_count} points"
            )
        # Faces of fewer than three points bound nothing; their corners are dropped, and
        # the face-varying values with them.
        kept_faces = np.flatnonzero(counts >= 3)
        kept_corners = np.repeat(counts >= 3, counts)
        sizes, indices = counts[kept_faces], indices[kept_corners]
        holes = np.zeros(len(counts), dtype=bool)
        hole_list = np.asarray(hole_indices, dtype=np.int64).reshape(-1)
        holes[hole_list[(hole_list >= 0) & (hole_list < len(counts))]] = True
        holes = holes[kept_faces]
        keys, sharpness, vertex_sharpness = _tags(
            point_count,
            crease_indices,
            crease_lengths,
            crease_sharpnesses,
            corner_indices,
            corner_sharpnesses,
            where,
        )
        self._kept_corners = kept_corners
        faces = kept_faces
        top = _topology(sizes, indices, point_count, keys, sharpness, vertex_sharpness, boundary)
        if boundary == "none":
            # No boundary interpolation: faces with a point on the boundary have no limit
            # surface, and draw as holes.
            holes = holes | np.bincount(
                top.corner_face, weights=top.on_boundary[indices], minlength=len(sizes)
            ).astype(bool)
        self._cage, self._where = top, where
        self._levels = _Levels.of(top, levels, boundary, limit)
        for step in self._levels.steps:
            faces = faces[step.topology.corner_face]
            holes = holes[step.topology.corner_face]
        #: Per rule, the last values refined: their bytes, their weld, its levels and the
        #: result (a mesh whose points move reads the same coordinates every frame).
        self._face_varying: dict[str, tuple[tuple[int, bytes], bytes, _Levels | None, F64]] = {}
        drawn = ~holes
        self.point_count = self._levels.last.point_count
        indices = self._levels.last.corner_point
        #: The refined faces (quads) that draw, and each one's face in the cage.
        self.face_vertex_indices = indices.reshape(-1, 4)[drawn].reshape(-1)
        self.face_vertex_counts = np.full(int(drawn.sum()), 4, dtype=np.int64)
        self.faces = faces[drawn]
        self._drawn_corners = np.repeat(drawn, 4)

    def refine(self, points: npt.ArrayLike) -> F64:
        """The refined points of a cage's `points` (on the limit surface unless built
        without it)."""
        refined = np.asarray(points, dtype=np.float64)
        if refined.ndim != 2:
            refined = refined.reshape(len(refined), -1)
        return self._levels.refine(refined)

    def refine_face_varying(
        self, values: npt.ArrayLike, interpolation: str = "cornersPlus1"
    ) -> F64:
        """Values per face-vertex of the cage (texture coordinates) refined as
        `faceVaryingLinearInterpolation` says: one row per face-vertex of the drawn
        refined faces. Values are one where they are equal at a point (a seam is where
        they differ), and refine as their own mesh with the cage's creases, its seams as
        boundaries and the corners each rule sharpens; `all` refines them linearly in each
        face, as do values that are not all finite (so that one cannot spread). The result
        is kept, read-only, for the same values again."""
        if interpolation not in FACE_VARYING_INTERPOLATIONS:
            raise SubdivisionError(
                f"{self._where}: faceVaryingLinearInterpolation '{interpolation}' is not one of "
                f"{', '.join(FACE_VARYING_INTERPOLATIONS)}"
            )
        refined = np.asarray(values, dtype=np.float64)
        refined = refined.reshape(len(refined), -1)[self._kept_corners]
        key = (refined.shape[1], refined.tobytes())
        last = self._face_varying.get(interpolation)
        if last is not None and last[0] == key:
            return last[3]
        if interpolation == "all" or not np.isfinite(refined).all():
            result = self._linear_face_varying(refined)
            result.flags.writeable = False
            self._face_varying[interpolation] = (key, b"", None, result)
            return result
        ids, table = _weld(self._cage.corner_point, refined)
        weld = ids.tobytes()
        levels = last[2] if last is not None and last[1] == weld else None
        if levels is None:
            value_point = table[:, 0].astype(np.int64)
            top = _face_varying_topology(self._cage, ids, value_point)
            top = _sharpened(top, self._cage, value_point, interpolation)
            levels = _Levels.of(top, len(self._levels.steps), "edgeOnly", self._levels.limit)
        result = levels.refine(table[:, 1:])[levels.last.corner_point][self._drawn_corners]
        result.flags.writeable = False
        self._face_varying[interpolation] = (key, weld, levels, result)
        return result

    def _linear_face_varying(self, refined: F64) -> F64:
        for step in self._levels.steps:
            top = step.topology
            centres = _sum_by(top.corner_face, refined, top.face_total) / top.sizes[:, None]
            refined = np.stack(
                [
                    refined,
                    0.5 * (refined + refined[top.corner_next]),
                    centres[top.corner_face],
                    0.5 * (refined + refined[top.corner_previous]),
                ],
                axis=1,
            ).reshape(-1, refined.shape[1])[_child_order(top)]
        return refined[self._drawn_corners]
