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


def test_face_varying_values_refine_linearly_in_each_face() -> None:
    """Texture coordinates at a quad's corners refine to the quarters between them."""
    quad = {"face_vertex_counts": [4], "face_vertex_indices": [0, 1, 2, 3], "point_count": 4}
    refinement = CatmullClark(**quad, levels=2)
    uvs = refinement.refine_face_varying(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float))
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
