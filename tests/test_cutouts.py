"""Alpha cutouts through `render_arrays`: a card cut by a mask shadows and hides as the same
card with the mask's empty parts cut out of its geometry, for every method."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scenes import build_scene, flatten

import crepuscular
from crepuscular import AlphaMask, InvalidInputError, render_arrays

METHODS = ("reference", "minmax", "prefiltered")
#: Stripes along u: texels 1, 3, 5 and 7 of 8 solid, so that the filtered alpha crosses
#: one half at every u = k/8 and the card is solid where u lies in [1/8, 2/8], [3/8, 4/8],
#: [5/8, 6/8] and [7/8, 1].
STRIPES = np.array([[0, 1, 0, 1, 0, 1, 0, 1]], dtype=np.float32)
SOLID_U = [(1 / 8, 2 / 8), (3 / 8, 4 / 8), (5 / 8, 6 / 8), (7 / 8, 1.0)]
CARD_ID = 9


def _card(u0: float, u1: float) -> tuple[np.ndarray, np.ndarray]:
    """The part u0 ≤ u ≤ u1 of a 4 m card at height 3, u running along x from x = -2."""
    x0, x1 = -2.0 + 4.0 * u0, -2.0 + 4.0 * u1
    positions = np.array([[x0, 3, -2], [x1, 3, -2], [x1, 3, 2], [x0, 3, 2]], dtype=np.float32)
    return positions, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def _with(arrays: dict[str, Any], parts: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    positions, triangles = [arrays["positions"]], [arrays["triangles"]]
    ids = [arrays["object_ids"]]
    base = len(arrays["positions"])
    for part_positions, part_triangles in parts:
        positions.append(part_positions)
        triangles.append(part_triangles + base)
        ids.append(np.full(len(part_triangles), CARD_ID, dtype=np.uint32))
        base += len(part_positions)
    return {
        **arrays,
        "positions": np.concatenate(positions),
        "triangles": np.concatenate(triangles),
        "object_ids": np.concatenate(ids),
    }


def _scene(method: str) -> dict[str, Any]:
    scene = build_scene(width=96, height=54, steps=256, shadow_map_size=256, occluder=False)
    scene["render"]["method"] = method
    # The camera looks at the card from below its edge, so that it also sees through it.
    scene["camera"]["world_from_camera"][13] = 2.2
    return flatten(scene)


def _masked(arrays: dict[str, Any], mask: AlphaMask) -> dict[str, Any]:
    """The whole card, cut by `mask`; the ground keeps no mask."""
    card = _with(arrays, [_card(0.0, 1.0)])
    ground_count = len(arrays["positions"])
    u = np.r_[np.zeros(ground_count), 0.0, 1.0, 1.0, 0.0]
    v = np.r_[np.zeros(ground_count), 0.0, 0.0, 1.0, 1.0]
    masks = np.full(len(card["triangles"]), -1, dtype=np.int64)
    masks[len(arrays["triangles"]) :] = 0
    return {**card, "uvs": np.c_[u, v], "triangle_masks": masks, "masks": [mask]}


def _mean_relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).mean() / max(np.abs(b).mean(), 1e-12))


@pytest.mark.parametrize("method", METHODS)
def test_a_cut_card_renders_as_its_solid_parts(method: str) -> None:
    arrays = _scene(method)
    cut = render_arrays(**_masked(arrays, AlphaMask(STRIPES)))
    strips = render_arrays(**_with(arrays, [_card(u0, u1) for u0, u1 in SOLID_U]))
    whole = render_arrays(**_with(arrays, [_card(0.0, 1.0)]))
    # Not vacuous: the stripes let half the card's light through.
    assert _mean_relative(strips.volume, whole.volume) > 0.02
    assert _mean_relative(strips.depth, whole.depth) > 0.01
    # Samples exactly on a cut line may fall either way; nothing else may differ.
    for name in ("volume", "visibility", "depth"):
        error = _mean_relative(getattr(cut, name), getattr(strips, name))
        assert error < 1e-4, (name, error)
    assert np.isfinite(cut.volume).all()


def test_a_solid_mask_is_the_plain_card_and_an_empty_one_no_card() -> None:
    arrays = _scene("prefiltered")
    solid = render_arrays(**_masked(arrays, AlphaMask(np.ones((3, 5), np.float32))))
    card = render_arrays(**_with(arrays, [_card(0.0, 1.0)]))
    empty = render_arrays(**_masked(arrays, AlphaMask(STRIPES, threshold=1.5)))
    bare = render_arrays(**arrays)
    for name in ("volume", "visibility", "depth"):
        np.testing.assert_array_equal(getattr(solid, name), getattr(card, name))
        np.testing.assert_array_equal(getattr(empty, name), getattr(bare, name))


def test_the_mask_rows_run_from_v_zero_up() -> None:
    """A mask solid in its first row only (v near 0, the card's -z edge) equals the card's
    -z half; flipped, its +z half."""
    arrays = _scene("reference")
    rows = np.array([[1.0], [0.0]], dtype=np.float32)  # row 0: v = 0
    low = render_arrays(**_masked(arrays, AlphaMask(rows)))

    def half(z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
        positions, triangles = _card(0.0, 1.0)
        positions[:2, 2], positions[2:, 2] = z0, z1
        return positions, triangles

    # Filtered and repeating, alpha 1 at v = 1/4 and 0 at 3/4 crosses one half at v = 1/2
    # and at v = 0 (= 1): the solid part is v in [0, 1/2], z from -2 to 0.
    expected = render_arrays(**_with(arrays, [half(-2.0, 0.0)]))
    other = render_arrays(**_with(arrays, [half(0.0, 2.0)]))
    assert _mean_relative(low.volume, expected.volume) < 1e-4
    assert _mean_relative(low.volume, other.volume) > 0.02


#: Solid but for its first texel: filtered, its alpha crosses 0.5 at u = 1/4 and, where
#: the texture repeats, at u = 1 (blending texel 3 into texel 0).
FIRST_EMPTY = np.array([[0, 1, 1, 1]], dtype=np.float32)


@pytest.mark.parametrize(
    ("wrap", "filter_", "threshold", "border", "solid_u"),
    [
        ("repeat", "linear", 0.5, 0.0, [(-0.75, 0.0), (0.25, 1.0), (1.25, 2.0)]),
        ("extend", "linear", 0.5, 0.0, [(0.25, 2.0)]),
        ("mirror", "linear", 0.5, 0.0, [(-1.0, -0.25), (0.25, 1.75)]),
        # v repeats: clipped, the one row would fade out over half of it at each end.
        (("clip", "repeat"), "linear", 0.5, 0.0, [(0.25, 1.0)]),
        # Filtered, alpha 0.75 lies a quarter of the way from a texel centre to the next.
        (("clip", "repeat"), "linear", 0.75, 0.0, [(0.3125, 0.9375)]),
        # A solid border (an inverted alpha's) crosses 0.5 halfway from texel 0 to it.
        (("clip", "repeat"), "linear", 0.5, 1.0, [(-1.0, 0.0), (0.25, 2.0)]),
        ("clip", "closest", 0.75, 0.0, [(0.25, 1.0)]),
        (("extend", "repeat"), "closest", 0.75, 0.0, [(0.25, 2.0)]),
    ],
)
def test_each_wrap_and_filter_cuts_past_the_edges_as_the_texture_reads(
    wrap: Any, filter_: str, threshold: float, border: float, solid_u: list[tuple[float, float]]
) -> None:
    """A card whose u runs from -1 to 2, three times the texture, cut by `FIRST_EMPTY`:
    read past its edges as Blender's extension modes (and USD's wrap modes) read a
    texture, it renders as the card's parts where the read alpha reaches the threshold."""
    arrays = _scene("reference")
    mask = AlphaMask(FIRST_EMPTY, threshold, wrap=wrap, filter=filter_, border=border)
    masked = _masked(arrays, mask)
    masked["uvs"][-4:, 0] = [-1.0, 2.0, 2.0, -1.0]
    cut = render_arrays(**masked)
    # Parts of the card, u from -1 to 2 over its 4 m, as `_card` lays [0, 1] over them.
    parts = [_card((u0 + 1) / 3, (u1 + 1) / 3) for u0, u1 in solid_u]
    expected = render_arrays(**_with(arrays, parts))
    repeating = render_arrays(**_masked(arrays, AlphaMask(FIRST_EMPTY, threshold)))
    for name in ("volume", "visibility", "depth"):
        error = _mean_relative(getattr(cut, name), getattr(expected, name))
        assert error < 1e-4, (name, error)
    if (wrap, filter_, threshold, border) != ("repeat", "linear", 0.5, 0.0):
        assert _mean_relative(cut.volume, repeating.volume) > 0.01


def test_bad_cutouts_are_named() -> None:
    arrays = _masked(_scene("reference"), AlphaMask(STRIPES))
    cases = [
        ({"uvs": None}, "triangle_masks", "come together"),
        ({"uvs": arrays["uvs"][:-1]}, "uvs", "one row per position"),
        ({"triangle_masks": arrays["triangle_masks"][:-1]}, "triangle_masks", "one per"),
        ({"triangle_masks": np.full_like(arrays["triangle_masks"], -2)}, "triangle_masks[0]", ""),
        ({"masks": []}, "triangle_masks[", "indexes past the 0 masks"),
        ({"masks": [AlphaMask(np.ones(4))]}, "masks[0]", "(height, width)"),
        ({"masks": [AlphaMask(np.full((2, 2), np.nan))]}, "masks[0]", "not finite"),
        ({"masks": [AlphaMask(np.ones((0, 2)))]}, "masks[0]", "empty"),
        ({"masks": [AlphaMask(STRIPES, wrap="border")]}, "masks[0].wrap", "clip or a (u, v)"),
        ({"masks": [AlphaMask(STRIPES, wrap=("clip",))]}, "masks[0].wrap", "got ('clip',)"),
        ({"masks": [AlphaMask(STRIPES, filter="cubic")]}, "masks[0].filter", "linear, closest"),
        # Masks that no triangle reads were ignored, whatever they held.
        ({"uvs": None, "triangle_masks": None}, "masks", "need uvs and triangle_masks"),
    ]
    for change, field, words in cases:
        with pytest.raises(InvalidInputError) as caught:
            render_arrays(**{**arrays, **change})
        assert caught.value.field.startswith(field), (change, caught.value)
        assert words in str(caught.value), (change, caught.value)
    with pytest.raises(TypeError, match=r"masks\[1\] must be a crepuscular\.AlphaMask, got str"):
        render_arrays(**{**arrays, "masks": [AlphaMask(STRIPES), "x"]})


def test_cut_frames_on_vulkan_match_the_cpu(capfd: pytest.CaptureFixture[str]) -> None:
    """The Vulkan backend cuts by the masks in its own depth passes (on lavapipe here): its
    frames stay on the GPU, without a fallback, and match the CPU's. Skipped where no
    Vulkan loader is present."""
    arrays = _masked(_scene("prefiltered"), AlphaMask(STRIPES))
    cpu = render_arrays(**arrays)
    vulkan = {**arrays, "settings": {**arrays["settings"], "backend": "vulkan"}}
    capfd.readouterr()
    gpu = render_arrays(**vulkan)
    err = capfd.readouterr().err
    if "no Vulkan loader" in err or "no usable Vulkan device" in err:
        pytest.skip(err.strip())
    assert "Vulkan backend unavailable" not in err, err
    for name in ("volume", "visibility", "depth"):
        assert _mean_relative(getattr(gpu, name), getattr(cpu, name)) < 1e-3, name
    # Not vacuous: the stripes change the frame far more than that.
    uncut = render_arrays(**{**vulkan, "uvs": None, "triangle_masks": None, "masks": []})
    assert _mean_relative(uncut.volume, gpu.volume) > 0.02


def _stripes_png(path: Path) -> Path:
    from PIL import Image

    rgba = np.zeros((1, 8, 4), dtype=np.uint8)
    rgba[..., 3] = (STRIPES * 255).astype(np.uint8)
    Image.fromarray(rgba).save(path)
    return path


def test_a_scene_files_mesh_cuts_by_its_alpha_mask_image(tmp_path: Path) -> None:
    """The scene description's `uvs` and `alpha_mask` (an image beside the scene file,
    named relative to it) cut as `render_arrays`' masks do; a missing image and a mask
    without coordinates are named."""
    scene = build_scene(width=96, height=54, steps=256, shadow_map_size=256, occluder=False)
    scene["render"]["method"] = "prefiltered"
    scene["camera"]["world_from_camera"][13] = 2.2
    positions, triangles = _card(0.0, 1.0)
    _stripes_png(tmp_path / "stripes.png")
    scene["meshes"].append(
        {
            "name": "card",
            "object_id": CARD_ID,
            "positions": positions.tolist(),
            "triangles": triangles.tolist(),
            "uvs": [[0, 0], [1, 0], [1, 1], [0, 1]],
            "alpha_mask": {"image": "stripes.png"},
        }
    )
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    cut = crepuscular.render(path)
    strips = render_arrays(**_with(_scene("prefiltered"), [_card(u0, u1) for u0, u1 in SOLID_U]))
    for name in ("volume", "visibility", "depth"):
        assert _mean_relative(getattr(cut, name), getattr(strips, name)) < 1e-4, name
    # Its wrap and filter, as `AlphaMask`'s: u from -1 to 2, clipped past the image.
    scene["meshes"][-1]["uvs"] = [[-1, 0], [2, 0], [2, 1], [-1, 1]]
    scene["meshes"][-1]["alpha_mask"].update(wrap=["clip", "repeat"], filter="closest")
    path.write_text(json.dumps(scene))
    clipped = crepuscular.render(path)
    masked = _masked(_scene("prefiltered"), AlphaMask(STRIPES, wrap=("clip", "repeat")))
    masked["uvs"][-4:, 0] = [-1.0, 2.0, 2.0, -1.0]
    masked["masks"] = [AlphaMask(STRIPES, wrap=("clip", "repeat"), filter="closest")]
    assert _mean_relative(clipped.volume, render_arrays(**masked).volume) < 1e-6
    assert _mean_relative(clipped.volume, cut.volume) > 0.01
    for wrap, words in (("border", "wrap mode (repeat, extend"), (["clip"], "wrap mode")):
        scene["meshes"][-1]["alpha_mask"]["wrap"] = wrap
        with pytest.raises(InvalidInputError, match=re.escape(words)) as caught:
            crepuscular.render(scene)
        assert caught.value.field == "meshes[1].alpha_mask.wrap", caught.value
    scene["meshes"][-1]["alpha_mask"]["wrap"] = "clip"
    scene["meshes"][-1]["alpha_mask"]["image"] = "missing.png"
    with pytest.raises(InvalidInputError, match=r"missing\.png") as caught:
        crepuscular.render(scene)
    assert caught.value.field == "meshes[1].alpha_mask.image"
    del scene["meshes"][-1]["uvs"]
    with pytest.raises(InvalidInputError) as caught:
        crepuscular.render(scene)
    assert caught.value.field == "meshes[1].alpha_mask"
