"""Catmull-Clark refinement of USD meshes (`crepuscular_usd.subdivision`): the textbook
rules, limit positions that do not depend on the level they are taken at (the limit
surface is one surface), sharp features, boundaries, holes, face-varying values and
bad tags."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from crepuscular_usd.subdivision import CatmullClark, SubdivisionError

#: A cube of side 2 about the origin, faces wound outwards.
CUBE_POINTS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
CUBE_FACES = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
CUBE = {
    "face_vertex_counts": [4] * 6,
    "face_vertex_indices": [i for face in CUBE_FACES for i in face],
    "point_count": 8,
}

#: A pentagon with a pyramid of triangles on it: faces of three, and one of five.
PENTAGON_POINTS = np.array(
    [[np.cos(t), np.sin(t), 0.0] for t in np.linspace(0, 2 * np.pi, 6)[:-1]] + [[0.0, 0.0, 1.0]]
)
PENTAGON = {
    "face_vertex_counts": [5, 3, 3, 3, 3, 3],
    "face_vertex_indices": [0, 4, 3, 2, 1, 0, 1, 5, 1, 2, 5, 2, 3, 5, 3, 4, 5, 4, 0, 5],
    "point_count": 6,
}


def _grid(columns: int, rows: int) -> tuple[np.ndarray, dict]:
    """An open grid of quads over a bumpy height field."""
    x, y = np.meshgrid(np.arange(columns + 1.0), np.arange(rows + 1.0))
    points = np.stack([x.ravel(), y.ravel(), 0.2 * np.sin(x.ravel() + 2 * y.ravel())], axis=1)
    first = (np.arange(rows)[:, None] * (columns + 1) + np.arange(columns)).ravel()
    faces = np.stack([first, first + 1, first + columns + 2, first + columns + 1], axis=1)
    return points, {
        "face_vertex_counts": [4] * len(faces),
        "face_vertex_indices": faces.ravel(),
        "point_count": len(points),
    }


def _limits(points: np.ndarray, mesh: dict, levels: int, **tags: object) -> np.ndarray:
    return CatmullClark(**mesh, levels=levels, **tags).refine(points)


def test_one_level_follows_the_textbook_rules() -> None:
    """A cube's corner moves to 5/9 of itself, each face's point is its centre and each
    edge's the mean of its ends and the faces beside it; every face-vertex becomes a
    quad, and the points are the cage's, then the edges', then the faces'."""
    refinement = CatmullClark(**CUBE, levels=1, limit=False)
    refined = refinement.refine(CUBE_POINTS)
    assert refinement.point_count == len(refined) == 8 + 12 + 6
    np.testing.assert_allclose(refined[:8], CUBE_POINTS * 5 / 9, atol=1e-15)
    edge_points = refined[8:20]
    np.testing.assert_allclose(np.sort(np.abs(edge_points), axis=1)[:, 0], 0.0, atol=1e-15)
    np.testing.assert_allclose(np.sort(np.abs(edge_points), axis=1)[:, 1:], 0.75, atol=1e-15)
    np.testing.assert_allclose(np.abs(refined[20:]).sum(axis=1), 1.0, atol=1e-15)
    assert len(refinement.faces) == 24
    assert refinement.face_vertex_counts.tolist() == [4] * 24
    np.testing.assert_array_equal(refinement.faces, np.repeat(np.arange(6), 4))


@pytest.mark.parametrize(
    "tags",
    [
        {},
        {"crease_indices": [0, 1, 3, 2, 0], "crease_lengths": [5], "crease_sharpnesses": [10]},
        {"corner_indices": [7], "corner_sharpnesses": [10]},
        # Semi-sharp, per crease and per edge, and a semi-sharp corner.
        {"crease_indices": [0, 1], "crease_lengths": [2], "crease_sharpnesses": [2.5]},
        {"crease_indices": [0, 1, 3], "crease_lengths": [3], "crease_sharpnesses": [0.4, 3.7]},
        {"corner_indices": [7], "corner_sharpnesses": [1.7]},
        # A dart: one infinitely sharp edge, smooth at both its ends.
        {"crease_indices": [0, 4], "crease_lengths": [2], "crease_sharpnesses": [10]},
    ],
)
def test_limit_positions_do_not_depend_on_the_level(tags: dict) -> None:
    """The limit surface is one surface: a point's limit position taken after one level,
    after two or after three is the same (each level keeps the points before it first)."""
    limits = [_limits(CUBE_POINTS, CUBE, levels, **tags) for levels in (1, 2, 3)]
    for coarse, fine in itertools.pairwise(limits):
        np.testing.assert_allclose(fine[: len(coarse)], coarse, atol=1e-6)
    assert np.abs(limits[0] - limits[1][: len(limits[0])]).max() < 1e-6


def test_faces_of_other_sizes_reach_the_same_limit() -> None:
    limits = [_limits(PENTAGON_POINTS, PENTAGON, levels) for levels in (1, 2, 3)]
    np.testing.assert_allclose(limits[1][: len(limits[0])], limits[0], atol=1e-12)
    np.testing.assert_allclose(limits[2][: len(limits[1])], limits[1], atol=1e-12)


def test_sharp_features_keep_their_shape() -> None:
    """A cube creased infinitely along every edge stays the cube; smooth, it rounds to
    well inside it; a sharp corner stays where it is."""
    edges = [[0, 1], [1, 3], [3, 2], [2, 0], [4, 5], [5, 7], [7, 6], [6, 4]]
    edges += [[0, 4], [1, 5], [2, 6], [3, 7]]
    creased = _limits(
        CUBE_POINTS,
        CUBE,
        3,
        crease_indices=[i for edge in edges for i in edge],
        crease_lengths=[2] * 12,
        crease_sharpnesses=[10] * 12,
    )
    np.testing.assert_allclose(np.abs(creased).max(axis=1), 1.0, atol=1e-12)
    smooth = _limits(CUBE_POINTS, CUBE, 3)
    assert np.abs(smooth).max() < 0.9
    cornered = _limits(CUBE_POINTS, CUBE, 2, corner_indices=[7], corner_sharpnesses=[10])
    np.testing.assert_allclose(cornered[7], CUBE_POINTS[7])
    assert np.linalg.norm(cornered[6]) < np.sqrt(3) - 0.3


def test_boundaries_interpolate_as_authored() -> None:
    """An open grid's boundary is a B-spline curve of its boundary points: with
    edgeAndCorner its corners stay put, with edgeOnly they are pulled in; with none, the
    faces touching the boundary draw nothing. Limits hold across levels for each."""
    points, grid = _grid(4, 3)
    for boundary in ("edgeOnly", "edgeAndCorner", "none"):
        one = _limits(points, grid, 1, boundary=boundary)
        two = _limits(points, grid, 2, boundary=boundary)
        np.testing.assert_allclose(two[: len(one)], one, atol=1e-12)
    corners = [0, 4, 15, 19]
    kept = _limits(points, grid, 2, boundary="edgeAndCorner")
    np.testing.assert_allclose(kept[corners], points[corners], atol=1e-15)
    pulled = _limits(points, grid, 2, boundary="edgeOnly")
    assert np.linalg.norm(pulled[corners] - points[corners], axis=1).min() > 0.1
    # A boundary point's limit is (a + 4p + b) / 6 of its boundary neighbours.
    np.testing.assert_allclose(pulled[2], (points[1] + 4 * points[2] + points[3]) / 6)
    inner = CatmullClark(**grid, levels=1, boundary="none")
    assert sorted(set(inner.faces.tolist())) == [5, 6]


def test_holes_shape_their_neighbours_but_draw_nothing() -> None:
    points, grid = _grid(3, 3)
    whole = CatmullClark(**grid, levels=2)
    holed = CatmullClark(**grid, levels=2, hole_indices=[4, 99])
    np.testing.assert_array_equal(holed.refine(points), whole.refine(points))
    assert 4 not in holed.faces
    assert len(holed.faces) == len(whole.faces) - 16
    np.testing.assert_array_equal(
        holed.face_vertex_indices.reshape(-1, 4),
        whole.face_vertex_indices.reshape(-1, 4)[whole.faces != 4],
    )


def test_face_varying_values_refine_linearly_in_each_face_under_all() -> None:
    """Texture coordinates at a quad's corners refine to the quarters between them."""
    quad = {"face_vertex_counts": [4], "face_vertex_indices": [0, 1, 2, 3], "point_count": 4}
    refinement = CatmullClark(**quad, levels=2)
    uvs = refinement.refine_face_varying(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), "all")
    assert uvs.shape == (4 * 16, 2)
    assert sorted({tuple(uv) for uv in uvs.tolist()}) == [
        (u / 4, v / 4) for u in range(5) for v in range(5)
    ]
    # Each refined face-vertex takes the value its point has in the face.
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    flat = CatmullClark(**quad, levels=2, limit=False, boundary="edgeAndCorner")
    refined = flat.refine(square)[flat.face_vertex_indices]
    # A flat square with sharp corners refines as a tensor B-spline: not linearly, so
    # only the corners and the centre agree.
    at_corners = np.isin(flat.face_vertex_indices, [0, 1, 2, 3])
    np.testing.assert_allclose(refined[at_corners, :2], uvs[at_corners])


def _jittered_grid() -> tuple[np.ndarray, dict]:
    points, grid = _grid(4, 3)
    points[:, :2] += np.random.default_rng(3).uniform(-0.2, 0.2, (len(points), 2))
    return points, grid


@pytest.mark.parametrize("interpolation", ["none", "cornersOnly", "cornersPlus1", "cornersPlus2"])
def test_values_without_seams_refine_as_the_points_do(interpolation: str) -> None:
    """Coordinates that are the points' own (one island, no seam) refine to the refined
    points' under every rule that smooths the inside of an island: the values' mesh is the
    points' mesh. Refined linearly, or kept linear along the boundary, they do not."""
    points, grid = _jittered_grid()
    refinement = CatmullClark(**grid, levels=2)
    corners = np.asarray(grid["face_vertex_indices"])
    expected = refinement.refine(points)[refinement.face_vertex_indices][:, :2]
    uvs = refinement.refine_face_varying(points[corners, :2], interpolation)
    np.testing.assert_allclose(uvs, expected, atol=1e-12)
    for linear in ("boundaries", "all"):
        apart = np.abs(refinement.refine_face_varying(points[corners, :2], linear) - expected)
        assert apart.max() > 1e-2, linear


def _two_islands() -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
    """A jittered grid whose left two columns of faces and the rest are separate islands
    (the right one's coordinates shifted), the values per face-vertex, and the left faces."""
    points, grid = _jittered_grid()
    faces = np.asarray(grid["face_vertex_indices"]).reshape(-1, 4)
    left = np.flatnonzero(points[faces[:, 0], 0] < 1.5)
    values = points[faces.reshape(-1), :2].copy()
    values[np.repeat(~np.isin(np.arange(len(faces)), left), 4)] += [5.0, 0.0]
    return points, grid, values, left


@pytest.mark.parametrize(
    ("interpolation", "alone"), [("none", "edgeOnly"), ("cornersOnly", "edgeAndCorner")]
)
def test_an_island_refines_as_a_mesh_of_its_own(interpolation: str, alone: str) -> None:
    """Along a seam each island's values refine as a boundary of their own, whatever the
    other side holds: the left island refines as its faces alone would, its corners smooth
    (`none`) or kept (`cornersOnly`, which keeps the ends of the seam too)."""
    points, grid, values, left = _two_islands()
    refinement = CatmullClark(**grid, levels=2, boundary="edgeOnly")
    uvs = refinement.refine_face_varying(values, interpolation)
    faces = np.asarray(grid["face_vertex_indices"]).reshape(-1, 4)[left]
    island = CatmullClark([4] * len(left), faces.reshape(-1), len(points), 2, boundary=alone)
    expected = island.refine(points)[island.face_vertex_indices][:, :2]
    on_left = np.repeat(np.isin(refinement.faces, left), 4)
    np.testing.assert_allclose(uvs[on_left], expected, atol=1e-12)
    # Moving the other island's values moves nothing on this one.
    values[np.repeat(~np.isin(np.arange(len(faces) + 6), left), 4)] *= 3.0
    moved = refinement.refine_face_varying(values, interpolation)
    np.testing.assert_array_equal(moved[on_left], uvs[on_left])


def test_junctions_of_three_islands_are_kept_from_cornersplus1() -> None:
    """Where three islands of two faces each meet, `cornersPlus1` and `cornersPlus2` keep
    each value where it is (the limit of a corner is its cage value); `cornersOnly` keeps
    only values of one face, so it smooths these along their seams."""
    angles = np.linspace(0.0, 2.0 * np.pi, 7)[:-1] + np.array([0.0, 0.3, -0.2, 0.1, 0.4, -0.3])
    points = np.vstack([[0.0, 0.0, 0.0], np.c_[np.cos(angles), np.sin(angles), np.zeros(6)]])
    fan = {
        "face_vertex_counts": [3] * 6,
        "face_vertex_indices": [i for k in range(6) for i in (0, 1 + k, 1 + (k + 1) % 6)],
        "point_count": 7,
    }
    corners = np.asarray(fan["face_vertex_indices"])
    values = points[corners, :2] + np.repeat([[0, 0], [3, 0], [0, 3]], 6, axis=0)
    refinement = CatmullClark(**fan, levels=2, boundary="edgeOnly")
    at_centre = refinement.face_vertex_indices == 0
    kept = {tuple(uv) for uv in np.round(values[corners == 0], 12).tolist()}
    for interpolation, stays in [
        ("cornersOnly", False),
        ("cornersPlus1", True),
        ("cornersPlus2", True),
    ]:
        uvs = refinement.refine_face_varying(values, interpolation)
        found = {tuple(uv) for uv in np.round(uvs[at_centre], 12).tolist()}
        assert len(found) == 3
        assert (found == kept) == stays, interpolation


def test_non_finite_values_refine_linearly_and_bad_rules_are_named() -> None:
    """A NaN stays in the faces that hold it rather than spreading through the smoothing;
    a rule that is not USD's is named with the mesh."""
    points, grid = _grid(2, 2)
    refinement = CatmullClark(**grid, levels=1, where="/World/grid")
    values = points[np.asarray(grid["face_vertex_indices"]), :2]
    values[0] = np.nan
    uvs = refinement.refine_face_varying(values)
    spoilt = np.isnan(uvs).any(axis=1)
    assert spoilt.any()
    assert not spoilt[np.repeat(refinement.faces != 0, 4)].any()  # only the first face's
    with pytest.raises(
        SubdivisionError, match=r"^/World/grid: faceVaryingLinearInterpolation 'smooth'"
    ):
        refinement.refine_face_varying(values, "smooth")


def test_degenerate_faces_and_their_values_are_dropped() -> None:
    mesh = {"face_vertex_counts": [4, 2], "face_vertex_indices": [0, 1, 2, 3, 0, 2]}
    refinement = CatmullClark(**mesh, point_count=4, levels=1)
    assert len(refinement.faces) == 4
    assert set(refinement.faces.tolist()) == {0}
    assert refinement.refine_face_varying(np.arange(6.0)).shape == (16, 1)


@pytest.mark.parametrize(
    ("tags", "message"),
    [
        ({"crease_indices": [0, 1, 2], "crease_lengths": [2]}, "creaseLengths"),
        ({"crease_indices": [0], "crease_lengths": [1]}, "creaseLengths"),
        (
            {"crease_indices": [0, 1, 3], "crease_lengths": [3], "crease_sharpnesses": [1, 2, 3]},
            "creaseSharpnesses has 3 values",
        ),
        (
            {"crease_indices": [0, 9], "crease_lengths": [2], "crease_sharpnesses": [1]},
            "creaseIndices reach past the 8 points",
        ),
        ({"corner_indices": [1, 2], "corner_sharpnesses": [1]}, "2 cornerIndices but 1"),
        ({"corner_indices": [8], "corner_sharpnesses": [1]}, "cornerIndices reach past"),
        ({"boundary": "everywhere"}, "interpolateBoundary 'everywhere'"),
        ({"levels": 0}, "at least one level"),
    ],
)
def test_bad_tags_are_named(tags: dict, message: str) -> None:
    arguments = {"levels": 1, **tags}
    with pytest.raises(SubdivisionError, match=message) as raised:
        CatmullClark(**CUBE, where="/World/cube", **arguments)
    assert str(raised.value).startswith("/World/cube: ")
