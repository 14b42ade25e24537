"""Per-piece variation of instance kinds (workers.pieces): the spread of the pieces' offsets from the surface's
background is measured and taken out of the noise's input, and drawn back, one offset per piece, by graph nodes."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from workers import graph as G
from workers.errors import GraphError
from workers.instances import piece_labels
from workers.nodes.instances import sample_instances
from workers.pieces import PieceStats, Trend, kind_piece_labels, piece_residual, piece_trend

N = 192
COV = np.array([[0.004, 0.002, 0.0], [0.002, 0.003, 0.0], [0.0, 0.0, 0.001]])


def _bricks(course: int = 12, length: int = 24, joint: int = 2, n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """Running-bond cells (bool, mortar False) and their piece labels (1..n, 0 on the mortar)."""
    y, x = np.mgrid[:n, :n]
    row = y // course
    xs = (x + (row % 2) * (length // 2)) % n
    cells = (y % course >= joint) & (xs % length >= joint)
    return cells, ndimage.label(cells)[0]


def _shaded(seed: int = 0, within: float = 0.05, n: int = N) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                      np.ndarray]:
    """(image, cells, labels, per-piece offsets): mean colour + one N(0, COV) offset per brick + white noise."""
    rng = np.random.default_rng(seed)
    cells, lab = _bricks(n=n)
    off = rng.multivariate_normal(np.zeros(3), COV, size=lab.max() + 1)
    img = np.float32([0.4, 0.2, 0.1]) + np.where(cells[..., None], off[lab], 0.0)
    img = img + within * rng.standard_normal(img.shape)
    return img.astype(np.float32), cells, lab, off


def _piece_means(img: np.ndarray, lab: np.ndarray) -> np.ndarray:
    ids = np.arange(1, lab.max() + 1)
    return np.stack([ndimage.mean(img[..., c], lab, ids) for c in range(img.shape[-1])], 1)


def test_residual_takes_out_each_pieces_mean_and_the_stats_recover_the_spread():
    """Every piece's mean in the residual is the kind's mean (to float precision), the mortar is untouched, and
    the between-piece covariance comes back within 15 % (diagonal) of the drawn offsets' although strong
    within-piece noise (std 0.3 over ~200 px pieces) inflates the raw covariance of the means by up to 40 %."""
    img, cells, lab, off = _shaded(within=0.3, n=384)
    res, stats = piece_residual(img, lab, cells)
    ids = np.arange(1, lab.max() + 1)
    kind_mean = img[cells].mean(0)
    assert np.abs(_piece_means(res, lab) - kind_mean).max() < 1e-5
    assert np.allclose(res[~cells], img[~cells])
    drawn = np.diag(np.cov(off[ids].T))
    raw = np.diag(np.cov(_piece_means(img, lab).T))
    print(f"{stats.pieces} pieces; cov diag {np.diag(stats.cov)} (drawn {drawn}, raw {raw})")
    assert stats.pieces == lab.max()
    assert (np.abs(np.diag(stats.cov) - drawn) / drawn).max() < 0.15 < (np.abs(raw - drawn) / drawn).max()
    # few pieces: no spread to estimate
    few = np.where(lab <= 3, lab, 0)
    assert not piece_residual(img, few, few > 0)[1].cov.any()


def test_offsets_are_measured_against_the_surfaces_drift():
    """A drift across the map (a height integrated from normals, stains) ten times the offsets' variance, under
    two kinds whose means differ by 0.5: each kind's offsets' covariance comes back within 20 % of the drawn
    one (against the kind's mean instead: 3x too large or more)."""
    n = 384
    img, cells, lab, off = _shaded(seed=3, n=n)
    y, x = np.mgrid[:n, :n] / n
    drift = 0.25 * np.sin(2 * np.pi * x + 1.0) * np.cos(2 * np.pi * y) + 0.15 * np.sin(2 * np.pi * (x + y))
    kinds = np.random.default_rng(1).integers(0, 2, lab.max())
    kind_shift = np.concatenate([[0.0], 0.5 * kinds])[lab]
    img = (img + (drift + kind_shift)[..., None] * cells[..., None]).astype(np.float32)
    trend = piece_trend(img, lab, kinds)
    for k in (0, 1):
        kl = kind_piece_labels(lab, kinds, k)
        mine = cells & (kl > 0)
        stats = piece_residual(img, kl, mine, trend)[1]
        flat = piece_residual(img, kl, mine, Trend(np.zeros_like(trend.field), trend.density, 1e9))[1]
        ids = np.unique(kl[mine])
        drawn = np.diag(np.cov(off[ids].T))
        err = np.abs(np.diag(stats.cov) - drawn) / drawn
        print(f"kind {k}: {ids.size} pieces; cov diag {np.diag(stats.cov)} (drawn {drawn}; against the kind's "
              f"mean {np.diag(flat.cov)})")
        assert err.max() < 0.2 and (np.diag(flat.cov) > 3 * drawn).all()


def test_kind_pieces_follow_the_instance_split():
    """The pieces of one kind are the instance labels of that kind, the gaps given to the nearest piece, so
    the kinds' pieces partition the labelled area exactly as the kind masks do."""
    cells, lab = _bricks()
    kinds = np.arange(lab.max()) % 3
    per = [kind_piece_labels(lab, kinds, k) for k in range(3)]
    assert all(((p > 0) == np.isin(p, np.nonzero(kinds == k)[0] + 1)).all() for k, p in enumerate(per))
    assert (sum((p > 0).astype(int) for p in per) == 1).all()        # nearest-filled: the whole plane
    assert (per[1][cells] == np.where(kinds[lab[cells] - 1] == 1, lab[cells], 0)).all()


def test_offsets_node_is_one_draw_per_piece_with_the_stored_covariance():
    """piece_offsets over piece_labels: constant on each piece, zero outside, the empirical covariance of the
    pieces' values within 30 % of cov (diagonal; 256 pieces), the same for the same seed and another for
    another seed; the labels are the partition sample_instances draws its kinds on."""
    cells, lab = _bricks(course=12, length=24)
    ctx = G.EvalContext(width=N, height=N, seed=5, working_size=(N, N))
    labels_t, offsets_t = G.NODE_TYPES["piece_labels"], G.NODE_TYPES["piece_offsets"]
    lab_img = labels_t.evaluate({"separate": 0.0}, {"parent": cells[..., None].astype(np.float32)}, ctx, "pl")
    assert (np.rint(lab_img[..., 0]).astype(int) == piece_labels(cells)).all()
    params = {"cov": COV.tolist()}
    offsets_t.validate(params)
    off = offsets_t.evaluate(params, {"labels": lab_img}, ctx, "po")
    assert off.shape == (N, N, 3) and not off[~cells].any()
    ids = np.arange(1, lab.max() + 1)
    per = np.stack([ndimage.mean(off[..., c], lab, ids) for c in range(3)], 1)
    spread = np.stack([ndimage.standard_deviation(off[..., c], lab, ids) for c in range(3)], 1)
    assert spread.max() < 1e-6
    emp = np.cov(per.T)
    print(f"{ids.size} pieces: empirical diag {np.diag(emp)} vs {np.diag(COV)}")
    assert (np.abs(np.diag(emp) - np.diag(COV)) / np.diag(COV)).max() < 0.3
    again = offsets_t.evaluate(params, {"labels": lab_img}, ctx, "po")
    other = offsets_t.evaluate(params, {"labels": lab_img}, G.EvalContext(width=N, height=N, seed=6), "po")
    assert np.array_equal(off, again) and not np.allclose(off, other)
    kinds = sample_instances(cells, [0.5, 0.5], np.random.default_rng(0))
    assert all(len(np.unique(kinds[lab == i])) == 1 for i in ids[:50])
    for bad in ({"cov": [[1.0, 0.0]]}, {"cov": "x"}, {"cov": [[-1.0]]}, {}):
        with pytest.raises(GraphError):
            offsets_t.validate(bad)


def test_stats_round_trip():
    s = PieceStats(COV, 40)
    t = PieceStats.from_dict(s.to_dict())
    assert t.pieces == 40 and np.allclose(t.cov, COV)
    r = PieceStats(COV, 40, ramp=np.array([[0.0, 0.004]]))
    assert np.allclose(PieceStats.from_dict(r.to_dict()).ramp, [[0.0, 0.004]]) and "ramp" not in s.to_dict()


def _slates(slope: float, seed: int = 0, n: int = N, wrap_shift: int = 5) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """(height, cells, labels): bricks whose height rises by ``slope`` per px down each piece (about its centroid)
    plus one offset per piece and white noise, the whole rolled by ``wrap_shift`` px so that pieces wrap around
    the tile's edges (joined across them, as the decomposition's labels are)."""
    rng = np.random.default_rng(seed)
    cells, _ = _bricks(course=16, length=24, joint=2, n=n)
    y, x = np.mgrid[:n, :n]
    row = y // 16
    lab = np.where(cells, 1 + row * (n // 24) + ((x + (row % 2) * 12) % n) // 24, 0)   # one label across the edge
    y = y.astype(np.float64)
    ids = np.arange(1, lab.max() + 1)
    cy = np.zeros(lab.max() + 1)
    cy[ids] = ndimage.mean(y, lab, ids)
    off = 0.03 * rng.standard_normal(lab.max() + 1)
    h = 0.5 + np.where(cells, off[lab] + slope * (y - cy[lab]), 0.0) + 0.01 * rng.standard_normal((n, n))
    roll = lambda a: np.roll(a, (wrap_shift, wrap_shift), (0, 1))  # noqa: E731
    return roll(h).astype(np.float32), roll(cells), roll(lab)


def test_ramps_of_sloped_pieces_are_measured_and_taken_out():
    """Pieces whose height rises 0.004 per px down each (14 px high: 0.052 over a piece, as roof_slates_02's
    slates at 512 px) with pieces wrapping around the tile's edges: the ramp comes back within 5 % with no slope
    across, the residual inside the pieces has no ramp left (one would explain under RAMP_MIN_SHARE of it) and
    the offsets' spread is unchanged (within 15 %); flat pieces get no ramp."""
    h, cells, lab = _slates(0.004)
    lab = np.where(cells, lab, 0)
    res, stats = piece_residual(h, lab, cells)
    assert stats.ramp is not None
    gx, gy = stats.ramp[0]
    print(f"ramp {stats.ramp[0]}; cov {stats.cov[0, 0]:.5f} (drawn 0.0009)")
    assert abs(gy - 0.004) < 0.05 * 0.004 and abs(gx) < 0.05 * 0.004
    assert 6.0 <= stats.reach[1] <= 8.0 and 10.0 <= stats.reach[0] <= 12.0      # 14 x 22 px pieces
    from workers.pieces import piece_coordinates, piece_ramp
    left, _ = piece_ramp(res[cells][:, None] - res[cells].mean(), piece_coordinates(lab, cells))
    assert left is None
    assert abs(stats.cov[0, 0] - 0.0009) < 0.15 * 0.0009
    flat, flat_cells, flab = _slates(0.0)
    assert piece_residual(flat, np.where(flat_cells, flab, 0), flat_cells)[1].ramp is None


def test_ramps_node_tilts_each_piece_about_its_centroid():
    """piece_ramps over piece_labels and over a pptbf node's cells: inside every piece the value rises by the
    stored slope per working px (x and y, at scale 1 and, per output px, halved at scale 2), its mean over the
    piece is zero, and it is zero outside the pieces (labels); cells are connected regions of one key (distant
    cells that share a key each get their own centroid); with a reach the ramp stops at it."""
    cells, lab = _bricks(course=16, length=24)
    ramp = [[0.001, 0.004]]
    node = G.NODE_TYPES["piece_ramps"]
    node.validate({"ramp": ramp})
    for scale in (1.0, 2.0):
        ctx = G.EvalContext(width=N, height=N, scale=scale, working_size=(N, N))
        out = node.evaluate({"ramp": ramp}, {"labels": lab[..., None].astype(np.float32)}, ctx, "pr")[..., 0]
        inner = ndimage.binary_erosion(cells) & np.roll(cells, -1, 0) & np.roll(cells, -1, 1)
        dy, dx = (np.roll(out, -1, 0) - out)[inner], (np.roll(out, -1, 1) - out)[inner]
        assert np.allclose(dy, 0.004 / scale, atol=1e-6) and np.allclose(dx, 0.001 / scale, atol=1e-6)
        assert not out[~cells].any()
        ids = np.arange(1, lab.max() + 1)
        assert np.abs(ndimage.mean(out, lab, ids)).max() < 1e-5
    # cell keys cover every pixel and are hashes: distant cells share one (here every fifth piece)
    keys = np.where(lab > 0, 1 + lab % 5, 0).astype(np.float32)[..., None]
    ctx = G.EvalContext(width=N, height=N, working_size=(N, N))
    by_cell = node.evaluate({"ramp": ramp}, {"cells": keys}, ctx, "pr")[..., 0]
    assert np.allclose((np.roll(by_cell, -1, 0) - by_cell)[inner], 0.004, atol=1e-6)
    assert np.abs(ndimage.mean(by_cell, lab, ids)).max() < 1e-5
    # the distance from the centroid is clipped at the reach: at most 2 px of slope each way
    clipped = node.evaluate({"ramp": ramp, "reach": [2.0, 2.0]}, {"labels": lab[..., None].astype(np.float32)},
                            ctx, "pr")[..., 0]
    assert np.abs(clipped).max() <= 2 * (0.004 + 0.001) + 1e-7 < np.abs(out).max()
    for bad in ({"ramp": [[1.0]]}, {"ramp": "x"}, {"ramp": [[np.nan, 0.0]]}, {},
                {"ramp": ramp, "reach": [1.0]}, {"ramp": ramp, "reach": [0.0, 1.0]}):
        with pytest.raises(GraphError):
            node.validate(bad)
