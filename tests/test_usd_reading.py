"""The USD step's stage reading: frames syntax, triangulation, units, instancing, time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdSkel, UsdVol, Vt
from scenes import build_scene, flatten, move_occluder_off_the_float32_grid
from test_usd_subdivision import CUBE, CUBE_FACES, CUBE_POINTS
from usd_helpers import (
    STRIP_REST,
    author_rig,
    author_skinned_strip,
    author_stage,
    light_matrix,
    posed_strip,
)

import crepuscular
import crepuscular_usd
from crepuscular_usd import FrameSpecError, FrameSpecIterator, MeshError, StageReader, triangulate
from crepuscular_usd import geometry as geometry_module
from crepuscular_usd.attributes import (
    ATTRIBUTES,
    RELATIONSHIPS,
    SUBDIVISION_LEVELS,
    SUBDIVISION_LIMIT,
)
from crepuscular_usd.frames import convert_frame_placeholder_to_float_spec
from crepuscular_usd.implicit import RADIAL_SEGMENTS, tessellate_implicit
from crepuscular_usd.schema import API_NAME, PROPERTY_NAMES, SchemaError, fallback
from crepuscular_usd.subdivision import CatmullClark

SMALL = {"steps": 32, "shadow_map_size": 128}


def _layers_close(a: crepuscular.Layers, b: crepuscular.Layers, tol: float = 1e-4) -> None:
    for name in ("volume", "visibility", "depth"):
        left, right = getattr(a, name), getattr(b, name)
        scale = max(float(np.abs(left).max()), 1e-6)
        assert np.abs(left - right).max() <= tol * scale, name


def _render(reader: StageReader, time: float | None = None) -> crepuscular.Layers:
    code = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    return crepuscular.render_arrays(**reader.read(code).render_kwargs())


# --- frames ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "frames"),
    [
        ("1-100x2", list(range(1, 100, 2))),
        ("1:10x3", [1, 4, 7, 10]),
        ("1,5,9", [1, 5, 9]),
        ("42", [42]),
        ("5-1x2", [5, 3, 1]),
        ("-3--1", [-3, -2, -1]),
        ("101:102x0.5", [101, 101.5, 102]),
        ("1-2,7", [1, 2, 7]),
    ],
)
def test_frame_specs_follow_usd_conventions(spec: str, frames: list[float]) -> None:
    assert FrameSpecIterator(spec).frames() == frames


@pytest.mark.parametrize("spec", ["", "1-", "a-b", "1-10x0", "1-10y2", "1,,2", "1-2-3"])
def test_bad_frame_specs_are_rejected(spec: str) -> None:
    with pytest.raises(FrameSpecError):
        FrameSpecIterator(spec)


def test_frame_placeholders_format_like_usdrecord() -> None:
    template = convert_frame_placeholder_to_float_spec("out/shafts.####.exr")
    assert template is not None
    assert template.format(frame=7.0) == "out/shafts.0007.exr"
    template = convert_frame_placeholder_to_float_spec("a.###.##.exr")
    assert template is not None
    assert template.format(frame=12.5) == "a.012.50.exr"
    assert convert_frame_placeholder_to_float_spec("plain.exr") is None
    with pytest.raises(FrameSpecError):
        convert_frame_placeholder_to_float_spec("a.##.b.##.exr")
    assert FrameSpecIterator("1:2x0.25").min_float_precision == 2


# --- triangulation --------------------------------------------------------------------


def test_polygons_fan_triangulate_and_skip_holes_and_degenerate_faces() -> None:
    counts = [4, 5, 3, 2, 3]
    indices = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16]
    triangles = triangulate(counts, indices, [2], point_count=17)
    expected = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8], [14, 15, 16]]
    assert triangles.tolist() == expected
    flipped = triangulate(counts, indices, [2], left_handed=True, point_count=17)
    assert flipped.tolist() == [[a, c, b] for a, b, c in expected]


def test_quads_folded_along_their_first_diagonal_split_along_the_other() -> None:
    """As Blender splits them: a quad whose fan triangles face opposite ways (concave at
    its second corner here) splits along its other diagonal, one that is not keeps the
    fan; a skinned mesh's quads split again by where its posed points put them."""
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    dented = square.copy()
    dented[1] = [0.8, 0.9, 0.0]  # past the diagonal from the first corner
    counts, indices = [4, 3], [0, 1, 2, 3, 0, 1, 2]
    fan = [[0, 1, 2], [0, 2, 3], [0, 1, 2]]
    assert triangulate(counts, indices, points=square).tolist() == fan
    assert triangulate(counts, indices).tolist() == fan
    split = [[0, 1, 3], [1, 2, 3], [0, 1, 2]]
    assert triangulate(counts, indices, points=dented).tolist() == split
    mirrored = triangulate(counts, indices, left_handed=True, points=dented)
    assert mirrored.tolist() == [[a, c, b] for a, b, c in split]
    _, faces = crepuscular_usd.geometry.triangle_corners(counts, indices)
    quads = crepuscular_usd.geometry._Quads.of(counts, np.array(indices), faces, False)
    rest = triangulate(counts, indices, points=square)
    assert quads.split(rest, dented).tolist() == split
    assert quads.split(quads.split(rest, dented), square).tolist() == fan


#: Polygons that are not convex, in the z = 0 plane, wound anticlockwise: an L, a U (a wall's
#: face around a window's top), a square around a square hole joined by a slit there and
#: back (as Boolean cuts leave them), and a five-pointed star.
CONCAVE = {
    "L": [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)],
    "U": [(0, 0), (3, 0), (3, 2), (2, 2), (2, 1), (1, 1), (1, 2), (0, 2)],
    "keyhole": [
        (0, 0), (4, 0), (4, 4), (0, 4), (0, 2), (1, 2),
        (1, 3), (3, 3), (3, 1), (1, 1), (1, 2), (0, 2),
    ],
    "star": [
        (np.cos(t) * (1.0 if k % 2 == 0 else 0.4), np.sin(t) * (1.0 if k % 2 == 0 else 0.4))
        for k, t in enumerate(np.linspace(0.0, 2.0 * np.pi, 11)[:-1])
    ],
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(CONCAVE))
def test_polygons_that_are_not_convex_are_ear_clipped(name: str) -> None:
    """As Blender triangulates them (and any renderer that does so properly): triangles
    that tile the polygon, facing as it does, where a fan would cover its notches. Tilted
    out of its plane and given a neighbour, it still does; convex faces keep the fan."""
    flat = np.array(CONCAVE[name], dtype=np.float64)
    area = 0.5 * float(
        (flat[:, 0] * np.roll(flat[:, 1], -1) - np.roll(flat[:, 0], -1) * flat[:, 1]).sum()
    )
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, -0.8, 0.6]])
    polygon = np.c_[flat, np.zeros(len(flat))] @ tilt.T
    n = len(polygon)
    hexagon = (
        np.c_[
            np.cos(np.arange(6) / 6 * 2 * np.pi), np.sin(np.arange(6) / 6 * 2 * np.pi), np.zeros(6)
        ]
        + 9
    )
    points = np.vstack([hexagon, polygon])
    counts, indices = [6, n], [*range(6), *range(6, 6 + n)]
    triangles = triangulate(counts, indices, points=points).astype(np.int64)
    assert len(triangles) == 4 + n - 2
    assert triangles[:4].tolist() == triangulate([6], list(range(6))).tolist()
    mine = triangles[4:]
    normal = tilt @ [0.0, 0.0, 1.0]
    a, b, c = (points[mine[:, k]] for k in range(3))
    signed = 0.5 * np.cross(b - a, c - a) @ normal
    assert signed.min() > -1e-12
    np.testing.assert_allclose(signed.sum(), area, rtol=1e-12)
    fan = triangulate([n], list(range(n))).astype(np.int64) + 6
    a, b, c = (points[fan[:, k]] for k in range(3))
    assert np.abs(0.5 * np.cross(b - a, c - a) @ normal).sum() > area + 1e-9 or name == "L"
    mirrored = triangulate(counts, indices, left_handed=True, points=points)
    assert mirrored[4:].tolist() == [[x, z, y] for x, y, z in mine.tolist()]


def test_inconsistent_topology_names_the_mesh() -> None:
    with pytest.raises(MeshError, match="/World/bad: faceVertexCounts sum to 4"):
        triangulate([4], [0, 1, 2], where="/World/bad")
    with pytest.raises(MeshError, match="reach 9 but there are 4 points"):
        triangulate([3], [0, 1, 9], point_count=4, where="/World/bad")


def test_a_stage_far_from_its_origin_renders_as_near_it(tmp_path: Path) -> None:
    # Georeferenced stages place their scene 100 km and more from the origin, where float32
    # world positions lie 8 mm apart: the reader hands them over relative to the camera.
    # The occluder's corners are not on any float32 grid there; the camera's are.
    scene = build_scene(**SMALL)
    move_occluder_off_the_float32_grid(scene)
    near = author_stage(str(tmp_path / "near.usda"), scene)
    far = author_stage(str(tmp_path / "far.usda"), scene)
    UsdGeom.Xformable(far.GetPrimAtPath("/World")).AddTranslateOp().Set(Gf.Vec3d(1e5, -7e4, 32))
    frames = [
        StageReader(stage, "/World/Camera", "/World/Sun", width=64).read(Usd.TimeCode.Default())
        for stage in (near, far)
    ]
    assert np.abs(frames[1].geometry.positions).max() < 20
    np.testing.assert_allclose(
        frames[1].geometry.origin - frames[0].geometry.origin, [1e5, -7e4, 32]
    )
    _layers_close(*(crepuscular.render_arrays(**frame.render_kwargs()) for frame in frames), 1e-5)


def test_usd_face_holes_and_orientation_are_read(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "s.usda"), scene)
    ground = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ground"))
    occluder = UsdGeom.Mesh(stage.GetPrimAtPath("/World/occluder"))
    # The occluder as one quad whose only face is a hole: no shadow, as if absent.
    occluder.GetFaceVertexCountsAttr().Set([4])
    occluder.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3])
    occluder.CreateHoleIndicesAttr().Set([0])
    ground.GetFaceVertexCountsAttr().Set([4])
    ground.GetFaceVertexIndicesAttr().Set([0, 3, 2, 1])
    ground.CreateOrientationAttr().Set(UsdGeom.Tokens.leftHanded)
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    frame = reader.read(Usd.TimeCode.Default())
    assert len(frame.geometry.triangles) == 2
    assert frame.geometry.triangles.tolist() == [[0, 2, 3], [0, 1, 2]]
    empty = build_scene(occluder=False, **SMALL)
    _layers_close(
        crepuscular.render_arrays(**frame.render_kwargs()), crepuscular.render(empty), 1e-5
    )


def test_meshes_authored_as_subdivision_surfaces_cast_their_cages_and_say_so(
    tmp_path: Path,
) -> None:
    """A mesh that authors catmullClark (as Blender's exporter writes one with a
    Subdivision Surface modifier) casts its cage, as Storm draws it, and one note names
    it with the export option that carries the subdivided surface; unauthored (USD's
    fallback, which most stages leave) or "none", no note."""
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "s.usda"), scene)
    occluder = UsdGeom.Mesh(stage.GetPrimAtPath("/World/occluder"))
    time = Usd.TimeCode.Default()

    def read() -> crepuscular_usd.geometry.SceneGeometry:
        return StageReader(stage, "/World/Camera", "/World/Sun", width=64).read(time).geometry

    plain = read()
    assert not any("subdivisionScheme" in note for note in plain.notes)
    occluder.CreateSubdivisionSchemeAttr().Set(UsdGeom.Tokens.none)
    assert not any("subdivisionScheme" in note for note in read().notes)
    occluder.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.catmullClark)
    cage = read()
    notes = [note for note in cage.notes if "subdivisionScheme" in note]
    assert len(notes) == 1
    assert "(/World/occluder) cast as their control cages" in notes[0]
    assert "give --complexity medium, high or veryhigh" in notes[0]
    np.testing.assert_array_equal(cage.triangles, plain.triangles)
    np.testing.assert_array_equal(cage.positions, plain.positions)


def test_catmull_clark_meshes_refine_to_their_own_or_the_renders_levels(tmp_path: Path) -> None:
    """A Catmull-Clark cube refines as many levels as it authors
    (`crepuscular:subdivision:levels`, which Blender's export writes), else as the
    reader's `subdivision_levels` (`--complexity`) say, onto its limit surface unless it
    authors `crepuscular:subdivision:limitSurface` false; a mesh whose scheme is none
    never refines, and a Loop mesh is named and cast as its cage."""
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "s.usda"), scene)
    cube = UsdGeom.Mesh.Define(stage, "/World/blob")
    points = CUBE_POINTS + np.array([0.0, 0.0, 30.0])
    cube.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    cube.CreateFaceVertexCountsAttr().Set([4] * 6)
    cube.CreateFaceVertexIndicesAttr().Set([i for face in CUBE_FACES for i in face])
    time = Usd.TimeCode.Default()

    def blob(levels: int = 0) -> np.ndarray:
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        reader.subdivision_levels = levels
        geometry = reader.read(time).geometry
        ids = np.asarray(geometry.object_ids)
        mine = ids == geometry.ids_by_path[Sdf.Path("/World/blob")]
        corners = geometry.triangles[mine].reshape(-1)
        return geometry.positions[corners] + geometry.origin, geometry.notes

    cage, notes = blob()
    assert len(cage) == 12 * 3
    assert not any("subdivisionScheme" in note for note in notes)
    refined, notes = blob(2)
    assert len(refined) == 6 * 16 * 2 * 3
    assert not notes
    expected = CatmullClark(**CUBE, levels=2).refine(points)
    apart = np.linalg.norm(refined[:, None] - expected[None], axis=2)
    assert apart.min(axis=1).max() < 1e-5
    assert apart.min(axis=0).max() < 1e-5
    # Rounded well inside the cube, and no point on its corners.
    assert np.abs(refined - [0.0, 0.0, 30.0]).max() < 0.9
    own = cube.GetPrim().CreateAttribute(SUBDIVISION_LEVELS, Sdf.ValueTypeNames.Int, custom=True)
    own.Set(1)
    assert len(blob()[0]) == len(blob(3)[0]) == 6 * 4 * 2 * 3
    limit = cube.GetPrim().CreateAttribute(SUBDIVISION_LIMIT, Sdf.ValueTypeNames.Bool, custom=True)
    limit.Set(False)
    # One level not on the limit: the cube's corners at 5/9 of themselves.
    corners = np.abs(blob()[0] - [0.0, 0.0, 30.0])
    assert np.isclose(corners.max(axis=1), 5 / 9).any()
    assert corners.max() < 1.0 + 1e-6
    cube.CreateSubdivisionSchemeAttr().Set(UsdGeom.Tokens.none)
    assert len(blob(2)[0]) == 12 * 3
    cube.GetSubdivisionSchemeAttr().Set("loop")
    loop, notes = blob(2)
    assert len(loop) == 12 * 3
    assert any("subdivisionScheme is loop (/World/blob)" in note for note in notes)
    cube.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.catmullClark)
    # Too many levels: named, and the mesh left out as other invalid meshes are.
    own.Set(9)
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    geometry = reader.read(time).geometry
    assert Sdf.Path("/World/blob") not in geometry.ids_by_path
    assert any("/World/blob.crepuscular:subdivision:levels is 9" in i for i in geometry.invalid)
    for value, kind in ((1.5, Sdf.ValueTypeNames.Float), ("two", Sdf.ValueTypeNames.String)):
        cube.GetPrim().RemoveProperty(SUBDIVISION_LEVELS)
        cube.GetPrim().CreateAttribute(SUBDIVISION_LEVELS, kind, custom=True).Set(value)
        geometry = reader.read(time).geometry
        assert any(f"levels is {value!r}; give a whole number" in i for i in geometry.invalid)


# --- units and up axis ------------------------------------------------------------------


def _styled_medium(stage: Usd.Stage, meters_per_unit: float, up: str) -> None:
    """A box medium from a Cube and a closing radius, both in stage units."""
    cube = UsdGeom.Cube.Define(stage, "/World/Fog")
    cube.CreateSizeAttr().Set(2.0)
    centre = np.array([0.0, 2.0, 0.0])
    if up == "Y":
        centre = np.array([centre[0], centre[2], -centre[1]])
    xform = cube.AddTransformOp()
    matrix = Gf.Matrix4d().SetScale(Gf.Vec3d(6.0, 6.0, 6.0) / meters_per_unit)
    matrix.SetTranslateOnly(Gf.Vec3d(*(centre / meters_per_unit)))
    xform.Set(matrix)
    light = stage.GetPrimAtPath("/World/Sun")
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([cube.GetPath()])
    light.GetAttribute("crepuscular:closing:enable").Set(True)
    light.GetAttribute("crepuscular:closing:radius").Set(0.4 / meters_per_unit)
    stage.GetRootLayer().Save()


def test_z_up_metres_and_y_up_centimetres_give_the_same_layers(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    layers = {}
    for up, meters in (("Z", 1.0), ("Y", 0.01)):
        stage = author_stage(str(tmp_path / f"{up}.usda"), scene, up=up, meters_per_unit=meters)
        _styled_medium(stage, meters, up)
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        layers[up] = _render(reader)
    _layers_close(layers["Z"], layers["Y"], 1e-4)
    # And both equal the scene description with the same box and closing, in metres.
    direct = dict(scene)
    box = np.diag([6.0, 6.0, 6.0, 1.0])
    box[:3, 3] = [0.0, 2.0, 0.0]
    direct["medium"] = {
        **scene["medium"],
        "extent": {"kind": "box", "world_from_cube": list(box.T.ravel())},
    }
    direct["style"] = {"closing": {"radius": 0.4}}
    _layers_close(layers["Z"], crepuscular.render(direct), 1e-4)
    assert float(layers["Z"].volume[..., 3].max()) > 0.0


def test_camera_apertures_offsets_and_orthographic_map_exactly(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "cam.usda"), scene, meters_per_unit=0.5)
    camera = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    camera.GetHorizontalApertureAttr().Set(24.0)
    camera.GetVerticalApertureAttr().Set(24.0)
    camera.CreateHorizontalApertureOffsetAttr().Set(3.0)
    camera.CreateVerticalApertureOffsetAttr().Set(-1.5)
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64, height=36)
    projection = reader.camera(Usd.TimeCode.Default())["projection"]
    # A square aperture in a 16:9 image fits vertically: offsets in units of its height.
    assert projection["sensor_fit"] == "vertical"
    assert projection["sensor_height"] == 24.0
    assert projection["shift_x"] == pytest.approx(3.0 / 24.0)
    assert projection["shift_y"] == pytest.approx(-1.5 / 24.0)
    camera.GetProjectionAttr().Set(UsdGeom.Tokens.orthographic)
    ortho = reader.camera(Usd.TimeCode.Default())
    # Apertures are tenths of a stage unit; a stage unit is half a metre here.
    assert ortho["projection"]["ortho_scale"] == pytest.approx(24.0 * 0.1 * 0.5)
    assert ortho["clip_end"] == pytest.approx(scene["camera"]["clip_end"])
    # Without --height the image keeps the aperture's aspect ratio, as usdrecord does.
    assert (
        StageReader(stage, "/World/Camera", None, width=50).camera(Usd.TimeCode.Default())["height"]
        == 50
    )


# --- instancing ---------------------------------------------------------------------------


def _box_points(size: float) -> tuple[list[Gf.Vec3f], list[int], list[int]]:
    s = size / 2
    points = [Gf.Vec3f(x, y, z) for x in (-s, s) for y in (-s, s) for z in (-s, s)]
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    return points, [4] * 6, [i for face in faces for i in face]


def _instanced_stage(path: str, mode: str) -> Usd.Stage:
    """mode: "instancer" (a PointInstancer), "instanceable" (instanceable references) or
    "plain" (the same references, not instanceable)."""
    flattened = mode != "instancer"
    scene = build_scene(occluder=False, **SMALL)
    stage = author_stage(path, scene)
    rng = np.random.default_rng(5)
    count = 60
    positions = np.column_stack(
        [rng.uniform(-3, 3, count), rng.uniform(2.5, 4.0, count), rng.uniform(-3, 3, count)]
    )
    # Unit quaternions that half precision holds exactly, so both forms see one rotation.
    signs = rng.choice([-0.5, 0.5], (count, 4))
    # Every third instance turns a quarter or half turn about one axis (a lone +-1).
    orientations = [
        Gf.Quath(*(q if i % 3 else 2 * q * (np.arange(4) == i % 4))) for i, q in enumerate(signs)
    ]
    scales = rng.uniform(0.5, 1.5, (count, 3))
    proto_indices = rng.integers(0, 5, count)
    root = "/World/Flat" if flattened else "/World/Instancer"
    prototypes: list[str] = []
    proto_parent = "/World/Protos" if flattened else f"{root}/Protos"
    if flattened:
        UsdGeom.Scope.Define(stage, proto_parent)
    for index, size in enumerate((0.3, 0.5, 0.2, 0.4, 0.25)):
        proto = UsdGeom.Xform.Define(stage, f"{proto_parent}/P{index}")
        proto.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.1 * index, 0.0))  # prototype root xform
        mesh = UsdGeom.Mesh.Define(stage, f"{proto_parent}/P{index}/Mesh")
        mesh.AddRotateYOp().Set(15.0 * index)
        points, counts, indices = _box_points(size)
        mesh.CreatePointsAttr(points)
        mesh.CreateFaceVertexCountsAttr(counts)
        mesh.CreateFaceVertexIndicesAttr(indices)
        prototypes.append(str(proto.GetPath()))
    if flattened:
        UsdGeom.Imageable(stage.GetPrimAtPath(proto_parent)).MakeInvisible()
        for i in range(count):
            if i == 7:
                continue  # the instancer's invisible id
            holder = UsdGeom.Xform.Define(stage, f"{root}/I{i}")
            holder.AddTranslateOp().Set(Gf.Vec3d(*positions[i]))
            holder.AddOrientOp(UsdGeom.XformOp.PrecisionHalf).Set(orientations[i])
            holder.AddScaleOp().Set(Gf.Vec3f(*scales[i]))
            instance = stage.DefinePrim(f"{root}/I{i}/Proto")
            instance.GetReferences().AddInternalReference(prototypes[proto_indices[i]])
            instance.SetInstanceable(mode == "instanceable")
    else:
        instancer = UsdGeom.PointInstancer.Define(stage, root)
        instancer.CreatePrototypesRel().SetTargets([Sdf.Path(p) for p in prototypes])
        instancer.CreateProtoIndicesAttr([int(i) for i in proto_indices])
        instancer.CreatePositionsAttr([Gf.Vec3f(*p) for p in positions])
        instancer.CreateOrientationsAttr(Vt.QuathArray(orientations))
        instancer.CreateScalesAttr([Gf.Vec3f(*s) for s in scales])
        instancer.CreateInvisibleIdsAttr([7])
    stage.GetRootLayer().Save()
    return stage


def test_point_instancer_equals_the_flattened_scene(tmp_path: Path) -> None:
    frames = {}
    for mode in ("instancer", "instanceable", "plain"):
        stage = _instanced_stage(str(tmp_path / f"{mode}.usda"), mode)
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        frames[mode] = reader.read(Usd.TimeCode.Default())
    assert frames["instanceable"].geometry.ids_by_path == frames["plain"].geometry.ids_by_path
    rendered = {mode: crepuscular.render_arrays(**f.render_kwargs()) for mode, f in frames.items()}
    # 59 visible boxes of 12 triangles (one id is invisible), plus the ground.
    for mode, frame in frames.items():
        assert len(frame.geometry.triangles) == 59 * 12 + 2, mode
    ordered = lambda g: np.sort(g.positions[g.triangles].reshape(len(g.triangles), -1), axis=0)  # noqa: E731
    for mode in ("instanceable", "plain"):
        np.testing.assert_allclose(
            ordered(frames["instancer"].geometry), ordered(frames[mode].geometry), atol=1e-5
        )
        _layers_close(rendered["instancer"], rendered[mode], 1e-4)
    np.testing.assert_array_equal(rendered["instanceable"].volume, rendered["plain"].volume)


# --- implicit surfaces ----------------------------------------------------------------


def _signed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """The volume a closed triangle mesh encloses, positive where its fronts face out."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _closed(triangles: np.ndarray) -> bool:
    """Whether every edge is shared by exactly two triangles, once each way."""
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    forward = {tuple(edge) for edge in directed.tolist()}
    return len(forward) == len(directed) and all((b, a) in forward for a, b in forward)


def _define(stage: Usd.Stage, schema: str, path: str, **attributes: object) -> Usd.Prim:
    prim = getattr(UsdGeom, schema).Define(stage, path).GetPrim()
    for name, value in attributes.items():
        assert prim.GetAttribute(name).Set(value), name
    return prim


_SOLIDS = [
    ("Cube", {"size": 3.0}, 27.0, [1.5, 1.5, 1.5]),
    ("Sphere", {"radius": 2.0}, 4 / 3 * np.pi * 8, [2.0, 2.0, 2.0]),
    ("Cylinder", {"radius": 0.5, "height": 3.0, "axis": "X"}, np.pi * 0.75, [1.5, 0.5, 0.5]),
    ("Cone", {"radius": 1.0, "height": 3.0, "axis": "Y"}, np.pi, [1.0, 1.5, 1.0]),
    (
        "Capsule",
        {"radius": 0.5, "height": 2.0, "axis": "Z"},
        np.pi * 0.5 + 4 / 3 * np.pi * 0.125,
        [0.5, 0.5, 1.5],
    ),
    (
        "Cylinder_1",
        {"radiusTop": 0.5, "radiusBottom": 1.0, "height": 2.0, "axis": "Y"},
        np.pi * 2 / 3 * (0.25 + 0.5 + 1.0),
        [1.0, 1.0, 1.0],
    ),
]


@pytest.mark.parametrize(("schema", "attributes", "volume", "half_extent"), _SOLIDS)
def test_implicit_solids_are_closed_outward_and_of_the_authored_size(
    schema: str, attributes: dict[str, object], volume: float, half_extent: list[float]
) -> None:
    if not hasattr(UsdGeom, schema):
        pytest.skip(f"this USD build has no {schema}")
    stage = Usd.Stage.CreateInMemory()
    prim = _define(stage, schema, "/Shape", **attributes)
    points, triangles, varying = tessellate_implicit(prim, Usd.TimeCode.Default())
    assert not varying
    assert _closed(triangles)
    np.testing.assert_allclose(points.max(axis=0), half_extent, atol=1e-12)
    np.testing.assert_allclose(points.min(axis=0), np.negative(half_extent), atol=1e-12)
    # Inscribed polygons: a little less than the round solid, never more.
    enclosed = _signed_volume(points, triangles)
    assert 0.99 * volume <= enclosed <= volume * (1 + 1e-12), enclosed
    UsdGeom.Gprim(prim).GetOrientationAttr().Set(UsdGeom.Tokens.leftHanded)
    _, flipped, _ = tessellate_implicit(prim, Usd.TimeCode.Default())
    assert _signed_volume(points, flipped) == pytest.approx(-enclosed)


def test_round_surfaces_put_every_vertex_on_the_surface() -> None:
    stage = Usd.Stage.CreateInMemory()
    time = Usd.TimeCode.Default()
    sphere, _, _ = tessellate_implicit(_define(stage, "Sphere", "/S", radius=1.5), time)
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.5, rtol=1e-12)
    # A capsule's points lie one radius from its spine, the segment between the caps' centres.
    capsule, _, _ = tessellate_implicit(
        _define(stage, "Capsule", "/C", radius=0.4, height=1.0, axis="X"), time
    )
    along = np.clip(capsule[:, 0], -0.5, 0.5)
    spine = np.column_stack([along, np.zeros_like(along), np.zeros_like(along)])
    np.testing.assert_allclose(np.linalg.norm(capsule - spine, axis=1), 0.4, rtol=1e-12)
    # A cylinder's ring holds RADIAL_SEGMENTS points, each on its radius.
    cylinder, _, _ = tessellate_implicit(
        _define(stage, "Cylinder", "/Y", radius=0.7, height=2.0), time
    )
    side = cylinder[np.abs(np.hypot(cylinder[:, 0], cylinder[:, 1]) - 0.7) < 1e-12]
    assert len(side) == 2 * RADIAL_SEGMENTS


@pytest.mark.parametrize(
    ("axis", "width_along", "length_along"), [("Z", 0, 1), ("X", 2, 1), ("Y", 0, 2)]
)
def test_a_plane_lies_across_its_axis_and_faces_along_it(
    axis: str, width_along: int, length_along: int
) -> None:
    stage = Usd.Stage.CreateInMemory()
    prim = _define(stage, "Plane", "/P", width=2.0, length=5.0, axis=axis)
    points, triangles, _ = tessellate_implicit(prim, Usd.TimeCode.Default())
    extent = points.max(axis=0) - points.min(axis=0)
    normal_axis = "XYZ".index(axis)
    assert extent[width_along] == 2.0
    assert extent[length_along] == 5.0
    assert extent[normal_axis] == 0.0
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a).sum(axis=0) / 2.0
    np.testing.assert_allclose(normal, 10.0 * np.eye(3)[normal_axis], atol=1e-12)


def _sphere_mesh(stage: Usd.Stage, path: str, radius: float, segments: int) -> UsdGeom.Mesh:
    """A finely tessellated sphere as a plain Mesh, quads and pole triangles."""
    theta = np.linspace(0.0, np.pi, segments // 2 + 1)[1:-1]
    phi = 2.0 * np.pi * np.arange(segments) / segments
    rings = np.stack(
        [
            np.outer(np.sin(theta), np.cos(phi)),
            np.outer(np.sin(theta), np.sin(phi)),
            np.outer(np.cos(theta), np.ones_like(phi)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    points = radius * np.vstack([[0, 0, 1], rings, [0, 0, -1]])
    counts: list[int] = []
    indices: list[int] = []
    n = segments
    for k in range(n):
        counts.append(3)
        indices += [0, 1 + k, 1 + (k + 1) % n]
    for r in range(len(theta) - 1):
        for k in range(n):
            a, b = 1 + r * n + k, 1 + r * n + (k + 1) % n
            counts.append(4)
            indices += [a, a + n, b + n, b]
    south = len(points) - 1
    for k in range(n):
        base = 1 + (len(theta) - 1) * n
        counts.append(3)
        indices += [south, base + (k + 1) % n, base + k]
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in points])
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    return mesh


def test_implicit_occluders_shadow_as_the_same_meshes(tmp_path: Path) -> None:
    """A Cube casts the shadow of the same box authored as a Mesh, and a Sphere that of a
    sphere tessellated four times finer; both shadows are there."""
    scene = build_scene(occluder=False, width=128, height=72, steps=64, shadow_map_size=256)
    layers = {}
    for form in ("implicit", "mesh"):
        stage = author_stage(str(tmp_path / f"{form}.usda"), scene)
        for name, at, turn in (("Box", (-1.2, 3.0, 0.0), 25.0), ("Ball", (1.2, 3.2, -0.5), 0.0)):
            holder = UsdGeom.Xform.Define(stage, f"/World/{name}")
            holder.AddTranslateOp().Set(Gf.Vec3d(*at))
            holder.AddRotateYOp().Set(turn)
        if form == "implicit":
            _define(stage, "Cube", "/World/Box/Shape", size=1.2)
            _define(stage, "Sphere", "/World/Ball/Shape", radius=0.8)
        else:
            box = UsdGeom.Mesh.Define(stage, "/World/Box/Shape")
            points, counts, indices = _box_points(1.2)
            box.CreatePointsAttr(points)
            box.CreateFaceVertexCountsAttr(counts)
            box.CreateFaceVertexIndicesAttr(indices)
            _sphere_mesh(stage, "/World/Ball/Shape", 0.8, 4 * RADIAL_SEGMENTS)
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=128)
        frame = reader.read(Usd.TimeCode.Default())
        assert not frame.geometry.unsupported
        assert not frame.geometry.invalid
        layers[form] = crepuscular.render_arrays(**frame.render_kwargs())
    empty = crepuscular.render(scene)
    implicit, mesh = (np.asarray(layers[f].volume)[..., :3] for f in ("implicit", "mesh"))
    unshadowed = np.asarray(empty.volume)[..., :3]
    shadowed = np.abs(unshadowed - mesh).sum() / unshadowed.sum()
    assert shadowed > 0.05, shadowed
    difference = np.abs(implicit - mesh).sum() / unshadowed.sum()
    assert difference < 0.02 * shadowed, (difference, shadowed)
    # Depths differ only on the sphere's silhouette, where its facets leave a pixel or not.
    same_depth = np.isclose(layers["implicit"].depth, layers["mesh"].depth, rtol=2e-3)
    assert same_depth.mean() > 0.995, same_depth.mean()


def test_implicit_prototypes_instance_as_plain_prims(tmp_path: Path) -> None:
    """A PointInstancer of a Sphere and a Cylinder places the triangles that Xforms holding
    the same prims do."""
    geometry = {}
    placements = [((0.0, 3.0, 0.0), 0), ((1.5, 3.5, -1.0), 1), ((-1.0, 2.8, 1.0), 0)]
    for mode in ("instancer", "plain"):
        stage = author_stage(str(tmp_path / f"{mode}.usda"), build_scene(occluder=False, **SMALL))
        UsdGeom.Scope.Define(stage, "/World/Protos")
        _define(stage, "Sphere", "/World/Protos/Ball", radius=0.4)
        _define(stage, "Cylinder", "/World/Protos/Post", radius=0.2, height=1.5, axis="Y")
        protos = ["/World/Protos/Ball", "/World/Protos/Post"]
        if mode == "instancer":
            UsdGeom.Imageable(stage.GetPrimAtPath("/World/Protos")).MakeInvisible()
            instancer = UsdGeom.PointInstancer.Define(stage, "/World/Instancer")
            instancer.CreatePrototypesRel().SetTargets([Sdf.Path(p) for p in protos])
            instancer.CreateProtoIndicesAttr([proto for _, proto in placements])
            instancer.CreatePositionsAttr([Gf.Vec3f(*at) for at, _ in placements])
        else:
            stage.RemovePrim("/World/Protos")
            for i, (at, proto) in enumerate(placements):
                holder = UsdGeom.Xform.Define(stage, f"/World/I{i}")
                holder.AddTranslateOp().Set(Gf.Vec3d(*at))
                if proto == 0:
                    _define(stage, "Sphere", f"/World/I{i}/Ball", radius=0.4)
                else:
                    _define(
                        stage, "Cylinder", f"/World/I{i}/Post", radius=0.2, height=1.5, axis="Y"
                    )
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        geometry[mode] = reader.read(Usd.TimeCode.Default()).geometry
    ordered = lambda g: np.sort(g.positions[g.triangles].reshape(len(g.triangles), -1), axis=0)  # noqa: E731
    assert len(geometry["instancer"].triangles) == len(geometry["plain"].triangles) > 2
    np.testing.assert_allclose(
        ordered(geometry["instancer"]), ordered(geometry["plain"]), atol=1e-5
    )


def _quad_mesh(stage: Usd.Stage, path: str) -> None:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(-0.2, 0, -0.1), Gf.Vec3f(0.2, 0, -0.1), Gf.Vec3f(0, 0, 0.3)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])


def _tree(stage: Usd.Stage, path: str) -> None:
    """A tree's prototype root, lifted a little, and its trunk (the leaves come apart)."""
    tree = UsdGeom.Xform.Define(stage, path)
    tree.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.1, 0.0))
    trunk = UsdGeom.Cylinder.Define(stage, f"{path}/Trunk")
    trunk.GetAxisAttr().Set(UsdGeom.Tokens.y)
    trunk.GetRadiusAttr().Set(0.1)
    trunk.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.5, 0.0))


_LEAVES = [
    (Gf.Vec3f(0.3, 0.0, 0.0), Gf.Quath(0.5, 0.5, -0.5, 0.5), Gf.Vec3f(1.0, 1.0, 1.0)),
    (Gf.Vec3f(-0.2, 0.2, 0.1), Gf.Quath(1.0, 0.0, 0.0, 0.0), Gf.Vec3f(1.5, 0.5, 1.0)),
    (Gf.Vec3f(0.0, 0.3, -0.3), Gf.Quath(0.0, 0.0, 1.0, 0.0), Gf.Vec3f(0.8, 0.8, 0.8)),
]
_TREES = [
    (Gf.Vec3f(-1.5, 2.5, 0.0), Gf.Quath(1.0, 0.0, 0.0, 0.0), Gf.Vec3f(1.0, 1.0, 1.0)),
    (Gf.Vec3f(1.0, 2.2, -1.0), Gf.Quath(0.5, -0.5, 0.5, 0.5), Gf.Vec3f(1.2, 0.9, 1.2)),
    (Gf.Vec3f(0.0, 2.8, 1.0), Gf.Quath(0.0, 1.0, 0.0, 0.0), Gf.Vec3f(0.7, 0.7, 0.7)),
]


def _place(xform: UsdGeom.Xform, at: Gf.Vec3f, turn: Gf.Quath, scale: Gf.Vec3f) -> None:
    """The ops that place a prototype as a PointInstancer's instance does."""
    xform.AddTranslateOp().Set(Gf.Vec3d(at))
    xform.AddOrientOp(UsdGeom.XformOp.PrecisionHalf).Set(turn)
    xform.AddScaleOp().Set(scale)


def _instancer(
    stage: Usd.Stage, path: str, prototype: str, placements: list[tuple[object, ...]]
) -> UsdGeom.PointInstancer:
    instancer = UsdGeom.PointInstancer.Define(stage, path)
    instancer.CreatePrototypesRel().SetTargets([Sdf.Path(prototype)])
    instancer.CreateProtoIndicesAttr([0] * len(placements))
    instancer.CreatePositionsAttr([at for at, _, _ in placements])
    instancer.CreateOrientationsAttr([turn for _, turn, _ in placements])
    instancer.CreateScalesAttr([scale for _, _, scale in placements])
    return instancer


def test_nested_point_instancers_place_what_plain_xforms_do(tmp_path: Path) -> None:
    """A forest: a PointInstancer of trees, each a trunk and a PointInstancer of leaves,
    reads as the same trees and leaves authored one Xform each; the second tree is
    masked out by the forest's invisibleIds."""
    geometry = {}
    for mode in ("nested", "plain"):
        stage = author_stage(str(tmp_path / f"{mode}.usda"), build_scene(occluder=False, **SMALL))
        if mode == "nested":
            tree = "/World/Forest/Protos/Tree"
            _tree(stage, tree)
            leaves = _instancer(stage, f"{tree}/Leaves", f"{tree}/Leaves/Protos/Leaf", _LEAVES)
            leaves.AddTranslateOp().Set(Gf.Vec3d(0.0, 1.0, 0.0))
            leaf = UsdGeom.Xform.Define(stage, f"{tree}/Leaves/Protos/Leaf")
            leaf.AddRotateXOp().Set(30.0)
            _quad_mesh(stage, f"{tree}/Leaves/Protos/Leaf/Blade")
            forest = _instancer(stage, "/World/Forest", tree, _TREES)
            forest.CreateInvisibleIdsAttr([1])
        else:
            for i, placement in enumerate(_TREES):
                if i == 1:
                    continue
                holder = UsdGeom.Xform.Define(stage, f"/World/T{i}")
                _place(holder, *placement)
                _tree(stage, f"/World/T{i}/Tree")
                leaves = UsdGeom.Xform.Define(stage, f"/World/T{i}/Tree/Leaves")
                leaves.AddTranslateOp().Set(Gf.Vec3d(0.0, 1.0, 0.0))
                for j, leaf_placement in enumerate(_LEAVES):
                    instance = UsdGeom.Xform.Define(stage, f"/World/T{i}/Tree/Leaves/L{j}")
                    _place(instance, *leaf_placement)
                    leaf = UsdGeom.Xform.Define(stage, f"/World/T{i}/Tree/Leaves/L{j}/Leaf")
                    leaf.AddRotateXOp().Set(30.0)
                    _quad_mesh(stage, f"/World/T{i}/Tree/Leaves/L{j}/Leaf/Blade")
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        geometry[mode] = reader.read(Usd.TimeCode.Default()).geometry
        assert not geometry[mode].unsupported, geometry[mode].unsupported
    ordered = lambda g: np.sort(g.positions[g.triangles].reshape(len(g.triangles), -1), axis=0)  # noqa: E731
    trunk = 4 * RADIAL_SEGMENTS
    assert len(geometry["nested"].triangles) == 2 + 2 * (trunk + len(_LEAVES))
    assert len(geometry["nested"].triangles) == len(geometry["plain"].triangles)
    np.testing.assert_allclose(ordered(geometry["nested"]), ordered(geometry["plain"]), atol=1e-5)


def test_a_prototype_instancing_itself_is_expanded_once_and_reported(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "s.usda"), build_scene(occluder=False, **SMALL))
    proto = "/World/Outer/Protos/Box"
    _define(stage, "Cube", f"{proto}/Shape", size=0.3)
    placements = [(Gf.Vec3f(0, 3, 0), Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1, 1, 1))]
    _instancer(stage, "/World/Outer", proto, placements)
    _instancer(stage, f"{proto}/Again", proto, placements)
    geometry = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default()).geometry
    assert len(geometry.triangles) == 2 + 12
    assert geometry.unsupported == {"PointInstancer (instancing its own prototype)": 1}


def test_an_instancer_too_large_for_memory_is_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stage = author_stage(str(tmp_path / "s.usda"), build_scene(occluder=False, **SMALL))
    proto = "/World/Pebbles/Protos/Pebble"
    _define(stage, "Sphere", proto, radius=0.01)
    turn, scale = Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1, 1, 1)
    placements = [(Gf.Vec3f(0.01 * i, 3, 0), turn, scale) for i in range(1000)]
    _instancer(stage, "/World/Pebbles", proto, placements)
    reader = StageReader(stage, None, None, width=64)
    assert len(reader.read(Usd.TimeCode.Default()).geometry.positions) > 1_000_000
    monkeypatch.setattr(geometry_module, "available_memory", lambda: 2**26)
    with pytest.raises(MeshError) as info:
        reader.read(Usd.TimeCode.Default())
    message = str(info.value)
    assert message.startswith("/World/Pebbles: too large for memory"), message
    assert "GiB are free" in message


def test_an_animated_radius_is_read_each_frame_and_a_bad_one_is_named(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "s.usda"), build_scene(occluder=False, **SMALL))
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.AddTranslateOp().Set(Gf.Vec3d(0.0, 3.0, 0.0))
    ball.GetRadiusAttr().Set(0.5, Usd.TimeCode(1))
    ball.GetRadiusAttr().Set(1.0, Usd.TimeCode(2))
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    spans = []
    for time in (1, 2, 1):
        positions = reader.read(Usd.TimeCode(time)).geometry.positions
        spans.append(float(np.ptp(positions[4:, 0])))
    assert spans == pytest.approx([1.0, 2.0, 1.0])
    ball.GetRadiusAttr().Set(float("nan"), Usd.TimeCode(3))
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=64).read(Usd.TimeCode(3))
    assert len(frame.geometry.invalid) == 1
    assert frame.geometry.invalid[0].startswith("/World/Ball: ")
    assert "finite" in frame.geometry.invalid[0]


# --- time samples ---------------------------------------------------------------------


def test_animated_camera_light_and_schema_change_each_frame_as_authored(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "anim.usda"), scene)
    camera_op = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera")).GetOrderedXformOps()[0]
    base = camera_op.Get()
    for frame, dx in ((1, 0.0), (3, 1.0)):
        moved = Gf.Matrix4d(base)
        moved.SetTranslateOnly(base.ExtractTranslation() + Gf.Vec3d(dx, 0, 0))
        camera_op.Set(moved, Usd.TimeCode(frame))
    light = stage.GetPrimAtPath("/World/Sun")
    light_op = UsdGeom.Xformable(light).GetOrderedXformOps()[0]
    light_op.Set(light_matrix([0.3, -1.0, -0.2], "Z"), Usd.TimeCode(1))
    light_op.Set(light_matrix([-0.3, -1.0, 0.2], "Z"), Usd.TimeCode(3))
    intensity = light.GetAttribute("inputs:intensity")
    intensity.Set(3.0, Usd.TimeCode(1))
    intensity.Set(5.0, Usd.TimeCode(3))
    extinction = light.GetAttribute("crepuscular:medium:extinction")
    extinction.Set(0.08, Usd.TimeCode(1))
    extinction.Set(0.16, Usd.TimeCode(3))
    radius = light.GetAttribute("crepuscular:closing:radius")
    light.GetAttribute("crepuscular:closing:enable").Set(True)
    radius.Set(0.0, Usd.TimeCode(1))
    radius.Set(1.0, Usd.TimeCode(3))
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64, height=36)
    frames = {t: reader.read(Usd.TimeCode(t)) for t in (1, 2, 3)}
    assert frames[2].camera["world_from_camera"][12] == pytest.approx(0.5)
    assert frames[3].camera["world_from_camera"][12] == pytest.approx(1.0)
    assert frames[2].sun["strength"] == pytest.approx(4.0)
    assert frames[3].sun["direction"][0] < 0 < frames[1].sun["direction"][0]
    assert frames[2].medium["extinction"] == pytest.approx(0.12)
    assert frames[3].style["closing"]["radius"] == pytest.approx(1.0)
    assert frames[2].style["time"] == pytest.approx(2 / 24)
    layers = {t: crepuscular.render_arrays(**f.render_kwargs()) for t, f in frames.items()}
    assert not np.array_equal(layers[1].volume, layers[2].volume)
    assert not np.array_equal(layers[2].volume, layers[3].volume)
    # Frame 3 renders exactly like a still scene with the values authored for frame 3.
    still = build_scene(**SMALL)
    still["camera"]["world_from_camera"][12] = 1.0
    still["sun"] = {"direction": frames[3].sun["direction"], "strength": 5.0}
    still["medium"]["extinction"] = 0.16
    still["style"] = {"closing": {"radius": 1.0}}
    _layers_close(layers[3], crepuscular.render(still), 1e-4)


# --- schema -----------------------------------------------------------------------------


def test_schema_defines_exactly_the_attributes_the_reader_maps() -> None:
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(API_NAME)
    assert set(definition.GetPropertyNames()) == set(PROPERTY_NAMES)
    # The shared table (which the Blender add-on's export hook authors with) has the
    # schema's value types, and its relationships are the schema's.
    for name, attribute in ATTRIBUTES.items():
        assert definition.GetAttributeDefinition(name).GetTypeName() == attribute.type_name, name
    for name in RELATIONSHIPS:
        assert definition.GetRelationshipDefinition(name), name


def test_schema_fallbacks_are_the_renderers_defaults() -> None:
    core = crepuscular.scene_from_json(json.dumps(build_scene()))["render"]
    for attribute, key in {
        "crepuscular:method": "method",
        "crepuscular:shadowMapSize": "shadow_map_size",
        "crepuscular:steps": "steps",
        "crepuscular:supersampling": "supersampling",
        "crepuscular:epipoleBlock": "epipole_block",
        "crepuscular:downsample": "downsample",
        "crepuscular:adaptiveTolerance": "adaptive_tolerance",
        "crepuscular:bases": "bases",
        "crepuscular:basisStorage": "basis_storage",
        "crepuscular:rectification": "rectification",
        "crepuscular:nearPlaneCorrection": "near_plane_correction",
        "crepuscular:exactRayEnds": "exact_ray_ends",
    }.items():
        defaults = crepuscular.scene_from_json(json.dumps({**build_scene(), "render": {}}))[
            "render"
        ]
        assert fallback(attribute) == pytest.approx(defaults[key]), attribute
    assert core["steps"] == 32  # the test scene's own value, not a default
    styled = crepuscular.load_style({"closing": {}, "silhouette": {}, "holes": {}})
    for name, value in styled["holes"].items():
        usd_name = "crepuscular:holes:" + "".join(
            part.capitalize() if i else part for i, part in enumerate(name.split("_"))
        )
        if usd_name in PROPERTY_NAMES and name not in ("pivot", "objects"):
            assert fallback(usd_name) == pytest.approx(value), usd_name
    assert fallback("crepuscular:closing:operation") == styled["closing"]["operation"]
    assert fallback("crepuscular:silhouette:operation") == styled["silhouette"]["operation"]


def test_exact_ray_ends_read_tokens_and_the_bools_of_older_layers(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "ends.usda"), build_scene(**SMALL))
    light = stage.GetPrimAtPath("/World/Sun")
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64, height=36)
    assert reader.read(Usd.TimeCode.Default()).settings["exact_ray_ends"] == "auto"
    attribute = light.GetAttribute("crepuscular:exactRayEnds")
    assert attribute.Set("off")
    assert reader.read(Usd.TimeCode.Default()).settings["exact_ray_ends"] == "off"
    # A layer saved while the attribute was a bool.
    text = "\n".join(
        line
        for line in stage.GetRootLayer().ExportToString().splitlines()
        if "crepuscular:exactRayEnds" not in line
    )
    sun = text.index("{", text.index('def DistantLight "Sun"')) + 1
    for flag, setting in (("1", "on"), ("0", "off")):
        old = Sdf.Layer.CreateAnonymous(".usda")
        assert old.ImportFromString(
            f"{text[:sun]}\n        bool crepuscular:exactRayEnds = {flag}{text[sun:]}"
        )
        opened = Usd.Stage.Open(old)
        assert opened.GetPrimAtPath("/World/Sun").GetAttribute(
            "crepuscular:exactRayEnds"
        ).Get() is bool(int(flag))
        frame = StageReader(opened, "/World/Camera", "/World/Sun", width=64, height=36).read(
            Usd.TimeCode.Default()
        )
        assert frame.settings["exact_ray_ends"] == setting, flag
        assert np.isfinite(crepuscular.render_arrays(**frame.render_kwargs()).volume).all()
    assert attribute.Set("always")
    with pytest.raises(SchemaError, match="exactRayEnds: 'always' is not one of auto, on, off"):
        reader.read(Usd.TimeCode.Default())


def test_transfer_function_inline_and_as_asset_and_holes_objects(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "tf.usda"), scene)
    tf = {
        "mode": "monochrome",
        "depth_range": {"near": 0, "far": 30},
        "layers": [{"kind": "solid", "color": [0.2, 0.2, 0.2, 1.0]}],
    }
    preset = tmp_path / "presets" / "dim.json"
    preset.parent.mkdir()
    preset.write_text(json.dumps({"version": 1, "tf": tf}))
    light = stage.GetPrimAtPath("/World/Sun")
    light.GetAttribute("crepuscular:tf:json").Set(json.dumps(tf))
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    inline = reader.read(Usd.TimeCode.Default())
    assert inline.style["tf"] == tf
    light.GetAttribute("crepuscular:tf:json").Set("")
    light.GetAttribute("crepuscular:tf:asset").Set(Sdf.AssetPath("./presets/dim.json"))
    light.GetAttribute("crepuscular:holes:enable").Set(True)
    light.GetRelationship("crepuscular:holes:objects").SetTargets(["/World/occluder"])
    asset = reader.read(Usd.TimeCode.Default())
    assert asset.style["tf"] == crepuscular.load_style({"version": 1, "tf": tf})["tf"]
    occluder_id = asset.geometry.ids_by_path[Sdf.Path("/World/occluder")]
    assert asset.style["holes"]["objects"] == [occluder_id]
    expected = flatten(scene)
    assert np.array_equal(np.unique(asset.geometry.object_ids), [1, 2])
    direct = crepuscular.render_arrays(
        **{**expected, "object_ids": asset.geometry.object_ids}, style=asset.style
    )
    _layers_close(crepuscular.render_arrays(**asset.render_kwargs()), direct, 1e-6)
    plain = crepuscular.render(scene)
    assert float(crepuscular.render_arrays(**asset.render_kwargs()).volume[..., :3].sum()) < float(
        plain.volume[..., :3].sum()
    )


def test_a_tf_assets_images_are_found_beside_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "shot").mkdir()
    stage = author_stage(str(tmp_path / "shot" / "tf.usda"), build_scene(**SMALL))
    looks = tmp_path / "looks"
    looks.mkdir()
    ramp = np.array([[0.0, 1.0]], dtype=np.float32)
    crepuscular.write_exr_channels(looks / "ramp.exr", {"R": ramp, "G": ramp, "B": 1.0 - ramp})
    image_layer = {"kind": "image", "image": {"kind": "file", "path": "ramp.exr"}}
    tf = {"mode": "color", "depth_range": {"near": 0, "far": 30}, "layers": [image_layer]}
    (looks / "ramp-look.json").write_text(json.dumps({"version": 1, "tf": tf}))
    light = stage.GetPrimAtPath("/World/Sun")
    light.GetAttribute("crepuscular:tf:asset").Set(Sdf.AssetPath("../looks/ramp-look.json"))
    farm_job = tmp_path / "farm-job"
    farm_job.mkdir()
    monkeypatch.chdir(farm_job)
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=64).read(Usd.TimeCode.Default())
    assert Path(frame.style["tf"]["layers"][0]["image"]["path"]) == looks / "ramp.exr"
    styled = crepuscular.render_arrays(**frame.render_kwargs())
    assert np.isfinite(styled.volume).all()


def test_stage_without_the_api_gets_physical_defaults(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "plain.usda"), scene, apply_api=False)
    frame = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
    assert frame.light_settings.has_api is False
    assert frame.medium["extinction"] == pytest.approx(0.05)
    assert frame.medium["extent"] == {"kind": "unbounded"}
    assert set(frame.style) == {"version", "time"}


def test_defaults_render_a_centimetre_stage_as_the_same_stage_in_metres(tmp_path: Path) -> None:
    """Without the API, and with `apply_schema`'s defaults, a Y-up centimetre stage gives the
    layers of the Z-up metre one: the fallbacks are metres, authored in stage units."""
    scene = build_scene(**SMALL)
    layers = {}
    for up, meters in (("Z", 1.0), ("Y", 0.01)):
        path = str(tmp_path / f"{up}.usda")
        stage = author_stage(path, scene, up=up, meters_per_unit=meters, apply_api=False)
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        layers[up, "no API"] = _render(reader)
        light = stage.GetPrimAtPath("/World/Sun")
        crepuscular_usd.apply_schema(light)
        assert light.GetAttribute("crepuscular:medium:extinction").Get() == pytest.approx(
            0.05 * meters
        )
        assert light.GetAttribute("crepuscular:maxDistance").Get() == pytest.approx(100 / meters)
        assert light.GetAttribute("crepuscular:shadowBias").Get() == -1.0
        reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
        layers[up, "applied"] = _render(reader)
    reference = layers["Z", "no API"]
    assert float(np.asarray(reference.volume)[..., :3].mean()) > 0.0
    for key in (("Y", "no API"), ("Z", "applied"), ("Y", "applied")):
        _layers_close(layers[key], reference, 1e-4)


def test_a_stage_that_does_not_declare_its_units_takes_the_fallbacks_in_its_own(
    tmp_path: Path,
) -> None:
    stage = author_stage(str(tmp_path / "s.usda"), build_scene(**SMALL), apply_api=False)
    stage.ClearMetadata("metersPerUnit")  # centimetres, as USD reads it
    frame = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
    assert frame.medium["extinction"] == pytest.approx(0.05 / 0.01)
    assert frame.render_kwargs()["settings"]["max_distance"] == pytest.approx(100 * 0.01)
    light = stage.GetPrimAtPath("/World/Sun")
    crepuscular_usd.apply_schema(light)
    assert light.GetAttribute("crepuscular:medium:extinction").Get() == pytest.approx(0.05)
    assert light.GetAttribute("crepuscular:maxDistance").Get() == pytest.approx(100)


def test_channel_extinction_is_read_per_stage_unit_and_negative_leaves_it_unset(
    tmp_path: Path,
) -> None:
    stage = author_stage(str(tmp_path / "s.usda"), build_scene(**SMALL), meters_per_unit=0.01)
    light = stage.GetPrimAtPath("/World/Sun")
    attribute = light.GetAttribute("crepuscular:medium:channelExtinction")
    reader = StageReader(stage, None, None, width=64)
    assert "channel_extinction" not in reader.read(Usd.TimeCode.Default()).medium
    attribute.Set(Gf.Vec3f(0.001, 0.002, 0.004))
    medium = reader.read(Usd.TimeCode.Default()).medium
    assert medium["channel_extinction"] == pytest.approx([0.1, 0.2, 0.4])
    attribute.Set(Gf.Vec3f(0.001, -1.0, 0.004))
    assert "channel_extinction" not in reader.read(Usd.TimeCode.Default()).medium


def test_xform_resets_nested_transforms_and_animated_points(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "xf.usda"), build_scene(**SMALL))
    parent = UsdGeom.Xform.Define(stage, "/World/Parent")
    parent.AddTranslateOp().Set(Gf.Vec3d(100.0, 0.0, 0.0))
    parent.AddRotateZOp().Set(90.0)
    child = UsdGeom.Mesh.Define(stage, "/World/Parent/Reset")
    child.SetResetXformStack(True)
    child.AddTranslateOp().Set(Gf.Vec3d(0.0, 5.0, 0.0))
    child.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    child.CreateFaceVertexCountsAttr([3])
    child.CreateFaceVertexIndicesAttr([0, 1, 2])
    points = child.CreatePointsAttr()
    points.Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(0, 1, 0)], Usd.TimeCode(1))
    points.Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(3, 0, 0), Gf.Vec3f(0, 1, 0)], Usd.TimeCode(2))
    kept = UsdGeom.Mesh.Define(stage, "/World/Parent/Kept")
    kept.CreatePointsAttr([Gf.Vec3f(1, 0, 0), Gf.Vec3f(2, 0, 0), Gf.Vec3f(1, 1, 0)])
    kept.CreateFaceVertexCountsAttr([3])
    kept.CreateFaceVertexIndicesAttr([0, 1, 2])
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    for time, x in ((1, 2.0), (2, 6.0), (1, 2.0)):
        geometry = reader.read(Usd.TimeCode(time)).geometry
        reset_id = geometry.ids_by_path[Sdf.Path("/World/Parent/Reset")]
        world = geometry.positions + geometry.origin
        corners = world[geometry.triangles[geometry.object_ids == reset_id][0]]
        np.testing.assert_allclose(corners, [[0, 5, 0], [x, 5, 0], [0, 7, 0]], atol=1e-6)
        kept_id = geometry.ids_by_path[Sdf.Path("/World/Parent/Kept")]
        corners = world[geometry.triangles[geometry.object_ids == kept_id][0]]
        np.testing.assert_allclose(corners, [[100, 1, 0], [100, 2, 0], [99, 1, 0]], atol=1e-5)


def _points_of(geometry: crepuscular_usd.SceneGeometry, path: str) -> np.ndarray:
    object_id = geometry.ids_by_path[Sdf.Path(path)]
    used = np.unique(geometry.triangles[geometry.object_ids == object_id])
    return (geometry.positions[used] + geometry.origin).astype(np.float64)


def test_skinned_meshes_are_posed_by_blend_shapes_then_joints_each_frame(tmp_path: Path) -> None:
    """As UsdSkel defines a skinned mesh: its rest points, plus its animation's weighted
    blend shapes, skinned by its joints (the halfway points blended by weight), in the
    skeleton's space; its own transform ignored. Read again after a later frame, the first
    frame's pose comes back."""
    stage = author_stage(str(tmp_path / "skel.usda"), build_scene(occluder=False, **SMALL))
    skeleton = author_rig(stage, "/World/Rig", {1.0: 0.0, 2.0: 90.0, 3.0: -40.0})
    author_skinned_strip(stage, "/World/Rig/Strip", skeleton)
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    for time, degrees in ((1, 0.0), (2, 90.0), (3, -40.0), (1, 0.0)):
        geometry = reader.read(Usd.TimeCode(time)).geometry
        assert not geometry.invalid
        assert not geometry.unsupported
        points = _points_of(geometry, "/World/Rig/Strip")
        expected = posed_strip(degrees)
        order = lambda rows: rows[np.lexsort(rows.T[::-1])]  # noqa: E731
        np.testing.assert_allclose(order(points), order(expected), atol=1e-5)
    # Not a pose the reader could reach by reading the rest points under the mesh's own
    # transform, nor by skipping the blend shape.
    rest = np.array(STRIP_REST) + np.array([100.0, 100.0, 100.0])
    assert np.abs(posed_strip(90.0) - rest).max() > 90.0


def test_dual_quaternion_skinning_turns_blended_points_by_half_the_angle(
    tmp_path: Path,
) -> None:
    """With `skinningMethod = dualQuaternion`, the points weighted half to each joint turn
    45 degrees about joint b's pivot when b turns 90, where linear blending would pull them
    inwards to the chord's midpoint."""
    stage = author_stage(str(tmp_path / "dqs.usda"), build_scene(occluder=False, **SMALL))
    skeleton = author_rig(stage, "/World/Rig", {1.0: 90.0})
    author_skinned_strip(stage, "/World/Rig/Strip", skeleton)
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/World/Rig/Strip"))
    binding.CreateSkinningMethodAttr().Set(UsdSkel.Tokens.dualQuaternion)
    geometry = StageReader(stage, None, None, width=64).read(Usd.TimeCode(1)).geometry
    points = _points_of(geometry, "/World/Rig/Strip")
    halfway = points[np.abs(points[:, 1] + 0.5 * np.sin(np.pi / 4)) < 1e-4]
    np.testing.assert_allclose(np.sort(halfway[:, 0]), [10.0, 10.5], atol=1e-5)
    np.testing.assert_allclose(halfway[:, 2], 1.0 + 0.5 * np.cos(np.pi / 4), atol=1e-5)


def test_skinned_prototypes_are_posed_in_every_instance(tmp_path: Path) -> None:
    """A PointInstancer of a rig (a crowd): each copy is the posed strip where the instance
    puts it, and the pose follows the animation from frame to frame."""
    stage = author_stage(str(tmp_path / "crowd.usda"), build_scene(occluder=False, **SMALL))
    rig = "/World/Crowd/Protos/Rig"
    skeleton = author_rig(stage, rig, {1.0: 90.0, 2.0: -40.0})
    author_skinned_strip(stage, f"{rig}/Strip", skeleton)
    placements = [(Gf.Vec3f(0, 3 * k, 0), Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1)) for k in range(2)]
    _instancer(stage, "/World/Crowd", rig, placements)
    reader = StageReader(stage, None, None, width=64)
    for time, degrees in ((1, 90.0), (2, -40.0)):
        geometry = reader.read(Usd.TimeCode(time)).geometry
        assert not geometry.invalid
        points = _points_of(geometry, "/World/Crowd")
        posed = posed_strip(degrees)
        expected = np.concatenate([posed + np.array([0.0, 3.0 * k, 0.0]) for k in range(2)])
        order = lambda rows: rows[np.lexsort(rows.T[::-1])]  # noqa: E731
        np.testing.assert_allclose(order(points), order(expected), atol=1e-5)


@pytest.mark.parametrize("schema", ["Mesh", "Cube"])
def test_a_rigidly_bound_surface_follows_its_joint(tmp_path: Path, schema: str) -> None:
    """Constant joint influences (a prop held by a hand) move the whole surface with joint
    b: a box Mesh authored at (0, 0, 2), or a Cube at its origin that its geomBindTransform
    puts there."""
    stage = author_stage(str(tmp_path / "rigid.usda"), build_scene(occluder=False, **SMALL))
    skeleton = author_rig(stage, "/World/Rig", {1.0: 90.0})
    raised = Gf.Matrix4d().SetTranslate(Gf.Vec3d(0.0, 0.0, 2.0))
    if schema == "Mesh":
        prop = _define(stage, "Mesh", "/World/Rig/Prop")
        points, counts, indices = _box_points(0.2)
        mesh = UsdGeom.Mesh(prop)
        mesh.CreatePointsAttr([p + Gf.Vec3f(0.0, 0.0, 2.0) for p in points])
        mesh.CreateFaceVertexCountsAttr(counts)
        mesh.CreateFaceVertexIndicesAttr(indices)
    else:
        prop = _define(stage, "Cube", "/World/Rig/Prop", size=0.2)
    binding = UsdSkel.BindingAPI.Apply(prop)
    assert binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set([1])
    binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
    if schema == "Cube":
        binding.CreateGeomBindTransformAttr(raised)
    geometry = StageReader(stage, None, None, width=64).read(Usd.TimeCode(1)).geometry
    points = _points_of(geometry, "/World/Rig/Prop")
    # (0, 0, 2) turned 90 degrees about x around (0, 0, 1) is (0, -1, 1).
    np.testing.assert_allclose(points.mean(axis=0), [10.0, -1.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(np.ptp(points, axis=0), [0.2, 0.2, 0.2], atol=1e-5)


def test_a_skinned_mesh_whose_influences_do_not_fit_is_named(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "bad.usda"), build_scene(occluder=False, **SMALL))
    skeleton = author_rig(stage, "/World/Rig", {1.0: 90.0})
    author_skinned_strip(stage, "/World/Rig/Strip", skeleton)
    # Two influences a point for five of its six points.
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/World/Rig/Strip"))
    binding.GetJointIndicesPrimvar().Set([0] * 10)
    binding.GetJointWeightsPrimvar().Set([1.0] * 10)
    geometry = StageReader(stage, None, None, width=64).read(Usd.TimeCode(1)).geometry
    assert Sdf.Path("/World/Rig/Strip") not in geometry.ids_by_path
    assert len(geometry.invalid) == 1
    assert "/World/Rig/Strip" in geometry.invalid[0]


def test_basis_curves_cast_as_ribbons_of_their_widths(tmp_path: Path) -> None:
    """BasisCurves (hair, grass, wires) cast as ribbons along their points, one across the
    sun (two radii past the strand along the sun) and one across the camera, each reaching
    half the point's width, with widths per point, per curve or one for all; widths that
    fit none of those, or none at all, are named."""
    stage = author_stage(str(tmp_path / "curves.usda"), build_scene(occluder=False, **SMALL))
    curves = UsdGeom.BasisCurves.Define(stage, "/World/Hair")
    y = np.linspace(0.0, 3.0, 4)
    strands = [np.c_[np.full_like(y, x), y, np.full_like(y, 2.0)] for x in (0.0, 1.0, 2.0)]
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.concatenate(strands).astype(np.float32)))
    curves.CreateCurveVertexCountsAttr([4, 4, 4])
    curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
    curves.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
    curves.CreateWrapAttr(UsdGeom.Tokens.pinned)
    widths = curves.CreateWidthsAttr()
    # A reader keeps what it read of a static stage: a new one for each edit.
    read = lambda: StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())  # noqa: E731
    for value, expected in (([0.2] * 12, 0.1), ([0.2], 0.1), ([0.1, 0.2, 0.3], None)):
        widths.Set(value)
        frame = read()
        geometry = frame.geometry
        assert not geometry.invalid
        # Catmull-Rom: each of a strand's 3 segments cut into CATMULL_ROM_STEPS.
        segments = 3 * 3 * crepuscular.CATMULL_ROM_STEPS
        assert len(geometry.triangles[geometry.object_ids == 2]) == segments * 2 * 2
        sun = np.asarray(frame.sun["direction"])
        for flag in (crepuscular.BLOCKS_SUN, crepuscular.SEEN_BY_CAMERA):
            rows = (geometry.object_ids == 2) & (geometry.visibility == flag)
            points = geometry.positions[np.unique(geometry.triangles[rows])] + geometry.origin
            points = points.astype(np.float64)
            x = points[:, 0]
            radius = expected if expected is not None else 0.05 * (np.round(x) + 1)
            if flag == crepuscular.BLOCKS_SUN:
                points -= crepuscular.STRAND_SHADOW_GAP * np.multiply.outer(radius, sun)
            x, z = points[:, 0], points[:, 2]
            distance = np.hypot(x - np.round(x), z - 2.0)
            np.testing.assert_allclose(distance, radius, rtol=1e-5)
    for value, words in (([0.2] * 5, "5 widths match neither"), ([], "no widths")):
        widths.Set(value)
        geometry = read().geometry
        assert len(geometry.invalid) == 1
        assert words in geometry.invalid[0]


def _place_turned(instancer: UsdGeom.PointInstancer, count: int, spacing: float) -> np.ndarray:
    """`count` placements of the first prototype along x, `spacing` apart, each turned
    about z by a random angle (seeded by `count`); returns the angles."""
    turns = np.random.default_rng(count).uniform(0, 2 * np.pi, count)
    instancer.CreateProtoIndicesAttr([0] * count)
    instancer.CreatePositionsAttr([Gf.Vec3f(spacing * k, -4.0, 1.0) for k in range(count)])
    # In single precision (half precision would turn them by other angles).
    instancer.CreateOrientationsfAttr(
        [Gf.Quatf(float(np.cos(t / 2)), 0.0, 0.0, float(np.sin(t / 2))) for t in turns]
    )
    return turns


def _seen_extent(vertices: np.ndarray, first: np.ndarray, last: np.ndarray, sun: np.ndarray):
    """The extent of `vertices` along the straight strand from `first` to `last` as the
    sun sees it, and the end points' own."""
    axis = (last - first) / np.linalg.norm(last - first)
    seen = axis - (axis @ sun) * sun
    seen /= np.linalg.norm(seen)
    along = vertices @ seen
    return [along.min(), along.max()], sorted([first @ seen, last @ seen])


def test_curves_are_ribbons_across_the_sun_and_the_camera(tmp_path: Path) -> None:
    """Seen from the sun, each strand's sun ribbon ends at its end points, as Cycles cuts a
    strand's ends across each ray, and each camera ribbon lies across the camera's ray:
    for curves of their own (under a turned, scaled transform) and placed by a
    PointInstancer, whether its placements see the sun and camera from a few directions
    (a build each) or from many (copies built at once)."""
    stage = author_stage(str(tmp_path / "cut.usda"), build_scene(occluder=False, **SMALL))
    # Straight, so that its ends' direction is the line between them, which the check uses.
    strand = [Gf.Vec3f(t, 3 * t, t) for t in (0.0, 0.25, 0.6, 1.0)]

    def define(path: str) -> UsdGeom.BasisCurves:
        curves = UsdGeom.BasisCurves.Define(stage, path)
        curves.CreatePointsAttr(strand)
        curves.CreateCurveVertexCountsAttr([4])
        curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
        curves.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
        curves.CreateWidthsAttr([0.3])
        return curves

    own = define("/World/Hair")
    own.AddRotateXYZOp().Set(Gf.Vec3f(20.0, 0.0, 50.0))
    own.AddScaleOp().Set(Gf.Vec3f(1.5, 1.5, 1.5))
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Clumps")
    define("/World/Clumps/Clump")
    instancer.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Clumps/Clump")])
    ends = np.array([[0.0, 0.0, 0.0], [1.0, 3.0, 1.0]])
    for count in (3, 40):
        turns = _place_turned(instancer, count, spacing=3.0)
        frame = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
        sun = np.asarray(frame.sun["direction"])
        geometry = frame.geometry
        eye = np.asarray(frame.camera["world_from_camera"][12:15])
        placed = geometry.positions.astype(np.float64) + geometry.origin
        flags = geometry.visibility
        sun_rows = flags == crepuscular.BLOCKS_SUN
        camera_rows = flags == crepuscular.SEEN_BY_CAMERA
        hair = placed[np.unique(geometry.triangles[(geometry.object_ids == 2) & sun_rows])]
        world = np.array(UsdGeom.Xformable(own).ComputeLocalToWorldTransform(0)).T
        first, last = (world[:3, :3] @ ends.T).T + world[:3, 3]
        extent, expected = _seen_extent(hair, first, last, sun)
        np.testing.assert_allclose(extent, expected, atol=1e-4)
        # The camera ribbon: every edge vertex is across the ray from the eye.
        seen = placed[np.unique(geometry.triangles[(geometry.object_ids == 2) & camera_rows])]
        axis = (last - first) / np.linalg.norm(last - first)
        centres = first + np.outer((seen - first) @ axis, axis)
        rays = centres - eye
        offsets = seen - centres
        np.testing.assert_allclose(np.einsum("ij,ij->i", offsets, rays), 0.0, atol=1e-4)
        np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), 0.15 * 1.5, rtol=1e-4)
        clumps = np.unique(geometry.triangles[(geometry.object_ids == 3) & sun_rows])
        copies = placed[clumps].reshape(count, -1, 3)
        # Placements that see the sun alike are built together: find each one's copy.
        found = np.argsort(copies.mean(axis=1)[:, 0])
        for copy, turn, k in zip(copies[found], turns, range(count), strict=True):
            rotation = np.array(
                [[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]
            )
            first, last = (rotation @ ends.T).T + np.array([3.0 * k, -4.0, 1.0])
            extent, expected = _seen_extent(copy, first, last, sun)
            np.testing.assert_allclose(extent, expected, atol=1e-4)


def test_points_cast_as_spheres_of_their_widths(tmp_path: Path) -> None:
    """Points (dust, spray, particles) cast a sphere around each point, of half its width,
    with widths per point or one for all, from `widths` or an indexed `primvars:widths`
    (which Hydra takes over `widths`); also as a PointInstancer's prototype. Widths that
    fit neither, or none at all, are named."""
    stage = author_stage(str(tmp_path / "points.usda"), build_scene(occluder=False, **SMALL))
    dust = UsdGeom.Points.Define(stage, "/World/Dust")
    dust.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.0))
    centres = np.array([[0.0, 0.0, 2.0], [2.0, 1.0, 2.0], [-1.0, 3.0, 4.0]])
    dust.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(centres.astype(np.float32)))
    widths = dust.CreateWidthsAttr()
    read = lambda: StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())  # noqa: E731
    count = crepuscular.SPHERE_VERTICES

    def spheres() -> np.ndarray:
        geometry = read().geometry
        assert not geometry.invalid, geometry.invalid
        object_id = geometry.ids_by_path[Sdf.Path("/World/Dust")]
        rows = geometry.triangles[geometry.object_ids == object_id]
        assert len(rows) == 3 * crepuscular.SPHERE_TRIANGLES
        used = np.unique(rows)
        return (geometry.positions[used] + geometry.origin).astype(np.float64).reshape(3, count, 3)

    for value, radii in (([0.2, 0.4, 0.6], [0.1, 0.2, 0.3]), ([0.5], [0.25] * 3)):
        widths.Set(value)
        found = spheres()
        np.testing.assert_allclose(
            found.mean(axis=1), centres + np.array([0.0, 0.0, 1.0]), atol=1e-5
        )
        np.testing.assert_allclose(
            np.ptp(found, axis=1) / (2 * np.array(radii))[:, None], 1, atol=0.06
        )
    primvar = UsdGeom.PrimvarsAPI(dust.GetPrim()).CreatePrimvar(
        "widths", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex
    )
    primvar.Set([0.8, 0.2])
    primvar.SetIndices(Vt.IntArray([1, 0, 1]))
    np.testing.assert_allclose(np.ptp(spheres(), axis=1)[:, 0] / [0.2, 0.8, 0.2], 1, atol=0.06)
    primvar.GetAttr().Clear()
    primvar.GetIndicesAttr().Clear()
    # As a prototype: a sphere per point per placement.
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Swarm")
    proto = UsdGeom.Points.Define(stage, "/World/Swarm/Mote")
    proto.CreatePointsAttr([Gf.Vec3f(0.0, 0.0, 0.0), Gf.Vec3f(1.0, 0.0, 0.0)])
    proto.CreateWidthsAttr([0.1])
    instancer.CreatePrototypesRel().SetTargets([proto.GetPath()])
    instancer.CreateProtoIndicesAttr([0, 0, 0])
    instancer.CreatePositionsAttr([Gf.Vec3f(0, -3, 2), Gf.Vec3f(1, -3, 2), Gf.Vec3f(2, -3, 2)])
    geometry = read().geometry
    swarm = geometry.ids_by_path[Sdf.Path("/World/Swarm")]
    assert (geometry.object_ids == swarm).sum() == 3 * 2 * crepuscular.SPHERE_TRIANGLES
    for value, words in (([0.2] * 2, "2 widths match neither"), ([], "no widths")):
        widths.Set(value)
        geometry = read().geometry
        assert len(geometry.invalid) == 1
        assert "/World/Dust" in geometry.invalid[0]
        assert words in geometry.invalid[0]


def test_points_show_each_view_the_side_its_rays_hit(tmp_path: Path) -> None:
    """Cycles culls a point's back side for every ray: the camera sees the triangles of a
    point's sphere that face it, the sun's shadow map those that face away from the sun,
    for points of their own (under a turned, scaled transform; one around the camera, which
    sees none of it) and placed by a PointInstancer, whose placements see the sun and
    camera from a few directions (a drawing each) or from many (all flagged in one call)."""
    stage = author_stage(str(tmp_path / "motes.usda"), build_scene(occluder=False, **SMALL))
    start = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
    eye = np.asarray(start.camera["world_from_camera"])
    dust = UsdGeom.Points.Define(stage, "/World/Dust")
    dust.AddRotateXYZOp().Set(Gf.Vec3f(20.0, 0.0, 50.0))
    dust.AddScaleOp().Set(Gf.Vec3f(1.5, 1.5, 1.5))
    dust.CreatePointsAttr([Gf.Vec3f(0.0, 0.0, 2.0), Gf.Vec3f(2.0, 1.0, 2.0)])
    dust.CreateWidthsAttr([0.4, 0.8])
    around = UsdGeom.Points.Define(stage, "/World/Around")
    around.CreatePointsAttr([Gf.Vec3f(*(float(v) for v in eye[12:15]))])
    around.CreateWidthsAttr([1.0])
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Swarm")
    mote = UsdGeom.Points.Define(stage, "/World/Swarm/Mote")
    mote.CreatePointsAttr([Gf.Vec3f(0.0, 0.0, 0.0), Gf.Vec3f(0.5, 0.0, 0.3)])
    mote.CreateWidthsAttr([0.3])
    instancer.CreatePrototypesRel().SetTargets([mote.GetPath()])
    for count in (3, 40):
        _place_turned(instancer, count, spacing=1.5)
        frame = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
        sun = np.asarray(frame.sun["direction"])
        geometry = frame.geometry
        camera = np.asarray(frame.camera["world_from_camera"][12:15])
        corners = (geometry.positions.astype(np.float64) + geometry.origin)[geometry.triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        facing_eye = np.einsum("ij,ij->i", normals, corners[:, 0] - camera) < 0
        ids = geometry.ids_by_path
        for path, placed in (("/World/Dust", 2), ("/World/Around", 1), ("/World/Swarm", 2 * count)):
            rows = geometry.object_ids == ids[Sdf.Path(path)]
            assert rows.sum() == placed * crepuscular.SPHERE_TRIANGLES
            flags = geometry.visibility[rows]
            seen = (flags & crepuscular.SEEN_BY_CAMERA) > 0
            np.testing.assert_array_equal(seen, facing_eye[rows] & (path != "/World/Around"))
            blocks = (flags & crepuscular.BLOCKS_SUN) > 0
            np.testing.assert_array_equal(blocks, normals[rows] @ sun > 0)


def test_the_lights_shadow_linking_decides_what_blocks_it(tmp_path: Path) -> None:
    """UsdLuxLightAPI's shadowLink collection: an owner it leaves out (a mesh, or a
    PointInstancer with all it places) does not block the sun but still hides the fog from
    the camera; unauthored, everything blocks. Excluding the occluder renders its shadow
    away and keeps its outline in the depth. A light whose `shadow:enable` is false is
    blocked by nothing."""
    stage = author_stage(str(tmp_path / "linked.usda"), build_scene(**SMALL))
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Posts")
    post = UsdGeom.Cube.Define(stage, "/World/Posts/Post")
    instancer.CreatePrototypesRel().SetTargets([post.GetPath()])
    instancer.CreateProtoIndicesAttr([0, 0])
    instancer.CreatePositionsAttr([Gf.Vec3f(3, 1, 0), Gf.Vec3f(-3, 1, 0)])
    link = UsdLux.LightAPI(stage.GetPrimAtPath("/World/Sun")).GetShadowLinkCollectionAPI()

    def flags_by_owner() -> tuple[dict[str, set[int]], crepuscular.Layers]:
        frame = StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())
        geometry = frame.geometry
        flags = geometry.visibility
        if flags is None:
            flags = np.full(len(geometry.triangles), 3, dtype=np.uint8)
        found = {
            str(path): set(flags[geometry.object_ids == object_id].tolist())
            for path, object_id in geometry.ids_by_path.items()
        }
        return found, crepuscular.render_arrays(**frame.render_kwargs())

    everything, plain = flags_by_owner()
    assert everything == {"/World/ground": {3}, "/World/occluder": {3}, "/World/Posts": {3}}
    link.GetExcludesRel().AddTarget("/World/occluder")
    found, unlinked = flags_by_owner()
    assert found["/World/occluder"] == {crepuscular.SEEN_BY_CAMERA}
    assert found["/World/Posts"] == {3}
    volume, plain_volume = np.asarray(unlinked.volume), np.asarray(plain.volume)
    assert np.abs(volume - plain_volume).mean() / plain_volume.mean() > 0.01
    np.testing.assert_array_equal(unlinked.depth, plain.depth)
    link.GetExcludesRel().ClearTargets(True)
    link.GetIncludeRootAttr().Set(False)
    link.GetIncludesRel().AddTarget("/World/ground")
    found, _ = flags_by_owner()
    assert found == {
        "/World/ground": {3},
        "/World/occluder": {crepuscular.SEEN_BY_CAMERA},
        "/World/Posts": {crepuscular.SEEN_BY_CAMERA},
    }
    # A light that casts no shadows (UsdLuxShadowAPI), from a time on: nothing blocks it,
    # nor does the fog dim it, and a note says so.
    enable = UsdLux.ShadowAPI.Apply(stage.GetPrimAtPath("/World/Sun")).CreateShadowEnableAttr()
    enable.Set(True, 1.0)
    enable.Set(False, 2.0)
    reader = StageReader(stage, None, None, width=64)
    shadowed = reader.read(Usd.TimeCode(1.0))
    assert shadowed.geometry.notes == []
    assert shadowed.sun["attenuated_by_medium"] is True
    shadowless = reader.read(Usd.TimeCode(2.0))
    assert set(shadowless.geometry.visibility.tolist()) == {crepuscular.SEEN_BY_CAMERA}
    assert shadowless.sun["attenuated_by_medium"] is False
    assert "casts no shadows (inputs:shadow:enable is false)" in shadowless.geometry.notes[0]


def test_a_medium_left_out_of_the_lights_linking_is_named(tmp_path: Path) -> None:
    """A path tracer lights no fog that the light's lightLink or shadowLink collection
    leaves out; the step renders the shafts and says so, naming the medium's prim."""
    stage = author_stage(str(tmp_path / "linked.usda"), build_scene(**SMALL))
    box = UsdGeom.Cube.Define(stage, "/World/Fog")
    light = stage.GetPrimAtPath("/World/Sun")
    light.GetRelationship("crepuscular:mediumExtent").SetTargets([box.GetPath()])
    api = UsdLux.LightAPI(light)
    read = lambda: StageReader(stage, None, None, width=64).read(Usd.TimeCode.Default())  # noqa: E731
    assert not read().geometry.notes
    api.GetLightLinkCollectionAPI().GetExcludesRel().AddTarget("/World/Fog")
    (note,) = read().geometry.notes
    assert note.startswith("/World/Sun: its lightLink collection leaves the medium /World/Fog")
    api.GetShadowLinkCollectionAPI().GetIncludeRootAttr().Set(False)
    api.GetShadowLinkCollectionAPI().GetIncludesRel().AddTarget("/World/ground")
    assert [n.split(" collection")[0] for n in read().geometry.notes] == [
        "/World/Sun: its lightLink",
        "/World/Sun: its shadowLink",
    ]


def test_medium_extent_from_a_box_mesh_and_a_volume(tmp_path: Path) -> None:
    scene = build_scene(**SMALL)
    stage = author_stage(str(tmp_path / "extent.usda"), scene, meters_per_unit=0.1, up="Y")
    light = stage.GetPrimAtPath("/World/Sun")
    box = UsdGeom.Mesh.Define(stage, "/World/FogBox")
    box.AddTranslateOp().Set(Gf.Vec3d(10.0, 0.0, 0.0))
    box.CreatePointsAttr([Gf.Vec3f(x, y, z) for x in (-5, 15) for y in (0, 30) for z in (-5, 5)])
    volume = UsdVol.Volume.Define(stage, "/World/FogVolume")
    volume.AddTranslateOp().Set(Gf.Vec3d(10.0, 0.0, 0.0))
    volume.CreateExtentAttr([Gf.Vec3f(-5, 0, -5), Gf.Vec3f(15, 30, 5)])
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    boxes = []
    for target in ("/World/FogBox", "/World/FogVolume"):
        light.GetRelationship("crepuscular:mediumExtent").SetTargets([Sdf.Path(target)])
        frame = reader.read(Usd.TimeCode.Default())
        # The extent prim holds the medium; it does not cast shadows.
        assert Sdf.Path(target) not in frame.geometry.ids_by_path
        boxes.append(np.reshape(frame.medium["extent"]["world_from_cube"], (4, 4)).T)
    # Stage box x 5..25, y 0..30, z -5..5 in decimetres; Y up turns stage y into +z and
    # stage z into -y: cube axes (1, 0, 0), (0, 0, 1.5), (0, -0.5, 0) metres about the centre.
    expected = np.array(
        [[1.0, 0.0, 0.0, 1.5], [0.0, 0.0, -0.5, 0.0], [0.0, 1.5, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]]
    )
    np.testing.assert_allclose(boxes[0], expected, atol=1e-6)
    np.testing.assert_allclose(boxes[0], boxes[1], atol=1e-6)


def test_distant_light_exposure_color_temperature_angle_and_visibility(tmp_path: Path) -> None:
    stage = author_stage(str(tmp_path / "sun.usda"), build_scene(**SMALL))
    light = UsdLux.DistantLight(stage.GetPrimAtPath("/World/Sun"))
    light.GetIntensityAttr().Set(2.0)
    light.CreateExposureAttr().Set(1.5)
    light.GetColorAttr().Set(Gf.Vec3f(1.0, 0.5, 0.25))
    light.CreateEnableColorTemperatureAttr().Set(True)
    light.CreateColorTemperatureAttr().Set(3000.0)
    light.GetAngleAttr().Set(2.0)
    reader = StageReader(stage, "/World/Camera", "/World/Sun", width=64)
    sun = reader.sun(Usd.TimeCode.Default())
    assert sun["strength"] == pytest.approx(2.0 * 2**1.5)
    blackbody = UsdLux.BlackbodyTemperatureAsRgb(3000.0)
    assert sun["color"] == pytest.approx(
        [1.0 * blackbody[0], 0.5 * blackbody[1], 0.25 * blackbody[2]]
    )
    assert sun["angular_diameter"] == pytest.approx(np.radians(2.0))
    UsdGeom.Imageable(light.GetPrim()).GetVisibilityAttr().Set(UsdGeom.Tokens.invisible, 3.0)
    UsdGeom.Imageable(light.GetPrim()).GetVisibilityAttr().Set(UsdGeom.Tokens.inherited, 1.0)
    assert reader.sun(Usd.TimeCode(1))["strength"] > 0
    off = reader.read(Usd.TimeCode(3))
    assert off.sun["strength"] == 0.0
    layers = crepuscular.render_arrays(**off.render_kwargs())
    assert float(np.abs(layers.volume[..., :3]).max()) == 0.0
    assert float(layers.volume[..., 3].max()) > 0.0  # the medium still hides what is behind
    # The schema's intensity scale (what Blender's exporter divides a sun's strength by).
    stage.GetPrimAtPath("/World/Sun").GetAttribute("crepuscular:intensityScale").Set(4.0)
    assert reader.read(Usd.TimeCode(1)).sun["strength"] == pytest.approx(4 * 2.0 * 2**1.5)
    # And its angle scale (Blender's exporter writes half a sun's angle); a disc wider than
    # the real sun's softens the shafts over several directions, a point sun takes one.
    frame = reader.read(Usd.TimeCode(1))
    assert frame.settings["sun_disc_samples"] == crepuscular.SUN_DISC_SAMPLES
    light.GetAngleAttr().Set(0.25)
    assert reader.read(Usd.TimeCode(1)).settings["sun_disc_samples"] == 1
    stage.GetPrimAtPath("/World/Sun").GetAttribute("crepuscular:angleScale").Set(4.0)
    frame = reader.read(Usd.TimeCode(1))
    assert frame.sun["angular_diameter"] == pytest.approx(np.radians(1.0))
    assert frame.settings["sun_disc_samples"] == crepuscular.SUN_DISC_SAMPLES
