"""workers.graph: the procedural material file (format, validation, evaluation, editing, array encoding)."""
from __future__ import annotations

import base64
import json
import zlib

import numpy as np
import pytest

from workers import graph
from workers.arrays import decode_array, encode_array
from workers.errors import GraphError
from workers.graph import evaluate, load, new_material, save, set_param
from workers.nodes import EvalContext, NodeType, gaussian_blur, register_node


@register_node
class _StripesNode(NodeType):
    """Test-only generator: vertical sine stripes whose period (working-size px) follows the pattern scale."""

    name = "test_stripes"
    inputs: tuple[str, ...] = ()

    def validate(self, params: dict) -> None:
        if not params.get("period", 0) > 0:
            raise GraphError("test_stripes.period must be > 0")

    def evaluate(self, params, inputs, ctx, node_id):
        x = np.arange(ctx.width, dtype=np.float32)
        v = 0.5 + 0.5 * np.sin(2 * np.pi * x / (params["period"] * ctx.px_scale))
        return np.broadcast_to(v[None, :, None], (ctx.height, ctx.width, 1)).copy()


def brick_like() -> graph.ProceduralMaterial:
    """A small graph using every built-in node type, with an encoded array in a param."""
    m = new_material(seed=7, working_size=(64, 64))
    m.add("stripes", "test_stripes", {"period": 16.0})
    m.add("mask", "blur", {"sigma": 1.5}, input="stripes")
    m.add("red", "constant", {"value": [0.6, 0.2, 0.1]})
    m.add("grey", "constant", {"value": [0.3, 0.3, 0.3]})
    m.add("albedo", "blend", {"sigma": 0.0}, mask="mask", fg="red", bg="grey")
    m.add("r0", "constant", {"value": 0.8})
    m.add("r1", "level", {"a": 0.5, "d": 0.1, "clamp": True}, input="stripes")
    m.add("inv", "level", {"a": -1.0, "d": 1.0}, input="mask")
    m.add("rough", "blend", {"sigmas": [0.0, 2.0]}, mask0="mask", child0="r0", mask1="inv", child1="r1")
    m.add("h_sum", "add", {}, a="mask", b="r1")
    m.add("height", "clamp", {"lo": 0.0, "hi": 1.0}, input="h_sum")
    m.add("pick", "channel", {"channels": [0]}, input="albedo")
    m.maps = [{"name": "albedo", "node": "albedo", "colorspace": "srgb"},
              {"name": "roughness", "node": "rough"},
              {"name": "height", "node": "height"},
              {"name": "red_only", "node": "pick"},
              {"name": "normal", "from_height": "height", "strength": 4.0}]
    m.meta = {"lut": encode_array(np.linspace(0, 1, 17)), "source": "test"}
    return m


def test_save_load_round_trip(tmp_path):
    m = brick_like()
    p = save(m, tmp_path / "sub" / "material.json")
    doc = json.loads(p.read_text())
    assert doc["format"] == "proceduralize/1.3" and doc["seed"] == 7 and doc["working_size"] == [64, 64]
    m2 = load(p)
    assert m2.to_json() == m.to_json()
    a, b = evaluate(m, 48, 40), evaluate(m2, 48, 40)
    assert set(a) == {"albedo", "roughness", "height", "red_only", "normal"}
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert np.allclose(decode_array(m2.meta["lut"]), np.linspace(0, 1, 17), atol=1e-3)


def test_evaluate_sizes_and_values():
    m = brick_like()
    for w, h in [(16, 16), (64, 64), (100, 37), (257, 129)]:
        out = evaluate(m, w, h)
        assert out["albedo"].shape == (h, w, 3) and out["roughness"].shape == (h, w, 1)
        assert out["normal"].shape == (h, w, 3) and out["albedo"].dtype == np.float32
        assert np.allclose(np.linalg.norm(out["normal"], axis=-1), 1.0, atol=1e-5)
        assert 0.0 <= out["albedo"].min() and out["albedo"].max() <= 1.0
    out = evaluate(m, 64, 8)
    mask = out["height"]  # == clamp(mask + r1)
    assert np.allclose(out["red_only"][..., 0], out["albedo"][..., 0])
    only = evaluate(m, 64, 8, maps=["normal"])
    assert set(only) == {"normal"} and np.allclose(only["normal"], out["normal"])
    assert mask.shape == (8, 64, 1)
    with pytest.raises(GraphError, match="bad evaluation size"):
        evaluate(m, 0, 10)


def test_blend_forms_give_expected_values():
    m = new_material()
    m.add("one", "constant", {"value": 1.0})
    m.add("zero", "constant", {"value": 0.0})
    m.add("a", "constant", {"value": [0.2, 0.4, 0.6]})
    m.add("b", "constant", {"value": [1.0, 0.0, 0.5]})
    m.add("half", "constant", {"value": 0.25})
    m.add("fgbg", "blend", {}, mask="half", fg="a", bg="b")
    m.add("multi", "blend", {"sigmas": [0, 0]}, mask0="one", child0="a", mask1="zero", child1="b")
    m.maps = [{"name": "fgbg", "node": "fgbg"}, {"name": "multi", "node": "multi"}]
    out = evaluate(m, 4, 4)
    assert np.allclose(out["fgbg"][0, 0], 0.25 * np.array([0.2, 0.4, 0.6]) + 0.75 * np.array([1.0, 0.0, 0.5]))
    assert np.allclose(out["multi"], [0.2, 0.4, 0.6])


def stripe_contrast(img: np.ndarray) -> float:
    return float(img.max() - img.min())


def test_blur_and_pattern_follow_scale():
    """Pattern and blur both scale with `scale`: at scale 2 and twice the size the result is the same image
    upsampled (same contrast), while a blur that ignored scale would flatten the stripes less."""
    m = new_material()
    m.add("s", "test_stripes", {"period": 8.0})
    m.add("b", "blur", {"sigma": 2.0}, input="s")
    m.maps = [{"name": "height", "node": "b", "clamp": False}]
    c1 = stripe_contrast(evaluate(m, 64, 4)["height"])
    c2 = stripe_contrast(evaluate(m, 128, 4, scale=2.0)["height"])
    assert c1 == pytest.approx(c2, rel=0.02)
    expected = np.exp(-0.5 * (2 * np.pi * 2.0 / 8.0) ** 2)  # Gaussian attenuation of a sine
    assert c1 == pytest.approx(expected, rel=0.05)
    ctx = EvalContext(width=128, height=4, scale=2.0)
    unscaled = gaussian_blur(_StripesNode().evaluate({"period": 8.0}, {}, ctx, "s"), 2.0)
    assert stripe_contrast(unscaled) > c2 + 0.2


def test_normal_from_height_zooms_with_scale_and_keeps_tilt():
    """scale zooms the relief: the same slopes at scale 2 and twice the size; a stored tilt is applied."""
    m = new_material()
    m.add("s", "test_stripes", {"period": 16.0})
    m.maps = [{"name": "height", "node": "s"},
              {"name": "normal", "from_height": "height", "strength": 8.0, "tilt": [0.0, 0.1]}]
    n1 = evaluate(m, 64, 8)["normal"]
    n2 = evaluate(m, 128, 8, scale=2.0)["normal"]
    assert float(np.abs(n1[..., 0]).max()) == pytest.approx(float(np.abs(n2[..., 0]).max()), rel=0.03)
    assert float(np.abs(n1[..., 0]).max()) > 0.5
    assert np.allclose(n1[..., 1] / n1[..., 2], 0.1, atol=1e-5)  # OpenGL: +tilt along rows -> ny > 0


def test_seed_and_rng_are_deterministic():
    c = EvalContext(width=4, height=4, seed=3)
    assert np.array_equal(c.rng("a").random(5), EvalContext(4, 4, seed=3).rng("a").random(5))
    assert not np.array_equal(c.rng("a").random(5), c.rng("b").random(5))
    assert not np.array_equal(c.rng("a").random(5), EvalContext(4, 4, seed=4).rng("a").random(5))
    assert c.node_seed("a") == EvalContext(4, 4, seed=3).node_seed("a")


@pytest.mark.parametrize("doc,pattern", [
    ({"format": "proceduralize/2", "nodes": [], "maps": []}, "unsupported format 'proceduralize/2'"),
    ({"nodes": [], "maps": []}, "unsupported format None"),
    ([1, 2], "top level must be a JSON object"),
    ({"format": "proceduralize/1", "nodes": {}, "maps": []}, "'nodes' and 'maps' must be lists"),
    ({"format": "proceduralize/1", "nodes": [{"type": "constant"}], "maps": []}, r"nodes\[0\] needs string 'id'"),
    ({"format": "proceduralize/1", "nodes": [{"id": "x", "type": "warp9"}], "maps": []}, "unknown type 'warp9'"),
    ({"format": "proceduralize/1", "nodes": [{"id": "x", "type": "blur", "params": {"sigma": -1},
                                              "inputs": {}}], "maps": []}, "blur.sigma"),
    ({"format": "proceduralize/1", "nodes": [{"id": "x", "type": "blur", "inputs": {"input": "y"}}], "maps": []},
     "refers to missing node 'y'"),
    ({"format": "proceduralize/1", "nodes": [], "maps": [{"name": "albedo", "node": "q"}]}, "missing node 'q'"),
    ({"format": "proceduralize/1", "nodes": [], "maps": [{"name": "normal", "from_height": "height"}]},
     "derives from missing map 'height'"),
    ({"format": "proceduralize/1", "nodes": [{"id": "c", "type": "constant", "params": {"value": 1}},
                                             {"id": "c", "type": "constant", "params": {"value": 2}}], "maps": []},
     "duplicate node id 'c'"),
    ({"format": "proceduralize/1", "nodes": [{"id": "blend_root.0", "type": "constant", "params": {"value": 1}}],
      "maps": []}, "contain no '.'"),
    ({"format": "proceduralize/1.2", "nodes": [{"id": "r", "type": "piece_ramps", "params": {"ramp": [[0, 1]]}}],
      "maps": []}, "a piece_ramps node needs format 'proceduralize/1.3' or later"),
    ({"format": "proceduralize/1.1", "nodes": [{"id": "p", "type": "pptbf", "params": {
        "params": [0.5, 0, 0.1, 32.0, 0, 1.0] + [0.0] * 23, "ref_width": 64, "field": "value"}}], "maps": []},
     "'field' needs format 'proceduralize/1.2'"),
])
def test_malformed_documents_rejected(tmp_path, doc, pattern):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(GraphError, match=pattern) as exc:
        load(p)
    assert "bad.json" in str(exc.value)


def test_older_formats_still_read_what_they_introduced(tmp_path):
    """A 1.2 document with a pptbf node's field and a 1.1 one with input_size load (each feature needs the format
    that introduced it or a later one, not the current one)."""
    pptbf = {"id": "p", "type": "pptbf", "params": {"params": [0.5, 0, 0.1, 32.0, 0, 1.0] + [0.0] * 23,
                                                       "field": "value", "ref_width": 64}}
    for fmt, doc in (("proceduralize/1.2", {"nodes": [pptbf]}),
                     ("proceduralize/1.1", {"nodes": [], "input_size": [64, 64]})):
        p = tmp_path / "old.json"
        p.write_text(json.dumps({"format": fmt, "maps": [], **doc}))
        assert load(p).nodes.keys() == {n["id"] for n in doc["nodes"]}


def test_unreadable_files_rejected(tmp_path):
    with pytest.raises(GraphError, match=r"missing\.json: file not found"):
        load(tmp_path / "missing.json")
    (tmp_path / "trunc.json").write_text('{"format": "proceduralize/1", "nodes": [')
    with pytest.raises(GraphError, match=r"trunc\.json: not valid JSON"):
        load(tmp_path / "trunc.json")


def test_cycles_rejected(tmp_path):
    doc = {"format": "proceduralize/1", "maps": [{"name": "h", "node": "a"}], "nodes": [
        {"id": "a", "type": "blur", "params": {"sigma": 1}, "inputs": {"input": "b"}},
        {"id": "b", "type": "level", "params": {}, "inputs": {"input": "c"}},
        {"id": "c", "type": "add", "params": {}, "inputs": {"x": "a"}}]}
    (tmp_path / "cyc.json").write_text(json.dumps(doc))
    with pytest.raises(GraphError, match="cycle through node"):
        load(tmp_path / "cyc.json")
    m = new_material()
    m.add("a", "level", {}, input="a")
    m.maps = [{"name": "h", "node": "a"}]
    with pytest.raises(GraphError, match="cycle"):
        save(m, tmp_path / "never.json")
    assert not (tmp_path / "never.json").exists()


def test_set_param_edits_and_validates(tmp_path):
    m = brick_like()
    before = evaluate(m, 32, 8)["albedo"]
    set_param(m, "red.value", [0.1, 0.9, 0.1])
    set_param(m, "rough.sigmas.1", 0.5)
    set_param(m, "seed", 99)
    assert m.nodes["rough"]["params"]["sigmas"] == [0.0, 0.5] and m.seed == 99
    after = evaluate(m, 32, 8)["albedo"]
    assert float(after[..., 1].max()) > float(before[..., 1].max()) + 0.3
    with pytest.raises(GraphError, match="no parameter 'colour'"):
        set_param(m, "red.colour", 1.0)
    with pytest.raises(GraphError, match="no node with id 'nope'"):
        set_param(m, "nope.value", 1.0)
    with pytest.raises(GraphError, match="blur.sigma"):
        set_param(m, "mask.sigma", -2.0)
    with pytest.raises(GraphError, match="node_id.param"):
        set_param(m, "justaname", 1)
    m.nodes["mask"]["params"]["sigma"] = 1.5
    assert load(save(m, tmp_path / "m.json")).nodes["red"]["params"]["value"] == [0.1, 0.9, 0.1]


def test_node_errors_are_graph_errors():
    m = new_material()
    m.add("c", "constant", {"value": [0.1, 0.2]})
    m.add("p", "channel", {"channels": [3]}, input="c")
    m.maps = [{"name": "x", "node": "p"}]
    with pytest.raises(GraphError, match="input has 2 channels"):
        evaluate(m, 4, 4)
    with pytest.raises(GraphError, match="duplicate node id"):
        m.add("c", "constant", {"value": 1})
    with pytest.raises(GraphError, match="contain no '.'"):   # edit paths are node.param: ids cannot hold dots
        m.add("mask_root.0", "constant", {"value": 1})


def test_encode_decode_arrays():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 5, 7)).astype(np.float32)
    enc = encode_array(a)
    assert enc["dtype"] == "float16" and enc["shape"] == [3, 5, 7]
    assert np.allclose(decode_array(enc), a, rtol=1e-3, atol=1e-3) and decode_array(enc).dtype == np.float32
    assert np.array_equal(decode_array(encode_array(a, "float32")), a)
    u = rng.integers(0, 255, size=100).astype(np.uint8)
    assert np.array_equal(decode_array(encode_array(u, "uint8")), u)
    assert np.array_equal(decode_array([[1, 2], [3, 4]]), np.array([[1, 2], [3, 4]], np.float32))
    smooth = np.zeros(4096, np.float32)
    assert len(json.dumps(encode_array(smooth))) < 200  # compressed
    with pytest.raises(GraphError, match="corrupt array"):
        decode_array({"__array__": True, "dtype": "float16", "shape": [4], "data": "!!notbase64"})
    with pytest.raises(GraphError, match="corrupt array"):
        decode_array({**enc, "shape": [2, 2]})


def test_no_pickles(tmp_path):
    """The file is plain JSON; an object-dtype array (the only way to smuggle a pickle) is refused."""
    m = brick_like()
    text = save(m, tmp_path / "m.json").read_text()
    doc = json.loads(text)
    arrays = []

    def walk(o):
        if isinstance(o, dict):
            if o.get("__array__"):
                arrays.append(o)
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(doc)
    assert arrays and all(np.dtype(a["dtype"]).kind in "fiub" for a in arrays)
    evil = {"__array__": True, "dtype": "O", "shape": [1],
            "data": base64.b64encode(zlib.compress(b"\x80\x04K\x01.")).decode()}
    with pytest.raises(GraphError):
        decode_array(evil)
