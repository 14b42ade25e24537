"""Spectrum-aware KNN matting: scribble decoding, Laplacian, spectral benefit, n layers, auto mode, sub-splits."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from workers.errors import InputError
from workers.matting import MattingConfig, decode_scribbles, feature_maps, knn_laplacian, matte, pixel_features


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def fine_coarse(n: int = 160, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Grey albedo: a disc of coarse noise in fine noise, same mean and variance; and the disc mask."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:n, :n]
    truth = (xx - n / 2) ** 2 + (yy - n / 2) ** 2 < (0.3 * n) ** 2
    fine = rng.standard_normal((n, n))
    coarse = ndimage.gaussian_filter(rng.standard_normal((n, n)), 4, mode="wrap")
    coarse /= coarse.std()
    g = np.clip(0.4 + 0.12 * np.where(truth, coarse, fine), 0, 1)
    return np.repeat(g[..., None], 3, axis=2).astype(np.float32), truth


def test_decode_scribbles_layers_unknown_and_errors():
    img = np.zeros((20, 30, 4), np.uint8)
    img[..., 3] = 255
    img[2:4, 2:10, :3] = (0, 255, 0)
    img[10:12, 2:10, :3] = (255, 0, 0)
    img[15:17, 2:10, :3] = (0, 0, 255)
    img[15:17, 20:25] = (255, 255, 255, 0)  # transparent: unknown whatever its colour
    lab = decode_scribbles(img, (20, 30))
    # lexicographic RGB order: (0,0,255) < (0,255,0) < (255,0,0)
    assert lab[15, 3] == 0 and lab[2, 3] == 1 and lab[10, 3] == 2
    assert lab[15, 21] == -1 and lab[0, 0] == -1
    assert (lab >= 0).sum() == 3 * 16
    # float images in [0, 1] work the same
    np.testing.assert_array_equal(decode_scribbles(img.astype(np.float32) / 255, (20, 30)), lab)
    with pytest.raises(InputError, match=r"strokes\.png.*30x20.*40x40"):
        decode_scribbles(img, (40, 40), source="strokes.png")
    one = np.zeros((20, 30, 3), np.uint8)
    one[3:5, 3:9] = (200, 10, 10)
    with pytest.raises(InputError, match=r"strokes\.png.*1 layer"):
        decode_scribbles(one, (20, 30), source="strokes.png")


def test_laplacian_is_symmetric_with_zero_row_sums():
    alb, _ = fine_coarse(48)
    fm = feature_maps(alb)
    f, d = pixel_features(fm, np.ones((48, 48), bool))
    assert d == 3 + 3 + 2
    lap = knn_laplacian(f)
    assert abs(lap - lap.T).max() < 1e-12
    np.testing.assert_allclose(np.asarray(lap.sum(axis=1)).ravel(), 0, atol=1e-9)
    assert lap.diagonal().min() > 0  # every pixel has neighbours with positive affinity


def test_spectral_features_separate_equal_mean_textures_with_scribbles():
    alb, truth = fine_coarse(256)
    n = truth.shape[0]
    scrib = np.zeros((n, n, 3), np.uint8)
    scrib[n // 2 - 2:n // 2 + 2, n // 2 - 50:n // 2 + 50] = (255, 0, 0)  # inside the disc
    scrib[4:8, 10:n - 10] = (0, 0, 255)                                   # outside
    scrib[n - 8:n - 4, 10:n - 10] = (0, 0, 255)
    results = {}
    for w in (0.5, 0.0):
        fm = feature_maps(alb, spectrum_dims=16 if w > 0 else 0)
        res = matte(fm, scribbles=scrib, config=MattingConfig(spectral_weight=w))
        np.testing.assert_allclose(res.alphas.sum(axis=0), 1.0, atol=1e-5)
        inside_layer = res.scribbles[n // 2, n // 2]  # layer 1 = red (0,0,255) < (255,0,0)
        assert inside_layer == 1
        results[w] = iou(res.labels == inside_layer, truth)
    print(f"scribbles, IoU with spectral features {results[0.5]:.3f}, without {results[0.0]:.3f}")
    assert results[0.5] >= 0.9
    assert results[0.5] - results[0.0] >= 0.2


def test_auto_mode_recovers_textures_and_is_deterministic():
    alb, truth = fine_coarse(256)
    fm = feature_maps(alb)
    res = matte(fm, n_layers=2, seed=3)
    best = max(iou(res.labels == i, truth) for i in range(2))
    fm0 = feature_maps(alb, spectrum_dims=0)
    res0 = matte(fm0, n_layers=2, config=MattingConfig(spectral_weight=0.0), seed=3)
    best0 = max(iou(res0.labels == i, truth) for i in range(2))
    print(f"auto 2 layers, IoU with spectral features {best:.3f}, without {best0:.3f}; {res.meta}")
    assert best >= 0.9 and best - best0 >= 0.3
    again = matte(fm, n_layers=2, seed=3)
    np.testing.assert_array_equal(again.labels, res.labels)


def test_auto_layer_count_and_three_layers():
    rng = np.random.default_rng(5)
    n = 144
    truth = np.zeros((n, n), int)
    truth[:, n // 3:2 * n // 3] = 1
    truth[:, 2 * n // 3:] = 2
    truth = np.roll(truth, 7, axis=0)
    colours = np.array([[0.6, 0.2, 0.1], [0.1, 0.4, 0.2], [0.5, 0.5, 0.6]], np.float32)
    alb = np.clip(colours[truth] + 0.03 * rng.standard_normal((n, n, 3)), 0, 1).astype(np.float32)
    rough = np.where(truth == 2, 0.8, 0.3)[..., None] + 0.02 * rng.standard_normal((n, n, 1))
    fm = feature_maps(alb, roughness=rough.astype(np.float32))
    res = matte(fm, n_layers="auto")
    assert res.alphas.shape[0] == 3, res.meta
    ious = [max(iou(res.labels == i, truth == t) for i in range(3)) for t in range(3)]
    print(f"auto layer count {res.meta['n_layers']} (silhouette {res.meta['silhouette']}), IoUs {ious}")
    assert min(ious) > 0.95
    # the same with explicit 3 layers and scribbles
    scrib = np.full((n, n), -1)
    for t in range(3):
        ys, xs = np.nonzero(truth == t)
        scrib[ys[::97], xs[::97]] = t
    res3 = matte(fm, scribbles=scrib)
    assert min(iou(res3.labels == t, truth == t) for t in range(3)) > 0.95


def test_sub_split_solves_only_inside_parent():
    alb, truth = fine_coarse(96)
    parent = np.zeros((96, 96), bool)
    parent[:, :60] = True
    res = matte(feature_maps(alb), mask=parent, n_layers=2)
    assert (res.labels[~parent] == -1).all() and (res.labels[parent] >= 0).all()
    assert np.abs(res.alphas[:, ~parent]).max() == 0
    assert res.meta["pixels"] == parent.sum()
    masks = res.masks()
    assert not (masks[0] & masks[1]).any() and ((masks[0] | masks[1]) == parent).all()


def test_bad_layer_count_and_scribbles_outside_parent():
    alb, _ = fine_coarse(32)
    fm = feature_maps(alb)
    with pytest.raises(InputError, match="layers"):
        matte(fm, n_layers=1)
    scrib = np.full((32, 32), -1)
    scrib[0, 0], scrib[0, 31] = 0, 1
    parent = np.zeros((32, 32), bool)
    parent[10:, :] = True
    with pytest.raises(InputError, match="inside"):
        matte(fm, mask=parent, scribbles=scrib, source="s.png")
