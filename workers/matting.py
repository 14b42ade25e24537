"""Spectrum-aware KNN matting (paper 4.1) with n layers, scribble decoding and automatic seeding.

Feature per pixel: sRGB albedo (3), height, roughness, the spectral PCA-3 times ``spectral_weight``, and
xy divided by the image diagonal. Maps that are missing are left out (the feature dimension shrinks).
Height is high-passed (normal-integrated heights drift at large scales) and height/roughness are scaled
by their 1st..99th percentiles. The local spectra (workers.spectrum) are reduced to PCA-16 once per
material; each split re-fits the PCA-3 and the min-max range on its parent's pixels only.
Neighbours come from two KD-tree passes (K=10 with full xy weight, then K=2 with xy/100: non-local),
approximate (cKDTree eps=2: ~83% recall of the exact 10-NN at 3-4x the speed; measured on real bricks);
affinity max(0, 1 - L1 / (d + 2)). For each layer i we solve (D - A + lambda*S) alpha_i = lambda*v_i by
Jacobi-preconditioned CG over the pixels of the parent mask only. The system matrix is the same for all
layers and (D - A) 1 = 0, so the alphas sum to 1 exactly: n-1 solves are run and the last layer is
1 - sum of the others (equal to solving it). Binary masks are the argmax of the alphas, times the parent.

Scribbles: an HxW(x3|x4) image; every distinct colour (quantised to 8 bits) is one layer, ordered by colour
value (lexicographic RGB); black (0,0,0) and fully transparent pixels (alpha = 0) are "unknown".

Automatic mode: a spherical Gaussian mixture (one variance per cluster; EM from a k-means++ start, fixed
seed) on a 10k-pixel subsample of the features without xy, colour channels smoothed (sigma 1 px) inside
the parent;
"auto" picks the smallest k in 2..5 whose mean silhouette (on a 2000-pixel subsample) is within 0.02 of
the best k's: parsimony, because the extra clusters that win by a hair are thin bands along region
boundaries (where window spectra and smoothed colours mix two regions). Scribbles are the
confident pixels: GMM posterior >= ``confidence`` (0.98) and still in the cluster after a 1-pixel erosion.
BIC was tried for the count: on real maps it always asks for the most components. Layers are ordered
by decreasing area of their cluster (largest first).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy import ndimage
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree
from scipy.special import logsumexp

from .errors import InputError
from .spectrum import SpectrumConfig, minmax, pca_project, spectrum_stack

logger = logging.getLogger(__name__)

MAX_LAYERS = 8
AUTO_RANGE = (2, 5)


@dataclass
class MattingConfig:
    """Reference defaults of the spectrum-aware KNN matting."""

    spectral_weight: float = 0.5
    spectral_dims: int = 3
    k: int = 10                   # first pass, full xy weight
    k_nonlocal: int = 2           # second pass, xy / 100
    nonlocal_xy_scale: float = 0.01
    knn_eps: float = 2.0          # cKDTree approximate search: neighbours within (1+eps) x true distance
    lam: float = 100.0
    tol: float = 1e-5
    maxiter: int = 2000
    confidence: float = 0.98      # auto mode: GMM posterior a pixel needs to become a seed
    erosion: int = 1              # auto mode: erode each cluster before taking seeds
    seed_smooth: float = 1.0      # auto mode: Gaussian sigma (px) of the colour channels used for clustering
    cluster_sample: int = 10_000  # auto mode: pixels the GMM is fitted on
    silhouette_sample: int = 2000
    auto_tolerance: float = 0.02  # "auto": smallest k whose silhouette is within this of the best


@dataclass
class FeatureMaps:
    """Per-pixel maps the features are built from, plus the spectrum stack (PCA-16, cached per material)."""

    colour: np.ndarray            # HxWxC: sRGB albedo, height, roughness (those present), in [0,1]
    spectrum: np.ndarray | None   # HxWxP: global PCA of the local spectra (re-projected per parent)
    names: list[str] = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int]:
        return self.colour.shape[:2]


@dataclass
class MatteResult:
    """Soft alphas (n, H, W) (zero outside the parent), argmax labels (H, W; -1 outside), seeds used."""

    alphas: np.ndarray
    labels: np.ndarray
    scribbles: np.ndarray         # HxW int: layer index or -1
    meta: dict = field(default_factory=dict)

    def masks(self) -> list[np.ndarray]:
        """One binary mask per layer (argmax of alphas inside the parent)."""
        return [self.labels == i for i in range(self.alphas.shape[0])]


# ----------------------------------------------------------------------------- features

def _grey(img: np.ndarray) -> np.ndarray:
    return img[..., 0] if img.ndim == 3 else img


def _robust_unit(m: np.ndarray) -> np.ndarray:
    """Map the 1st..99th percentile of m to [0, 1] (clipped): one outlier pixel must not squash the rest."""
    lo, hi = np.percentile(m, [1.0, 99.0])
    return np.clip((m - lo) / (hi - lo), 0, 1).astype(np.float32) if hi > lo else np.zeros_like(m, np.float32)


def feature_maps(albedo: np.ndarray, height: np.ndarray | None = None, roughness: np.ndarray | None = None,
                 spectrum_dims: int = 16, config: SpectrumConfig = SpectrumConfig(), seed: int = 0,
                 height_highpass: float = 1 / 32) -> FeatureMaps:
    """Build the per-pixel colour channels and the spectrum (global PCA to spectrum_dims) once per material.

    albedo: HxWx3 linear in [0,1] (converted to sRGB for perceptual distances); height, roughness HxW(x1).
    Height loses its low frequencies (minus a Gaussian blur of sigma = height_highpass * max(H, W); 0 = off):
    heights integrated from normals drift at large scales, which says nothing about which part a pixel is.
    Height and roughness are scaled by their 1st..99th percentiles to [0, 1].
    """
    from .maps import linear_to_srgb

    albedo = np.asarray(albedo, np.float32)
    if albedo.ndim != 3 or albedo.shape[2] != 3:
        raise InputError(f"albedo must be HxWx3, got shape {albedo.shape}")
    h, w = albedo.shape[:2]
    srgb = np.clip(linear_to_srgb(np.clip(albedo, 0, 1)), 0, 1).astype(np.float32)
    chans, names, greys = [srgb], ["r", "g", "b"], [srgb @ np.array([0.299, 0.587, 0.114], np.float32)]
    for name, m in (("height", height), ("roughness", roughness)):
        if m is None:
            continue
        m = _grey(np.asarray(m, np.float32))
        if m.shape != (h, w):
            raise InputError(f"{name} map is {m.shape[1]}x{m.shape[0]} but the albedo is {w}x{h}")
        if name == "height" and height_highpass > 0:
            m = m - ndimage.gaussian_filter(m, height_highpass * max(h, w), mode="wrap")
        chans.append(_robust_unit(m)[..., None])
        names.append(name)
        greys.append(m)
    spec = None
    if spectrum_dims > 0:
        stack = spectrum_stack(greys, config).reshape(h * w, -1)
        spec = pca_project(stack, spectrum_dims, seed=seed).reshape(h, w, spectrum_dims)
    return FeatureMaps(colour=np.concatenate(chans, axis=2), spectrum=spec, names=names)


def pixel_features(fm: FeatureMaps, mask: np.ndarray, config: MattingConfig = MattingConfig(),
                   seed: int = 0) -> tuple[np.ndarray, int]:
    """Feature rows (N x d) of the pixels in mask, xy in the last two columns; also the feature dim d."""
    h, w = fm.shape
    idx = np.flatnonzero(mask.reshape(-1))
    parts = [fm.colour.reshape(h * w, -1)[idx]]
    if fm.spectrum is not None and config.spectral_weight > 0 and config.spectral_dims > 0:
        spec = fm.spectrum.reshape(h * w, -1)[idx]
        spec = minmax(pca_project(spec, config.spectral_dims, seed=seed))  # PCA-3 inside the parent
        parts.append(spec * np.float32(config.spectral_weight))
    ys, xs = np.divmod(idx, w)
    diag = float(np.hypot(h, w))
    parts.append(np.stack([xs / diag, ys / diag], axis=1).astype(np.float32))
    f = np.concatenate(parts, axis=1).astype(np.float32)
    return f, f.shape[1]


# ----------------------------------------------------------------------------- Laplacian and solve

def knn_laplacian(f: np.ndarray, config: MattingConfig = MattingConfig()) -> sp.csr_matrix:
    """D - A of the two-pass KNN graph over feature rows f (xy in the last two columns)."""
    n, d = f.shape
    rows, cols, vals = [], [], []
    for k, xy_scale in ((config.k, 1.0), (config.k_nonlocal, config.nonlocal_xy_scale)):
        k_eff = min(k + 1, n)
        if k_eff < 2:
            continue
        g = f.copy()
        g[:, -2:] *= xy_scale
        _, nb = cKDTree(g).query(g, k=k_eff, workers=-1, eps=config.knn_eps)
        nb = nb[:, 1:]
        i = np.repeat(np.arange(n), nb.shape[1])
        j = nb.reshape(-1)
        dist = np.abs(f[i] - f[j]).sum(axis=1)  # affinity always on the full-weight features
        rows.append(i)
        cols.append(j)
        vals.append(np.maximum(0.0, 1.0 - dist / (d + 2)).astype(np.float64))
    a = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    a = (a + a.T) * 0.5
    deg = np.asarray(a.sum(axis=1)).ravel()
    return (sp.diags(deg) - a).tocsr()


def solve_alphas(lap: sp.csr_matrix, seeds: np.ndarray, n_layers: int,
                 config: MattingConfig = MattingConfig()) -> tuple[np.ndarray, list[int]]:
    """Alphas (n_layers x N) from (L + lambda*S) alpha_i = lambda*v_i; seeds: N ints (-1 = unknown)."""
    n = lap.shape[0]
    s = (seeds >= 0).astype(np.float64)
    system = (lap + sp.diags(config.lam * s)).tocsr()
    diag = system.diagonal()
    precond = spla.LinearOperator((n, n), matvec=lambda x: x / np.where(diag > 0, diag, 1.0), dtype=np.float64)
    alphas = np.zeros((n_layers, n), np.float64)
    iters: list[int] = []
    for i in range(n_layers - 1):
        b = config.lam * (seeds == i).astype(np.float64)
        count = [0]

        def cb(_x, count=count):
            count[0] += 1

        x0 = (seeds == i).astype(np.float64)
        x, info = spla.cg(system, b, x0=x0, rtol=config.tol, maxiter=config.maxiter, M=precond, callback=cb)
        if info > 0:
            logger.warning("matting CG for layer %d stopped after %d iterations without reaching tol %g",
                           i, info, config.tol)
        alphas[i] = x
        iters.append(count[0])
    alphas[n_layers - 1] = 1.0 - alphas[: n_layers - 1].sum(axis=0)
    return np.clip(alphas, 0.0, 1.0), iters


# ----------------------------------------------------------------------------- scribbles

def decode_scribbles(image: np.ndarray, shape: tuple[int, int] | None = None,
                     source: str | None = None) -> np.ndarray:
    """HxW int layer map from a scribble image: one layer per distinct colour, -1 = unknown.

    Unknown = black (0,0,0) or alpha 0. Colours are quantised to 8 bits and ordered lexicographically
    (R, then G, then B). Float images are read in [0,1], integer ones in [0, 255].
    """
    where = f"{source}: " if source else "scribbles: "
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4):
        raise InputError(f"{where}scribble image must be HxW, HxWx3 or HxWx4, got shape {img.shape}")
    if shape is not None and img.shape[:2] != tuple(shape):
        raise InputError(f"{where}scribble image is {img.shape[1]}x{img.shape[0]} but the maps are "
                         f"{shape[1]}x{shape[0]}; draw the scribbles on an image of the maps' size")
    q = (np.clip(img.astype(np.float64), 0, 1) * 255 + 0.5).astype(np.int64) if img.dtype.kind == "f" \
        else np.clip(img.astype(np.int64), 0, 255)
    alpha = None
    if q.shape[2] in (2, 4):
        alpha, q = q[..., -1], q[..., :-1]
    if q.shape[2] == 1:
        q = np.repeat(q, 3, axis=2)
    code = (q[..., 0] << 16) | (q[..., 1] << 8) | q[..., 2]
    unknown = code == 0
    if alpha is not None:
        unknown |= alpha == 0
    colours, inv = np.unique(code[~unknown], return_inverse=True)
    if colours.size < 2:
        raise InputError(f"{where}scribble image marks {colours.size} layer(s); it needs at least two distinct "
                         "non-black colours (black and transparent pixels mean 'unknown')")
    if colours.size > MAX_LAYERS:
        raise InputError(f"{where}scribble image has {colours.size} distinct colours (at most {MAX_LAYERS} layers); "
                         "save scribbles losslessly (PNG) with flat colours, black = unknown")
    out = np.full(code.shape, -1, np.int64)
    out[~unknown] = inv.reshape(-1)
    return out


# ----------------------------------------------------------------------------- automatic seeding

def _silhouette(x: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette coefficient (Euclidean) of a small labelled sample."""
    d = np.sqrt(np.maximum(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1), 0))
    ks = np.unique(labels)
    if ks.size < 2:
        return -1.0
    mean_d = np.stack([d[:, labels == k].sum(1) / max(1, (labels == k).sum()) for k in ks], axis=1)
    own = np.searchsorted(ks, labels)
    size_own = np.array([(labels == k).sum() for k in ks])[own]
    a = mean_d[np.arange(len(x)), own] * size_own / np.maximum(size_own - 1, 1)
    mean_d[np.arange(len(x)), own] = np.inf
    b = mean_d.min(axis=1)
    s = np.where(size_own > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-12), 0.0)
    return float(s.mean())


def _kmeans(x: np.ndarray, k: int, seed: int) -> np.ndarray:
    """k-means centres (k x d), deterministic from seed, best of 3 restarts by inertia."""
    best, best_inertia = None, np.inf
    for r in range(3):
        cent, lab = kmeans2(x, k, minit="++", seed=np.random.default_rng([seed, r]), iter=30)
        inertia = float(((x - cent[lab]) ** 2).sum())
        if inertia < best_inertia and np.unique(lab).size == k:
            best, best_inertia = cent, inertia
    if best is None:
        best = cent
    return best


def _seed_features(fm: FeatureMaps, f: np.ndarray, mask: np.ndarray, index: np.ndarray,
                   config: MattingConfig) -> np.ndarray:
    """Clustering features: the matting features without xy, colour channels smoothed inside the mask.

    Per-pixel colour of a noisy texture is not a property of its region; a masked Gaussian (normalised
    convolution, sigma = seed_smooth px) turns it into the local mean, which is.
    """
    nc = fm.colour.shape[2]
    out = f[:, :-2].copy()
    if config.seed_smooth > 0:
        m = mask.astype(np.float32)
        norm = ndimage.gaussian_filter(m, config.seed_smooth, mode="wrap")
        for c in range(nc):
            blurred = ndimage.gaussian_filter(fm.colour[..., c] * m, config.seed_smooth, mode="wrap")
            out[:, c] = (blurred / np.maximum(norm, 1e-6)).reshape(-1)[index]
    return out


@dataclass
class Gaussians:
    """A fitted spherical Gaussian mixture: weights (k,), means (k, d), one variance per component (k,)."""

    weights: np.ndarray
    means: np.ndarray
    variances: np.ndarray

    def log_joint(self, x: np.ndarray) -> np.ndarray:
        """log(w_j N(x | mu_j, var_j I)) for rows of x: (N, k)."""
        d = x.shape[1]
        d2 = np.stack([((x - m) ** 2).sum(axis=1) for m in self.means], axis=1)
        return np.log(self.weights) - 0.5 * d2 / self.variances - 0.5 * d * np.log(2 * np.pi * self.variances)

    def posteriors(self, x: np.ndarray, chunk: int = 65536) -> np.ndarray:
        """Responsibilities (N, k), float32, computed in chunks."""
        out = np.empty((x.shape[0], self.weights.size), np.float32)
        for i in range(0, x.shape[0], chunk):
            lj = self.log_joint(x[i:i + chunk].astype(np.float64))
            out[i:i + chunk] = np.exp(lj - logsumexp(lj, axis=1, keepdims=True))
        return out


def fit_gmm(x: np.ndarray, k: int, seed: int = 0, reg: float = 1e-6, iters: int = 200,
            tol: float = 1e-6) -> Gaussians:
    """Spherical Gaussian mixture (one variance per component) by EM from k-means (deterministic from seed).

    Why spherical: distances stay Euclidean in the weighted features (spectral_weight matters, as in the
    matting), yet a wide cluster (coarse texture, many local colours) can sit next to a tight one (fine
    texture), which plain k-means cuts wrongly. A full-covariance GMM is affine-invariant, so it ignores the
    feature weights; on castle_brick_broken_06 it split light from dark bricks instead of mortar from bricks.
    """
    n, d = x.shape
    cent = _kmeans(x, k, seed)
    d2 = np.stack([((x - c) ** 2).sum(axis=1) for c in cent], axis=1)
    resp = np.eye(k)[np.argmin(d2, axis=1)]
    prev, model = -np.inf, None
    for _ in range(iters):
        nk = resp.sum(axis=0) + 1e-10
        means = resp.T @ x / nk[:, None]
        d2 = np.stack([((x - m) ** 2).sum(axis=1) for m in means], axis=1)
        model = Gaussians(nk / n, means, (resp * d2).sum(axis=0) / (nk * d) + reg)
        lj = model.log_joint(x)
        ll = logsumexp(lj, axis=1, keepdims=True)
        resp = np.exp(lj - ll)
        if ll.mean() - prev < tol:
            break
        prev = float(ll.mean())
    return model


def auto_seeds(f: np.ndarray, index: np.ndarray, shape: tuple[int, int], n_layers: int | str,
               config: MattingConfig = MattingConfig(), seed: int = 0) -> tuple[np.ndarray, int, dict]:
    """Seed labels (N ints, -1 unknown) from confident pixels of a GMM of the features; returns (seeds, n, info).

    f: clustering features (no xy). index: flat pixel index of each row (for the erosion).
    """
    rng = np.random.default_rng(seed)
    n = f.shape[0]
    sample = f[np.sort(rng.choice(n, min(n, config.cluster_sample), replace=False))].astype(np.float64)
    info: dict = {}
    models: dict[int, Gaussians] = {}
    if n_layers == "auto":
        sil = sample[rng.choice(sample.shape[0], min(sample.shape[0], config.silhouette_sample), replace=False)]
        scores = {}
        for k in range(AUTO_RANGE[0], AUTO_RANGE[1] + 1):
            models[k] = fit_gmm(sample, k, seed)
            scores[k] = _silhouette(sil, np.argmax(models[k].log_joint(sil), axis=1))
        best = max(scores.values())
        n_layers = min(k for k, v in scores.items() if v >= best - config.auto_tolerance)
        info["silhouette"] = {str(k): round(v, 4) for k, v in scores.items()}
        logger.info("auto layer count: silhouette %s -> %d layers", info["silhouette"], n_layers)
    k = int(n_layers)
    model = models.get(k) or fit_gmm(sample, k, seed)
    post = model.posteriors(f)
    lab = np.argmax(post, axis=1)
    top = post[np.arange(n), lab]
    # order layers by decreasing area so ids are stable and meaningful (largest first)
    counts = np.bincount(lab, minlength=k)
    rank = np.empty(k, np.int64)
    rank[np.argsort(-counts, kind="stable")] = np.arange(k)
    lab = rank[lab]
    h, w = shape
    seeds = np.full(n, -1, np.int64)
    for layer in range(k):
        img = np.zeros(h * w, bool)
        img[index[lab == layer]] = True
        if config.erosion > 0:
            img = ndimage.binary_erosion(img.reshape(h, w), iterations=config.erosion).reshape(-1)
        keep = img[index] & (top >= config.confidence) & (lab == layer)
        if keep.sum() < 10:  # tiny or fragmented cluster: fall back to its most confident tenth
            members = np.flatnonzero(lab == layer)
            keep = np.zeros(n, bool)
            keep[members[np.argsort(-top[members], kind="stable")[: max(1, members.size // 10)]]] = True
        seeds[keep] = layer
    info.update(n_layers=k, seed_fraction=float((seeds >= 0).mean()),
                cluster_share=[float(c) / n for c in np.sort(counts)[::-1]])
    return seeds, k, info


# ----------------------------------------------------------------------------- entry point

def matte(fm: FeatureMaps, mask: np.ndarray | None = None, n_layers: int | str = 2,
          scribbles: np.ndarray | None = None, config: MattingConfig = MattingConfig(), seed: int = 0,
          source: str | None = None) -> MatteResult:
    """Split the pixels of mask (HxW bool; None = all) into layers by spectrum-aware KNN matting.

    scribbles: an image (see decode_scribbles) or an HxW int label map (-1 unknown); None = automatic mode
    with n_layers an int or "auto".
    """
    t0 = time.perf_counter()
    h, w = fm.shape
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (h, w):
        raise InputError(f"parent mask is {mask.shape[1]}x{mask.shape[0]} but the maps are {w}x{h}")
    index = np.flatnonzero(mask.reshape(-1))
    if index.size < 4:
        raise InputError(f"cannot split a region of {index.size} pixel(s); the parent mask is (nearly) empty")
    f, d = pixel_features(fm, mask, config, seed)
    info: dict = {}
    if scribbles is not None:
        lab_img = np.asarray(scribbles)
        if not (lab_img.ndim == 2 and lab_img.dtype.kind in "iu" and lab_img.min() < 0):
            lab_img = decode_scribbles(lab_img, (h, w), source)
        elif lab_img.shape != (h, w):
            raise InputError(f"{source or 'scribbles'}: label map is {lab_img.shape[1]}x{lab_img.shape[0]}, "
                             f"maps are {w}x{h}")
        seeds = lab_img.reshape(-1)[index].astype(np.int64)
        present = np.unique(seeds[seeds >= 0])
        n = int(lab_img.max()) + 1
        if present.size < 2:
            raise InputError(f"{source or 'scribbles'}: only {present.size} scribble layer(s) fall inside the "
                             "region being split; mark at least two layers inside it")
    else:
        if not (n_layers == "auto" or (isinstance(n_layers, (int, np.integer)) and 2 <= n_layers <= MAX_LAYERS)):
            raise InputError(f"layers must be an integer in 2..{MAX_LAYERS} or 'auto', got {n_layers!r}")
        seeds, n, info = auto_seeds(_seed_features(fm, f, mask, index, config), index, (h, w), n_layers,
                                    config, seed)
    t1 = time.perf_counter()
    lap = knn_laplacian(f, config)
    t2 = time.perf_counter()
    al, iters = solve_alphas(lap, seeds, n, config)
    t3 = time.perf_counter()
    alphas = np.zeros((n, h * w), np.float32)
    alphas[:, index] = al
    labels = np.full(h * w, -1, np.int64)
    labels[index] = np.argmax(al, axis=0)
    sc = np.full(h * w, -1, np.int64)
    sc[index] = seeds
    info.update(feature_dim=d, pixels=int(index.size), cg_iterations=iters,
                seconds={"features_seeds": round(t1 - t0, 3), "laplacian": round(t2 - t1, 3),
                         "solve": round(t3 - t2, 3)})
    logger.info("matting %d px into %d layers: features %.2fs, laplacian %.2fs, solve %.2fs (CG its %s)",
                index.size, n, t1 - t0, t2 - t1, t3 - t2, iters)
    return MatteResult(alphas=alphas.reshape(n, h, w), labels=labels.reshape(h, w), scribbles=sc.reshape(h, w),
                       meta=info)
