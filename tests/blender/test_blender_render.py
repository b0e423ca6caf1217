"""F12 and animation renders with real Cycles, each job in a subprocess (see blender_job.py):
the composite in the render output, the layer EXRs written next to it, per-frame evaluation,
edges against the sky, and fidelity against Cycles' own fog box.

Cycles renders are kept tiny (at most 96 by 54) so that the whole set runs in well under a
minute on two cores."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

import crepuscular

pytest.importorskip("bpy")

from blender_scenes import run_job


def rgba(path: Path) -> np.ndarray:
    channels = crepuscular.read_exr(path)
    return np.stack([channels[c] for c in "RGBA"], axis=-1)


def volume(path: Path) -> np.ndarray:
    channels = crepuscular.read_exr(path)
    return np.stack([channels[f"volume.{c}"] for c in "RGBA"], axis=-1)


def test_f12_composites_the_layers_over_the_beauty(installed: ModuleType, tmp_path: Path) -> None:
    run_job(tmp_path, "composite", width=64, height=36, samples=8)
    beauty = rgba(tmp_path / "beauty.exr")
    composite = rgba(tmp_path / "composite.exr")
    layers = volume(tmp_path / "composite_crepuscular_0001.exr")
    assert layers.shape == beauty.shape == (36, 64, 4)
    assert layers[..., 3].max() > 0.3
    assert layers[..., :3].max() > 0.01
    # Premultiplied over, in scene-linear (the EXR holds values before the view transform).
    expected = layers + (1.0 - layers[..., 3:4]) * beauty
    np.testing.assert_allclose(composite, expected, rtol=1e-4, atol=1e-5)
    assert np.abs(composite - beauty).mean() > 0.01


def test_a_layer_file_that_cannot_be_written_is_reported(
    installed: ModuleType, tmp_path: Path
) -> None:
    run_job(tmp_path, "unwritable_layers", width=32, height=18, samples=1)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["last_error"].startswith("writing layers:")
    assert "blocked_crepuscular_0001.exr" in report["last_error"]
    assert rgba(tmp_path / "blocked.exr").shape == (18, 32, 4)


def test_depth_matches_cycles_depth_pass(installed: ModuleType, tmp_path: Path) -> None:
    run_job(tmp_path, "composite", width=64, height=36, samples=4)
    planar = crepuscular.read_exr(tmp_path / "passes.exr")["ViewLayer.Depth.Z"]
    ours = crepuscular.read_exr(tmp_path / "centres.exr")["depth"]
    # Cycles writes z-depth along the view axis; ours is the distance along the ray.
    # 35 mm lens, 36 mm sensor fitted to the 64 pixel width.
    pixel = 36.0 / 35.0 / 64
    xs = (np.arange(64) + 0.5 - 32) * pixel
    ys = (18 - (np.arange(36) + 0.5)) * pixel
    stretch = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    surface = planar < 1e9
    # Away from silhouettes, where Cycles' single depth sample may land on either side.
    smooth = np.ones_like(surface)
    for axis in (0, 1):
        curvature = np.roll(planar, 1, axis) + np.roll(planar, -1, axis) - 2 * planar
        smooth &= np.abs(curvature) < 0.01 * planar
    compared = surface & smooth
    assert compared.sum() > 0.5 * surface.sum()
    np.testing.assert_allclose(ours[compared], (planar * stretch)[compared], rtol=2e-3)
    assert np.all(ours[~surface] == pytest.approx(100.0))  # background: max distance


def test_animation_renders_every_frame_composited(installed: ModuleType, tmp_path: Path) -> None:
    run_job(tmp_path, "animation", width=64, height=36, samples=4)
    shots = [rgba(tmp_path / f"shot_{f:04d}.exr") for f in (1, 2, 3)]
    beauties = [rgba(tmp_path / f"beauty_{f:04d}.exr") for f in (1, 2, 3)]
    layers = [crepuscular.read_exr(tmp_path / f"shot_crepuscular_{f:04d}.exr") for f in (1, 2, 3)]
    for shot, beauty, channels in zip(shots, beauties, layers, strict=True):
        vol = np.stack([channels[f"volume.{c}"] for c in "RGBA"], axis=-1)
        np.testing.assert_allclose(shot, vol + (1 - vol[..., 3:4]) * beauty, rtol=1e-4, atol=1e-5)
    # Each frame's layers are that frame's: the operator at the same frame agrees.
    for frame, channels in zip((1, 2, 3), layers, strict=True):
        again = crepuscular.read_exr(tmp_path / f"operator_{frame}.exr")
        for name in ("volume.R", "volume.A", "visibility", "depth"):
            np.testing.assert_allclose(channels[name], again[name], rtol=1e-4, atol=1e-5)
    # The camera moves (depth changes) and the closing fills the hole's shaft (visibility).
    assert np.abs(layers[0]["depth"] - layers[2]["depth"]).max() > 0.1
    assert not np.array_equal(layers[0]["visibility"], layers[1]["visibility"])
    assert not np.array_equal(shots[0], shots[2])


def test_silhouettes_match_the_beauty_alpha(installed: ModuleType, tmp_path: Path) -> None:
    run_job(tmp_path, "silhouette", width=96, height=54, samples=32, edge_samples=[1, 4])
    beauty_alpha = rgba(tmp_path / "beauty.exr")[..., 3]
    edges = (beauty_alpha > 0.03) & (beauty_alpha < 0.97)
    assert edges.sum() > 40, "the card has no edge pixels"
    errors = {}
    for samples in (1, 4):
        alpha = volume(tmp_path / f"layers_{samples}.exr")[..., 3]
        # Orthographic: the card's pixels share one alpha and the sky's another.
        inside = np.median(alpha[beauty_alpha > 0.999])
        sky = np.median(alpha[beauty_alpha < 0.001])
        assert sky > inside + 0.3
        sky_share = (alpha - inside) / (sky - inside)
        errors[samples] = float(np.abs(sky_share - (1 - beauty_alpha))[edges].mean())
    # With edge samples, the layer's alpha edge follows the beauty's coverage (no halo,
    # no stair steps); one sample per pixel shows both.
    assert errors[4] < 0.04, errors
    assert errors[1] > 2.5 * errors[4], errors


SAMPLES = 256


@pytest.fixture(scope="module")
def fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("fidelity")
    seconds = run_job(out, "fidelity", width=96, height=54, samples=SAMPLES)
    print(f"fidelity job: 2 Cycles renders at {SAMPLES} spp, 96x54, {seconds:.1f} s in all")
    return {"out": out, "seconds": seconds}


def test_fog_object_matches_cycles(fidelity: dict[str, Any]) -> None:
    """Black surfaces and world, no bounces: Cycles' image is the in-scattered light alone.
    The medium, box, camera and sun all come through the add-on's export."""
    out = fidelity["out"]
    ours = volume(out / "layers.exr")[..., :3]
    cycles = rgba(out / "cycles_black.exr")[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    luminance = ours.mean(axis=-1)
    lit = luminance > 0
    assert np.ptp(luminance[lit]) > 0.5 * luminance[lit].max()  # shadow, shaft and open sky
    # Whole-image mean: Monte Carlo noise averages out, so this is tight.
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)
    # Per pixel: mean absolute difference within 3% of the mean, noise included.
    relative = np.abs(ours - cycles).mean() / cycles.mean()
    assert relative < 0.03, relative


def test_the_default_method_matches_cycles(fidelity: dict[str, Any]) -> None:
    """The same comparison with the default (prefiltered) method, which may differ from
    the reference march by up to 2% (1.9% measured here), on top of Cycles' noise."""
    out = fidelity["out"]
    ours = volume(out / "layers_default_method.exr")[..., :3]
    cycles = rgba(out / "cycles_black.exr")[..., :3]
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)
    relative = np.abs(ours - cycles).mean() / cycles.mean()
    assert relative < 0.04, relative


def _cycles_job(tmp_path_factory: pytest.TempPathFactory, job: str, renders: int) -> Path:
    """Runs a job of Cycles renders at 96x54 and `SAMPLES`; returns its folder."""
    out = tmp_path_factory.mktemp(job)
    seconds = run_job(out, job, width=96, height=54, samples=SAMPLES)
    print(f"{job} job: {renders} Cycles renders at {SAMPLES} spp, 96x54, {seconds:.1f} s in all")
    return out


@pytest.fixture(scope="module")
def mapped_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "mapped_fidelity", 3)


@pytest.mark.parametrize("method", ["reference", "prefiltered"])
@pytest.mark.parametrize("view", ["orthographic", "inside", "anamorphic"])
def test_mapped_settings_match_cycles(mapped_fidelity: Path, view: str, method: str) -> None:
    """A tinted Principled Volume with an absorption colour, whose extinction is coloured
    (0.96, 0.75 and 0.50 times the density), a sun with colour, temperature and
    exposure, an orthographic camera with lens shift and a vertical sensor fit, a camera
    inside the box, and one through 2:1 anamorphic pixels: each mapped as Cycles reads it.
    Square pixels put the anamorphic view's 2x2 blocks 19% off (1.5% with the aspect).
    Leaving out any other one of those moves a channel's mean by 15% or more, or the
    difference of 2x2-pixel blocks by 14% or more: the extinction's luminance for all
    three channels put red 20% and 50% high and blue 29% and 47% low, the blocks 17% and
    35% off. (The sun's 3° disc softens the shafts over 16 directions; its penumbrae here
    are within Cycles' noise.)"""
    cycles = rgba(mapped_fidelity / f"cycles_{view}.exr")[..., :3]
    ours = volume(mapped_fidelity / f"{view}_{method}.exr")[..., :3]
    # Blender's EXR tells viewers the pixels' shape; so does ours.
    aspect = crepuscular.read_exr_pixel_aspect(mapped_fidelity / f"cycles_{view}.exr")
    assert aspect == (2.0 if view == "anamorphic" else 1.0)
    assert crepuscular.read_exr_pixel_aspect(mapped_fidelity / f"{view}_{method}.exr") == aspect
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    assert (ours.mean(axis=-1) > 0).mean() > 0.3, "the fog box fills too little of the view"
    np.testing.assert_allclose(ours.mean(axis=(0, 1)), cycles.mean(axis=(0, 1)), rtol=0.02)
    # Cycles' noise at 256 spp is most of this: per pixel 2.7% and 4.7% measured (the blue
    # channel is dim), in 2x2 blocks 1.4% and 2.4%, either method.
    relative = np.abs(blocks(ours) - blocks(cycles)).mean() / cycles.mean()
    assert relative < 0.04, relative


@pytest.fixture(scope="module")
def region_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "region_fidelity", 2)


@pytest.mark.parametrize("method", ["reference", "prefiltered"])
@pytest.mark.parametrize("crop", ["cropped", "framed"])
def test_a_render_region_renders_as_in_cycles(
    region_fidelity: Path, crop: str, method: str
) -> None:
    """A render region of 53 x 27 pixels (Blender truncates the border's fractions of the
    96 x 54 frame), cropped to it or kept in the frame with nothing around it, as Cycles
    renders it: 2x2 blocks 2.1% apart, where a region one pixel off in any direction reads
    6.6-13%. Before, any render region was refused."""
    cycles = rgba(region_fidelity / f"cycles_{crop}.exr")
    ours = volume(region_fidelity / f"{crop}_{method}.exr")
    assert ours.shape == cycles.shape == ((27, 53, 4) if crop == "cropped" else (54, 96, 4))
    if crop == "framed":
        inside = np.zeros(ours.shape[:2], dtype=bool)
        inside[17:44, 28:81] = True
        assert not ours[~inside].any()
        assert not cycles[~inside].any()
        assert (ours[inside][:, 3] > 0).mean() > 0.5
        cycles, ours = cycles[17:44, 28:81], ours[17:44, 28:81]
    cycles, ours = cycles[..., :3], ours[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    np.testing.assert_allclose(ours.mean(), cycles.mean(), rtol=0.02)
    relative = np.abs(blocks(ours) - blocks(cycles)).mean() / cycles.mean()
    assert relative < 0.04, relative


@pytest.fixture(scope="module")
def cutout_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "cutout_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_alpha_cutouts_match_cycles(cutout_fidelity: Path, method: str) -> None:
    """A roof of two cards cut by an image's alpha (through a Principled BSDF's Alpha, and
    a Mix Shader with a Transparent BSDF), over the fidelity scene's fog: the shafts
    through the cut stripes and holes, and the fog seen through the cards, as Cycles
    renders them (measured: means within 0.03%, pixels 1.0% apart, Cycles' noise). Read
    as opaque, the cards let almost no light in: 99% off."""
    _assert_like_cycles(cutout_fidelity, method, "opaque", off=0.15, pixels=0.04)


@pytest.fixture(scope="module")
def extension_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "extension_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_image_extensions_and_closest_interpolation_cut_as_in_cycles(
    extension_fidelity: Path, method: str
) -> None:
    """Cards whose texture coordinates run past the image, read as their Image Texture's
    extension says (Clip, through an alpha and through an inverted Mix Shader factor,
    Extend and Mirror, these two through chains of Mapping nodes) and a coarse image of
    scattered solid texels read with Closest interpolation: as Cycles renders them
    (measured: means within 0.01%, pixels 1.24% and 1.27% apart). Read as before, every
    texture repeating and linear: 12.2% off. With the Point mapping's rotation turned the
    other way, 1.88%; with the Texture mapping not inverted, 14%; the mappings left out,
    3.0%. (Each card alone, without the mappings, against Cycles: 0.4-0.55%.)"""
    _assert_like_cycles(extension_fidelity, method, "repeating", off=0.10, pixels=0.017)


@pytest.fixture(scope="module")
def alpha_chain_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "alpha_chain_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_value_nodes_on_the_alpha_cut_as_in_cycles(alpha_chain_fidelity: Path, method: str) -> None:
    """Cards of one smooth alpha sharpened by value nodes (a Math node Greater Than 0.3, as
    Blender 4.2 versions EEVEE's Alpha Clip; a constant Color Ramp on the Color; an Invert
    and a Math node Less Than 0.45 into an inverted Mix Shader): cut where their binary
    alpha is, as Cycles renders them (measured: means within 0.12%, pixels 1.7% apart).
    With the nodes muted, the raw alpha cut at one half: 44% off. (Before, such materials
    cast as opaque, with a note.)"""
    _assert_like_cycles(alpha_chain_fidelity, method, "unchained", off=0.3, pixels=0.025)


@pytest.fixture(scope="module")
def hair_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "hair_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_hair_curves_match_cycles(hair_fidelity: Path, method: str) -> None:
    """A roof of hair strands over the fidelity scene's fog: drawn as ribbons across the sun
    and the camera, their shadows shape the shafts as Cycles' round strands do; hidden,
    the layers are 84% off. Measured: mean within 0.02% of Cycles, pixels 1.2% apart,
    either method. (As 16-sided tubes: 0.42% dark. As 8-sided tubes, whose width varies by
    8% with the direction they are seen from: 2.6% bright.)"""
    _assert_like_cycles(hair_fidelity, method, "bare", off=0.5, pixels=0.03)


@pytest.fixture(scope="module")
def strand_gap_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("strand_gap_fidelity")
    seconds = run_job(out, "strand_gap_fidelity", width=32, height=128, samples=SAMPLES)
    print(f"strand gap job: 4 Cycles renders at {SAMPLES} spp, 32x128, {seconds:.1f} s in all")
    return out


@pytest.mark.parametrize("tilt", [0, 60])
def test_a_thick_strand_shadows_from_two_radii_past_its_axis_as_in_cycles(
    strand_gap_fidelity: Path, tilt: int
) -> None:
    """A strand of radius r seen side-on, each image row a view ray at one height. Cycles'
    round strands (Embree curves) skip a curve's hits within 2r of a shadow ray's start,
    measured at the axis: the fog from the strand down to 2r below its axis (along the
    sun) is lit. So, under a sun straight above, the rows 1.1r to 1.9r below the axis, which
    cross the strand's shadow column whole, lose nothing in Cycles, nor in ours, whose sun
    ribbon lies 2r past the axis; at the axis they lost 4.3%. Every row's light over the
    bare frame's is within 0.4% of Cycles', under that sun and one 30 degrees up."""
    ratios = {}
    for renderer, layer in (("cycles", rgba), ("ours", volume)):
        shown = layer(strand_gap_fidelity / f"{renderer}_{tilt}.exr")[..., :3].mean(axis=(1, 2))
        bare = layer(strand_gap_fidelity / f"bare_{renderer}_{tilt}.exr")[..., :3]
        ratios[renderer] = shown / bare.mean(axis=(1, 2))
    rows = len(ratios["ours"])
    below_axis = 3.0 - (3.0 + 1.0 - (np.arange(rows) + 0.5) * 2.0 / rows)
    in_radii = below_axis / 0.2
    shadowed = in_radii > 2.2
    assert ratios["cycles"][shadowed].max() < 0.99, "the strand cast no shadow in Cycles"
    np.testing.assert_allclose(ratios["ours"], ratios["cycles"], atol=0.004)
    if tilt == 0:
        gap = (in_radii > 1.1) & (in_radii < 1.9)
        assert ratios["cycles"][gap].min() > 0.998
        assert ratios["ours"][gap].min() > 0.998


@pytest.fixture(scope="module")
def points_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "points_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_point_clouds_match_cycles(points_fidelity: Path, method: str) -> None:
    """A roof of points (a geometry-nodes point cloud) over the fidelity scene's fog: drawn
    as spheres of their radius, their shadows shape the shafts as Cycles' round points
    do. Measured: mean 0.23% under Cycles', pixels 1.1% apart (Cycles' noise), either
    method; with the points hidden, 61% off."""
    _assert_like_cycles(points_fidelity, method, "bare", off=0.3, pixels=0.03)


@pytest.mark.parametrize("method", ["reference", "prefiltered"])
def test_a_point_around_the_camera_matches_cycles(points_fidelity: Path, method: str) -> None:
    """A point of radius 8 around the camera, reaching into the box: Cycles culls a point's
    back side for every ray, so the camera sees out of it and the fog inside it is lit,
    while its far side still shadows the fog beyond it (drawn closed, the camera saw only
    its inside). Measured: means within 0.03% of Cycles', pixels 0.45% apart, either
    method (3.7% with the sphere's 80 triangles, before large points were split finer);
    the frame without the point is 24% off."""
    cycles = rgba(points_fidelity / "cycles_shell.exr")[..., :3]
    ours = volume(points_fidelity / f"shell_{method}.exr")[..., :3]
    without = volume(points_fidelity / "bare.exr")[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    assert np.abs(without - cycles).mean() / cycles.mean() > 0.15
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.01)
    relative = np.abs(ours - cycles).mean() / cycles.mean()
    assert relative < 0.015, relative


@pytest.fixture(scope="module")
def closures_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "closures_fidelity", 3)


@pytest.mark.parametrize("case", ["added", "mixed", "coefficients"])
def test_fog_shaders_of_several_closures_match_cycles(closures_fidelity: Path, case: str) -> None:
    """A fog of an Add Shader (Volume Scatter and a coloured Volume Absorption), a Mix
    Shader (Volume Scatter and Principled Volume) or Volume Coefficients (beside an
    Emission): each channel as Cycles renders it. Measured: channel means within 0.25% of
    Cycles', 2x2 blocks 1.0 to 1.9% apart (Cycles' noise at these dim means). Until these
    mapped, such a fog object was refused."""
    cycles = rgba(closures_fidelity / f"cycles_{case}.exr")[..., :3]
    ours = volume(closures_fidelity / f"{case}.exr")[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    channels = ours.mean(axis=(0, 1)) / cycles.mean(axis=(0, 1))
    relative = np.abs(blocks(ours) - blocks(cycles)).mean() / cycles.mean()
    np.testing.assert_allclose(channels, 1.0, atol=0.01)
    assert relative < 0.03, relative


@pytest.fixture(scope="module")
def disc_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "disc_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_a_wide_sun_disc_softens_the_shafts_as_in_cycles(disc_fidelity: Path, method: str) -> None:
    """An 8° sun: the shafts through the roof's slot blur over its penumbrae as Cycles'
    do, over 16 directions on the disc. Measured: means within 0.3% of Cycles', 2x2
    blocks 2.1% apart (Cycles' noise is about 1.4% of that), where under a point sun they
    are 3.3% apart; 64 directions did no better (2.1%)."""
    cycles = rgba(disc_fidelity / "cycles.exr")[..., :3]
    ours = volume(disc_fidelity / f"{method}.exr")[..., :3]
    point = volume(disc_fidelity / "point.exr")[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    relative = np.abs(blocks(ours) - blocks(cycles)).mean() / cycles.mean()
    hard = np.abs(blocks(point) - blocks(cycles)).mean() / cycles.mean()
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.01)
    assert relative < 0.8 * hard, (relative, hard)
    assert relative < 0.03, relative


@pytest.fixture(scope="module")
def particle_hair_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "particle_hair_fidelity", 1)


@pytest.mark.parametrize("method", ["reference", "default"])
def test_particle_hair_matches_cycles(particle_hair_fidelity: Path, method: str) -> None:
    """A roof of legacy particle hair (tapering, its emitter not rendered) over the fidelity
    scene's fog: drawn as ribbons along its paths with Cycles' radii, it shapes the shafts
    as Cycles' strands do. Measured: mean 0.4% over Cycles', pixels 1.9% apart; with the
    particle system off, 109% off. (As 16-sided tubes it read 1.5% bright, which Cycles
    rendering the same tube mesh reproduced: the tubes' geometry, not the reading.)"""
    _assert_like_cycles(particle_hair_fidelity, method, "bare", off=0.5, pixels=0.03)


@pytest.fixture(scope="module")
def visibility_fidelity(installed: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _cycles_job(tmp_path_factory, "visibility_fidelity", 8)


@pytest.mark.parametrize(
    "case",
    [
        "unlinked",
        "included",
        "wall",
        "ghost",
        "wall_light_path",
        "ghost_light_path",
        "shadowless",
    ],
)
def test_ray_visibility_and_shadow_linking_match_cycles(
    visibility_fidelity: Path, case: str
) -> None:
    """The sun's shadow linking (a blocker collection that excludes a slat; one that
    includes a slat and an instanced copy through its instancer), and a card in view hidden
    from shadow rays (it still hides the fog behind it) or from the camera (it still casts
    its shadow), by its ray visibility or by its material (Light Path's Is Shadow Ray or Is
    Camera Ray into a Mix Shader towards a Transparent BSDF), and a sun whose Cast Shadow
    is off (nothing blocks it, and the fog does not dim it): each as Cycles renders it,
    and each a change from the plain scene.
    Measured: means within 0.08% of Cycles', 2x2 blocks 0.9 to 1.4% apart, where each case
    moves Cycles' blocks 22 to 49% from the plain scene. The Light Path cases had read 22%
    and 49% off Cycles, their materials cast as opaque."""
    cycles = rgba(visibility_fidelity / f"cycles_{case}.exr")[..., :3]
    ours = volume(visibility_fidelity / f"ours_{case}.exr")[..., :3]
    # A surface that Light Path hides from some rays changes its counterpart of the
    # other way round (which casts where it does not, or hides the fog where it does not).
    control = {"wall_light_path": "wall", "ghost_light_path": "ghost"}.get(case, "plain")
    plain = rgba(visibility_fidelity / f"cycles_{control}.exr")[..., :3]
    changed = np.abs(blocks(cycles) - blocks(plain)).mean() / plain.mean()
    assert changed > 0.02, changed
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)
    relative = np.abs(blocks(ours) - blocks(cycles)).mean() / cycles.mean()
    assert relative < 0.03, relative


def _assert_like_cycles(folder: Path, method: str, without: str, off: float, pixels: float) -> None:
    """`folder`'s layers of `method` against its Cycles render: the means within 2%, the
    pixels within `pixels` of Cycles' mean; the layers `without` what is under test (the
    control) more than `off` apart, so that the comparison can fail."""
    cycles = rgba(folder / "cycles.exr")[..., :3]
    ours = volume(folder / f"{method}.exr")[..., :3]
    control = volume(folder / f"{without}.exr")[..., :3]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    assert np.abs(control - cycles).mean() / cycles.mean() > off
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)
    relative = np.abs(ours - cycles).mean() / cycles.mean()
    assert relative < pixels, relative


def blocks(image: np.ndarray) -> np.ndarray:
    """Means of 2x2-pixel blocks (an odd last row or column left out)."""
    height, width = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
    cropped = image[:height, :width]
    return cropped.reshape(height // 2, 2, width // 2, 2, -1).mean(axis=(1, 3))


def test_grey_surfaces_composite_like_cycles(fidelity: dict[str, Any]) -> None:
    """F12 with shafts on hides the fog object and composites: it matches Cycles' own fog."""
    out = fidelity["out"]
    cycles = rgba(out / "cycles_grey.exr")[..., :3]
    composite = rgba(out / "composite_grey.exr")[..., :3]
    black = rgba(out / "cycles_black.exr")[..., :3]
    assert cycles.mean() > 1.5 * black.mean(), "the grey backdrop is not in view"
    assert composite.mean() == pytest.approx(cycles.mean(), rel=0.02)
    relative = np.abs(composite - cycles).mean() / cycles.mean()
    assert relative < 0.03, relative
