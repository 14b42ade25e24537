"""n-way splits partition the plane: the masks of a split sum to 1 at every pixel (any size, scale, seed), and a
material of known flat layers comes back with every pixel one layer's value (or a convex mix across a blurred
edge) and each layer's coverage within 5 % of the truth."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from service.pipeline import fit_region
from workers import graph as G
from workers import noise as N
from workers.actors import MaskFitter
from workers.assemble import build_material
from workers.maps import Material
from workers.masks import MaskFitConfig
from workers.tree import MaskNode, root_node

SIZE = 96
# grey-free colours, far apart: a pixel's value says which layer (or which pair across an edge) it came from
ALBEDOS = np.float32([[0.8, 0.1, 0.1], [0.1, 0.7, 0.1], [0.1, 0.1, 0.8], [0.7, 0.7, 0.2]])
WEIGHTS = {3: (1.0, 0.85, 0.7), 4: (1.0, 0.9, 0.8, 0.7)}


def _labels(n: int, seed: int = 4) -> np.ndarray:
    """Layer labels from the argmax of n smoothed, weighted noise fields (blobs of unequal coverage)."""
    rng = np.random.default_rng(seed)
    fields = np.stack([w * ndimage.gaussian_filter(rng.standard_normal((SIZE, SIZE)), 5.0, mode="wrap")
                       for w in WEIGHTS[n]])
    fields /= fields.std(axis=(1, 2), keepdims=True)
    return np.argmax(fields * np.asarray(WEIGHTS[n])[:, None, None], axis=0)


@pytest.fixture(scope="module")
def fitter() -> MaskFitter:
    return MaskFitter()


def _procedural(n: int, fitter: MaskFitter) -> tuple[G.ProceduralMaterial, np.ndarray]:
    """Fit an n-layer synthetic through the masks stage's fit regions and assemble its graph."""
    lab = _labels(n)
    albedo = ALBEDOS[:n][lab]
    tree = root_node(SIZE, SIZE)
    tree.method = "matting"
    tree.children = [MaskNode(f"root.{i}", lab == i) for i in range(n)]
    cfg = MaskFitConfig(max_evals=20, rounds=1, time_budget_s=15.0, lattice=False, validate=0)
    fits = {}
    for c in tree.children[:-1]:
        fit = fitter.fit(c.mask, valid=fit_region(tree, tree, c), config=cfg, seed=1)
        fits[c.id] = {"fit": fit.to_dict()}
    noises = {(c.id, "albedo"): N.fit_noise(albedo, c.mask).to_params() for c in tree.children}
    mat = Material(albedo=albedo, name=f"layers{n}")
    proc = build_material(mat, tree, noises, fits, seed=0)
    return proc, np.bincount(lab.ravel(), minlength=n) / lab.size


def _owner(albedo: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(nearest layer per pixel, distance to it)."""
    d = np.linalg.norm(albedo[..., None, :] - ALBEDOS[:n][None, None], axis=-1)
    return np.argmin(d, axis=-1), np.min(d, axis=-1)


def _split_masks(proc: G.ProceduralMaterial, ctx: G.EvalContext) -> np.ndarray:
    """The root blend's masks (L x H x W) as the graph renders them."""
    node = proc.node("blend_root_albedo")
    ports = sorted((k for k in node["inputs"] if k.startswith("mask")), key=lambda k: int(k[4:]))
    return np.stack([G.evaluate_node(proc, node["inputs"][k], ctx)[..., 0] for k in ports])


@pytest.mark.parametrize("n", [3, 4])
def test_layers_partition_and_keep_their_values(n, fitter):
    proc, truth = _procedural(n, fitter)
    assert proc.node("blend_root_albedo")["params"]["normalise"] is True
    # the masks of the split sum to exactly 1 at every pixel, whatever the extent, scale and realisation
    for w, h, scale, seed in ((SIZE, SIZE, 1.0, 0), (160, 72, 2.0, 7), (64, 128, 0.5, 3)):
        ctx = G.EvalContext(w, h, scale, seed, tuple(proc.working_size))
        m = _split_masks(proc, ctx)
        assert m.min() >= 0.0 and np.abs(m.sum(axis=0) - 1.0).max() < 1e-6, (w, h, scale, seed)
    # every pixel takes one layer's value; the coverage of each is within 5 % (absolute) of the truth
    cover = np.zeros(n)
    for seed in (1, 2, 3):
        alb = G.evaluate(proc, 2 * SIZE, 2 * SIZE, seed=seed)["albedo"]
        owner, dist = _owner(alb, n)
        assert dist.max() < 2e-3, f"a pixel is no layer's value (distance {dist.max():.3f})"
        cover += np.bincount(owner.ravel(), minlength=n) / owner.size / 3
    assert np.abs(cover - truth).max() <= 0.05, (cover.round(3), truth.round(3))


def test_blurred_edges_blend_convexly(fitter):
    """With blurred masks (different sigmas per layer) a pixel is a convex mix of the layers: the normalised
    blend never leaves the layers' hull (an unnormalised sum of blurred masks does)."""
    proc, _ = _procedural(3, fitter)
    G.set_param(proc, "blend_root_albedo.sigmas", [0.5, 2.0, 4.0])
    alb = G.evaluate(proc, SIZE, SIZE, seed=2)["albedo"].reshape(-1, 3)
    # barycentric weights over the three (affinely independent) layer colours sum to 1 and are all >= 0
    A = ALBEDOS[:3].T.astype(np.float64)
    wts = np.linalg.solve(A, alb.T)
    assert wts.min() > -1e-4 and np.abs(wts.sum(axis=0) - 1).max() < 1e-4
    mixed = (wts.max(axis=0) < 0.99).mean()
    assert mixed > 0.05, f"blurs should mix layers along the edges ({mixed:.3f} of pixels mixed)"
    proc.node("blend_root_albedo")["params"]["normalise"] = False
    raw = G.evaluate(proc, SIZE, SIZE, seed=2)["albedo"].reshape(-1, 3)
    wr = np.linalg.solve(A, raw.T)
    assert np.abs(wr.sum(axis=0) - 1).max() > 0.05  # what the normalisation prevents
