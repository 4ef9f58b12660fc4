"""The simulated camera's noise only around the markers (RenderOptions.region "markers") against the
whole noisy frame: the same random numbers where it draws them, the generator left in the same state,
and the same marker detection bit for bit (flightstack.vision.markers.extract_markers with the frame's
roi), on random views with tilted, partly visible and absent markers, with and without blur."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flightstack.sim_backend.scene.render import (
    RenderOptions,
    _gaussian_noise_int16,
    _noise_span,
    render_markers_region,
)
from flightstack.vision.markers import extract_markers
from tests.test_vision import CAL_FWD, CAL_TELLO

P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])


def test_noise_span_is_the_full_draw_in_place() -> None:
    n = 320 * 240 * 3
    for e0, e1 in ((0, 0), (0, 5), (3, 3001), (1001, n), (0, n), (n - 1, n)):
        a, b = np.random.default_rng(7), np.random.default_rng(7)
        full = _gaussian_noise_int16(a, n, 2.0)
        span = _noise_span(b, n, e0, e1, 2.0)
        assert np.array_equal(full[e0:e1], span)
        assert a.bit_generator.random_raw() == b.bit_generator.random_raw()


@pytest.mark.parametrize("cal", [CAL_TELLO, CAL_FWD], ids=["tello_down_320", "forward_960"])
@pytest.mark.parametrize("blur", [0.0, 3.0])
def test_markers_region_detects_as_the_full_frame(cal, blur: float) -> None:
    full = RenderOptions(marker_radius_m=0.025, noise_std=2.0, blur_px=blur, blur_dir_rad=0.4)
    roi_opts = dataclasses.replace(full, region="markers")
    gen = np.random.default_rng(3)
    accepted = 0
    for _ in range(60):
        centres = P0 + np.array([*gen.uniform(-0.7, 0.7, 2), gen.uniform(0.3, 1.5)])
        normals = np.tile([0.0, 0.0, 1.0], (4, 1)) + gen.normal(0.0, 0.1, (4, 3))
        seed = int(gen.integers(1 << 30))
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        img_full, px_full, view_full, roi_full = render_markers_region(cal, centres, normals, full, a)
        img, px, view, roi = render_markers_region(cal, centres, normals, roi_opts, b)
        assert roi_full is None and roi is not None
        assert np.array_equal(px, px_full, equal_nan=True) and np.array_equal(view, view_full)
        x0, y0, x1, y1 = roi
        assert np.array_equal(img[y0:y1, x0:x1], img_full[y0:y1, x0:x1])
        assert a.bit_generator.random_raw() == b.bit_generator.random_raw()
        d_full, d = extract_markers(img_full, cal), extract_markers(img, cal, roi=roi)
        assert d.reason == d_full.reason
        if d_full.ok:
            accepted += 1
            assert np.array_equal(d.pixels, d_full.pixels) and np.array_equal(d.areas, d_full.areas)
            assert np.array_equal(d.normalized, d_full.normalized)
    assert accepted >= 10  # the views exercise accepted frames, not only rejections


def test_region_falls_back_to_the_full_frame_when_noise_could_look_like_a_marker() -> None:
    # a saturated red floor: noise on it may enter the red marker's colour box, so no roi is promised
    opts = RenderOptions(noise_std=2.0, background_rgb=(200, 40, 40), region="markers")
    _, _, _, roi = render_markers_region(
        CAL_TELLO, P0 + np.array([0.0, 0.0, 1.0]), None, opts, np.random.default_rng(0)
    )
    assert roi is None


def test_unknown_region_is_refused() -> None:
    with pytest.raises(ValueError, match="region"):
        RenderOptions(region="somewhere")
