"""Batched, differentiable GGX Cook-Torrance renderer of a flat material sample under point lights (torch).

Model (paper 5.3, SPEC-pipeline "Recomposition"): the maps lie on a plane of width ``plane_width`` (9.728) centred
at the origin in z = 0 (x to the right, y up = image row 0 at the top, normals OpenGL). Each point light sits at
``p`` with the camera at the same place (so v = l and h = l), intensity ``1500 pi`` and 1/r^2 falloff::

    L = I / r^2 * (n.l) * [ (1 - m) albedo / pi + D(n.h) F(v.h) G(n.l) G(n.v) / (4 (n.l)(n.v)) ]
    D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2),  alpha = roughness^2
    F = F0 + (1 - F0)(1 - v.h)^5,  F0 = 0.04 (mixed to albedo by metallic m when a metallic map is given)
    G(x) = x / (x (1 - k) + k),  k = alpha / 2   (Smith-Schlick)

Outputs are linear radiance; :func:`tonemap` gives sRGB in [0, 1] for display and losses.
"""
from __future__ import annotations

import math

import numpy as np
import torch

PLANE_WIDTH = 9.728
LIGHT_INTENSITY = 1500.0 * math.pi
LIGHT_DISTANCE = 35.0
EPS = 1e-6


def _light_positions(theta_deg, phi_deg, distance: float) -> torch.Tensor:
    """(L, 3) positions at polar angles ``theta`` (from the normal) and azimuths ``phi`` (degrees)."""
    t = torch.as_tensor(theta_deg, dtype=torch.float64) * (math.pi / 180)
    p = torch.as_tensor(phi_deg, dtype=torch.float64) * (math.pi / 180)
    pos = torch.stack([torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)], dim=-1) * distance
    return pos.to(torch.float32)


def paper_lights(distance: float = LIGHT_DISTANCE) -> torch.Tensor:
    """The paper's 16 lights, (16, 3): 8 at 15 deg and 8 at 60 deg from the normal, every 45 deg in azimuth."""
    phi = np.arange(8) * 45.0
    theta = np.concatenate([np.full(8, 15.0), np.full(8, 60.0)])
    return _light_positions(theta, np.concatenate([phi, phi]), distance)


def random_lights(n: int, generator: torch.Generator | int | None = None, max_theta: float = 60.0,
                  distance: float = LIGHT_DISTANCE) -> torch.Tensor:
    """(n, 3) light positions at ``distance``, polar angle uniform in cos over [0, max_theta] deg, any azimuth."""
    if not isinstance(generator, torch.Generator):
        generator = torch.Generator().manual_seed(0 if generator is None else int(generator))
    u = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    cos_min = math.cos(math.radians(max_theta))
    theta = torch.rad2deg(torch.arccos(1.0 - u[:, 0] * (1.0 - cos_min)))
    return _light_positions(theta, u[:, 1] * 360.0, distance)


def plane_positions(height: int, width: int, plane_width: float = PLANE_WIDTH, device=None,
                    dtype=torch.float32) -> torch.Tensor:
    """(H, W, 3) world positions of the pixel centres on the z = 0 plane (row 0 at the top, +y)."""
    ph = plane_width * height / width
    xs = ((torch.arange(width, device=device, dtype=dtype) + 0.5) / width - 0.5) * plane_width
    ys = (0.5 - (torch.arange(height, device=device, dtype=dtype) + 0.5) / height) * ph
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx, yy, torch.zeros_like(xx)], dim=-1)


def _hwc(x: torch.Tensor, name: str, channels: tuple[int, ...]) -> torch.Tensor:
    """Check/convert an HxW or HxWxC map."""
    if x.dim() == 2:
        x = x[..., None]
    if x.dim() != 3 or x.shape[-1] not in channels:
        raise ValueError(f"render: {name} must be HxWx{'|'.join(map(str, channels))}, got {tuple(x.shape)}")
    return x


def render(albedo: torch.Tensor, normal: torch.Tensor, roughness: torch.Tensor, lights: torch.Tensor,
           metallic: torch.Tensor | None = None, *, f0: float = 0.04, intensity: float = LIGHT_INTENSITY,
           plane_width: float = PLANE_WIDTH) -> torch.Tensor:
    """Linear radiance (L, H, W, 3) of the maps (HxWxC torch tensors, albedo linear) under point lights (L, 3).

    Differentiable w.r.t. every map; runs on the device of ``albedo``. Normals need not be unit length.
    """
    albedo = _hwc(albedo, "albedo", (1, 3))
    normal = _hwc(normal, "normal", (3,))
    rough = _hwc(roughness, "roughness", (1,))
    dev, dt = albedo.device, albedo.dtype
    h, w = albedo.shape[:2]
    for name, t in (("normal", normal), ("roughness", rough)):
        if t.shape[:2] != (h, w):
            raise ValueError(f"render: {name} is {tuple(t.shape[:2])}, albedo is {(h, w)}")
    lights = torch.as_tensor(lights, dtype=dt, device=dev).reshape(-1, 3)
    n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(EPS)
    pos = plane_positions(h, w, plane_width, dev, dt)
    d = lights[:, None, None, :] - pos[None]                         # (L, H, W, 3)
    r2 = (d * d).sum(-1, keepdim=True)
    l = d / r2.sqrt()
    ndl = (n[None] * l).sum(-1, keepdim=True).clamp_min(0.0)         # = n.v = n.h (camera at the light)
    alpha = rough.clamp(0.0, 1.0) ** 2
    a2 = (alpha * alpha).clamp_min(1e-8)
    dd = a2 / (math.pi * (ndl * ndl * (a2 - 1.0) + 1.0) ** 2)
    k = (alpha / 2.0).clamp_min(1e-6)
    if metallic is not None:
        m = _hwc(metallic, "metallic", (1,)).clamp(0.0, 1.0)
        f0_t = f0 * (1.0 - m) + albedo * m
        diffuse = albedo * (1.0 - m) / math.pi
    else:
        f0_t = torch.as_tensor(f0, dtype=dt, device=dev)
        diffuse = albedo / math.pi
    fres = f0_t  # v.h = 1 for a co-located light and camera: Schlick gives exactly F0
    # D F G G / (4 ndl ndv) with ndv = ndl; G1^2 / ndl^2 is finite as ndl -> 0 (g1 / ndl = 1 / (ndl (1-k) + k))
    gn = 1.0 / (ndl * (1.0 - k) + k)
    spec = dd * fres * gn * gn / 4.0
    out = intensity / r2 * ndl * (diffuse + spec)
    return out.expand(-1, -1, -1, 3) if out.shape[-1] == 1 else out


def tonemap(radiance: torch.Tensor) -> torch.Tensor:
    """Clip linear radiance to [0, 1] and apply the sRGB transfer curve (differentiable inside (0, 1))."""
    x = radiance.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)


def _to_tensor(a: np.ndarray) -> torch.Tensor:
    a = np.asarray(a, dtype=np.float32)
    return torch.from_numpy(np.ascontiguousarray(a[..., None] if a.ndim == 2 else a))


def preview_lights(distance: float = LIGHT_DISTANCE) -> torch.Tensor:
    """The two preview lights: straight above (top) and 60 deg from the normal at azimuth 135 deg (side)."""
    return _light_positions([0.0, 60.0], [0.0, 135.0], distance)


def preview_image(maps: dict[str, np.ndarray]) -> np.ndarray:
    """H x 2W x 3 sRGB image in [0, 1]: top light | side light, from numpy maps (albedo linear, normal OpenGL;
    roughness defaults to 0.5, a missing normal map is flat, metallic optional)."""
    if "albedo" not in maps:
        raise ValueError(f"preview_image needs an 'albedo' map, got {sorted(maps)}")
    alb = _to_tensor(maps["albedo"])
    if alb.shape[-1] == 1:
        alb = alb.expand(-1, -1, 3)
    alb = alb[..., :3]
    if maps.get("normal") is not None:
        nrm = _to_tensor(maps["normal"])
    else:  # an albedo-only material is flat: every normal straight up
        nrm = torch.zeros(alb.shape[:2] + (3,))
        nrm[..., 2] = 1.0
    rough = _to_tensor(maps["roughness"])[..., :1] if maps.get("roughness") is not None else \
        torch.full(alb.shape[:2] + (1,), 0.5)
    met = _to_tensor(maps["metallic"])[..., :1] if maps.get("metallic") is not None else None
    with torch.no_grad():
        img = tonemap(render(alb, nrm, rough, preview_lights(), met))
    return torch.cat([img[0], img[1]], dim=1).numpy().astype(np.float32)
