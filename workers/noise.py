"""Multi-layer procedural noise model of a masked region (paper 5.1, Algorithm 1; 5.1.1 colour).

Fit: the masked image is rotated to its PCA colour space and split by a masked Gaussian pyramid
(normalised convolution, so holes do not leak) into ``n_levels`` band-pass layers, a last low-pass layer
and a base colour. Band-pass layers keep a T x T amplitude spectrum estimated from the autocovariance over
the pairs of pixels inside the mask (``correlation_spectrum``: Welch's smoothing of T x T Hann windows, but
defined for regions no window fits in, such as rows of slates; the spec's windows wholly inside the mask gave
those 8 px windows or white noise); the last (lowest-frequency) layer's
full-image spectrum (holes weighted out by a smooth mask taper, then low-passed by the pyramid's own
Gaussian) is approximated by a few Gabor kernels (Galerne et al. 2012). Per-channel quantiles of the masked input
are kept for histogram matching and, for colour maps, a 3-D colour transport (iterated sliced histogram matching,
Pitie et al. 2007: the quantiles of the input's colours along a few fixed rotated axes), so the synthesis keeps
the joint colour distribution and not only its three marginals (matched channel by channel, a rust's noise had
1.5 times the input's share of red-dominant pixels). No input pixel is stored.

Synthesis is procedural: one complex white-noise field per PCA component is shaped by each layer's
spectrum resampled to the output grid (FFT at the output size: exactly stationary, periodic so maps
tile, variance-exact, no tile seams) and the real inverse FFT is taken. Outputs over 4096^2 px are built from
independent 2048 px tiles (wrapping, so still periodic) blended with weights normalised by their
root-sum-square, which keeps the variance in the overlaps; FFT memory then follows the tile, not the output.
The layers of a component share that white noise: they are band-pass pieces of one image, their bands overlap, and
independent phases would give the sum of powers instead of the power of the sum (measured on a known spectrum: down
to 35% of the power where bands overlap, radial log error 0.34 instead of 0.06).
``scale`` s means s output pixels per fitted pixel: the output amplitude at frequency f is
``s * sqrt(psd(s * f))``.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from .arrays import decode_array, encode_array
from .errors import GraphError, InputError
from .gabor import fit_gabor, gabor_psd

logger = logging.getLogger(__name__)

PARAMS_KIND = "proceduralize.noise/1.1"   # 1.1 adds "transport" (3-D colour transport)
#: noise params kinds this version reads (1: per-channel histogram matching only)
SUPPORTED_KINDS = ("proceduralize.noise/1", PARAMS_KIND)


@dataclass
class NoiseConfig:
    """Fitting parameters (reference defaults from the spec)."""

    erode_fraction: float = 0.01          # mask erosion radius as a fraction of min(H, W)
    var_threshold: float = 0.001          # a layer with less than this fraction of the masked variance is dropped
    kernel_sizes: tuple[int, ...] = (15, 29, 57, 113)  # Gaussian kernel sizes of the pyramid levels
    n_levels: int = 2                     # pyramid levels used -> n_levels + 1 noise layers + base
    window: int = 64                      # T: spectrum grid and lag window (the smoothing of T x T Hann windows)
    pairs: float = 64.0                   # pixel pairs at which a lag's covariance gets half weight (few pairs:
    #                                       shrunk toward 0, i.e. smoothed more where the region is small or thin)
    taper_ramp: float = 6.0               # px over which the last layer's mask weight ramps from 0 to 1
    gabor_last: bool = True               # last layer from the full-image spectrum as Gabor kernels
    n_gabor: int = 16                     # Gabor kernels per PCA component of the last layer
    n_quantiles: int = 64                 # stored quantiles per channel for histogram matching
    transport: int = 12                   # rotations of the colour transport of maps with >= 2 channels (0: none,
    #                                       channels matched one by one only)
    per_piece: tuple[str, ...] = ("height",)  # maps whose instance kinds get one offset per piece at render
    #                                       time, their noise fitted on the within-piece residual (workers.pieces):
    #                                       bricks set at different depths give the normals their steps at the
    #                                       brick edges; on albedo and roughness it measured worse (see pieces.py)

    def __post_init__(self) -> None:
        self.kernel_sizes = tuple(int(k) for k in self.kernel_sizes)
        self.per_piece = (self.per_piece,) if isinstance(self.per_piece, str) else tuple(self.per_piece)
        if not 0 <= self.n_levels <= len(self.kernel_sizes):
            raise InputError(f"NoiseConfig.n_levels={self.n_levels} must be in [0, {len(self.kernel_sizes)}]")
        if self.window < 4 or self.pairs < 0:
            raise InputError("NoiseConfig: need window >= 4 and pairs >= 0")
        if self.n_quantiles < 2 or self.n_gabor < 1 or self.transport < 0:
            raise InputError("NoiseConfig: need n_quantiles >= 2, n_gabor >= 1 and transport >= 0")


@dataclass
class NoiseLayer:
    """One noise layer in PCA space: a windowed amplitude spectrum or a Gabor-kernel PSD."""

    kind: str                                  # "window" | "gabor"
    spectrum: np.ndarray | None = None         # (C, T, T//2+1) amplitude |FFT|/T^2 (RMS over windows), rfft half
    gabor: list[np.ndarray] | None = None      # per component (K, 4) = (fx, fy, sigma, weight) PSD bumps

    def psd_on(self, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        """PSD density (C, H, W') of this layer on the frequency grid ``fy`` x ``fx`` (cycles per fitted pixel)."""
        if self.kind == "gabor":
            return np.stack([gabor_psd(g, fy, fx) for g in self.gabor])
        t = self.spectrum.shape[1]
        full = _full_from_half(self.spectrum.astype(np.float64) ** 2, t)  # power per bin S, sum = variance
        shifted = np.fft.fftshift(full, axes=(1, 2)) * (t * t)             # density p = S * T^2
        ry = _interp_matrix(fy, t).astype(np.float32)
        rx = _interp_matrix(fx, t).astype(np.float32)
        out = (ry @ shifted.astype(np.float32)) @ rx.T  # separable bilinear interpolation: (C, H, W')
        return np.maximum(out, 0.0)


#: fixed seed of the colour transport's rotations (they are stored with the model: this only makes fits repeatable)
_TRANSPORT_SEED = 0x636F6C6F


@dataclass
class ColourTransport:
    """Iterated sliced histogram matching onto a colour distribution (Pitie et al. 2007): each step rotates the
    colours, matches each rotated axis to the stored quantiles of the target's colours along it, and rotates
    back. A few steps move the joint distribution (hue and saturation, not only each channel) onto the target."""

    rotations: np.ndarray     # (R, C, C) orthonormal, columns the axes
    quantiles: np.ndarray     # (R, Q, C) quantiles of the target's colours along each step's axes

    @classmethod
    def fit(cls, pixels: np.ndarray, steps: int, n_quantiles: int) -> ColourTransport:
        """The transport onto ``pixels`` (N x C): ``steps`` random rotations (fixed seed) and their quantiles."""
        c = pixels.shape[1]
        rng = np.random.default_rng(_TRANSPORT_SEED)
        rots = []
        for _ in range(steps):
            q, r = np.linalg.qr(rng.standard_normal((c, c)))
            rots.append(q * np.sign(np.diag(r)))
        rotations = np.stack(rots).astype(np.float32)
        probs = np.linspace(0.0, 1.0, n_quantiles)
        px = pixels.astype(np.float32)
        quantiles = np.stack([np.quantile(px @ rot, probs, axis=0) for rot in rotations]).astype(np.float32)
        return cls(rotations=rotations, quantiles=quantiles)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The transported colours of ``x`` (C x H x W)."""
        for rot, q in zip(self.rotations, self.quantiles):
            y = np.tensordot(rot.T, x, axes=([1], [0]))
            y = histogram_match(y, q, channel_axis=0)
            x = np.tensordot(rot, y, axes=([1], [0]))
        return x.astype(np.float32, copy=False)

    def to_params(self) -> dict:
        """JSON-able params (arrays via :func:`workers.arrays.encode_array`)."""
        return {"rotations": encode_array(self.rotations, "float32"),
                "quantiles": encode_array(self.quantiles, "float32")}

    @classmethod
    def from_params(cls, params: dict, c: int) -> ColourTransport:
        """Rebuild from :meth:`to_params` output for C channels (GraphError naming the field if malformed)."""
        rot = decode_array(params["rotations"]).astype(np.float32)
        q = decode_array(params["quantiles"]).astype(np.float32)
        if rot.ndim != 3 or rot.shape[1:] != (c, c) or q.ndim != 3 or q.shape[0] != rot.shape[0] or q.shape[2] != c:
            raise GraphError(f"noise transport: rotations {rot.shape} and quantiles {q.shape} must be (R, {c}, {c}) "
                             f"and (R, Q, {c})")
        if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(q))):
            raise GraphError("noise transport: rotations and quantiles must be finite")
        return cls(rotations=rot, quantiles=q)


@dataclass
class NoiseModel:
    """A fitted noise model: everything synthesis needs, and nothing from the input pixels."""

    base: np.ndarray                 # (C,) base colour (original colour space)
    pca_mean: np.ndarray             # (C,) PCA centre
    pca_basis: np.ndarray            # (C, C) columns are principal axes
    layers: list[NoiseLayer]         # fine to coarse
    quantiles: np.ndarray            # (Q, C) quantiles of the masked input at linspace(0, 1, Q)
    fit_size: tuple[int, int]        # (height, width) of the fitted image
    info: dict = field(default_factory=dict)
    transport: ColourTransport | None = None   # joint colour distribution (colour maps), before ``quantiles``

    @property
    def channels(self) -> int:
        """Number of channels of the modelled image."""
        return int(self.base.size)

    def to_params(self) -> dict:
        """JSON-able node params; arrays via :func:`workers.arrays.encode_array` (spectra float16, max-normalised)."""
        layers = []
        for lay in self.layers:
            if lay.kind == "window":
                amax = lay.spectrum.reshape(lay.spectrum.shape[0], -1).max(axis=1)
                norm = lay.spectrum / np.maximum(amax, 1e-30)[:, None, None]
                layers.append({"kind": "window", "amax": [float(a) for a in amax],
                               "spectrum": encode_array(norm, "float16")})
            else:
                layers.append({"kind": "gabor", "kernels": [encode_array(g, "float32") for g in lay.gabor]})
        return {
            "kind": PARAMS_KIND,
            "base": [float(b) for b in self.base],
            "pca_mean": [float(b) for b in self.pca_mean],
            "pca_basis": encode_array(self.pca_basis, "float32"),
            "quantiles": encode_array(self.quantiles, "float32"),
            "layers": layers,
            "fit_size": [int(self.fit_size[0]), int(self.fit_size[1])],
            "info": _jsonable(self.info),
        } | ({"transport": self.transport.to_params()} if self.transport is not None else {})

    @classmethod
    def from_params(cls, params: dict) -> NoiseModel:
        """Rebuild a model from :meth:`to_params` output (GraphError naming the field if it is malformed)."""
        try:
            if params.get("kind") not in SUPPORTED_KINDS:
                raise GraphError(f"noise params 'kind' must be one of {', '.join(SUPPORTED_KINDS)}, "
                                 f"got {params.get('kind')!r}")
            base = np.asarray(params["base"], dtype=np.float32)
            c = base.size
            layers = []
            for i, lp in enumerate(params["layers"]):
                if lp["kind"] == "window":
                    spec = decode_array(lp["spectrum"]) * np.asarray(lp["amax"], np.float32)[:, None, None]
                    if spec.ndim != 3 or spec.shape[0] != c or spec.shape[2] != spec.shape[1] // 2 + 1:
                        raise GraphError(f"noise layers[{i}].spectrum has shape {spec.shape}, "
                                         f"expected ({c}, T, T//2+1)")
                    layers.append(NoiseLayer("window", spectrum=spec))
                elif lp["kind"] == "gabor":
                    ker = [decode_array(k).reshape(-1, 4) for k in lp["kernels"]]
                    if len(ker) != c:
                        raise GraphError(f"noise layers[{i}].kernels has {len(ker)} components, expected {c}")
                    layers.append(NoiseLayer("gabor", gabor=ker))
                else:
                    raise GraphError(f"noise layers[{i}].kind must be 'window' or 'gabor', got {lp['kind']!r}")
            model = cls(base=base, pca_mean=np.asarray(params["pca_mean"], np.float32),
                        pca_basis=decode_array(params["pca_basis"]).reshape(c, c),
                        layers=layers, quantiles=decode_array(params["quantiles"]).reshape(-1, c),
                        fit_size=tuple(int(v) for v in params.get("fit_size", (0, 0))),
                        info=dict(params.get("info", {})),
                        transport=ColourTransport.from_params(params["transport"], c) if "transport" in params
                        else None)
        except GraphError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise GraphError(f"malformed noise params: {type(exc).__name__}: {exc}") from None
        if not (np.all(np.isfinite(model.base)) and np.all(np.isfinite(model.quantiles))):
            raise GraphError("noise params: base and quantiles must be finite")
        return model


@dataclass
class NoiseLayers:
    """Synthesis result: base colour, the noise layers (original colour space, zero mean) and the final map."""

    base: np.ndarray              # (C,)
    layers: list[np.ndarray]      # each HxWxC
    matched: np.ndarray           # HxWxC: base + sum(layers), colour-transported, histogram-matched (quantiles)


# ----------------------------------------------------------------------------- helpers


def _jsonable(obj):
    """Plain JSON types for an info dict (numpy scalars -> Python)."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def kernel_sigma(ksize: int) -> float:
    """Gaussian sigma for a kernel size (the OpenCV rule the reference relies on)."""
    return 0.3 * ((ksize - 1) * 0.5 - 1.0) + 0.8


def _fft_blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Periodic Gaussian blur of HxW[xC] by FFT (cost independent of sigma)."""
    h, w = x.shape[:2]
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    g = np.exp(-2.0 * np.pi ** 2 * sigma ** 2 * (fy ** 2 + fx ** 2))
    if x.ndim == 3:
        g = g[..., None]
    return sfft.irfft2(sfft.rfft2(x, axes=(0, 1)) * g, s=(h, w), axes=(0, 1)).astype(np.float32)


def masked_blur(x: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised convolution blur(x*m)/blur(m): a Gaussian low-pass that ignores pixels outside the mask."""
    m = mask.astype(np.float32)
    num = _fft_blur(x * m[..., None], sigma)
    den = _fft_blur(m, sigma)[..., None]
    return np.where(den > 1e-4, num / np.maximum(den, 1e-4), 0.0).astype(np.float32)


def erode_mask(mask: np.ndarray, fraction: float, keep: float = 0.5) -> np.ndarray:
    """Erode by up to ``fraction`` of min(H, W) px, drop the mixed-colour pixels along a region's edge.

    The radius shrinks to the mask's own thickness: the largest one that keeps at least ``keep`` of the mask's
    pixels, so a thin network (mortar lines a few px wide) keeps its core instead of only its widest blobs
    (stains), and a wide region is eroded by the full radius. The image border counts as inside (maps tile)."""
    r = int(round(fraction * min(mask.shape)))
    if r < 1 or mask.all():
        return mask.copy()
    dist = ndimage.distance_transform_edt(np.pad(mask, r + 1, mode="wrap"))[r + 1:-r - 1, r + 1:-r - 1]
    inside = dist[mask]
    while r >= 1 and np.mean(inside > r) < keep:
        r -= 1
    return dist > r if r >= 1 else mask.copy()


def _lag_window(t: int) -> np.ndarray:
    """(2T-1)^2 lag window: the autocorrelation of a T px Hann taper, 1 at lag 0. Averaging the periodograms of
    Hann-tapered T x T windows (Welch) smooths the spectrum by exactly this product in the lag domain."""
    hann = np.hanning(t + 2)[1:-1]
    lw = np.correlate(hann, hann, "full")
    lw /= lw.max()
    return np.outer(lw, lw)


def correlation_spectrum(band: np.ndarray, mask: np.ndarray, t: int, pairs: float = 64.0) -> np.ndarray:
    """RMS amplitude spectrum (C, T, T//2+1) of ``band`` (HxWxC) inside ``mask`` (HxW bool), normalised like
    |rfft2|/T^2 of an untapered window (sum of squares = the masked variance).

    Masked-correlation (Blackman-Tukey) estimate: the autocovariance at each lag |dx|, |dy| < T is the mean
    product over the pairs of pixels that are both in the mask (two periodic FFTs: the masked signal's
    autocorrelation over the mask's), shrunk toward 0 by n / (n + ``pairs``) where a lag has few pairs, times
    the lag window of a T px Hann taper (``_lag_window``), then Fourier-transformed on the T grid (lags folded
    modulo T: the spectrum sampled at k / T); negative lobes are clipped. The mask's shape does not enter the
    estimate (no hard mask edge multiplies the signal), so thin or fragmented regions (slates 10 px tall,
    bricks, planks, where no T x T window fits inside and a spectrum averaged over windows falls back to
    8 px windows or white noise) keep their grain's direction; on a full mask it is Welch's estimate.
    """
    h, w, c = band.shape
    m = mask.astype(np.float64)
    fm = sfft.rfft2(m)
    lags = np.arange(-(t - 1), t)
    iy, ix = lags[:, None] % h, lags[None, :] % w
    n = sfft.irfft2(fm * np.conj(fm), s=(h, w))[iy, ix]
    weight = np.where(n > 0.5, 1.0 / np.maximum(n + pairs, 1e-9), 0.0) * _lag_window(t)
    cell = tuple(np.broadcast_to(a, n.shape) for a in (lags[:, None] % t, lags[None, :] % t))  # lag -> T grid
    out = np.zeros((c, t, t // 2 + 1), np.float64)
    inside = m.sum()
    for k in range(c):
        x = band[..., k].astype(np.float64)
        x = (x - (x * m).sum() / inside) * m
        spec = sfft.rfft2(x)
        cov = sfft.irfft2(spec * np.conj(spec), s=(h, w))[iy, ix] * weight
        folded = np.zeros((t, t))
        np.add.at(folded, cell, cov)
        power = np.maximum(np.real(sfft.fft2(folded)), 0.0)
        power[0, 0] = 0.0
        total = power.sum()
        var = float((x * x).sum() / inside)
        if total > 0:
            out[k] = (power * (var / total))[:, : t // 2 + 1]
    amp = np.sqrt(out)
    amp[:, 0, 0] = 0.0
    return amp.astype(np.float32)


def _full_from_half(half: np.ndarray, t: int) -> np.ndarray:
    """(C, T, T//2+1) rfft-half grid -> (C, T, T) full grid using the Hermitian symmetry of a real field."""
    full = np.empty(half.shape[:1] + (t, t), dtype=half.dtype)
    nh = half.shape[2]
    full[:, :, :nh] = half
    kx = np.arange(nh, t)
    ky = np.arange(t)
    full[:, :, nh:] = half[:, (-ky[:, None]) % t, (t - kx)[None, :]]
    return full


def _interp_matrix(f: np.ndarray, t: int) -> np.ndarray:
    """Linear-interpolation matrix (len(f), T) from an fftshift-ed T grid to frequencies ``f``; 0 beyond Nyquist."""
    u = np.asarray(f, dtype=np.float64) * t + t // 2
    i0 = np.floor(u).astype(int)
    fr = u - i0
    r = np.zeros((f.size, t))
    rows = np.arange(f.size)
    np.add.at(r, (rows, i0 % t), 1.0 - fr)
    np.add.at(r, (rows, (i0 + 1) % t), fr)
    r[np.abs(f) > 0.5 + 1e-9] = 0.0
    return r


def _pca(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, principal axes (columns, by decreasing variance) and variances of N x C pixels."""
    mean = pixels.mean(axis=0)
    c = pixels.shape[1]
    if c == 1:
        return mean, np.ones((1, 1)), np.atleast_1d(pixels.var(axis=0))
    cov = np.cov(pixels - mean, rowvar=False)
    val, vec = np.linalg.eigh(cov)
    order = np.argsort(val)[::-1]
    vec = vec[:, order]
    vec *= np.where(vec.sum(axis=0) < 0, -1.0, 1.0)  # deterministic sign
    return mean, vec, val[order]


def _check_inputs(image: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Validate image HxW[xC] and mask HxW; return float32 HxWxC and bool mask."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] < 1 or min(img.shape[:2]) < 8:
        raise InputError(f"fit_noise: image must be HxW or HxWxC with H, W >= 8, got shape {np.shape(image)}")
    img = img.astype(np.float32)
    if not np.all(np.isfinite(img)):
        raise InputError("fit_noise: image has NaN or infinite values; clean the map first")
    m = np.ones(img.shape[:2], bool) if mask is None else np.asarray(mask)
    if m.shape != img.shape[:2]:
        raise InputError(f"fit_noise: mask shape {m.shape} does not match image size {img.shape[:2]}")
    m = m.astype(bool) if m.dtype == bool else (m > 0.5)
    if not m.any():
        raise InputError("fit_noise: mask is empty (no pixel selected); give a mask with at least one True pixel")
    return img, m


# ----------------------------------------------------------------------------- fit


def fit_noise(image: np.ndarray, mask: np.ndarray | None = None, config: NoiseConfig | None = None) -> NoiseModel:
    """Fit the multi-layer noise model of ``image`` (HxWxC, any channels) inside ``mask`` (HxW bool)."""
    cfg = config or NoiseConfig()
    img, mask = _check_inputs(image, mask)
    h, w, c = img.shape
    em = erode_mask(mask, cfg.erode_fraction)
    if em.sum() < max(64, 0.1 * mask.sum()):
        em = mask
    qprobs = np.linspace(0.0, 1.0, cfg.n_quantiles)
    # the value histogram from the same pixels as the spectra: the eroded edge holds the neighbour's colours
    quantiles = np.quantile(img[em], qprobs, axis=0).astype(np.float32)

    transport = ColourTransport.fit(img[em], cfg.transport, cfg.n_quantiles) if c >= 2 and cfg.transport else None
    mean, basis, var = _pca(img[em].astype(np.float64))
    y = ((img - mean.astype(np.float32)) @ basis.astype(np.float32)).astype(np.float32)
    bands, cur = [], y
    sigmas = [kernel_sigma(k) for k in cfg.kernel_sizes[:cfg.n_levels]]
    for sg in sigmas:
        low = masked_blur(cur, em, sg)
        bands.append(np.where(em[..., None], cur - low, 0.0).astype(np.float32))
        cur = low
    base_pca = cur[em].mean(axis=0)
    last = np.where(em[..., None], cur - base_pca, 0.0).astype(np.float32)
    bands.append(last)
    base = (mean + basis @ base_pca).astype(np.float32)

    t = min(cfg.window, max(4, min(h, w) // 2))   # lags up to T - 1 stay distinct on the periodic grid
    total_var = float(var.sum())
    layers, info_layers = [], []
    for i, band in enumerate(bands):
        bvar = band[em].var(axis=0)
        is_last = i == len(bands) - 1
        if total_var > 0 and bvar.sum() < cfg.var_threshold * total_var:
            layers.append(NoiseLayer("window", spectrum=np.zeros((c, t, t // 2 + 1), np.float32)))
            info_layers.append({"kind": "window", "dropped": True, "var": bvar.tolist()})
        elif is_last and cfg.gabor_last:
            layers.append(_gabor_layer(y, em, sigmas, bvar, cfg, info_layers))
        else:
            layers.append(NoiseLayer("window", spectrum=correlation_spectrum(band, em, t, cfg.pairs)))
            info_layers.append({"kind": "window", "var": bvar.tolist()})
    info = {"window": t, "mask_fraction": float(mask.mean()), "eroded_fraction": float(em.mean()),
            "pca_var": var.tolist(), "layers": info_layers, "config": _jsonable(asdict(cfg))}
    logger.debug("fit_noise %dx%dx%d: T=%d", h, w, c, t)
    return NoiseModel(base=base, pca_mean=mean.astype(np.float32), pca_basis=basis.astype(np.float32),
                      layers=layers, quantiles=quantiles, fit_size=(h, w), info=info, transport=transport)


def mask_taper(mask: np.ndarray, ramp: float) -> np.ndarray:
    """Weight 0 outside ``mask`` rising as sin^2 over ``ramp`` px inside it (1 deep inside; maps tile).

    The ramp shrinks to half the largest inside distance, so thin regions keep some full-weight pixels."""
    if mask.all():
        return np.ones(mask.shape, np.float32)
    p = int(np.ceil(ramp)) + 1
    d = ndimage.distance_transform_edt(np.pad(mask, p, mode="wrap"))[p:-p, p:-p]
    ramp = float(np.clip(0.5 * d.max(), 1.0, ramp))
    return (np.sin(0.5 * np.pi * np.clip(d / ramp, 0.0, 1.0)) ** 2).astype(np.float32)


def _gabor_layer(y: np.ndarray, em: np.ndarray, sigmas: list[float], bvar: np.ndarray, cfg: NoiseConfig,
                 info: list) -> NoiseLayer:
    """Last layer: its PSD is g(f)^2 * PSD(image), g the pyramid's cumulative Gaussian low-pass; the image PSD is
    a full-image periodogram with holes weighted out by a smooth mask taper (a hard-edged or inpainted hole leaks
    broadband power that swamps the steep low-pass tail). Gabor-kernel fit, rescaled to the masked variance."""
    h, w, c = y.shape
    wgt = mask_taper(em, cfg.taper_ramp)
    x = (y - y[em].mean(axis=0)) * wgt[..., None]
    f = sfft.fft2(x, axes=(0, 1))
    r2 = np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None, :] ** 2
    g2 = np.exp(-4.0 * np.pi ** 2 * float(np.sum(np.square(sigmas))) * r2)[..., None]
    psd = (f.real ** 2 + f.imag ** 2) * g2 / max(float((wgt.astype(np.float64) ** 2).sum()), 1.0)
    kernels, errs = [], []
    for k in range(c):
        p = psd[..., k].astype(np.float64)
        p[0, 0] = 0.0
        g, err = fit_gabor(p, cfg.n_gabor)
        model_var = float((4.0 * np.pi * g[:, 3] * g[:, 2] ** 2).sum()) if g.size else 0.0
        if model_var > 0:
            g = g.copy()
            g[:, 3] *= bvar[k] / model_var
        kernels.append(g.astype(np.float32))
        errs.append(err)
    info.append({"kind": "gabor", "fit_error": errs, "kernels": [int(g.shape[0]) for g in kernels],
                 "var": bvar.tolist()})
    return NoiseLayer("gabor", gabor=kernels)


# ----------------------------------------------------------------------------- synthesis


def _white(rng: np.random.Generator, c: int, height: int, width: int) -> np.ndarray:
    """Complex white noise (C, H, W//2+1) whose real inverse rfft2 has unit variance per pixel."""
    wh = width // 2 + 1
    out = rng.standard_normal((c, height, 2 * wh), dtype=np.float32).view(np.complex64)
    out *= np.float32(np.sqrt(height * width / 2.0))
    # irfft2 keeps only the Hermitian part of the kx = 0 (and Nyquist) columns, i.e. half their power
    out[:, :, 0] *= np.float32(np.sqrt(2.0))
    if width % 2 == 0:
        out[:, :, -1] *= np.float32(np.sqrt(2.0))
    return out


def layer_amplitudes(model: NoiseModel, width: int, height: int, scale: float = 1.0) -> list[np.ndarray]:
    """Output-grid amplitudes (C, H, W//2+1) per layer: ``s * sqrt(psd(s * f))``, DC removed."""
    fy = np.fft.fftfreq(height) * scale
    fx = np.fft.rfftfreq(width) * scale
    amps = []
    for lay in model.layers:
        a = np.float32(scale) * np.sqrt(lay.psd_on(fy, fx))
        a[:, 0, 0] = 0.0
        amps.append(a.astype(np.float32))
    return amps


def expected_psd(model: NoiseModel, width: int, height: int, scale: float = 1.0) -> np.ndarray:
    """Expected PSD (C, H, W//2+1) of base + sum(layers) per PCA component, before histogram matching.

    Layers share the white noise, so amplitudes add: E|rfft2(out)|^2 / (H*W) = (sum_k A_k)^2.
    """
    amps = layer_amplitudes(model, width, height, scale)
    tot = np.sum(amps, axis=0) if amps else np.zeros((model.channels, height, width // 2 + 1), np.float32)
    return (tot.astype(np.float64) ** 2).astype(np.float32)


def _interp_lut(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, n: int = 1 << 16) -> np.ndarray:
    """``np.interp(x, xp, fp)`` via a uniform n-entry lookup table (nearest entry; error <= slope * range / n).

    A few in-place passes instead of a binary search per pixel: ~5x faster on big maps."""
    lo, hi = float(xp[0]), float(xp[-1])
    lut = np.interp(np.linspace(lo, hi, n), xp, fp).astype(np.float32)
    u = np.subtract(x, np.float32(lo), dtype=np.float32)
    u *= np.float32((n - 1) / (hi - lo))
    u += np.float32(0.5)
    np.clip(u, 0.0, n - 1, out=u)
    return lut[u.astype(np.int32)]


def histogram_match(x: np.ndarray, quantiles: np.ndarray, max_samples: int = 1 << 18,
                    channel_axis: int = -1) -> np.ndarray:
    """Map each channel of ``x`` (HxWxC, or CxHxW with channel_axis=0) monotonically onto ``quantiles`` (Q, C)."""
    q = quantiles.shape[0]
    probs = np.linspace(0.0, 1.0, q)
    xc = np.moveaxis(x, channel_axis, 0)
    out = np.empty(xc.shape, dtype=np.float32)
    stride = max(1, xc[0].size // max_samples)
    for k in range(xc.shape[0]):
        ch = xc[k]
        src = np.quantile(ch.ravel()[::stride], probs)
        if src[-1] - src[0] < 1e-12:
            out[k] = quantiles[q // 2, k]
            continue
        src = np.maximum.accumulate(src + np.arange(q) * 1e-9 * (src[-1] - src[0]))
        out[k] = _interp_lut(ch, src, quantiles[:, k])
    return np.moveaxis(out, 0, channel_axis)


#: outputs above this many pixels are synthesised in blended tiles (FFT memory ~ tile size, not output size)
TILE_PIXELS = 4096 * 4096
#: default tile side of the tiled synthesis (grown to hold the longest fitted wavelength at the output scale)
TILE = 2048


def _fields(model: NoiseModel, width: int, height: int, scale: float, rng: np.random.Generator,
            with_layers: bool) -> tuple[list[np.ndarray], np.ndarray]:
    """Zero-mean colour fields (C, H, W), per layer (when asked) and their sum, from one periodic FFT grid."""
    c = model.channels
    white = _white(rng, c, height, width)
    basis = model.pca_basis.astype(np.float32)
    amps = layer_amplitudes(model, width, height, scale)

    def to_space(spec: np.ndarray) -> np.ndarray:
        y = sfft.irfft2(spec, s=(height, width), axes=(1, 2))  # real field (no abs(): that would rectify it)
        return np.tensordot(basis, y.astype(np.float32, copy=False), axes=([1], [0]))  # (C, H, W) colour

    if with_layers:
        layers_c = [to_space(white * a) for a in amps]
        total = np.add.reduce(layers_c) if layers_c else np.zeros((c, height, width), np.float32)
        return layers_c, total
    total = to_space(white * np.add.reduce(amps)) if amps else np.zeros((c, height, width), np.float32)
    return [], total


def tile_plan(n: int, tile: int) -> tuple[list[int], np.ndarray]:
    """Tile starts along an axis of n px (tiles wrap around: the output stays periodic) and the tile's blend
    weight profile (sin^2 ramps over a quarter tile); one full-axis tile of weight 1 when tile >= n."""
    if tile >= n:
        return [0], np.ones(n, np.float32)
    ov = max(1, tile // 8)
    count = int(np.ceil(n / (tile - ov)))
    starts = [int(round(i * n / count)) for i in range(count)]
    u = np.arange(tile, dtype=np.float64) + 0.5
    prof = np.sin(0.5 * np.pi * np.clip(np.minimum(u, tile - u) / ov, 0.0, 1.0)) ** 2
    return starts, prof.astype(np.float32)


def tile_size(model: NoiseModel, width: int, height: int, scale: float, tile: int | None = None) -> int | None:
    """Tile side for this output, or None for a single FFT (small outputs, or patterns too large to tile)."""
    if tile is None:
        if width * height <= TILE_PIXELS:
            return None
        tile = TILE
    longest = int(np.ceil(scale * max(model.fit_size)))  # the full-image (Gabor) layer's longest wavelength
    tile = max(int(tile), longest, 16)
    return None if tile >= width and tile >= height else tile


def _tiled_fields(model: NoiseModel, width: int, height: int, scale: float, seed: int, tile: int,
                  with_layers: bool) -> tuple[list[np.ndarray], np.ndarray]:
    """Independent tiles blended with weights normalised by their root-sum-square: every pixel keeps the
    variance of one tile (a plain partition of unity would lose up to half of it in the overlaps)."""
    c = model.channels
    xs, px = tile_plan(width, tile)
    ys, py = tile_plan(height, tile)
    tw, th = px.size, py.size
    n_out = len(model.layers) if with_layers else 1
    acc = [np.zeros((c, height, width), np.float32) for _ in range(n_out)]
    sx, sy = np.zeros(width, np.float32), np.zeros(height, np.float32)
    for x0 in xs:
        np.add.at(sx, (x0 + np.arange(tw)) % width, px ** 2)
    for y0 in ys:
        np.add.at(sy, (y0 + np.arange(th)) % height, py ** 2)
    wgt = np.outer(py, px)[None]
    for j, y0 in enumerate(ys):
        iy = ((y0 + np.arange(th)) % height)[:, None]
        for i, x0 in enumerate(xs):
            rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x6E6F6973, j + 1, i + 1]))
            layers_c, total = _fields(model, tw, th, scale, rng, with_layers)
            ix = ((x0 + np.arange(tw)) % width)[None, :]
            for a, f in zip(acc, layers_c if with_layers else [total]):
                a[:, iy, ix] += f * wgt
    norm = (1.0 / np.sqrt(np.outer(sy, sx))).astype(np.float32)[None]
    for a in acc:
        a *= norm
    if with_layers:
        total = np.add.reduce(acc) if acc else np.zeros((c, height, width), np.float32)
        return acc, total
    return [], acc[0]


def _synthesize(model: NoiseModel, width: int, height: int, scale: float, seed: int,
                with_layers: bool, tile: int | None = None) -> NoiseLayers:
    """Shared synthesis; without layers the sum is formed in the frequency domain (one inverse FFT per component).

    Outputs over TILE_PIXELS (or with an explicit ``tile``) are built from blended tiles (see _tiled_fields)."""
    if int(width) < 1 or int(height) < 1 or not scale > 0 or not np.isfinite(scale):
        raise InputError(f"synthesize: bad size {width}x{height} or scale {scale}")
    width, height = int(width), int(height)
    t = tile_size(model, width, height, scale, tile)
    if t is None:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x6E6F6973]))
        layers_c, total = _fields(model, width, height, scale, rng, with_layers)
    else:
        layers_c, total = _tiled_fields(model, width, height, scale, seed, t, with_layers)
    layers = [np.ascontiguousarray(np.moveaxis(v, 0, -1)) for v in layers_c]
    del layers_c
    total += model.base.astype(np.float32)[:, None, None]
    if model.transport is not None:
        total = model.transport.apply(total)
    matched = np.ascontiguousarray(np.moveaxis(histogram_match(total, model.quantiles, channel_axis=0), 0, -1))
    return NoiseLayers(base=model.base.copy(), layers=layers, matched=matched)


def synthesize_layers(model: NoiseModel, width: int, height: int, scale: float = 1.0, seed: int = 0,
                      tile: int | None = None) -> NoiseLayers:
    """Procedural synthesis at any size/scale from the stored parameters only; same seed -> same output.

    ``scale`` = output pixels per fitted pixel of pattern. Layers are zero-mean, in the original colour space;
    ``matched`` = base + sum(layers), colour-transported (colour maps) and histogram-matched. Output is periodic
    (tiles) in both directions.
    """
    return _synthesize(model, width, height, scale, seed, with_layers=True, tile=tile)


def synthesize(model: NoiseModel, width: int, height: int, scale: float = 1.0, seed: int = 0,
               tile: int | None = None) -> np.ndarray:
    """The histogram-matched noise map HxWxC (see :func:`synthesize_layers`; same values, faster: no layers)."""
    return _synthesize(model, width, height, scale, seed, with_layers=False, tile=tile).matched


def noise_params(model: NoiseModel, filters: list[dict] | None = None, c: float = 1.0, d: float = 0.0,
                 seed: int | None = None) -> dict:
    """Node params for a fitted model with optional recomposition filters (one dict per layer)."""
    p = model.to_params()
    p["filters"] = filters if filters is not None else [{"a": 1.0, "b": 0.0, "sigma": 0.0} for _ in model.layers]
    p["c"], p["d"] = c, d
    if seed is not None:
        p["seed"] = int(seed)
    return p
