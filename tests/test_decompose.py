"""decompose(): spec validation, tree ids, hierarchical and instance splits, and a real brick wall."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from tests.conftest import real_material_files
from workers.decompose import decompose, validate_spec
from workers.errors import InputError, ManifestError


def two_textures_with_tiles(n: int = 128, seed: int = 0):
    """Left 3/8: 13x13 tiles of two reds (checkerboard) on light grey mortar; right 5/8: blue plaster."""
    rng = np.random.default_rng(seed)
    alb = np.zeros((n, n, 3), np.float32)
    tile_kind = np.full((n, n), -1)
    for i in range(n // 16):
        for j in range(3):
            k = (i + j) % 2
            alb[i * 16 + 2:i * 16 + 15, j * 16 + 2:j * 16 + 15] = (0.5, 0.1, 0.05) if k else (0.25, 0.06, 0.03)
            tile_kind[i * 16 + 2:i * 16 + 15, j * 16 + 2:j * 16 + 15] = k
    alb[(tile_kind < 0)] = 0.7
    alb[:, 48:] = (0.1, 0.2, 0.6)
    alb += 0.02 * rng.standard_normal(alb.shape).astype(np.float32)
    return np.clip(alb, 0, 1), tile_kind


def test_validate_spec_names_every_bad_field():
    assert validate_spec(None) == {"method": "matting", "layers": 2}
    bad = {"method": "matting", "layers": 9, "spektral_weight": 1,
           "children": {"0": {"method": "instances", "min_side": 0}, "2": {"method": "leaf"},
                        "x": {}, "1": {"method": "cluster"}}}
    with pytest.raises(ManifestError) as e:
        validate_spec(bad)
    msg = str(e.value)
    for part in ("decompose.layers", "decompose.spektral_weight", "decompose.children.0.min_side",
                 "decompose.children.x", "decompose.children.1.method"):
        assert part in msg, (part, msg)
    with pytest.raises(ManifestError, match=r"children\.2: this split has only 2 layers"):
        validate_spec({"layers": 2, "children": {"2": {"method": "leaf"}}})
    with pytest.raises(ManifestError, match=r"decompose\.children: a leaf has no children"):
        validate_spec({"method": "leaf", "children": {"0": {}}})
    with pytest.raises(ManifestError, match=r"decompose\.scribbles"):
        validate_spec({"scribbles": "strokes.png"})


def test_default_spec_and_hierarchy_ids_and_partition():
    alb, tile_kind = two_textures_with_tiles()
    maps = {"albedo": alb}
    root = decompose(maps, None)
    assert root.method == "matting" and [c.id for c in root.children] == ["root.0", "root.1"]
    # scribbles: blue (0,0,255) = layer 0 on the plaster, red = layer 1 on the tiled part;
    # then tiles+mortar -> tiles (larger, 0) | mortar (1) automatically -> tiles split by instances
    scrib = np.zeros((128, 128, 3), np.uint8)
    scrib[10:120, 100:104] = (0, 0, 255)
    scrib[10:120, 24:25] = (255, 0, 0)
    spec = {"method": "matting", "scribbles": scrib, "spectral_weight": 0.0,
            "children": {"1": {"layers": 2, "spectral_weight": 0.0,
                               "children": {"0": {"method": "instances", "min_side": 8}}}}}
    root = decompose(maps, spec, seed=1)
    ids = [n.id for n in root.walk()]
    assert ids == ["root", "root.0", "root.1", "root.1.0", "root.1.0.0", "root.1.0.1", "root.1.1"], ids
    for node in root.walk():
        if node.children:  # children partition their parent exactly
            stack = np.stack([c.mask for c in node.children]).astype(int)
            assert (stack.sum(0) == node.mask).all(), node.id
    plaster, left = root.children
    assert plaster.mask[:, 50:].mean() > 0.99 and plaster.mask[:, :46].mean() < 0.01
    tiles_node, mortar = left.children
    assert (tiles_node.mask == (tile_kind >= 0)).mean() > 0.97
    assert tiles_node.method == "instances" and tiles_node.meta["kept"] == 24
    np.testing.assert_allclose(tiles_node.shares, [0.5, 0.5])
    for child in tiles_node.children:
        kinds = tile_kind[child.mask & (tile_kind >= 0)]
        purity = np.bincount(kinds).max() / kinds.size
        assert purity > 0.97, (child.id, purity)
    desc = root.describe()
    assert desc["children"][1]["children"][0]["shares"] == [0.5, 0.5]


def test_dict_maps_with_normal_only_and_bad_inputs():
    alb, _ = two_textures_with_tiles(64)
    normal = np.dstack([np.zeros((64, 64)), np.zeros((64, 64)), np.ones((64, 64))]).astype(np.float32)
    root = decompose({"albedo": alb, "normal": normal, "roughness": alb[..., :1]}, {"layers": 2})
    assert root.meta["features"] == ["r", "g", "b", "height", "roughness"]
    with pytest.raises(InputError, match="roughness is 32x32"):
        decompose({"albedo": alb, "roughness": np.zeros((32, 32))})
    with pytest.raises(InputError, match="albedo"):
        decompose({"height": alb[..., 0]})
    scrib = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(InputError, match=r"my_strokes\.png"):
        decompose({"albedo": alb}, {"scribbles": scrib, "scribbles_source": "my_strokes.png"})


def test_real_bricks_auto_split_separates_mortar(materials_dir, artifacts_dir):
    """Automatic 2-layer colour split (structure first off) of castle_brick_broken_06 at 256 px.

    Check: the mortar layer (the lighter of the two) is rougher, covers less than half the wall, and is thin
    (mean distance to its own boundary smaller than the bricks layer's). Masks go to artifacts/decompose.
    """
    from workers.maps import load_material, write_image

    f = real_material_files("castle_brick_broken_06")
    mat = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                        working_size=256)
    root = decompose(mat, {"method": "matting", "layers": 2, "structure": False}, seed=0)  # the colour matting
    assert len(root.children) == 2
    lum = [float(mat.albedo[c.mask].mean()) for c in root.children]
    mortar, bricks = (root.children[i] for i in np.argsort(lum)[::-1])
    fig = {}
    for name, node in (("mortar", mortar), ("bricks", bricks)):
        m = node.mask
        lab, ncomp = ndimage.label(m)
        fig[name] = {"id": node.id, "share": float(m.mean()), "luminance": float(mat.albedo[m].mean()),
                     "roughness": float(mat.roughness[..., 0][m].mean()),
                     "height": float(mat.height[..., 0][m].mean()),
                     "thickness": float(ndimage.distance_transform_edt(m)[m].mean()), "components": int(ncomp)}
    print("castle_brick_broken_06 auto split:", fig, root.meta.get("seconds"))
    out = artifacts_dir / "decompose"
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "castle_brick_broken_06_mortar.png", mortar.mask.astype(np.float32))
    write_image(out / "castle_brick_broken_06_bricks.png", bricks.mask.astype(np.float32))
    write_image(out / "castle_brick_broken_06_albedo.png", mat.albedo ** (1 / 2.2))
    assert fig["mortar"]["luminance"] > 1.5 * fig["bricks"]["luminance"]
    assert fig["mortar"]["roughness"] > fig["bricks"]["roughness"]
    assert 0.15 < fig["mortar"]["share"] < 0.5
    assert fig["mortar"]["thickness"] < 0.9 * fig["bricks"]["thickness"]
