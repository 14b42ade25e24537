"""Scale semantics of material.json: scale 1 = the input's pattern size (format 1.1 records the input size);
files of format 1 keep scale 1 = the working size's pattern."""
from __future__ import annotations

import json

import numpy as np
import pytest

from workers import graph as G
from workers import lattice as L
from workers.errors import GraphError
from workers.masks import downsample_mask

INPUT, WORKING, PERIOD = 256, 128, 32   # a brick wall with 32 px courses in a 256 px input, fitted at 128 px


def _running_bond(size: int, period: int) -> np.ndarray:
    """Binary mortar mask: courses ``period`` px apart, bricks 2 periods long, half-bond offset, 3 px joints."""
    y, x = np.mgrid[:size, :size]
    row = y // period
    xs = (x + (row % 2) * period) % (2 * period)
    return (y % period < 3) | (xs < 3)


def _input_period() -> float:
    """The lattice period (shortest lattice vector) of the input mask at the input's size."""
    return float(L.analyse_lattice(_running_bond(INPUT, PERIOD)).period)


def _material(input_size) -> G.ProceduralMaterial:
    """A material whose one PPTBF node lies on the lattice of the input downsampled to the working size."""
    work = downsample_mask(_running_bond(INPUT, PERIOD), WORKING, WORKING)
    lat = L.analyse_lattice(work)
    assert lat.kind == "2d" and lat.period == pytest.approx(_input_period() * WORKING / INPUT, rel=0.05)
    mat = G.new_material(seed=3, working_size=(WORKING, WORKING), input_size=input_size)
    p = L.pptbf_starts(lat, WORKING)[0]
    mat.add("m", "pptbf", {"params": [float(v) for v in p], "ref_width": WORKING, "complement": False})
    mat.maps.append({"name": "height", "node": "m"})
    return mat


def _period(mat: G.ProceduralMaterial, size: int, scale: float = 1.0) -> float:
    h = G.evaluate(mat, size, size, scale=scale, seed=2)["height"][..., 0] > 0.5
    lat = L.analyse_lattice(h)
    assert lat.kind != "none"
    return float(lat.period)


def test_scale_one_is_the_input_pattern_size(tmp_path):
    mat = _material((INPUT, INPUT))
    G.save(mat, tmp_path / "material.json")
    doc = json.loads((tmp_path / "material.json").read_text())
    assert doc["format"] == "proceduralize/1.3" and doc["input_size"] == [INPUT, INPUT]
    loaded = G.load(tmp_path / "material.json")
    assert loaded.pattern_unit == INPUT / WORKING
    # rendered at the input's size, the lattice is the input's (not the working size's, half as large)
    assert _period(loaded, INPUT) == pytest.approx(_input_period(), rel=0.05)
    # a larger canvas extends the surface: same pattern size; --scale still zooms
    assert _period(loaded, 2 * INPUT) == pytest.approx(_input_period(), rel=0.05)
    assert _period(loaded, INPUT, scale=0.5) == pytest.approx(_input_period() / 2, rel=0.05)
    # working_scale draws the pattern as it was at the working size
    working_period = _input_period() * WORKING / INPUT
    assert _period(loaded, WORKING, scale=loaded.working_scale) == pytest.approx(working_period, rel=0.05)


def test_old_files_keep_their_meaning(tmp_path):
    doc = _material(None).to_json()
    doc["format"] = "proceduralize/1"
    old = G.from_json(json.loads(json.dumps(doc)))
    assert old.input_size is None and old.pattern_unit == 1.0
    # the working size's pattern
    assert _period(old, INPUT) == pytest.approx(_input_period() * WORKING / INPUT, rel=0.05)
    bad = dict(doc, input_size=[INPUT, INPUT])
    with pytest.raises(GraphError, match="input_size"):
        G.from_json(bad)
    for v in ([0, 5], [1.5, 2], "256", [256]):
        with pytest.raises(GraphError, match="input_size"):
            G.from_json(dict(doc, format=G.FORMAT, input_size=v))


def test_a_border_cut_needs_the_format_that_knows_it():
    """Format 1.1 readers ignore the pptbf node's ``field`` (they would cut the value): such files are 1.2, a
    1.1 file without it still loads, one with it is refused with the reason."""
    doc = _material((INPUT, INPUT)).to_json()
    mask = next(n for n in doc["nodes"] if n["type"] == "pptbf")
    assert G.from_json(json.loads(json.dumps(dict(doc, format="proceduralize/1.1")))).input_size is not None
    mask["params"]["field"] = "border"
    assert G.from_json(json.loads(json.dumps(doc))).node(mask["id"])["params"]["field"] == "border"
    with pytest.raises(GraphError, match="field"):
        G.from_json(dict(doc, format="proceduralize/1.1"))
