"""Alpha cutouts read from a USD stage: a card whose UsdPreviewSurface takes its opacity from
a UsdUVTexture renders as the same card with the texture's empty parts cut out of its
geometry; a GeomSubset's own material cuts its faces alone; what cannot be mapped is named."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt
from scenes import build_scene
from usd_helpers import author_stage, cut_material, write_alpha_png

import crepuscular
from crepuscular_usd import StageReader
from crepuscular_usd.subdivision import CatmullClark

#: Stripes along u, as in test_cutouts.py: solid where u lies in [1/8, 2/8], [3/8, 4/8],
#: [5/8, 6/8] and [7/8, 1].
STRIPES = np.array([[0, 1, 0, 1, 0, 1, 0, 1]], dtype=np.float32)
SOLID_U = [(1 / 8, 2 / 8), (3 / 8, 4 / 8), (5 / 8, 6 / 8), (7 / 8, 1.0)]


def _stage(tmp_path: Path, name: str) -> Usd.Stage:
    scene = build_scene(width=96, height=54, steps=256, shadow_map_size=256, occluder=False)
    scene["camera"]["world_from_camera"][13] = 2.2  # below the card's edge, seeing through it
    return author_stage(str(tmp_path / f"{name}.usda"), scene)


def _quad(stage: Usd.Stage, path: str, x0: float, x1: float, z0: float = -2, z1: float = 2) -> Any:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(x0, 3, z0), (x1, 3, z0), (x1, 3, z1), (x0, 3, z1)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return mesh


def _card_uvs(mesh: UsdGeom.Mesh, interpolation: str = UsdGeom.Tokens.faceVarying) -> None:
    """st running 0 to 1 along x from -2 to 2, and along z from -2 to 2."""
    points = np.array(mesh.GetPointsAttr().Get())
    uv = np.c_[(points[:, 0] + 2) / 4, (points[:, 2] + 2) / 4]
    if interpolation == UsdGeom.Tokens.faceVarying:
        uv = uv[np.array(mesh.GetFaceVertexIndicesAttr().Get())]
    primvar = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, interpolation
    )
    primvar.Set(Vt.Vec2fArray.FromNumpy(uv.astype(np.float32)))


def _render(stage: Usd.Stage) -> crepuscular.Layers:
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    return crepuscular.render_arrays(**frame.render_kwargs())


def _mean_relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).mean() / max(np.abs(b).mean(), 1e-12))


def _strips(tmp_path: Path) -> crepuscular.Layers:
    stage = _stage(tmp_path, "strips")
    for k, (u0, u1) in enumerate(SOLID_U):
        _quad(stage, f"/World/Strip{k}", -2 + 4 * u0, -2 + 4 * u1)
    return _render(stage)


@pytest.mark.parametrize("interpolation", ["faceVarying", "vertex"])
def test_a_textured_opacity_cuts_the_card_as_its_solid_parts(
    tmp_path: Path, interpolation: str
) -> None:
    stage = _stage(tmp_path, "cut")
    card = _quad(stage, "/World/Card", -2, 2)
    _card_uvs(card, interpolation)
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(
        cut_material(stage, "/World/Looks/Leaf", file)
    )
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    assert frame.geometry.notes == []
    assert len(frame.geometry.masks) == 1
    cut = crepuscular.render_arrays(**frame.render_kwargs())
    strips = _strips(tmp_path)
    stage_opaque = _stage(tmp_path, "opaque")
    _quad(stage_opaque, "/World/Card", -2, 2)
    opaque = _render(stage_opaque)
    assert _mean_relative(strips.volume, opaque.volume) > 0.02
    for name in ("volume", "visibility", "depth"):
        assert _mean_relative(getattr(cut, name), getattr(strips, name)) < 1e-4, name


#: Solid but for its first column, in four equal rows: filtered, it crosses 0.5 at s = 1/4
#: and, where it repeats, at s = 1.
FIRST_EMPTY = np.tile(np.array([[0, 1, 1, 1]], dtype=np.float32), (4, 1))


@pytest.mark.parametrize(
    ("wrap_s", "inputs", "solid_s"),
    [
        ("repeat", {}, [(-0.75, 0.0), (0.25, 1.0), (1.25, 2.0)]),
        ("clamp", {}, [(0.25, 2.0)]),
        ("mirror", {}, [(-1.0, -0.25), (0.25, 1.75)]),
        ("black", {}, [(0.25, 1.0)]),
        # USD's fallback for a file without wrap metadata (none of ours has any): black.
        ("useMetadata", {}, [(0.25, 1.0)]),
        (None, {}, [(0.25, 1.0)]),
        # Inverted by scale and bias: past a black edge it reads 0 · -1 + 1, solid.
        ("black", {"scale": (-1.0,) * 4, "bias": (1.0,) * 4}, [(-1.0, 0.25), (1.0, 2.0)]),
        # A wrap USD has no such mode: named, and the card casts whole.
        ("clampToEdge", {}, [(-1.0, 2.0)]),
    ],
)
def test_each_wrap_mode_cuts_past_the_texture_as_usd_reads_it(
    tmp_path: Path, wrap_s: str | None, inputs: dict[str, Any], solid_s: list[tuple[float, float]]
) -> None:
    """A card whose s runs from -1 to 2 across it (t from 1/4 to 3/4, inside the texture),
    cut by `FIRST_EMPTY` read past its edges as `wrapS` says: the card's parts where the
    read opacity reaches the cut. Left to the file (`useMetadata`, or nothing authored),
    the texture reads black, and a note says that Blender's import repeats it."""
    stage = _stage(tmp_path, "wrapped")
    card = _quad(stage, "/World/Card", -2, 2)
    points = np.array(card.GetPointsAttr().Get())
    st = np.c_[-1 + 3 * (points[:, 0] + 2) / 4, 0.25 + 0.5 * (points[:, 2] + 2) / 4]
    UsdGeom.PrimvarsAPI(card).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
    ).Set(Vt.Vec2fArray.FromNumpy(st.astype(np.float32)))
    file = write_alpha_png(tmp_path / "first_empty.png", FIRST_EMPTY)
    material = cut_material(stage, "/World/Looks/Leaf", file, wrap=None)
    texture = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Alpha"))
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    if wrap_s is not None:
        texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap_s)
    for name, value in inputs.items():
        texture.CreateInput(name, Sdf.ValueTypeNames.Float4).Set(value)
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material)
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    notes = frame.geometry.notes
    expected_note = {
        "useMetadata": "Blender's USD import repeats it",
        None: "Blender's USD import repeats it",
        "clampToEdge": "wrap 'clampToEdge' is none of",
    }.get(wrap_s)
    assert len(notes) == (expected_note is not None), notes
    if expected_note is not None:
        assert expected_note in notes[0], notes
    cut = crepuscular.render_arrays(**frame.render_kwargs())
    parts = _stage(tmp_path, "parts")
    for k, (s0, s1) in enumerate(solid_s):
        _quad(parts, f"/World/Part{k}", -2 + 4 * (s0 + 1) / 3, -2 + 4 * (s1 + 1) / 3)
    expected = _render(parts)
    for name in ("volume", "visibility", "depth"):
        assert _mean_relative(getattr(cut, name), getattr(expected, name)) < 1e-4, name


def test_rows_run_from_the_image_top_and_an_exr_reads_the_same(tmp_path: Path) -> None:
    """A texture solid in its bottom row (v near 0, the card's -z edge) cuts the card to
    its -z half, from a PNG and from an EXR alike."""
    bottom_solid = np.array([[0.0], [1.0]], dtype=np.float32)  # file rows: top, bottom
    png = write_alpha_png(tmp_path / "bottom.png", bottom_solid)
    exr = tmp_path / "bottom.exr"
    zeros = np.zeros_like(bottom_solid)
    crepuscular.write_exr_channels(exr, {"R": zeros, "G": zeros, "B": zeros, "A": bottom_solid})
    half = _stage(tmp_path, "half")
    _quad(half, "/World/Card", -2, 2, -2, 0)
    expected = _render(half)
    for file in (png, exr.name):
        stage = _stage(tmp_path, f"from_{file.replace('.', '_')}")
        card = _quad(stage, "/World/Card", -2, 2)
        _card_uvs(card)
        material = cut_material(stage, "/World/Looks/Leaf", file)
        UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material)
        assert _mean_relative(_render(stage).volume, expected.volume) < 1e-4, file


@pytest.mark.parametrize(
    ("interpolation", "authored", "rule"),
    [
        (UsdGeom.Tokens.faceVarying, None, "cornersPlus1"),
        (UsdGeom.Tokens.faceVarying, "none", "none"),
        (UsdGeom.Tokens.faceVarying, "boundaries", "boundaries"),
        (UsdGeom.Tokens.faceVarying, "all", "all"),
        (UsdGeom.Tokens.vertex, "all", "none"),
        (UsdGeom.Tokens.varying, "none", "all"),
    ],
)
def test_a_subdivided_cards_coordinates_refine_as_their_interpolation_says(
    tmp_path: Path, interpolation: str, authored: str | None, rule: str
) -> None:
    """A cut card of 3 by 3 quads, refined two levels: face-varying coordinates by the
    mesh's `faceVaryingLinearInterpolation` (USD's fallback `cornersPlus1`), vertex ones
    as its points whatever that says, varying ones linearly in each face. The coordinates
    of all but the corners are moved off the grid, so that the rules differ."""
    stage = _stage(tmp_path, "subdivided")
    x, z = np.meshgrid(np.linspace(-2, 2, 4), np.linspace(-2, 2, 4))
    jitter = np.random.default_rng(4).uniform(-0.3, 0.3, (16, 2)) * [[1, 1]]
    on_edge = (np.abs(x.ravel()) == 2)[:, None] | (np.abs(z.ravel()) == 2)[:, None]
    jitter = np.where(on_edge, 0.0, jitter)
    points = np.c_[x.ravel() + jitter[:, 0], np.full(16, 3.0), z.ravel() + jitter[:, 1]]
    first = (np.arange(3)[:, None] * 4 + np.arange(3)).ravel()
    faces = np.stack([first, first + 1, first + 5, first + 4], axis=1).reshape(-1)
    card = UsdGeom.Mesh.Define(stage, "/World/Card")
    card.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    card.CreateFaceVertexCountsAttr([4] * 9)
    card.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.astype(np.int32)))
    card.GetPrim().CreateAttribute(
        "crepuscular:subdivision:levels", Sdf.ValueTypeNames.Int, custom=True
    ).Set(2)
    if authored is not None:
        card.CreateFaceVaryingLinearInterpolationAttr(authored)
    corner = (np.abs(x.ravel()) == 2) & (np.abs(z.ravel()) == 2)
    moved = np.random.default_rng(5).uniform(-0.04, 0.04, (16, 2)) * ~corner[:, None]
    st = np.c_[(x.ravel() + 2) / 4, (z.ravel() + 2) / 4] + moved
    per_corner = st[faces] if interpolation == UsdGeom.Tokens.faceVarying else st
    primvar = UsdGeom.PrimvarsAPI(card).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, interpolation
    )
    primvar.Set(Vt.Vec2fArray.FromNumpy(per_corner.astype(np.float32)))
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(
        cut_material(stage, "/World/Looks/Leaf", file)
    )
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    geometry = frame.geometry
    assert geometry.notes == []
    assert geometry.uvs is not None
    mine = np.asarray(geometry.object_ids) == geometry.ids_by_path[Sdf.Path("/World/Card")]
    corners = geometry.triangles[mine].reshape(-1)
    read_points = geometry.positions[corners] + geometry.origin
    read_uvs = geometry.uvs[corners]
    refinement = CatmullClark([4] * 9, faces, 16, 2)
    refined = refinement.refine(points.astype(np.float32))[refinement.face_vertex_indices]

    def expected(rule: str) -> np.ndarray:
        uvs = refinement.refine_face_varying(st[faces].astype(np.float32), rule)
        apart = np.linalg.norm(read_points[:, None] - refined[None], axis=2)
        return uvs[apart.argmin(axis=1)]

    assert np.abs(read_uvs - expected(rule)).max() < 1e-6
    # On one island with its corners kept, `cornersPlus1` smooths as `none` does.
    others = {"none", "boundaries", "all"} - {"none" if rule == "cornersPlus1" else rule}
    for other in others:
        assert np.abs(read_uvs - expected(other)).max() > 1e-3, other


def test_a_subsets_material_cuts_its_faces_alone(tmp_path: Path) -> None:
    """A card of two faces: a GeomSubset binds the cut material to the x < 0 face; the
    mesh's own (opaque) material covers the other."""
    stage = _stage(tmp_path, "subset")
    card = UsdGeom.Mesh.Define(stage, "/World/Card")
    card.CreatePointsAttr([(-2, 3, -2), (0, 3, -2), (2, 3, -2), (2, 3, 2), (0, 3, 2), (-2, 3, 2)])
    card.CreateFaceVertexCountsAttr([4, 4])
    card.CreateFaceVertexIndicesAttr([0, 1, 4, 5, 1, 2, 3, 4])
    _card_uvs(card)
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    binding = UsdShade.MaterialBindingAPI.Apply(card.GetPrim())
    plain = UsdShade.Material.Define(stage, "/World/Looks/Plain")
    assert binding.Bind(plain)
    subset = binding.CreateMaterialBindSubset("leaves", Vt.IntArray([0]))
    UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(
        cut_material(stage, "/World/Looks/Leaf", file)
    )
    cut = _render(stage)
    reference = _stage(tmp_path, "subset_reference")
    for k, (u0, u1) in enumerate(SOLID_U[:2]):
        _quad(reference, f"/World/Strip{k}", -2 + 4 * u0, -2 + 4 * u1)
    _quad(reference, "/World/Solid", 0, 2)
    assert _mean_relative(cut.volume, _render(reference).volume) < 1e-4


@pytest.mark.parametrize(
    ("transforms", "parts"),
    [
        # s' = s/2 + 1/4 over the card: stripes [3/8, 4/8] and [5/8, 6/8] of the texture.
        ([{"scale": (0.5, 1.0), "translation": (0.25, 0.0)}], [(-1, 0, -2, 2), (1, 2, -2, 2)]),
        # A quarter turn: s' = 0.03 - t, so the stripes run across z.
        (
            [{"rotation": 90.0, "translation": (0.03, 0.0)}],
            [
                (-2, 2, -1.88, -1.38),
                (-2, 2, -0.88, -0.38),
                (-2, 2, 0.12, 0.62),
                (-2, 2, 1.12, 1.62),
            ],
        ),
        # Chained, the node nearest the texture last: a half turn after the first map,
        # s' = -(s/2 + 1/4) + 1 = 3/4 - s/2, the same stripes.
        (
            [
                {"rotation": 180.0, "translation": (1.0, 0.0)},
                {"scale": (0.5, 1.0), "translation": (0.25, 0.0)},
            ],
            [(-2, -1, -2, 2), (0, 1, -2, 2)],
        ),
    ],
)
def test_transform_2d_nodes_map_the_coordinates(
    tmp_path: Path, transforms: list[dict[str, Any]], parts: list[tuple[float, ...]]
) -> None:
    """`UsdTransform2d` nodes between the primvar reader and the texture (what Blender's
    exporter writes for a Mapping node) scale, turn (counter-clockwise, in degrees) and
    move the coordinates the texture reads: the card cuts as its parts where the mapped
    stripes are solid."""
    stage = _stage(tmp_path, "mapped")
    card = _quad(stage, "/World/Card", -2, 2)
    _card_uvs(card)
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    material = cut_material(stage, "/World/Looks/Leaf", file)
    texture = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Alpha"))
    reader = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/St"))
    into = texture.GetInput("st")
    for k, inputs in enumerate(transforms):
        node = UsdShade.Shader.Define(stage, f"/World/Looks/Leaf/Map{k}")
        node.CreateIdAttr("UsdTransform2d")
        for name, value in inputs.items():
            kind = Sdf.ValueTypeNames.Float if name == "rotation" else Sdf.ValueTypeNames.Float2
            node.CreateInput(name, kind).Set(value)
        assert into.ConnectToSource(node.ConnectableAPI(), "result")
        into = node.CreateInput("in", Sdf.ValueTypeNames.Float2)
    assert into.ConnectToSource(reader.ConnectableAPI(), "result")
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material)
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    assert frame.geometry.notes == []
    cut = crepuscular.render_arrays(**frame.render_kwargs())
    expected = _stage(tmp_path, "mapped_parts")
    for k, (x0, x1, z0, z1) in enumerate(parts):
        _quad(expected, f"/World/Part{k}", x0, x1, z0, z1)
    for name in ("volume", "visibility", "depth"):
        error = _mean_relative(getattr(cut, name), getattr(_render(expected), name))
        assert error < 1e-4, (name, error)


def test_missing_coordinates_read_the_readers_fallback(tmp_path: Path) -> None:
    """A primvar reader whose primvar the mesh lacks reads its `fallback` everywhere (named
    in a note), and a texture whose `st` is a value rather than a reader reads there: at
    s = 0.19 the stripes' filtered alpha is 0.98 (the whole card solid), at 0.3 it is 0.1
    (no card)."""
    plain = _stage(tmp_path, "plain_card")
    _quad(plain, "/World/Card", -2, 2)
    solid, bare = _render(plain), _render(_stage(tmp_path, "no_card"))
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    for s_value, expected in ((0.19, solid), (0.3, bare)):
        for how in ("fallback", "st value"):
            stage = _stage(tmp_path, f"missing_{how.replace(' ', '_')}_{s_value}")
            card = _quad(stage, "/World/Card", -2, 2)
            material = cut_material(stage, "/World/Looks/Leaf", file)
            if how == "fallback":
                reader = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/St"))
                reader.CreateInput("fallback", Sdf.ValueTypeNames.Float2).Set((s_value, 0.5))
            else:
                texture = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Alpha"))
                st = texture.GetInput("st")
                assert st.DisconnectSource()
                st.Set((s_value, 0.5))
            UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material)
            frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(
                Usd.TimeCode.Default()
            )
            notes = frame.geometry.notes
            if how == "fallback":
                assert len(notes) == 1
                assert f"primvar 'st' is missing; its mask reads ({s_value:g}, 0.5)" in notes[0]
            else:
                assert notes == []
            cut = crepuscular.render_arrays(**frame.render_kwargs())
            assert _mean_relative(cut.volume, expected.volume) < 1e-6, (how, s_value)


def test_unmappable_opacity_is_named_and_casts_as_opaque(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    stage = _stage(tmp_path, "notes")
    card = _quad(stage, "/World/Card", -2, 2)
    _card_uvs(card)
    missing = cut_material(stage, "/World/Looks/Missing", "no_such_file.png")
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(missing)
    other = _quad(stage, "/World/Other", 3, 4)
    veil = UsdShade.Material.Define(stage, "/World/Looks/Veil")
    surface = UsdShade.Shader.Define(stage, "/World/Looks/Veil/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.7)
    veil.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(other.GetPrim()).Bind(veil)
    # A material bound to many meshes is named once, on the first, and once only however
    # many frames one reader reads.
    third = _quad(stage, "/World/Third", 5, 6)
    UsdShade.MaterialBindingAPI.Apply(third.GetPrim()).Bind(veil)
    reader = StageReader(stage, None, None, width=96)
    reader.read(Usd.TimeCode.Default())
    frame = reader.read(Usd.TimeCode.Default())
    assert frame.geometry.triangle_masks is None
    notes = frame.geometry.notes
    assert len(notes) == 2, notes
    assert notes[0].startswith("/World/Card: ")
    assert "no_such_file.png was not found" in notes[0]
    assert notes[1].startswith("/World/Other: ")
    assert "opacity 0.70 is cut at 0.5: it casts as opaque" in notes[1]
    stage.GetRootLayer().Save()
    from crepuscular_usd.cli import main

    out = tmp_path / "o" / "shafts.exr"
    assert main(["render", str(tmp_path / "notes.usda"), "--out", str(out), "--width", "48"]) == 0
    err = capfd.readouterr().err
    assert "no_such_file.png was not found" in err
    assert "opacity 0.70 is cut" in err


def test_a_constant_opacity_is_cut_as_a_mask(tmp_path: Path) -> None:
    """A card of one opacity everywhere is cut as a mask of that value: below the cut it
    neither casts nor hides the fog (the frame is the one without it), at or above it is
    opaque. With an opacityThreshold that is USD's own meaning and needs no note; without,
    the cut is at 0.5 and a note names the light a renderer would let through."""
    bare = _render(_stage(tmp_path, "bare"))
    stage = _stage(tmp_path, "veiled")
    card = _quad(stage, "/World/Card", -2, 2)
    solid = _render(stage)
    veil = UsdShade.Material.Define(stage, "/World/Looks/Veil")
    surface = UsdShade.Shader.Define(stage, "/World/Looks/Veil/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    opacity = surface.CreateInput("opacity", Sdf.ValueTypeNames.Float)
    threshold = surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float)
    veil.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(veil)
    for value, cut, expected, note in (
        (0.2, 0.0, bare, "neither casts nor hides the fog (a renderer lets 80%"),
        (0.6, 0.0, solid, "casts as opaque"),
        (0.2, 0.3, bare, None),
        (0.4, 0.3, solid, None),
    ):
        opacity.Set(value)
        threshold.Set(cut)
        frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(
            Usd.TimeCode.Default()
        )
        layers = crepuscular.render_arrays(**frame.render_kwargs())
        np.testing.assert_array_equal(layers.depth, expected.depth)
        assert _mean_relative(layers.volume, expected.volume) < 1e-6
        if note is None:
            assert frame.geometry.notes == []
        else:
            assert len(frame.geometry.notes) == 1
            assert note in frame.geometry.notes[0]
    assert _mean_relative(solid.volume, bare.volume) > 0.01


def _interface_material(stage: Usd.Stage, path: str, file: str) -> UsdShade.Material:
    """`cut_material` as material libraries author it (and Pixar's UsdPreviewSurface
    tutorial): the texture and its primvar reader inside a NodeGraph whose output feeds the
    opacity, the file, the primvar's name and the threshold given by the material's
    interface inputs (its wrap too)."""
    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    graph = UsdShade.NodeGraph.Define(stage, f"{path}/Cutout")
    texture = UsdShade.Shader.Define(stage, f"{path}/Cutout/Alpha")
    texture.CreateIdAttr("UsdUVTexture")
    reader = UsdShade.Shader.Define(stage, f"{path}/Cutout/St")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    interface = {
        "file": (Sdf.ValueTypeNames.Asset, file),
        "frame:stPrimvarName": (Sdf.ValueTypeNames.Token, "st"),
        "cut": (Sdf.ValueTypeNames.Float, 0.5),
        "wrap": (Sdf.ValueTypeNames.Token, "repeat"),
    }
    for name, (kind, value) in interface.items():
        assert material.CreateInput(name, kind).Set(value)
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).ConnectToSource(material.GetInput("file"))
    for name in ("wrapS", "wrapT"):
        texture.CreateInput(name, Sdf.ValueTypeNames.Token).ConnectToSource(
            material.GetInput("wrap")
        )
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).ConnectToSource(
        material.GetInput("frame:stPrimvarName")
    )
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    alpha = graph.CreateOutput("alpha", Sdf.ValueTypeNames.Float)
    alpha.ConnectToSource(texture.CreateOutput("a", Sdf.ValueTypeNames.Float))
    surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(alpha)
    surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).ConnectToSource(
        material.GetInput("cut")
    )
    return material


def test_a_node_graph_and_interface_inputs_cut_as_the_plain_material(tmp_path: Path) -> None:
    """The texture behind a NodeGraph, its file, primvar name, threshold and wrap on the
    material's interface: the card cuts exactly as with `cut_material` (before, it cast
    as opaque with a note). A constant opacity on the interface is one value everywhere."""
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    layers = {}
    for name, build in (("plain", cut_material), ("graph", _interface_material)):
        stage = _stage(tmp_path, name)
        card = _quad(stage, "/World/Card", -2, 2)
        _card_uvs(card)
        UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(
            build(stage, "/World/Looks/Leaf", file)
        )
        frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(
            Usd.TimeCode.Default()
        )
        assert frame.geometry.notes == [], name
        assert len(frame.geometry.masks) == 1, name
        assert frame.geometry.masks[0].threshold == 0.5
        layers[name] = crepuscular.render_arrays(**frame.render_kwargs())
    for plane in ("volume", "visibility", "depth"):
        np.testing.assert_array_equal(
            getattr(layers["graph"], plane), getattr(layers["plain"], plane), err_msg=plane
        )
    # (Without the interface's primvar name, every corner would read texel (0, 0).)
    material = UsdShade.Material(stage.GetPrimAtPath("/World/Looks/Leaf"))
    # A constant opacity given by the interface, below the threshold: a 1x1 mask.
    surface = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Surface"))
    opacity = surface.GetInput("opacity")
    assert opacity.DisconnectSource()
    assert material.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.2)
    assert opacity.ConnectToSource(material.GetInput("opacity"))
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    assert len(frame.geometry.masks) == 1
    np.testing.assert_allclose(np.asarray(frame.geometry.masks[0].alpha), [[0.2]])


def test_a_usdz_packages_texture_cuts_and_a_broken_one_is_named(tmp_path: Path) -> None:
    """Textures inside a .usdz package are read through USD's resolver; a file that is not
    an image is named and its card casts as opaque."""
    from pxr import UsdUtils

    stage = _stage(tmp_path, "packaged")
    card = _quad(stage, "/World/Card", -2, 2)
    _card_uvs(card)
    file = write_alpha_png(tmp_path / "stripes.png", STRIPES)
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(
        cut_material(stage, "/World/Looks/Leaf", file)
    )
    stage.GetRootLayer().Save()
    package = tmp_path / "packaged.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(tmp_path / "packaged.usda"), str(package))
    (tmp_path / "stripes.png").unlink()  # only the package's copy is left
    packaged = _render(Usd.Stage.Open(str(package)))
    assert _mean_relative(packaged.volume, _strips(tmp_path).volume) < 1e-4

    (tmp_path / "broken.png").write_bytes(b"not an image")
    stage = _stage(tmp_path, "broken")
    card = _quad(stage, "/World/Card", -2, 2)
    _card_uvs(card)
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(
        cut_material(stage, "/World/Looks/Leaf", "broken.png")
    )
    frame = StageReader(stage, "/World/Camera", "/World/Sun", width=96).read(Usd.TimeCode.Default())
    assert len(frame.geometry.notes) == 1
    assert "broken.png could not be read" in frame.geometry.notes[0]
    opaque_stage = _stage(tmp_path, "opaque")
    _quad(opaque_stage, "/World/Card", -2, 2)
    broken = crepuscular.render_arrays(**frame.render_kwargs())
    np.testing.assert_array_equal(broken.volume, _render(opaque_stage).volume)
