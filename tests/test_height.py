"""workers.height: normal <-> height round trips, sign conventions, orientation detection, real materials."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from tests.conftest import REAL_MATERIALS, real_material_files
from workers.height import (
    angular_error,
    apply_orientation,
    detect_orientation,
    fit_height_scale,
    height_to_normal,
    integrability_residual,
    normal_tilt,
    normal_to_height,
    sobel_gradients,
)


def periodic_height(h: int = 96, w: int = 128, seed: int = 0) -> np.ndarray:
    """A smooth tileable test surface: a few random low-frequency waves plus periodic bumps, in [0,1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.zeros((h, w))
    for _ in range(6):
        kx, ky = rng.integers(-4, 5, size=2)
        z += rng.normal() * np.cos(2 * np.pi * (kx * x / w + ky * y / h) + rng.uniform(0, 2 * np.pi))
    for _ in range(5):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        dy = np.minimum(abs(y - cy), h - abs(y - cy))
        dx = np.minimum(abs(x - cx), w - abs(x - cx))
        z += 2.0 * np.exp(-(dx**2 + dy**2) / (2 * 6.0**2))
    return ((z - z.min()) / (z.max() - z.min())).astype(np.float32)


def corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


@pytest.mark.parametrize("convention", ["opengl", "directx"])
def test_height_normal_height_round_trip(convention):
    h = periodic_height()
    n = height_to_normal(h, strength=12.0, convention=convention)
    h2, scale = normal_to_height(n, convention=convention)
    assert h2.shape == h.shape and h2.dtype == np.float32
    assert h2.min() == 0.0 and h2.max() == pytest.approx(1.0)
    assert corr(h, h2) > 0.99
    assert scale == pytest.approx(12.0, rel=0.05)  # both heights span [0,1], so the scale is the strength
    err = angular_error(n, height_to_normal(h2, scale, convention=convention))
    assert float(err.mean()) < 0.5


def test_opengl_sign_with_known_slopes():
    """Image rows grow downward; OpenGL +y is up: a surface rising toward the top faces down (ny < 0)."""
    rows, cols = np.mgrid[0:32, 0:32].astype(np.float32)
    rising_right = cols * 0.1
    rising_up = -rows * 0.1  # larger height at smaller row index, i.e. toward the image top
    inner = (slice(4, 28), slice(4, 28))  # away from the wrap seam
    n = height_to_normal(rising_right, strength=1.0)
    assert np.allclose(n[inner][..., 0], -0.1 / np.sqrt(1.01), atol=1e-5)  # faces -x
    assert np.allclose(n[inner][..., 1], 0.0, atol=1e-6)
    n = height_to_normal(rising_up, strength=2.0)
    assert np.allclose(n[inner][..., 1], -0.2 / np.sqrt(1.04), atol=1e-5)  # faces -y (down)
    n_dx = height_to_normal(rising_up, strength=2.0, convention="directx")
    assert np.allclose(n_dx[inner][..., 1], 0.2 / np.sqrt(1.04), atol=1e-5)
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)


def test_sobel_gradients_of_a_ramp_and_wrap():
    h = np.tile(np.arange(16, dtype=np.float32), (8, 1)) * 0.5
    dx, dy = sobel_gradients(h)
    assert np.allclose(dx[:, 1:-1], 0.5) and np.allclose(dy, 0.0)
    assert dx[0, 0] == pytest.approx((0.5 - 7.5) / 2)  # wrap border: neighbours are columns 1 and 15


def test_directx_reading_of_opengl_normals_gives_mirrored_height():
    h = periodic_height(seed=3)
    n = height_to_normal(h, strength=8.0)
    h_wrong, _ = normal_to_height(n, convention="directx")
    assert corr(h, h_wrong) < 0.9


def test_scale_fit_and_tilt_round_trip():
    h = periodic_height(64, 64, seed=1)
    n = height_to_normal(h, strength=5.0, tilt=(0.05, -0.03))
    assert normal_tilt(n) == pytest.approx((0.05, -0.03), abs=1e-4)
    assert fit_height_scale(h, n) == pytest.approx(5.0, rel=1e-3)
    h2, s = normal_to_height(n)
    err = angular_error(n, height_to_normal(h2, s, tilt=normal_tilt(n)))
    assert float(err.mean()) < 0.3


def test_non_square_and_flat():
    h = periodic_height(40, 72, seed=2)
    h2, s = normal_to_height(height_to_normal(h, strength=6.0))
    assert h2.shape == (40, 72) and corr(h, h2) > 0.99
    flat, s0 = normal_to_height(np.dstack([np.zeros((8, 8)), np.zeros((8, 8)), np.ones((8, 8))]))
    assert s0 == 0.0 and np.all(flat == 0)


def test_orientation_detection_on_synthetic_maps():
    n = height_to_normal(periodic_height(seed=4), strength=10.0)
    assert integrability_residual(n) < 0.05
    noise = np.random.default_rng(0).normal(size=(64, 64, 3)) * [0.3, 0.3, 0.0] + [0, 0, 1]
    assert integrability_residual(noise / np.linalg.norm(noise, axis=-1, keepdims=True)) > 0.5
    rotated = np.stack([n[..., 1], -n[..., 0], n[..., 2]], axis=-1)  # vectors turned -90 degrees
    best, res = detect_orientation(rotated)
    assert best == "rot90" and res["rot90"] < 0.05 < res["opengl"]
    assert detect_orientation(apply_orientation(n, "directx"))[0] == "directx"


def test_bad_convention_rejected():
    with pytest.raises(ValueError, match="convention"):
        height_to_normal(np.zeros((4, 4)), convention="vulkan")


@pytest.fixture(scope="module")
def real_round_trips(materials_dir):
    from workers.maps import load_material

    rows = {}
    for name in REAL_MATERIALS:
        f = real_material_files(name)
        m = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                          working_size=256, normal_convention="auto")
        back = height_to_normal(m.height, strength=m.height_scale, tilt=m.normal_tilt)
        err = angular_error(m.normal, back)
        no_tilt = angular_error(m.normal, height_to_normal(m.height, strength=m.height_scale))
        rows[name] = {"orientation": m.meta["normal_orientation"], "mean_deg": float(err.mean()),
                      "median_deg": float(np.median(err)), "p95_deg": float(np.percentile(err, 95)),
                      "mean_deg_without_tilt": float(no_tilt.mean()), "height_scale": m.height_scale,
                      "residual": m.meta["normal_residuals"][m.meta["normal_orientation"]]}
    return rows


def test_real_materials_normal_height_normal(real_round_trips, artifacts_dir):
    print("\nnormal -> height -> normal at 256 px (mean / median / p95 angular error, degrees)")
    for name, r in real_round_trips.items():
        print(f"  {name:24s} {r['orientation']:7s} {r['mean_deg']:5.2f} {r['median_deg']:5.2f} {r['p95_deg']:6.2f}"
              f"  (no tilt {r['mean_deg_without_tilt']:5.2f})  scale {r['height_scale']:6.2f}")
    (artifacts_dir / "height_round_trip.json").write_text(json.dumps(real_round_trips, indent=1))
    for name, r in real_round_trips.items():
        assert r["mean_deg"] < 5.0, name
        assert r["orientation"] == ("rot90" if name == "roof_slates_02" else "opengl"), name


def test_declared_convention_warns_when_normals_are_rotated(materials_dir, caplog):
    from workers.maps import load_material

    f = real_material_files("roof_slates_02")
    with caplog.at_level(logging.WARNING, logger="workers.maps"):
        m = load_material(f["albedo"], f["normal"], working_size=128)
    assert m.meta["normal_orientation"] == "opengl"  # declared is kept ...
    assert "normal_convention='auto'" in caplog.text and "rot90" in caplog.text  # ... but flagged
