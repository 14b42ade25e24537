"""Instance split: component filtering, outliers, kinds of synthetic tiles, partition of the parent."""
from __future__ import annotations

import numpy as np

from workers.instances import InstanceConfig, cluster_instances, find_instances, separate_cells, split_instances


def tiles(n: int = 256, tile: int = 32, gap: int = 3, seed: int = 0):
    """Channels (r,g,b,height,roughness) of a tile grid with two random kinds, the tile mask, truth kind per pixel."""
    rng = np.random.default_rng(seed)
    g = n // tile
    kind = rng.integers(0, 2, (g, g))
    img = np.zeros((n, n, 5), np.float32)
    truth = np.full((n, n), -1)
    s = tile - gap
    xx = np.arange(s)[None, :]
    for i in range(g):
        for j in range(g):
            sl = (slice(i * tile, i * tile + s), slice(j * tile, j * tile + s))
            if kind[i, j] == 0:  # speckled, brighter
                v = 0.55 + 0.08 * rng.standard_normal((s, s))
            else:                # striped, period 6 px, random phase
                v = 0.45 + 0.1 * np.sin(xx * 2 * np.pi / 6 + rng.random() * 6) + 0.03 * rng.standard_normal((s, s))
            img[sl] = v[..., None]
            truth[sl] = kind[i, j]
    return np.clip(img, 0, 1), truth >= 0, truth, kind


def test_two_kinds_of_tiles_are_recovered():
    img, mask, truth, kind = tiles()
    res = split_instances(mask, img)
    n = int(res.labels.max())
    assert n == kind.size == 64
    true_kind = np.array([np.bincount(truth[res.labels == i]).argmax() for i in range(1, n + 1)])
    acc = max((res.kinds == true_kind).mean(), (res.kinds == 1 - true_kind).mean())
    print(f"instances {n}, kinds {res.meta['kinds']}, labelled right {acc:.3f}, shares {res.shares}")
    assert len(res.masks) == 2 and acc >= 0.95
    np.testing.assert_allclose(sorted(res.shares), sorted([(kind == 0).mean(), (kind == 1).mean()]), atol=0.05)
    # the kinds' masks partition the parent; mortar gaps are outside the parent here
    stack = np.stack(res.masks)
    assert (stack.sum(0) == mask).all()


def test_one_kind_stays_one_cluster():
    img, mask, truth, kind = tiles(seed=1)
    img[mask] = img[mask & (truth == 0)][: mask.sum()].mean(0)  # flat
    rng = np.random.default_rng(2)
    img = np.clip(img + 0.05 * rng.standard_normal(img.shape).astype(np.float32), 0, 1)
    res = split_instances(mask, img)
    assert res.meta["kinds"] == 1 and res.shares == [1.0]


def test_small_components_and_size_outliers_are_dropped_and_gaps_filled():
    mask = np.zeros((200, 200), bool)
    for i in range(4):
        for j in range(4):
            mask[10 + 40 * i:10 + 40 * i + 20, 10 + 40 * j:10 + 40 * j + 20] = True  # 16 normal 20x20
    mask[170:175, 10:60] = True     # 5 px tall: dropped (shorter side < 10)
    mask[165:199, 120:199] = True   # a giant: size outlier among 17
    labels, info = find_instances(mask, InstanceConfig())
    assert info["components"] == 18 and info["small"] == 1 and info["outliers"] == 1 and info["kept"] == 16
    assert labels.max() == 16 and labels[172, 30] == 0 and labels[180, 150] == 0
    img = np.repeat(mask[..., None].astype(np.float32) * 0.5, 5, axis=2)
    res = split_instances(mask, img)
    # dropped pixels of the parent still belong to a kind (nearest kept instance)
    assert (np.stack(res.masks).sum(0) == mask).all()
    assert res.meta["gap_fraction"] > 0


def test_open_close_removes_one_pixel_bridges():
    mask = np.zeros((40, 80), bool)
    mask[5:35, 5:35] = True
    mask[5:35, 45:75] = True
    mask[20, 35:45] = True  # a 1-px bridge joins the two squares
    assert find_instances(mask)[1]["kept"] == 1
    assert find_instances(mask, InstanceConfig(open_close=True))[1]["kept"] == 2


def test_cluster_order_and_threshold():
    rng = np.random.default_rng(0)
    a = rng.normal(0, 0.02, (30, 4))
    b = rng.normal(0, 0.02, (10, 4)) + [0.8, 0, 0, 0]
    kinds = cluster_instances(np.concatenate([b, a]), 1.5)
    assert (kinds[:10] == 1).all() and (kinds[10:] == 0).all()  # the bigger kind comes first
    assert (cluster_instances(np.concatenate([b, a]), 100.0) == 0).all()


def test_cluster_count_is_capped_by_max_kinds():
    rng = np.random.default_rng(1)
    centres = np.eye(6) * 3.0
    feats = np.concatenate([c + rng.normal(0, 0.02, (8, 6)) for c in centres])
    assert cluster_instances(feats, 1.5).max() + 1 == 6
    capped = cluster_instances(feats, 1.5, max_kinds=3)
    assert capped.max() + 1 == 3
    # the cap merges whole clusters: each original group stays inside one kind
    assert all(np.unique(capped[i * 8:(i + 1) * 8]).size == 1 for i in range(6))


def test_cut_at_the_necks_gives_one_piece_per_tile():
    """Tiles joined through 6 px gaps in 3 px grout, a gap in every tile's right and lower joint: one component;
    cut at the necks, one piece per tile, each piece inside one tile, touching the border tiles joined."""
    img, mask, truth, _ = tiles(n=128, tile=32, gap=3)
    tile_id = (np.arange(128)[:, None] // 32) * 4 + np.arange(128)[None, :] // 32
    joined = mask.copy()
    for c in range(29, 128, 32):
        for a in range(0, 128, 32):
            joined[a + 12:a + 18, c:c + 3] = True   # gap in the vertical joint
            joined[c:c + 3, a + 12:a + 18] = True   # and in the horizontal one
    assert find_instances(joined)[1]["kept"] == 1
    cut = separate_cells(joined, 32 / 3)
    labels, info = find_instances(cut)
    assert info["kept"] == 16, info
    for k in range(1, 17):
        ids, counts = np.unique(tile_id[(labels == k) & mask], return_counts=True)
        assert counts.max() >= 0.97 * counts.sum(), (k, ids, counts)
    assert (cut[mask] ^ mask[mask]).mean() < 0.06


def test_instances_cut_by_the_tile_border_are_joined():
    mask = np.zeros((64, 64), bool)
    mask[20:34, 58:64] = True  # one 14x12 brick wrapping around the left/right border
    mask[20:34, 0:6] = True
    mask[0:5, 30:42] = True    # and one 10x12 wrapping top/bottom
    mask[59:64, 30:42] = True
    labels, info = find_instances(mask)
    assert info["components"] == 2 and info["kept"] == 2 and info["small"] == 0
    assert labels[25, 60] == labels[25, 2] and labels[2, 35] == labels[61, 35] != labels[25, 2]
    flat = find_instances(mask, InstanceConfig(wrap=False))[1]
    assert flat["components"] == 4 and flat["kept"] == 0  # each half is under 10 px on one side
