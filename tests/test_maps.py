"""workers.maps: image I/O round trips, validation errors, colour spaces, resizing, material loading."""
from __future__ import annotations

import logging
import struct
import time
import zlib

import numpy as np
import pytest

from tests.conftest import real_material_files
from workers.errors import InputError
from workers.height import height_to_normal
from workers.maps import (
    Material,
    inspect_image,
    linear_to_srgb,
    load_material,
    read_image,
    resize_image,
    save_material,
    srgb_to_linear,
    write_image,
)


@pytest.fixture
def rand_img():
    return np.random.default_rng(0).random((37, 53, 3)).astype(np.float32)


def smooth_img(h: int = 64, w: int = 80) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    return np.stack([x, y, 0.5 + 0.3 * np.sin(6 * x + 4 * y)], axis=-1).astype(np.float32)


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext,bits,tol", [
    ("png", 8, 0.5 / 255 + 1e-6),
    ("png", 16, 0.5 / 65535 + 1e-7),
    ("tif", 8, 0.5 / 255 + 1e-6),
    ("tif", 16, 0.5 / 65535 + 1e-7),
    ("tif", "float", 0.0),
    ("exr", "float", 0.0),
    ("exr", "half", 2.5e-4),
])
def test_write_read_round_trip(tmp_path, rand_img, ext, bits, tol):
    p = write_image(tmp_path / f"img.{ext}", rand_img, bits=bits)
    back = read_image(p)
    assert back.shape == rand_img.shape and back.dtype == np.float32
    assert float(np.abs(back - rand_img).max()) <= tol
    info = inspect_image(p)
    assert info["bit_depth"] == {8: 8, 16: 16, "half": 16, "float": 32}[bits]
    assert (info["width"], info["height"]) == (53, 37) and len(info["channels"]) == 3


def test_exr_keeps_values_outside_unit_range(tmp_path):
    a = np.array([[[-2.5, 0.0, 7.25]]], dtype=np.float32)
    assert np.array_equal(read_image(write_image(tmp_path / "hdr.exr", a, bits="float")), a)


def test_jpeg_round_trip_is_close(tmp_path):
    a = smooth_img()
    back = read_image(write_image(tmp_path / "s.jpg", a, bits=8))
    assert float(np.abs(back - a).mean()) < 0.01 and float(np.abs(back - a).max()) < 0.1


@pytest.mark.parametrize("bits", [8, 16])
def test_png_alpha_is_not_premultiplied(tmp_path, bits):
    a = np.zeros((8, 8, 4), np.float32)
    a[..., :3] = [0.8, 0.4, 0.2]
    a[..., 3] = 0.25
    a[0, 0, 3] = 0.0  # fully transparent pixel keeps its colour
    back = read_image(write_image(tmp_path / "rgba.png", a, bits=bits))
    assert np.allclose(back[..., :3], [0.8, 0.4, 0.2], atol=1 / 255)
    assert np.allclose(back[..., 3], a[..., 3], atol=1 / 255)


def test_grey_and_channel_picks(tmp_path, rand_img):
    p = write_image(tmp_path / "rgb.png", rand_img, bits=16)
    assert np.allclose(read_image(p, "G")[..., 0], rand_img[..., 1], atol=1e-4)
    assert np.allclose(read_image(p, 2)[..., 0], rand_img[..., 2], atol=1e-4)
    assert read_image(p, ["B", "R"]).shape == (37, 53, 2)
    g = write_image(tmp_path / "grey.png", rand_img[..., 0])
    assert read_image(g).shape == (37, 53, 1)
    with pytest.raises(InputError, match=r"grey\.png.*no channel 'G'"):
        read_image(g, "G")
    with pytest.raises(InputError, match="out of range"):
        read_image(p, 5)


def test_write_rejects_bad_format_combinations(tmp_path, rand_img):
    with pytest.raises(InputError, match="png cannot hold bits='half'"):
        write_image(tmp_path / "x.png", rand_img, bits="half")
    with pytest.raises(InputError, match="JPEG"):
        write_image(tmp_path / "x.jpg", np.ones((4, 4, 4)))
    with pytest.raises(InputError, match="extension"):
        write_image(tmp_path / "x.bmpx", rand_img)
    with pytest.raises(InputError, match="NaN"):
        write_image(tmp_path / "x.exr", np.full((2, 2), np.nan), bits="float")


# ----------------------------------------------------------------------------- bad files


def test_missing_truncated_and_garbage_files(tmp_path, rand_img):
    with pytest.raises(InputError, match=r"nope\.png: file not found"):
        read_image(tmp_path / "nope.png")
    raw = write_image(tmp_path / "ok.png", rand_img, bits=16).read_bytes()
    (tmp_path / "trunc.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputError, match=r"trunc\.png: unreadable or truncated"):
        read_image(tmp_path / "trunc.png")
    (tmp_path / "random.png").write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(InputError, match=r"random\.png: cannot read as an image"):
        read_image(tmp_path / "random.png")


def test_nan_in_exr_rejected(tmp_path):
    import OpenImageIO as oiio

    a = np.ones((4, 5, 3), np.float32)
    a[1, 2, 0] = np.nan
    a[3, 3, 2] = np.inf
    path = tmp_path / "nan.exr"
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(5, 4, 3, oiio.FLOAT))
    out.write_image(a)
    out.close()
    with pytest.raises(InputError, match=r"nan\.exr: 2 pixel values are NaN or infinite"):
        read_image(path)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_pixel_limit_checked_from_header_before_decoding(tmp_path):
    """A 20000x20000 'decompression bomb' header with almost no data is refused before decoding (by our
    pixel limit or OpenImageIO's own header sanity check), fast and without allocating it."""
    ihdr = struct.pack(">IIBBBBB", 20_000, 20_000, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 1000)
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat)
                     + _png_chunk(b"IEND", b""))
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"bomb\.png: .*(exceeds the limit|header claims)"):
        read_image(bomb)
    assert time.perf_counter() - t0 < 1.0
    small = write_image(tmp_path / "small.png", np.zeros((10, 10)))
    with pytest.raises(InputError, match="exceeds the limit of 50"):
        read_image(small, max_pixels=50)


# ----------------------------------------------------------------------------- colour and resize


def test_srgb_curves():
    assert float(srgb_to_linear(np.float32(0.5))) == pytest.approx(0.21404, abs=1e-4)
    assert float(linear_to_srgb(np.float32(0.21404))) == pytest.approx(0.5, abs=1e-4)
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    assert np.abs(linear_to_srgb(srgb_to_linear(x)) - x).max() < 1e-5
    assert srgb_to_linear(np.float32(0.02)) == pytest.approx(0.02 / 12.92)


def test_resize_area_and_antialiased():
    rng = np.random.default_rng(0)
    a = rng.random((64, 96, 3)).astype(np.float32)
    half = resize_image(a, 48, 32)
    assert np.allclose(half[0, 0], a[:2, :2].mean(axis=(0, 1)), atol=1e-6)  # exact 2x2 block mean
    odd = resize_image(a, 35, 23)
    assert odd.shape == (23, 35, 3) and abs(float(odd.mean() - a.mean())) < 0.01
    assert float(odd.std()) < float(a.std()) * 0.5  # antialiased: white noise is averaged, not aliased
    assert resize_image(a[..., 0], 48, 32).shape == (32, 48)
    assert resize_image(a, 128, 192).shape == (192, 128, 3)


# ----------------------------------------------------------------------------- materials


def test_load_real_material(materials_dir):
    f = real_material_files("castle_brick_broken_06")
    m = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel="G", working_size=128)
    assert isinstance(m, Material) and m.name == "castle_brick_broken_06" and m.size == (128, 128)
    assert m.albedo.shape == (128, 128, 3) and m.roughness.shape == (128, 128, 1) and m.height.shape == (128, 128, 1)
    srgb = read_image(f["albedo"])
    assert np.allclose(m.albedo, resize_image(srgb_to_linear(srgb), 128, 128), atol=1e-6)  # linear, averaged
    assert float(m.albedo.mean()) < float(srgb.mean()) - 0.1
    rough = resize_image(read_image(f["roughness"], "G"), 128, 128)
    assert np.allclose(m.roughness, rough, atol=1e-6)
    assert np.allclose(np.linalg.norm(m.normal, axis=-1), 1.0, atol=1e-5)
    assert float(m.normal[..., 2].mean()) > 0.8
    assert m.height.min() == 0.0 and m.height.max() == pytest.approx(1.0) and m.height_scale > 1.0
    assert m.meta["height_source"] == "normal" and m.meta["original_size"] == [1024, 1024]
    assert set(m.sources) == {"albedo", "normal", "roughness"}
    mm = load_material(f["albedo"], metallic=f["roughness"], metallic_channel="B", working_size=64)
    assert np.allclose(mm.metallic, resize_image(read_image(f["roughness"], "B"), 64, 64), atol=1e-6)
    assert mm.height is None and mm.normal is None and set(mm.maps()) == {"albedo", "metallic"}


def test_packed_rgb_roughness_without_channel_warns(materials_dir, caplog):
    f = real_material_files("castle_brick_broken_06")
    with caplog.at_level(logging.WARNING, logger="workers.maps"):
        m = load_material(f["albedo"], roughness=f["roughness"], working_size=64)
    assert "roughness_channel" in caplog.text and m.roughness.shape == (64, 64, 1) and m.normal is None


def test_size_mismatch_names_both_files(tmp_path, rand_img):
    a = write_image(tmp_path / "a.png", rand_img)
    r = write_image(tmp_path / "r.png", rand_img[:20, :20, 0])
    with pytest.raises(InputError, match=r"r\.png: roughness map is 20x20 but the albedo .*a\.png is 53x37"):
        load_material(a, roughness=r)


def test_bad_normal_maps_rejected(tmp_path, rand_img):
    a = write_image(tmp_path / "a.png", rand_img)
    grey = write_image(tmp_path / "n1.png", rand_img[..., 0])
    with pytest.raises(InputError, match=r"n1\.png: a normal map needs 3 channels"):
        load_material(a, normal=grey)
    heightish = write_image(tmp_path / "n3.png", np.repeat(rand_img[..., :1], 3, axis=2))
    with pytest.raises(InputError, match=r"n3\.png: does not look like a tangent-space normal map"):
        load_material(a, normal=heightish)
    with pytest.raises(InputError, match="normal_convention"):
        load_material(a, normal=write_image(tmp_path / "n.png", np.ones((37, 53, 3)) * [0.5, 0.5, 1.0]),
                      normal_convention="vulkan")


def test_directx_normals_flipped_to_opengl(tmp_path):
    from tests.test_height import periodic_height

    h = periodic_height(64, 64)
    n_gl = height_to_normal(h, strength=6.0)
    n_dx = n_gl * [1, -1, 1]
    a = write_image(tmp_path / "a.png", smooth_img(64, 64))
    p = write_image(tmp_path / "n_dx.png", n_dx * 0.5 + 0.5, bits=16)
    m = load_material(a, normal=p, normal_convention="directx")
    assert np.abs(m.normal - n_gl).max() < 1e-3
    assert m.meta["normal_orientation"] == "directx"
    m_auto = load_material(a, normal=p, normal_convention="auto")
    assert m_auto.meta["normal_orientation"] == "directx" and np.abs(m_auto.normal - n_gl).max() < 1e-3


def test_height_file_scale_fitted_and_arrays_accepted(tmp_path):
    from tests.test_height import periodic_height

    h = periodic_height(64, 96, seed=5)
    n = height_to_normal(h, strength=7.0)
    hp = write_image(tmp_path / "h.png", h, bits=16)
    np_ = write_image(tmp_path / "n.exr", n, bits="float")  # signed float normals are taken as they are
    m = load_material(smooth_img(64, 96), normal=np_, height=hp, albedo_colorspace="linear", name="synth")
    assert m.name == "synth" and m.sources["albedo"] == "<albedo array>"
    assert m.height_scale == pytest.approx(7.0, rel=1e-3) and m.meta["height_source"] == "file"
    assert np.allclose(m.albedo, smooth_img(64, 96))
    only_h = load_material(smooth_img(64, 96), height=h, height_scale=7.0, working_size=(48, 32))
    assert only_h.size == (48, 32) and only_h.normal.shape == (32, 48, 3)
    assert only_h.meta["normal_source"] == "height"


def test_save_material_round_trip(tmp_path, materials_dir):
    f = real_material_files("metal_plate_02")
    m = load_material(f["albedo"], f["normal"], f["roughness"], working_size=96)
    files = save_material(m, tmp_path / "out")
    assert {p.name for p in files.values()} == {"albedo.png", "normal.png", "roughness.png", "height.png",
                                               "maps.json"}
    assert inspect_image(files["height"])["bit_depth"] == 16
    back = load_material(files["albedo"], files["normal"], files["roughness"], files["height"],
                         height_scale=m.height_scale)
    assert float(np.abs(linear_to_srgb(back.albedo) - linear_to_srgb(m.albedo)).max()) <= 0.5 / 255 + 1e-4
    assert float(np.abs(back.roughness - m.roughness).max()) <= 0.5 / 255 + 1e-6
    assert float(np.abs(back.height - m.height).max()) <= 1e-4
    cos = np.clip(np.sum(back.normal * m.normal, axis=-1), -1, 1)
    assert float(np.degrees(np.arccos(cos)).max()) < 1.0
