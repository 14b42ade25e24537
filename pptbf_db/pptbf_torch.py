"""Differentiable torch PPTBF: the shading of pptbf.py in torch over the (detached) numpy structure.

The discrete part (tiles, hashing, subdivision, relaxation, ranking, the cell borders) is computed once in numpy by
pptbf.prepare / pptbf.pixel_structure and enters as index tensors and detached values (spec §4). Everything
continuous is recomputed here with autograd: the coordinates (rotation, aspect, zoom with the int-cast resolution
passed straight-through, turbulence A/G/f), the jittered points p = J p* + (1 - J) c', the classical and cellular
windows (border radii get first-order gradients by an implicit-function step), the kernels and the mixtures.
In exact mode (stable=False) the values equal numpy's evaluate; stable=True hashes the cell centre instead of the
jittered point so that the jitter moves points without reshuffling their random values.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pptbf_db import pptbf as pp

EPS = 1e-12


class _Params:
    """The continuous parameters as (differentiable) 0-d tensors, plus the decoded discrete values."""

    def __init__(self, params: torch.Tensor, d: pp.Decoded):
        g = {n: params[i] for i, n in enumerate(pp.PARAM_NAMES)}
        self.d = d
        self.jitter = g["jitter"]
        res = g["resolution"]
        self.res = res + (float(d.res) - res).detach()          # int cast, gradient straight through
        self.alpha = math.pi * g["rotation"]
        self.aspect = g["aspect_ratio"]
        self.dist_a, self.dist_g, self.dist_f = g["distortion_base"], g["distortion_amplitude"], \
            g["distortion_frequency"]
        self.larp, self.wnorm, self.smooth = g["window_larp"], g["window_norm"], g["window_smoothness"]
        self.beta, self.sigma_w = g["window_blend"], g["window_sigma"]
        self.fnorm, self.corr, self.aniso = g["feature_norm"], g["feature_correlation"], g["feature_aniso"]
        self.sigcos, self.sigcosvar = g["feature_sigcos"], g["feature_sigcosvar"]
        self.phi = 0.5 * math.pi * g["feature_phase_shift"]
        self.thick, self.curv = g["feature_thickness"], g["feature_curvature"]
        self.theta_max = math.pi * g["feature_orientation"]


def _t(a, ref: torch.Tensor) -> torch.Tensor:
    """numpy -> tensor on ref's device (float arrays in ref's dtype, integer/bool arrays kept)."""
    a = np.asarray(a)
    if a.dtype.kind == "f":
        return torch.as_tensor(a, dtype=ref.dtype, device=ref.device)
    return torch.as_tensor(a, device=ref.device)


def value_noise_torch(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Value noise with smoothstep weights (C1 in x, y); lattice lookups are detached table reads."""
    perm = torch.as_tensor(pp.PERM, device=x.device)
    noise = torch.as_tensor(pp.NOISE, dtype=x.dtype, device=x.device)

    def lat(i, j):
        return noise[torch.remainder(perm[torch.remainder(i, 1024)] + 3 * perm[torch.remainder(j, 1024)]
                                     + 5 * int(pp.PERM[0]), 1024)]

    fx, fy = torch.floor(x.detach()), torch.floor(y.detach())
    ix, iy = fx.long(), fy.long()
    tx, ty = x - fx, y - fy
    sx, sy = tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty)
    v0 = lat(ix, iy) + (lat(ix, iy + 1) - lat(ix, iy)) * sy
    v1 = lat(ix + 1, iy) + (lat(ix + 1, iy + 1) - lat(ix + 1, iy)) * sy
    return v0 + (v1 - v0) * sx


def domain_coords_torch(x0: torch.Tensor, y0: torch.Tensor, c: _Params, ref_width: float):
    """Turbulence and model transform in torch (same formulas as pptbf.domain_coords)."""
    zoom = ref_width / c.res
    x1, y1 = x0, y0
    if c.d.dist_a != 0.0:
        fz = c.dist_f * zoom
        for o, m in enumerate(pp.OCTAVE_FACTORS):
            amp = c.dist_a * c.dist_g ** o
            x1 = x1 + amp * value_noise_torch(fz * m * x0 + 2.0, fz * m * y0)
            y1 = y1 + amp * value_noise_torch(fz * m * x0, fz * m * y0 + 5.0)
    ca, sa = torch.cos(c.alpha), torch.sin(c.alpha)
    return 100.0 + zoom * (x1 * ca - y1 * sa) / c.aspect, 100.0 + zoom * (x1 * sa + y1 * ca)


def _minkowski(ax, ay, p: torch.Tensor, pv: float):
    """Safe (|ax|^p + |ay|^p)^(1/p) (eps inside) for a tensor exponent p with value pv."""
    if pv == 2.0 and not p.requires_grad:
        return torch.sqrt(ax * ax + ay * ay + EPS)
    ax, ay = ax + EPS, ay + EPS
    return (ax ** p + ay ** p) ** (1.0 / p)


def _wnorm(ax, ay, p: torch.Tensor, pv: float):
    """Minkowski norm blended towards L-inf above 2 (windows, features)."""
    r = _minkowski(ax, ay, p, pv)
    if pv > 2.0:
        r = (p - 2.0) * torch.maximum(ax, ay) + (3.0 - p) * r
    return r


def _classical_window(r: torch.Tensor, d: pp.Decoded) -> torch.Tensor:
    """Classical window g(r); the rectangular shape gets a sigmoid surrogate gradient (value unchanged)."""
    F = d.footprint
    if d.shape in (0, 1):
        g = (torch.exp(-2.0 * r) - math.exp(-2.0 * F)) / (1.0 - math.exp(-2.0 * F))
    elif d.shape == 2:
        g = 1.0 - r / F
    else:
        hard = (r <= F).to(r.dtype)
        soft = torch.sigmoid((F - r) / 0.05)
        g = hard + (soft - soft.detach())
    return torch.clamp(g, 0.0, 1.0)


def _safe(den: torch.Tensor) -> torch.Tensor:
    """Denominator bounded away from 0 (keeps the sign)."""
    return torch.where(den.abs() < EPS, torch.full_like(den, EPS), den)


def _norm2(x, y):
    """Euclidean norm with a safe gradient at 0."""
    return torch.sqrt(x * x + y * y + EPS)


def _lam(p0x, p0y, wx, wy, ax, ay, bx, by):
    """Ray (p0 + lam w) / line (A, B) intersection parameter."""
    n = _norm2(bx - ax, by - ay)
    ux, uy = (bx - ax) / n, (by - ay) / n
    return (ux * (p0y - ay) - uy * (p0x - ax)) / _safe(wx * uy - wy * ux)


def _cell_dist(qx, qy, px, py, ccx, ccy, chx, chy, larp):
    """Border-search distance (L2 + larp box term) of q to points p with their cells."""
    dx, dy = qx - px, qy - py
    ax, ay = dx.abs(), dy.abs()
    ex = ax / _safe(torch.where(dx < 0, px - ccx + chx, ccx + chx - px))
    ey = ay / _safe(torch.where(dy < 0, py - ccy + chy, ccy + chy - py))
    return (1.0 - larp) * _norm2(dx, dy) + larp * torch.maximum(ex, ey)


def _border_radii(rho, comp, p0, theta, pts, c: _Params):
    """Border radii with first-order gradients: t = t* - (g(t*) - g(t*)_detached) / g'(t*)_detached.

    g(t) = D(p0 + t e, p0) - D(p0 + t e, p_comp): zero on the border between p0's cell and the competitor's.
    """
    px, py, ccx, ccy, chx, chy = pts
    ok = comp >= 0
    j = torch.where(ok, comp, p0)
    ex, ey = torch.cos(theta), torch.sin(theta)

    def g(t, detach=False):
        a = [v.detach() if detach else v for v in (px, py)]
        larp = c.larp.detach() if detach else c.larp
        qx, qy = a[0][p0] + t * ex, a[1][p0] + t * ey
        d0 = _cell_dist(qx, qy, a[0][p0], a[1][p0], ccx[p0], ccy[p0], chx[p0], chy[p0], larp)
        d1 = _cell_dist(qx, qy, a[0][j], a[1][j], ccx[j], ccy[j], chx[j], chy[j], larp)
        return d0 - d1

    with torch.no_grad():
        h = 1e-4
        slope = (g(rho + h, True) - g(rho - h, True)) / (2 * h)
        ok = ok & (slope.abs() > 1e-6)
    val = g(rho)
    step = (val - val.detach()) / torch.where(ok, slope, torch.ones_like(slope))
    return rho - torch.where(ok, step, torch.zeros_like(step))


def _cellular_cv(qx, qy, p0x, p0y, rot, ka, up, rho, c: _Params) -> torch.Tensor:
    """Cellular coordinate cv (same construction as pptbf.cellular_cv) with safe divisions."""
    d = c.d
    delta = d.delta
    dx, dy = qx - p0x, qy - p0y
    sdd = _norm2(dx, dy)
    wx, wy = dx / sdd, dy / sdd
    ta = ka * delta + rot

    def pt(r, t):
        return p0x + r * torch.cos(t), p0y + r * torch.sin(t)

    ax, ay = pt(rho[..., 0], ta)
    bx, by = pt(rho[..., 1], ta + delta)
    mx, my = 0.5 * (ax + bx), 0.5 * (ay + by)
    cx_, cy_ = pt(rho[..., 2], torch.where(up, ta + 2.0 * delta, ta - delta))
    nx = torch.where(up, 0.5 * (bx + cx_), 0.5 * (ax + cx_))
    ny = torch.where(up, 0.5 * (by + cy_), 0.5 * (ay + cy_))
    s0x, s0y = torch.where(up, mx, nx), torch.where(up, my, ny)
    s1x, s1y = torch.where(up, nx, mx), torch.where(up, ny, my)
    ctlx, ctly = torch.where(up, bx, ax), torch.where(up, by, ay)
    lam = _lam(p0x, p0y, wx, wy, s0x, s0y, s1x, s1y)
    sx, sy = p0x + lam * wx, p0y + lam * wy
    t = _norm2(sx - s0x, sy - s0y) / _norm2(s1x - s0x, s1y - s0y)
    qbx = (1 - t) ** 2 * s0x + 2 * t * (1 - t) * ctlx + t * t * s1x
    qby = (1 - t) ** 2 * s0y + 2 * t * (1 - t) * ctly + t * t * s1y
    r0 = _safe(_lam(p0x, p0y, wx, wy, ax, ay, bx, by))
    r1 = _norm2(sx - p0x, sy - p0y)
    r2 = _norm2(qbx - p0x, qby - p0y)
    sm = float(c.smooth.detach())
    if sm < 1.0:
        cv = (1.0 - c.smooth) * (1.0 - sdd / r0) + c.smooth * (1.0 - sdd / r1)
    elif sm < 2.0:
        cv = (2.0 - c.smooth) * (1.0 - sdd / r1) + (c.smooth - 1.0) * (1.0 - sdd / r2)
    else:
        cv = 1.0 - sdd / r2
    cv = torch.where(torch.isfinite(cv), cv, torch.zeros_like(cv))
    cv = torch.clamp(cv, 0.0, 1.0)
    at_point = torch.sqrt(dx.detach() ** 2 + dy.detach() ** 2) < 1e-4
    return torch.where(at_point, torch.ones_like(cv), cv)


def _cellular_weight(cv: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Wc = (exp(sigma (cv - 1)) - exp(-sigma)) / (1 - exp(-sigma))."""
    if float(sigma.detach()) < 1e-6:
        return cv
    return (torch.exp(sigma * (cv - 1.0)) - torch.exp(-sigma)) / (1.0 - torch.exp(-sigma))


def _kernels(qx, qy, pid, T: dict, c: _Params):
    """(ff, ddist, ex, active, pr, v) of the kernels of (pixel, point) pairs, each (M, kmax)."""
    d = c.d
    kd = T["kdraw"][pid]
    chx, chy = T["chx"][pid][:, None], T["chy"][pid][:, None]
    lx = T["ccx"][pid][:, None] + 0.99 * kd[..., 2] * chx
    ly = T["ccy"][pid][:, None] + 0.99 * kd[..., 3] * chy
    lx = c.corr * T["px"][pid][:, None] + (1.0 - c.corr) * lx
    ly = c.corr * T["py"][pid][:, None] + (1.0 - c.corr) * ly
    dlx, dly = (qx[:, None] - lx) / chx, (qy[:, None] - ly) / chy
    th = c.theta_max * kd[..., 4]
    ct, st = torch.cos(th), torch.sin(th)
    u = dlx * ct - dly * st
    v = (dlx * st + dly * ct) / 2.0 ** c.aniso
    rf = _wnorm(u.abs(), v.abs(), c.fnorm, d.fnorm)
    base = 0.5 + 0.5 * torch.cos(math.pi * d.freq * torch.sqrt((c.curv * u) ** 2 + v * v + EPS))
    ff = torch.clamp(base, min=EPS) ** (1.0 / (1e-4 + c.thick))
    s = c.sigcos * (1.0 + (0.5 * kd[..., 5] + 0.5) * c.sigcosvar)
    ddist = rf * s / d.footprint
    active = torch.arange(kd.shape[1], device=kd.device)[None, :] < T["nk"][pid][:, None]
    return ff, ddist, torch.exp(-ddist), active, 0.5 * kd[..., 1] + 0.5, kd[..., 0]


def _first_best(pix: np.ndarray, score: np.ndarray, n_pix: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the (pair, kernel) with the highest score (ties -> first pair, first kernel); score -inf = none."""
    if score.shape[-1] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty
    best_i = np.argmax(score, axis=-1)
    best = score[np.arange(score.shape[0]), best_i]
    top = np.full(n_pix, -np.inf)
    np.maximum.at(top, pix, best)
    hit = np.isfinite(best) & (best == top[pix])
    upix, first = np.unique(pix[hit], return_index=True)
    pair = np.flatnonzero(hit)[first]
    return upix, pair, best_i[pair]


def shade_torch(x, y, ps: pp.PixelStructure, T: dict, c: _Params) -> torch.Tensor:
    """PPTBF V of a chunk in torch (mirrors pptbf.shade)."""
    d = c.d
    h, w = x.shape
    n_pix = h * w
    nbr, val = _t(ps.nbr, x), _t(ps.nbr_valid, x)
    px, py = T["px"], T["py"]
    dx, dy = x[..., None] - px[nbr], y[..., None] - py[nbr]
    win = torch.zeros(nbr.shape, dtype=x.dtype, device=x.device)
    if d.mixture not in (3, 4):
        g = _classical_window(_wnorm(dx.abs(), dy.abs(), c.wnorm, d.wnorm), d)
        win = torch.where(val, (1.0 - c.beta) * g, torch.zeros_like(g))
        if pp.uses_cellular(d):
            p0 = nbr[..., 0]
            rot = d.delta * T["rot_u"][p0]
            ka, up = _t(ps.ka, x), _t(ps.up, x)
            j = torch.stack([ka, ka + 1, torch.where(up, ka + 2, ka - 1)], dim=-1)
            theta = j * d.delta + rot[..., None]
            rho = _border_radii(_t(ps.rho, x), _t(ps.rho_comp, x), p0[..., None].expand_as(j), theta,
                                (px, py, T["ccx"], T["ccy"], T["chx"], T["chy"]), c)
            cv = _cellular_cv(x, y, px[p0], py[p0], rot, ka, up, rho, c)
            wc = c.beta * _cellular_weight(cv, c.sigma_w)
            win = torch.cat([win[..., :1] + wc[..., None], win[..., 1:]], dim=-1)
    cp, sp = torch.cos(c.phi) ** 2, torch.sin(c.phi) ** 2
    if d.mixture in (0, 5):
        V = win.sum(-1) * (1.0 if d.mixture == 0 else cp)
    else:
        sel = (val & (win.detach() != 0.0)) if d.mixture in (1, 2) else val
        pix, kk = torch.nonzero(sel.reshape(n_pix, -1), as_tuple=True)
        pid = nbr.reshape(n_pix, -1)[pix, kk]
        ff, ddist, ex, act, pr, vr = _kernels(x.reshape(-1)[pix], y.reshape(-1)[pix], pid, T, c)
        zero = torch.zeros_like(ff)
        if d.mixture in (1, 2):
            if d.mixture == 1:
                vals = torch.where(vr < 0.0, -0.25 + 0.75 * vr, 0.25 + 0.75 * vr)
                F = 0.5 + 0.5 * torch.where(act, ff * vals * ex, zero).sum(-1)
            else:
                F = torch.where(act, ff * ex, zero).sum(-1) / max(d.npmax // 2, 1)
            F = F * cp + (1.0 - F) * sp
            wsel = win.reshape(n_pix, -1)[pix, kk]
            V = torch.zeros(n_pix, dtype=x.dtype, device=x.device).index_add(0, pix, wsel * F)
        else:
            if d.mixture == 3:
                ok = act & (ddist < 1.0) & (ff > 0.5)
                score = torch.where(ok, pr, torch.full_like(pr, -np.inf))
                value = 2.0 * (ff - 0.5) * ex
            else:
                value = ff * ex
                score = torch.where(act, value, torch.full_like(value, -np.inf))
            upix, pair, ki = _first_best(pix.cpu().numpy(), score.detach().cpu().numpy(), n_pix)
            V = torch.zeros(n_pix, dtype=x.dtype, device=x.device)
            V = V.index_put((_t(upix, x),), value[_t(pair, x), _t(ki, x)])
        V = V.reshape(h, w)
    if d.mixture not in (3, 4) and d.shape == 0:
        ws = win.sum(-1)
        pos = ws.detach() > 0.0
        V = torch.where(pos, V / torch.where(pos, ws, torch.ones_like(ws)), V)
    return torch.clamp(V, min=0.0)


def evaluate_torch(params, width: int, height: int | None = None, *, shift=(0.0, 0.0), pixel_scale: float = 1.0,
                   ref_width: int | None = None, stable: bool = False, device=None, dtype=None) -> torch.Tensor:
    """PPTBF V (H, W) as a torch tensor, differentiable in the continuous entries of `params` (29,).

    Same geometry arguments as pptbf.evaluate. dtype defaults to float64 on CPU (equals numpy to ~1e-6) and
    float32 elsewhere (median difference ~1e-6; isolated pixels, <0.5%, differ where a discrete decision such as
    the bombing test ddist < 1 or a cellular branch flips in float32). The structure is computed on the CPU.
    """
    if not isinstance(params, torch.Tensor):
        params = torch.as_tensor(np.asarray(params, dtype=np.float64))
    device = torch.device(device) if device is not None else params.device
    if dtype is None:
        dtype = torch.float64 if device.type == "cpu" else torch.float32
    params = params.to(device=device, dtype=dtype)
    p_np = params.detach().cpu().double().numpy()
    height = width if height is None else height
    d, zoom, x_np, y_np, st = pp.prepare(p_np, width, height, shift=shift, pixel_scale=pixel_scale,
                                         ref_width=ref_width, stable=stable)
    c = _Params(params, d)
    x0, y0 = (torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)
              for a in pp.base_coords(width, height, shift, pixel_scale, ref_width))
    x, y = domain_coords_torch(x0, y0, c, float(ref_width or width))
    ref = x
    P = st.points
    T = {k: _t(getattr(P, k), ref) for k in ("pstar_x", "pstar_y", "ccx", "ccy", "chx", "chy", "rot_u", "nk",
                                             "kdraw")}
    T["px"] = c.jitter * T["pstar_x"] + (1.0 - c.jitter) * T["ccx"]
    T["py"] = c.jitter * T["pstar_y"] + (1.0 - c.jitter) * T["ccy"]
    rows = pp._chunk_rows(width, st.cand.shape[1] * max(1, d.kmax))
    out = []
    memo = pp.BorderMemo()
    for r0 in range(0, height, rows):
        sl = slice(r0, r0 + rows)
        ps = pp.pixel_structure(x_np[sl], y_np[sl], st.code[sl], st, d, need_comp=True, memo=memo)
        out.append(shade_torch(x[sl], y[sl], ps, T, c))
    return torch.cat(out, dim=0)
