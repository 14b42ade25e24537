"""Exact cell-border radii (pptbf_db/border.py) against a fine brute-force march and the larp = 0 closed form."""
import numpy as np
import pytest

from pptbf_db import border
from pptbf_db import pptbf as pp


def _random_queries(rng, q=300, c=12):
    """Rays from p0 = origin among random candidates with random cell side distances."""
    th = rng.uniform(0, 2 * np.pi, q)
    rx, ry = rng.uniform(-1.2, 1.2, (q, c)), rng.uniform(-1.2, 1.2, (q, c))
    inv = tuple(1.0 / rng.uniform(0.05, 0.6, (q, c)) for _ in range(4))
    inv0 = tuple(1.0 / rng.uniform(0.05, 0.6, q) for _ in range(4))
    valid = rng.random((q, c)) > 0.1
    return np.cos(th), np.sin(th), rx, ry, inv, valid, inv0


def _brute(ex, ey, rx, ry, inv, valid, inv0, larp, t_max=4.0, step=2e-4):
    """First sampled t where some valid candidate's ranking distance beats p0's, and that candidate."""
    t = np.arange(step, t_max, step)
    rho, comp = np.full(ex.shape, border.NO_EXIT), np.full(ex.shape, -1)
    for i in range(ex.shape[0]):
        qx, qy = t * ex[i], t * ey[i]
        d0 = pp.rank_distance(qx, qy, tuple(np.full(t.shape, v[i]) for v in inv0), 2.0, larp)
        dj = pp.rank_distance(qx[:, None] - rx[i], qy[:, None] - ry[i], tuple(v[i][None] for v in inv), 2.0, larp)
        dj = np.where(valid[i], dj, np.inf)
        win = dj.min(axis=1) < d0
        if win.any():
            k = int(np.argmax(win))
            rho[i], comp[i] = t[k], int(np.argmin(dj[k]))
    return rho, comp


@pytest.mark.parametrize("larp", [0.0, 0.3, 0.8, 1.0])
def test_first_exit_matches_a_fine_march(larp):
    rng = np.random.default_rng(int(larp * 10))
    ex, ey, rx, ry, inv, valid, inv0 = _random_queries(rng)
    rho, comp = border.first_exit(ex, ey, rx, ry, inv, valid, inv0, larp)
    b_rho, b_comp = _brute(ex, ey, rx, ry, inv, valid, inv0, larp)
    found = b_comp >= 0
    assert found.mean() > 0.9
    # the march samples every 2e-4: its first winning sample lies just past the exact exit
    err = b_rho[found] - rho[found]
    assert np.all(err >= -1e-5) and np.all(err <= 2e-4 + 1e-5), (err.min(), err.max())
    assert np.mean(comp[found] == b_comp[found]) > 0.99
    assert np.all((comp[~found] < 0) | (rho[~found] >= 4.0 - 2e-4))     # none, or past the sampled range


def test_larp_zero_closed_form():
    """Spec §2.6: rho = min over b_j > 0 of |p_j - p0|^2 / (2 b_j), b_j = (p_j - p0) . e."""
    rng = np.random.default_rng(5)
    ex, ey, rx, ry, inv, valid, inv0 = _random_queries(rng, q=500)
    rho, _ = border.first_exit(ex, ey, rx, ry, (), valid, (), 0.0)
    b = ex[:, None] * rx + ey[:, None] * ry
    t = np.where(valid & (b > 0), (rx * rx + ry * ry) / (2 * np.where(b > 0, b, 1.0)), np.inf).min(axis=1)
    t = np.where(np.isfinite(t), t, border.NO_EXIT)
    assert np.allclose(rho, t, rtol=1e-9, atol=1e-12)


def test_float32_radii_stay_close_to_float64():
    rng = np.random.default_rng(7)
    args = _random_queries(rng, q=2000)
    r64, c64 = border.first_exit(*args, 0.5)
    f = np.float32
    ex, ey, rx, ry, inv, valid, inv0 = args
    r32, c32 = border.first_exit(ex.astype(f), ey.astype(f), rx.astype(f), ry.astype(f),
                                 tuple(v.astype(f) for v in inv), valid, tuple(v.astype(f) for v in inv0), 0.5)
    assert np.percentile(np.abs(r32 - r64) / r64, 99.9) < 1e-5
    assert np.mean(c32 == c64) > 0.999


def test_render_radii_are_the_cell_borders_among_all_points():
    """Inside a render: each sector radius is where the ray from the pixel's closest point first meets a point
    nearer (ranking distance over every valid point of the image), and it does not depend on the image size."""
    p = np.zeros(pp.N_PARAMS)
    vals = dict(tiling=7, jitter=0.6, resolution=16, window_shape=1, window_arity=4, window_larp=0.4,
                window_norm=2.0, window_blend=0.7, window_sigma=1.0, feature_mixture=0, aspect_ratio=1.0)
    for k, v in vals.items():
        p[pp.PARAM_INDEX[k]] = v
    d, zoom, x, y, st = pp.prepare(p, 64)
    ps = pp.pixel_structure(x, y, st.code, st, d)
    P = st.points
    rng = np.random.default_rng(0)
    pick = rng.choice(64 * 64, 150, replace=False)
    p0 = ps.nbr[..., 0].ravel()[pick]
    ka = ps.ka.ravel()[pick]
    theta = ka * d.delta + d.delta * P.rot_u[p0]
    valid = np.zeros(P.px.shape[0], dtype=bool)          # every valid point of the table (ring included)
    valid[np.unique(st.border.nbr[st.border.valid])] = True
    valid[st.border.row >= 0] = True
    others = np.flatnonzero(valid)
    for i in range(pick.size):
        j = others[others != p0[i]]
        e = (np.cos(theta[i]), np.sin(theta[i]))
        inv = tuple(v[j][None] for v in P.inv)
        inv0 = tuple(np.array([v[p0[i]]]) for v in P.inv)
        b_rho, _ = _brute(np.array([e[0]]), np.array([e[1]]), (P.px[j] - P.px[p0[i]])[None],
                          (P.py[j] - P.py[p0[i]])[None], inv, np.ones((1, j.size), bool), inv0, d.larp,
                          t_max=2.0, step=1e-3)
        assert abs(ps.rho.reshape(-1, 3)[pick[i], 0] - b_rho[0]) < 1.2e-3
    # a wider render of the same pattern has the same radii on the shared pixels
    d2, _, x2, y2, st2 = pp.prepare(p, 96, ref_width=64)
    ps2 = pp.pixel_structure(x2[:64, :64], y2[:64, :64], st2.code[:64, :64], st2, d2)
    assert np.allclose(ps2.rho, ps.rho, atol=1e-6)
