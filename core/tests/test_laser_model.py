"""The laser autofocus model: smooth offsets from the coverslip to the tissue, and readings."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.laser import LaserSpec, coverslip_offsets, laser_reading


def test_offsets_have_the_stated_mean_and_spread_and_are_smooth() -> None:
    spec = LaserSpec(offset_um=4.0, offset_sigma_um=0.4, offset_length_tiles=8.0)
    offsets = coverslip_offsets((60, 50), 3, spec)
    assert offsets.shape == (60, 50)
    spread = [coverslip_offsets((60, 50), seed, spec)[30, 25] for seed in range(200)]
    assert np.mean(spread) == pytest.approx(4.0, abs=0.1)  # over slides, as stated
    assert np.std(spread) == pytest.approx(0.4, rel=0.15)
    # neighbours differ by far less than the field spreads: smooth over several tiles
    assert np.abs(np.diff(offsets, axis=1)).mean() < 0.05
    np.testing.assert_array_equal(offsets, coverslip_offsets((60, 50), 3, spec))
    assert not np.allclose(offsets, coverslip_offsets((60, 50), 4, spec))


def test_a_reading_is_the_focus_less_the_offset_with_the_sensors_noise() -> None:
    rng = np.random.default_rng(0)
    readings = [laser_reading(10.0, 4.0, 0.05, rng) for _ in range(2000)]
    assert np.mean(readings) == pytest.approx(6.0, abs=0.01)
    assert np.std(readings) == pytest.approx(0.05, rel=0.1)


def test_bad_specs_are_refused() -> None:
    with pytest.raises(ValueError, match="offset_length_tiles"):
        LaserSpec(offset_length_tiles=0.0)
    with pytest.raises(ValueError, match="negative"):
        LaserSpec(noise_um=-0.1)
