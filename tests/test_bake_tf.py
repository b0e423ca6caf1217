"""`crepuscular.bake_tf`: a style's transfer function as its baked texture."""

from __future__ import annotations

import numpy as np
import pytest

import crepuscular


def _style(layers: list[dict], resolution: int = 16) -> dict:
    return {
        "version": 1,
        "tf": {
            "mode": "color",
            "depth_range": {"near": 0.0, "far": 10.0},
            "resolution": resolution,
            "layers": layers,
        },
    }


def test_solid_layer_fills_every_texel() -> None:
    texels = crepuscular.bake_tf(_style([{"kind": "solid", "color": [0.2, 0.4, 0.6, 1.0]}]))
    assert texels.shape == (16, 16, 4)
    assert texels.dtype == np.float32
    np.testing.assert_allclose(texels.reshape(-1, 4), [[0.2, 0.4, 0.6, 1.0]] * 256, atol=1e-6)


def test_axes_are_visibility_across_and_depth_up() -> None:
    ramp = [{"position": 0.0, "color": [0, 0, 0, 1]}, {"position": 1.0, "color": [1, 1, 1, 1]}]
    along_v = crepuscular.bake_tf(
        _style(
            [
                {
                    "kind": "gradient",
                    "shape": {"kind": "linear", "from": [0, 0], "to": [1, 0]},
                    "stops": ramp,
                }
            ]
        )
    )
    along_u = crepuscular.bake_tf(
        _style(
            [
                {
                    "kind": "gradient",
                    "shape": {"kind": "linear", "from": [0, 0], "to": [0, 1]},
                    "stops": ramp,
                }
            ]
        )
    )
    centres = (np.arange(16) + 0.5) / 16
    np.testing.assert_allclose(along_v[3, :, 0], centres, atol=1e-5)  # column i: V̄
    np.testing.assert_allclose(along_u[:, 3, 0], centres, atol=1e-5)  # row j: u rising


def test_key_frames_interpolate_in_time() -> None:
    style = _style([])
    style["tf"]["layers"] = []
    style["tf"]["keyframes"] = [
        {"time": 0.0, "layers": [{"kind": "solid", "color": [0, 0, 0, 1]}]},
        {"time": 2.0, "layers": [{"kind": "solid", "color": [1, 1, 1, 1]}]},
    ]
    assert crepuscular.bake_tf(style, time=1.0)[0, 0, 0] == pytest.approx(0.5)
    assert crepuscular.bake_tf(style, time=2.0)[0, 0, 0] == pytest.approx(1.0)


def test_a_style_without_tf_names_the_field() -> None:
    with pytest.raises(crepuscular.InvalidInputError, match=r"style\.tf"):
        crepuscular.bake_tf({"version": 1})
