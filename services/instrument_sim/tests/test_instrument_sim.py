"""The simulated microscope without Zenoh: optics, camera, stage, specimen and focus behaviour."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.geometry import ScanGrid
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_core.timing import TimingModel
from focustrack_instrument_sim import optics as opt
from focustrack_instrument_sim.camera import Camera, NoiseBank, expose
from focustrack_instrument_sim.instrument import AcquisitionRefusedError, Refusal
from focustrack_instrument_sim.microscope import (
    Microscope,
    MicroscopeSpec,
    slides_from_map,
    slides_from_seed,
)
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_instrument_sim.specimen import SpecimenSpec, blood_smear
from focustrack_instrument_sim.stage import StageSpec


def test_in_focus_otf_is_the_diffraction_limited_one() -> None:
    otf = opt.DefocusOTF(opt.Optics(), 0.55)
    s = otf.q_per_um / otf.q_per_um[-1]
    expected = 2 / np.pi * (np.arccos(s) - s * np.sqrt(1 - s**2))
    np.testing.assert_allclose(otf.profile(0.0)[:-1], expected, atol=0.01)
    defocused = otf.profile(1.0)[:-1]
    assert np.all(np.abs(defocused[1:]) <= expected[1:] + 0.01)  # defocus only loses contrast


def test_ccs_blur_equals_numpy_reference() -> None:
    shape, pixel_um = (32, 48), 0.108
    image = np.random.default_rng(1).random(shape).astype(np.float32)
    otf = opt.DefocusOTF(opt.Optics(), 0.55)
    profile = otf.profile(0.7)
    bins = opt.FrameGeometry(*shape, pixel_um).bins(otf)
    ours = opt.blurred(opt.spectrum(image), profile.take(bins), 1.0)
    radius = np.hypot(np.fft.fftfreq(shape[0])[:, None], np.fft.rfftfreq(shape[1])[None, :])
    reference_bins = np.rint(radius / pixel_um / otf.dq_per_um).astype(int)
    reference_bins = np.minimum(reference_bins, len(profile) - 1)
    reference = np.fft.irfft2(np.fft.rfft2(image) * profile[reference_bins], s=shape)
    np.testing.assert_allclose(ours, reference, atol=1e-4)


def _beads(seed: np.random.SeedSequence, shape: tuple[int, int], pixel_um: float) -> np.ndarray:
    """Sub-resolution absorbing beads (one pixel each) every 32 pixels on clear glass."""
    transmission = np.ones((*shape, 3), dtype=np.float32)
    transmission[16::32, 16::32] = 0.01
    return transmission


def test_depth_of_field_of_a_bead_stack_agrees_with_the_formula() -> None:
    """Rayleigh quarter-wave criterion: the bead's image keeps >= 80% of its in-focus depth."""
    spec = MicroscopeSpec(height=256, width=256, max_frames=64)
    slide = slides_from_seed(5, 1, SurfaceSpec(1, 1))[0]
    scope = Microscope([slide], spec, seed=1, specimen=_beads)
    truth_um = float(slide.focus_um[0, 0])
    stack = scope.acquire(slide.name, 0, 0, truth_um - 1.2, 0.04, 61)
    green = stack.pixels[..., 1].astype(float)
    dip = np.median(green, axis=(1, 2)) - green[:, 16::32, 16::32].mean(axis=(1, 2))
    inside = np.flatnonzero(dip >= 0.8 * dip.max())
    low, high = inside[0], inside[-1]
    assert np.all(dip[low : high + 1] >= 0.75 * dip.max()), "the in-focus region is not one piece"

    def crossing(a: int, b: int) -> float:  # z where the dip crosses 80% between frames a and b
        level = 0.8 * dip.max()
        t = (level - dip[a]) / (dip[b] - dip[a])
        return stack.z_um[a] + t * (stack.z_um[b] - stack.z_um[a])

    measured_um = crossing(high, high + 1) - crossing(low - 1, low)
    formula_um = spec.optics.depth_of_field_um
    print(f"depth of field: measured {measured_um:.3f} um, formula {formula_um:.3f} um")
    assert abs(measured_um - formula_um) < 0.2 * formula_um, (measured_um, formula_um)
    assert abs((crossing(high, high + 1) + crossing(low - 1, low)) / 2 - truth_um) < 0.1


def test_a_simple_focus_measure_peaks_at_the_true_focus() -> None:
    spec = MicroscopeSpec(height=256, width=256)
    slides = slides_from_seed(11, 1, SurfaceSpec(3, 4))
    scope = Microscope(slides, spec, seed=2)
    truth_um, _ = scope.truth_um("slide-0")
    offsets = np.random.default_rng(3).uniform(-0.25, 0.25, size=truth_um.shape)
    hits = 0
    for (row, col), z_star in np.ndenumerate(truth_um):
        stack = scope.acquire("slide-0", row, col, z_star - 2.5 + offsets[row, col], 0.5, 11)
        green = stack.pixels[..., 1].reshape(len(stack.z_um), -1).astype(float)
        normalised_variance = green.var(axis=1) / green.mean(axis=1)
        hits += abs(stack.z_um[np.argmax(normalised_variance)] - z_star) <= 0.5
    assert hits >= 0.8 * truth_um.size, f"{hits} of {truth_um.size} tiles in focus"


def test_specimen_is_deterministic_and_varies_between_tiles() -> None:
    spec = SpecimenSpec()
    seed = np.random.SeedSequence([1, 2, 3])
    first = blood_smear(spec, seed, (128, 128), 0.108)
    again = blood_smear(spec, np.random.SeedSequence([1, 2, 3]), (128, 128), 0.108)
    other = blood_smear(spec, np.random.SeedSequence([1, 2, 4]), (128, 128), 0.108)
    np.testing.assert_array_equal(first, again)
    assert first.shape == (128, 128, 3) and first.min() > 0 and first.max() <= 1
    assert not np.array_equal(first, other)


def test_a_stack_does_not_depend_on_the_render_threads_and_streams_in_order() -> None:
    stacks = []
    for workers in (1, 2):
        spec = MicroscopeSpec(height=64, width=64, workers=workers)
        scope = Microscope(slides_from_seed(3, 1, SurfaceSpec(2, 2)), spec, seed=4)
        stacks.append(scope.acquire("slide-0", 1, 0, -2.0, 0.5, 7).pixels)
        plan = scope.plan("slide-0", 1, 0, -2.0, 0.5, 7)
        frames = list(scope.render(plan))  # the same stack again, frame by frame
        scope.close()
        assert len(frames) == 7 and all(f.shape == (64, 64, 3) for f in frames)
        assert np.abs(np.asarray(frames, float) - stacks[-1]).mean() > 0  # fresh noise
    np.testing.assert_array_equal(stacks[0], stacks[1])


def test_the_cache_holds_as_many_tiles_as_its_megabytes() -> None:
    assert MicroscopeSpec(height=512, width=512).tiles_cached == 1024_000_000 // (4 * 512 * 512 * 4)
    assert MicroscopeSpec(cache_mb=0.0).tiles_cached == 1
    assert MicroscopeSpec(cached_tiles=3).tiles_cached == 3


def test_the_simulators_default_options_are_its_microscopes_defaults() -> None:
    scope = microscope_from_options(SimulatorOptions())
    scope.close()
    assert scope.spec == MicroscopeSpec()
    assert [slide.grid for slide in scope.slides.values()] == [ScanGrid(20, 20)]


def test_a_tile_looks_the_same_when_imaged_again() -> None:
    spec = MicroscopeSpec(height=128, width=128, cached_tiles=1)
    scope = Microscope(slides_from_seed(2, 1, SurfaceSpec(2, 2)), spec, seed=0)
    z_low = float(scope.slides["slide-0"].focus_um[0, 0])
    first = scope.acquire("slide-0", 0, 0, z_low, 0.5, 1).pixels.astype(float)
    scope.acquire("slide-0", 1, 1, z_low, 0.5, 1)  # evicts tile (0, 0) from the cache
    second = scope.acquire("slide-0", 0, 0, z_low, 0.5, 1).pixels.astype(float)
    noise_adu = np.sqrt(first.mean() * spec.camera.gain_e_per_adu) / spec.camera.gain_e_per_adu
    assert np.abs(first - second).mean() < 2 * noise_adu  # only the noise differs
    assert np.abs(first - second).mean() > 0  # and it does


@pytest.mark.parametrize("signal_e", [12_000.0, 30.0])
def test_camera_noise_is_shot_plus_read_noise(signal_e: float) -> None:
    camera = Camera()
    rng = np.random.default_rng(0)
    plane = np.full((256, 256), signal_e, dtype=np.float32)
    adu = expose(camera, plane, rng, NoiseBank(plane.shape, rng)).astype(float)
    gain = camera.gain_e_per_adu
    assert adu.mean() == pytest.approx(signal_e / gain + camera.offset_adu, rel=0.01)
    expected_var = (signal_e + camera.read_noise_e**2) / gain**2 + 1 / 12  # + quantisation
    assert adu.var() == pytest.approx(expected_var, rel=0.1)


@pytest.mark.parametrize("signal_e", [12_000.0, 30.0])
def test_exposing_into_buffers_gives_the_same_frame_as_allocating(signal_e: float) -> None:
    camera = Camera()
    signal = np.random.default_rng(1).normal(signal_e, signal_e / 10, (64, 64)).astype(np.float32)
    bank = NoiseBank(signal.shape, np.random.default_rng(2))
    fresh = expose(camera, signal.copy(), np.random.default_rng(3), bank)
    out, scratch = np.empty(signal.shape, np.uint16), np.empty_like(signal)
    in_place = expose(camera, signal.copy(), np.random.default_rng(3), bank, out, scratch)
    assert in_place is out
    np.testing.assert_array_equal(in_place, fresh)


def test_camera_saturates_at_full_well_and_bit_depth() -> None:
    camera = Camera(bit_depth=10)
    rng = np.random.default_rng(0)
    plane = np.full((64, 64), 1e6, dtype=np.float32)
    adu = expose(camera, plane, rng, NoiseBank(plane.shape, rng))
    assert adu.dtype == np.uint16 and adu.max() == camera.saturation_adu == 2**10 - 1


def test_timing_follows_the_timing_model_and_drift_moves_the_focus() -> None:
    timing = TimingModel()
    spec = MicroscopeSpec(height=64, width=64, stage=StageSpec(drift_um_per_s=0.01))
    scope = Microscope(slides_from_seed(4, 1, SurfaceSpec(2, 3)), spec, seed=0)
    first = scope.acquire("slide-0", 0, 1, 0.0, 0.5, 5)
    assert first.timing.move_s == pytest.approx(timing.move_s(200.0))
    assert first.timing.total_s == pytest.approx(timing.move_s(200.0) + timing.stack_s(5))
    second = scope.acquire("slide-0", 0, 2, 0.0, 0.5, 5, exposure_s=0.05)
    assert second.timing.exposure_s == pytest.approx(0.25)
    assert second.clock_s == pytest.approx(first.timing.total_s + second.timing.total_s)
    truth_um, drift_um = scope.truth_um("slide-0")
    assert drift_um == pytest.approx(0.01 * second.clock_s)
    np.testing.assert_allclose(truth_um - scope.slides["slide-0"].focus_um, drift_um)


def test_refusals_say_what_is_wrong() -> None:
    scope = Microscope(
        slides_from_seed(4, 1, SurfaceSpec(2, 3)), MicroscopeSpec(height=64, width=64), seed=0
    )
    with pytest.raises(AcquisitionRefusedError, match="outside the stage's travel") as refused:
        scope.acquire("slide-0", 0, 0, 95.0, 1.0, 10)
    assert refused.value.reason is Refusal.Z_OUT_OF_RANGE
    with pytest.raises(AcquisitionRefusedError, match="known: slide-0"):
        scope.acquire("slide-9", 0, 0, 0.0, 1.0, 3)


def test_slides_come_from_a_seed_or_a_map_file(tmp_path) -> None:
    spec = SurfaceSpec(3, 4)
    slides = slides_from_seed(7, 2, spec)
    np.testing.assert_array_equal(slides[1].focus_um, generate_surfaces(spec, 2, 7)[1])
    path = tmp_path / "map.csv"
    np.savetxt(path, slides[0].focus_um, delimiter=",")
    (loaded,) = slides_from_map(path, seed=7)
    np.testing.assert_allclose(loaded.focus_um, slides[0].focus_um)
    assert loaded.grid.shape == (3, 4)
