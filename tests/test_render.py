"""GGX renderer: analytic checks with numbers, gradients, determinism, preview."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.render import (
    LIGHT_INTENSITY,
    PLANE_WIDTH,
    paper_lights,
    plane_positions,
    preview_image,
    random_lights,
    render,
    tonemap,
)


def _flat(h: int = 32, w: int = 32, albedo: float = 0.5, rough: float = 0.5):
    a = torch.full((h, w, 3), albedo)
    n = torch.zeros(h, w, 3)
    n[..., 2] = 1.0
    r = torch.full((h, w, 1), rough)
    return a, n, r


def test_paper_lights_geometry():
    L = paper_lights()
    assert L.shape == (16, 3)
    assert torch.allclose(L.norm(dim=1), torch.full((16,), 35.0), atol=1e-4)
    theta = torch.rad2deg(torch.arccos(L[:, 2] / 35.0))
    assert torch.allclose(theta[:8], torch.full((8,), 15.0), atol=1e-3)
    assert torch.allclose(theta[8:], torch.full((8,), 60.0), atol=1e-3)
    az = torch.rad2deg(torch.atan2(L[:8, 1], L[:8, 0])) % 360
    assert torch.allclose(az, torch.arange(8) * 45.0, atol=1e-3)
    r1 = random_lights(4, torch.Generator().manual_seed(3))
    r2 = random_lights(4, torch.Generator().manual_seed(3))
    assert torch.equal(r1, r2) and r1.shape == (4, 3)
    assert float(torch.rad2deg(torch.arccos(r1[:, 2] / 35.0)).max()) <= 60.0 + 1e-3


def test_lambert_only_matches_analytic():
    h, w = 16, 24
    a, n, r = _flat(h, w, albedo=0.7, rough=0.3)
    a = a * torch.tensor([1.0, 0.5, 0.25])
    lights = torch.tensor([[3.0, -2.0, 20.0], [0.0, 0.0, 35.0]])
    out = render(a, n, r, lights, f0=0.0)
    pos = plane_positions(h, w)
    assert float(pos[..., 0].max() - pos[..., 0].min()) == pytest.approx(PLANE_WIDTH * (w - 1) / w, rel=1e-5)
    d = lights[:, None, None, :] - pos[None]
    r2 = (d * d).sum(-1, keepdim=True)
    cos = d[..., 2:3] / r2.sqrt()
    expected = LIGHT_INTENSITY * a[None] / math.pi * cos / r2
    assert torch.allclose(out, expected, rtol=1e-5, atol=1e-7)


def test_highlight_peak_ratio_rough_vs_smooth():
    # specular part only (albedo 0), light straight above the centre: spec = I/r^2 * D(1) * F0 / 4
    # D(1) = 1 / (pi alpha^2): ratio smooth/rough = (1 / 0.2^4) / 1 = 625
    h = w = 33  # odd: a pixel centre sits exactly under the light
    light = torch.tensor([[0.0, 0.0, 35.0]])
    peaks = {}
    for rough in (1.0, 0.2):
        a, n, r = _flat(h, w, albedo=0.0, rough=rough)
        out = render(a, n, r, light)
        peaks[rough] = float(out[0, h // 2, w // 2, 0])
        assert peaks[rough] == pytest.approx(LIGHT_INTENSITY / 35.0 ** 2 * 0.04 / 4 / (math.pi * rough ** 4),
                                             rel=1e-4)
    assert peaks[0.2] / peaks[1.0] == pytest.approx(625.0, rel=1e-3)
    # smooth highlight is concentrated: the corner is far dimmer than the centre
    a, n, r = _flat(h, w, albedo=0.0, rough=0.2)
    out = render(a, n, r, light)
    assert float(out[0, 0, 0, 0]) < 0.05 * float(out[0, h // 2, w // 2, 0])


def test_normal_incidence_brighter_than_grazing():
    a, n, r = _flat(albedo=0.5, rough=0.6)
    lights = torch.stack([torch.tensor([0.0, 0.0, 35.0]),
                          35.0 * torch.tensor([math.sin(math.radians(80)), 0.0, math.cos(math.radians(80))])])
    out = render(a, n, r, lights)
    top, graze = float(out[0].mean()), float(out[1].mean())
    assert top > 3.0 * graze > 0.0, (top, graze)


def test_tilted_normal_faces_the_light():
    # a normal tilted towards +x receives more light from a +x light than one tilted towards -x
    a, _, r = _flat(8, 8)
    light = torch.tensor([[20.0, 0.0, 25.0]])
    n_pos = torch.tensor([0.5, 0.0, 1.0]).expand(8, 8, 3)
    n_neg = torch.tensor([-0.5, 0.0, 1.0]).expand(8, 8, 3)
    assert float(render(a, n_pos, r, light).mean()) > 1.5 * float(render(a, n_neg, r, light).mean())


def test_metallic_mixes_f0():
    a, n, r = _flat(9, 9, albedo=0.8, rough=0.5)
    light = torch.tensor([[0.0, 0.0, 35.0]])
    dielectric = render(a, n, r, light, metallic=torch.zeros(9, 9, 1))
    plain = render(a, n, r, light)
    assert torch.allclose(dielectric, plain, rtol=1e-6)
    metal = render(a, n, r, light, metallic=torch.ones(9, 9, 1))
    # centre: metal = spec with F0 = 0.8 (no diffuse); dielectric = diffuse + spec with F0 = 0.04
    k = LIGHT_INTENSITY / 35.0 ** 2
    d1 = 1.0 / (math.pi * 0.25 ** 2)
    assert float(metal[0, 4, 4, 0]) == pytest.approx(k * d1 * 0.8 / 4, rel=1e-3)
    assert float(plain[0, 4, 4, 0]) == pytest.approx(k * (0.8 / math.pi + d1 * 0.04 / 4), rel=1e-3)


def test_gradients_flow_and_determinism():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(16, 16, 3, generator=g).requires_grad_(True)
    n = (torch.rand(16, 16, 3, generator=g) - 0.5) * 0.4
    n[..., 2] = 1.0
    n.requires_grad_(True)
    r = (0.2 + 0.6 * torch.rand(16, 16, 1, generator=g)).requires_grad_(True)
    lights = random_lights(4, torch.Generator().manual_seed(1))
    out = tonemap(render(a, n, r, lights))
    out.mean().backward()
    for t in (a, n, r):
        assert t.grad is not None and torch.isfinite(t.grad).all() and float(t.grad.abs().sum()) > 0
    again = tonemap(render(a.detach(), n.detach(), r.detach(), lights))
    assert torch.equal(out.detach(), again)


def test_preview_image():
    h, w = 20, 30
    maps = {"albedo": np.full((h, w, 3), 0.4, np.float32),
            "normal": np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]).astype(np.float32)}
    img = preview_image(maps)
    assert img.shape == (h, 2 * w, 3) and img.dtype == np.float32
    assert 0.0 <= img.min() and img.max() <= 1.0
    # top light brighter on average than the 60 deg side light
    assert img[:, :w].mean() > img[:, w:].mean() > 0.01
    rough_img = preview_image({**maps, "roughness": np.full((h, w), 1.0, np.float32)})
    assert not np.allclose(rough_img, img)
    with pytest.raises(ValueError, match="albedo"):
        preview_image({"normal": maps["normal"]})
