"""Texture statistics without downloaded weights: Gram matrices of a fixed random conv net, and SSIM.

Architecture of :class:`GramExtractor` (default, weight-free): ``len(widths)`` scales; scale ``i`` is
``conv3x3(c_{i-1} -> widths[i], circular padding) -> ReLU`` whose output is the feature map of that scale,
followed by ``avg-pool 2`` before the next scale. Filters are drawn from ``torch.Generator().manual_seed(seed)``
with He scaling (std = sqrt(2 / fan_in)), biases uniform in [-0.1, 0.1] (so ReLU does not discard half of every
zero-mean response). Random shallow networks give good texture Gram statistics (Ustyuzhaninov et al. 2017), and a
seed makes them identical on every machine, so no weights are ever downloaded.

Input normalisation: inputs are BxCxHxW in [0, 1]; they are centred by subtracting 0.5 per channel (a *fixed*
centre, so the Gram still sees the mean level of a map) before the first convolution.

Optional ``vgg_weights``: path of a local VGG19 ``state_dict`` (torchvision naming ``features.N.weight``); the
network is then VGG19's feature stack up to ``relu4_1`` (Gatys style layers relu1_1, relu2_1, relu3_1, relu4_1),
with ImageNet input normalisation, same interface.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .errors import InputError

logger = logging.getLogger(__name__)

# VGG19 feature stack up to relu4_1: (torchvision index of conv, out channels); "M" = max pool.
_VGG19_CFG: list[int | str] = [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512]
_VGG_STYLE_RELUS = (1, 6, 11, 20)  # torchvision indices of relu1_1, relu2_1, relu3_1, relu4_1
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


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
        if self.vgg:
            self.widths = (64, 128, 256, 512)  # channels of relu1_1 .. relu4_1
            self._build_vgg(Path(vgg_weights))
        else:
            self.widths = tuple(int(w) for w in widths)
            self._build_random()
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

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
        """VGG19 features (torchvision layout) up to relu4_1, weights from a local state_dict file."""
        layers: list[nn.Module] = []
        cin = 3
        for c in _VGG19_CFG:
            if c == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, int(c), 3, padding=1), nn.ReLU(inplace=False)]
                cin = int(c)
        self.features_seq = nn.Sequential(*layers)
        if not path.is_file():
            raise InputError(f"{path}: VGG19 weights file not found (give a local torchvision VGG19 state_dict "
                             f"file, or leave vgg_weights unset to use the weight-free random features)")
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file is an InputError
            raise InputError(f"{path}: cannot read VGG19 weights ({exc}); expected a torch.save'd state_dict") from None
        if not isinstance(sd, dict):
            raise InputError(f"{path}: expected a state_dict (dict of tensors), got {type(sd).__name__}")
        own = {}
        for k, v in self.features_seq.state_dict().items():
            key = f"features.{k}"
            if key not in sd:
                raise InputError(f"{path}: missing VGG19 weight {key!r} (expected torchvision 'features.N.weight' "
                                 f"names of a VGG19 state_dict)")
            if tuple(sd[key].shape) != tuple(v.shape):
                raise InputError(f"{path}: weight {key!r} has shape {tuple(sd[key].shape)}, VGG19 needs "
                                 f"{tuple(v.shape)} (is this a VGG19 file?)")
            own[k] = sd[key].float()
        self.features_seq.load_state_dict(own)
        self.register_buffer("_mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("_std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1))
        logger.info("loaded VGG19 features from %s", path)

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
        return (x - self._mean) / self._std

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Feature maps of every scale, BxC_ixH_ixW_i (H_i = H / 2^i), differentiable w.r.t. ``x``."""
        h = self._prepare(x)
        out: list[torch.Tensor] = []
        if self.vgg:
            for i, layer in enumerate(self.features_seq):
                h = layer(h)
                if i in _VGG_STYLE_RELUS:
                    out.append(h)
            return out
        for i, conv in enumerate(self.convs):
            if i > 0:
                h = F.avg_pool2d(h, 2) if min(h.shape[-2:]) >= 2 else h
            h = F.relu(conv(h))
            out.append(h)
        return out

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Same as :meth:`grams`."""
        return self.grams(x)

    def grams(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> list[torch.Tensor]:
        """Gram matrices (B, c, c) per scale, normalised by the (valid) pixel count.

        ``valid``: optional HxW, Bx1xHxW or BxHxW mask (bool/float); features are weighted by it (downsampled by
        area averaging to each scale) and the Gram is divided by the mask's sum instead of the pixel count.
        """
        feats = self.features(x)
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
