"""The decomposition tree and the working material store themselves as a JSON document plus named arrays."""
from __future__ import annotations

import json

import numpy as np

from workers.maps import Material
from workers.tree import MaskNode, root_node


def test_tree_round_trip_keeps_masks_mattes_shares_and_meta():
    rng = np.random.default_rng(0)
    tree = root_node(24, 32)
    tree.method = "instances"
    a = rng.random((24, 32)) > 0.5
    labels = rng.integers(0, 9, (24, 32))
    tree.shares = [np.float64(0.25), 0.75]
    tree.meta = {"instance_labels": labels, "instance_kinds": np.array([0, 1, 1]), "separate": np.float32(2.5),
                 "lattice": {"period": (12.0, 8.0)}}
    tree.children = [MaskNode("root.0", a, alpha=rng.random((24, 32)).astype(np.float32)), MaskNode("root.1", ~a)]
    doc, arrays = tree.to_arrays()
    doc = json.loads(json.dumps(doc))                          # the document is plain JSON
    assert set(arrays) == {"mask_root", "mask_root.0", "mask_root.1", "alpha_root.0", "meta_root__instance_labels"}
    back = MaskNode.from_arrays(doc, arrays)
    assert [n.id for n in back.walk()] == ["root", "root.0", "root.1"] and back.method == "instances"
    assert back.shares == [0.25, 0.75]
    assert np.array_equal(back.children[0].mask, a) and np.array_equal(back.children[1].mask, ~a)
    assert np.array_equal(back.children[0].alpha, tree.children[0].alpha) and back.children[1].alpha is None
    assert np.array_equal(back.meta["instance_labels"], labels)            # a large array: stored as an array
    assert back.meta["instance_kinds"] == [0, 1, 1] and back.meta["separate"] == 2.5
    assert back.meta["lattice"] == {"period": [12.0, 8.0]}
    assert doc["summary"]["children"][0]["coverage"] == float(a.mean())


def test_material_round_trip():
    rng = np.random.default_rng(1)
    mat = Material(albedo=rng.random((8, 10, 3)).astype(np.float32), roughness=rng.random((8, 10, 1)),
                   name="m", height_scale=2.5, normal_tilt=(0.1, -0.2), meta={"original_size": [20, 16]})
    arrays, meta = mat.to_arrays()
    back = Material.from_arrays(arrays, json.loads(json.dumps(meta)))
    assert set(back.maps()) == {"albedo", "roughness"} and back.roughness.dtype == np.float32
    assert np.array_equal(back.albedo, mat.albedo) and np.allclose(back.roughness, mat.roughness)
    assert (back.name, back.height_scale, back.normal_tilt, back.meta, back.size) == \
        ("m", 2.5, (0.1, -0.2), {"original_size": [20, 16]}, (10, 8))
