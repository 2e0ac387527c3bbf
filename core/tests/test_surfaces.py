"""Generated focus surfaces (determinism, smoothness, exact covariance) and the map loader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from focustrack_core.surfaces import (
    FAMILIES,
    SurfaceSpec,
    family_spec,
    generate_surfaces,
    load_map,
    surface_covariance,
)


def test_surfaces_are_deterministic_from_the_seed() -> None:
    spec = family_spec("standard")
    first = generate_surfaces(spec, 3, seed=7)
    assert first.shape == (3, 20, 20)
    assert np.array_equal(first, generate_surfaces(spec, 3, seed=7))
    assert not np.allclose(first, generate_surfaces(spec, 3, seed=8))
    # Map i does not depend on how many maps were asked for.
    assert np.array_equal(first[:2], generate_surfaces(spec, 2, seed=7))
    assert not np.allclose(first[0], first[1])


def test_surfaces_are_smooth() -> None:
    maps = generate_surfaces(family_spec("standard"), 16, seed=0)
    neighbour_steps = np.concatenate([np.diff(maps, axis=1).ravel(), np.diff(maps, axis=2).ravel()])
    relief = maps - maps.mean(axis=(1, 2), keepdims=True)
    # A neighbour differs by a small part of the map's relief (Gaussian-smoothed, range 15 tiles).
    assert np.sqrt(np.mean(neighbour_steps**2)) < 0.35 * np.sqrt(np.mean(relief**2))


def test_covariance_matches_the_empirical_one() -> None:
    spec = SurfaceSpec(rows=8, cols=8)
    maps = generate_surfaces(spec, 2000, seed=5)
    rows = np.array([0, 0, 3, 7, 7, 4])
    cols = np.array([0, 7, 4, 7, 0, 4])
    exact = surface_covariance(spec, rows, cols)
    empirical = np.cov(maps[:, rows, cols].T)
    assert np.allclose(exact, exact.T) and np.all(np.linalg.eigvalsh(exact) > 0)
    scale = np.sqrt(np.outer(np.diag(exact), np.diag(exact)))
    assert np.all(np.abs(empirical - exact) <= 0.12 * scale)
    assert np.all(np.abs(maps[:, rows, cols].mean(axis=0)) < 0.15)


def test_families() -> None:
    assert set(FAMILIES) >= {"standard", "steps", "tilted", "rough"}
    assert family_spec("standard", 6, 9).rows == 6 and family_spec("standard", 6, 9).cols == 9
    with pytest.raises(ValueError, match="unknown map family"):
        family_spec("wavy")
    # The same seed draws the same field; the steps family adds a smoothed 4 um step to it.
    step = generate_surfaces(family_spec("steps"), 4, 0) - generate_surfaces(
        family_spec("standard"), 4, 0
    )
    assert np.all(step >= -1e-9) and np.all(step <= 4.0 + 1e-9)
    assert np.all(step.min(axis=(1, 2)) < 0.5) and np.all(step.max(axis=(1, 2)) > 3.5)


def test_load_map_reads_npy_csv_and_tif(tmp_path: Path) -> None:
    maps = generate_surfaces(family_spec("standard", 5, 7), 3, seed=1)
    np.save(tmp_path / "one.npy", maps[0])
    np.save(tmp_path / "stack.npy", maps)
    np.savetxt(tmp_path / "one.csv", maps[0], delimiter=",")
    tifffile.imwrite(tmp_path / "one.tif", maps[0].astype(np.float32))
    tifffile.imwrite(tmp_path / "stack.tiff", maps.astype(np.float32), photometric="minisblack")

    assert np.array_equal(load_map(tmp_path / "one.npy"), maps[0])
    assert np.array_equal(load_map(tmp_path / "stack.npy"), maps)
    assert np.allclose(load_map(tmp_path / "one.csv"), maps[0])
    assert np.allclose(load_map(tmp_path / "one.tif"), maps[0], atol=1e-5)
    stack = load_map(tmp_path / "stack.tiff")
    assert stack.shape == (3, 5, 7) and stack.dtype == float
    assert np.allclose(stack, maps, atol=1e-5)
    np.savetxt(tmp_path / "row.csv", maps[0][:1], delimiter=",")
    assert load_map(tmp_path / "row.csv").shape == (1, 7)


def test_load_map_errors(tmp_path: Path) -> None:
    (tmp_path / "map.txt").write_text("1,2\n3,4\n")
    with pytest.raises(ValueError, match="unsupported map format"):
        load_map(tmp_path / "map.txt")
    (tmp_path / "nan.csv").write_text("1,2\n3,nan\n")
    with pytest.raises(ValueError, match="NaN or infinite"):
        load_map(tmp_path / "nan.csv")
    np.save(tmp_path / "line.npy", np.arange(4.0))
    with pytest.raises(ValueError, match="expected a 2-D map"):
        load_map(tmp_path / "line.npy")
    np.save(tmp_path / "four.npy", np.zeros((2, 2, 2, 2)))
    with pytest.raises(ValueError, match="expected a 2-D map"):
        load_map(tmp_path / "four.npy")
    with pytest.raises(FileNotFoundError):
        load_map(tmp_path / "missing.npy")
