"""Job manifests: TOML/JSON/YAML parsing, defaults, path resolution, strict validation listing every problem."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from service.manifest import load_manifest, validate
from workers.errors import ManifestError

GOOD = """
[job]
name = "demo"
output = "out/demo"
stages = ["load", "decompose"]

[defaults]
working_size = 128
roughness_channel = "G"
outputs = { sizes = [[256, 128], 512], seeds = [0, 3] }

[[materials]]
name = "brick"
folder = "maps"
albedo = "brick_diff.jpg"
normal = { file = "brick_nor.jpg", convention = "directx" }
roughness = "brick_arm.jpg"
decompose.mode = "scribbles"
decompose.scribbles = "brick_scribble.png"
decompose.children = { "1" = { method = "instances" }, "0" = { layers = 2, scribbles = "mortar.png" } }
seed = 7

[[materials]]
name = "sand"
albedo = "/abs/sand_diff.png"
roughness = { file = "sand_rough.png", channel = 0 }
working_size = [96, 64]
output = "nested/sand"
"""


def _write(tmp_path: Path, text: str, name: str = "job.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_toml_resolves_paths_and_merges_defaults(tmp_path):
    man = load_manifest(_write(tmp_path, GOOD))
    assert man.name == "demo" and man.output == (tmp_path / "out/demo").resolve()
    assert man.database == man.output / "proceduralize.db"
    assert man.stages == ["load", "decompose"]
    brick, sand = man.materials
    assert brick.maps["albedo"].file == (tmp_path / "maps/brick_diff.jpg").resolve()
    assert brick.maps["roughness"].channel == "G"
    assert brick.normal_convention == "directx"
    assert brick.working_size == 128 and brick.seed == 7  # the longer side; aspect kept at load
    assert brick.decompose["scribbles"] == str((tmp_path / "maps/brick_scribble.png").resolve())
    assert brick.decompose["scribbles_source"] == "brick_scribble.png"
    assert brick.decompose["children"]["0"]["scribbles"] == str((tmp_path / "maps/mortar.png").resolve())
    assert brick.decompose["children"]["1"] == {"method": "instances"}
    assert sand.decompose == {"mode": "auto"}  # the default: automatic two-layer matting
    assert brick.outputs.sizes == [(256, 128), (512, 512)] and brick.outputs.seeds == [0, 3]
    assert sand.maps["albedo"].file == Path("/abs/sand_diff.png")
    assert sand.maps["roughness"].channel == 0 and sand.working_size == (96, 64)
    assert man.material_dir(sand) == man.output / "nested" / "sand"
    assert brick.output == "brick"


def test_json_and_yaml_give_the_same_job(tmp_path):
    import tomllib

    doc = tomllib.loads(GOOD)
    a = load_manifest(_write(tmp_path, GOOD))
    b = load_manifest(_write(tmp_path, json.dumps(doc), "job.json"))
    c = load_manifest(_write(tmp_path, yaml.safe_dump(doc), "job.yaml"))
    assert a.to_json() | {"source": None} == b.to_json() | {"source": None} == c.to_json() | {"source": None}


def test_every_problem_listed_at_once_with_its_field(tmp_path):
    bad = """
[job]
name = "bad name!"
output = "out"
stages = ["load", "paint"]
max_atempts = 3

[defaults]
working_size = 4

[[materials]]
name = "a"
albedo = "a.png"
albedo_colorspace = "rec709"
normal_convention = "upside"
roughness = { file = "r.png", channel = "Q!" }
outputs = { sizes = [0], seeds = [-1], fromat = "png" }
decompose = { mode = "magic" }
recompose = { iterations = 5, itertions = 3 }

[[materials]]
name = "a"
normal = "n.png"
decompose = { layers = 1, depht = 2 }

[[materials]]
name = "esc"
albedo = "x.png"
output = "../../etc"
"""
    with pytest.raises(ManifestError) as ei:
        load_manifest(_write(tmp_path, bad))
    probs = ei.value.problems
    text = "\n".join(probs)
    for needle in ("job.name", "job.stages", "job.max_atempts", "did you mean 'max_attempts'",
                   "materials[0] (a).working_size", "materials[0] (a).albedo_colorspace",
                   "materials[0] (a).normal_convention", "materials[0] (a).roughness.channel",
                   "materials[0] (a).outputs.sizes[0]", "materials[0] (a).outputs.seeds",
                   "materials[0] (a).outputs.fromat", "materials[0] (a).decompose.mode",
                   "materials[1] (a).albedo", "name used twice", "materials[2] (esc).output",
                   "materials[1] (a).decompose.layers", "materials[1] (a).decompose.depht",
                   "materials[0] (a).recompose.itertions"):
        assert needle in text, f"{needle!r} not reported in:\n{text}"
    assert len(probs) >= 15
    assert str(tmp_path / "job.toml") in str(ei.value)


@pytest.mark.parametrize("device", ["gpu", "cuda:0"])
def test_recompose_device_is_one_the_placement_routes(tmp_path, device):
    """recompose.device takes the values the Ray placement routes (service.placement.DEVICES), reported once:
    "cuda:0" passed one check and failed the other, "gpu" was reported twice."""
    text = f"""
[job]
name = "d"
output = "out"

[[materials]]
name = "a"
albedo = "a.png"
recompose = {{ device = "{device}" }}
"""
    with pytest.raises(ManifestError) as ei:
        load_manifest(_write(tmp_path, text))
    assert [p for p in ei.value.problems if "recompose.device" in p and "a.png" not in p] != []
    assert sum("recompose.device" in p for p in ei.value.problems) == 1, ei.value.problems


@pytest.mark.parametrize("out", ["/tmp/elsewhere", "../outside", "a/../../b", "."])
def test_material_output_must_stay_inside_job_output(tmp_path, out):
    doc = {"job": {"name": "j", "output": "o"}, "materials": [{"name": "m", "albedo": "a.png", "output": out}]}
    with pytest.raises(ManifestError, match=r"materials\[0\] \(m\)\.output"):
        validate(doc, root=tmp_path)


def test_absolute_output_inside_job_folder_is_accepted(tmp_path):
    inside = tmp_path / "o" / "sub"
    doc = {"job": {"name": "j", "output": "o"}, "materials": [{"name": "m", "albedo": "a.png", "output": str(inside)}]}
    man = validate(doc, root=tmp_path)
    assert man.material_dir(man.materials[0]) == inside


def test_bad_syntax_and_missing_file_are_manifest_errors(tmp_path):
    with pytest.raises(ManifestError, match="not valid TOML"):
        load_manifest(_write(tmp_path, "[job\nname="))
    with pytest.raises(ManifestError, match="file not found"):
        load_manifest(tmp_path / "nope.toml")
    with pytest.raises(ManifestError, match="unknown manifest type"):
        load_manifest(_write(tmp_path, "x", "job.txt"))
    with pytest.raises(ManifestError, match="materials: required"):
        validate({"job": {"name": "j", "output": "o"}}, root=tmp_path)


def test_spec_hash_tracks_results_not_timeout_or_stage_choice(tmp_path):
    base = {"job": {"name": "j", "output": "o"}, "materials": [{"name": "m", "albedo": "a.png"}]}
    h0 = validate(base, root=tmp_path).materials[0].spec_hash()
    timed = json.loads(json.dumps(base))
    timed["job"]["stage_timeout"] = 60
    assert validate(timed, root=tmp_path).materials[0].spec_hash() == h0
    staged = json.loads(json.dumps(base))
    staged["materials"][0]["stages"] = ["load"]
    assert validate(staged, root=tmp_path).materials[0].spec_hash() == h0
    changed = json.loads(json.dumps(base))
    changed["materials"][0]["working_size"] = 64
    assert validate(changed, root=tmp_path).materials[0].spec_hash() != h0


@pytest.mark.parametrize("name,count", [("manifest.toml", 3), ("quick.toml", 1), ("all_materials.toml", 6)])
def test_example_manifests_are_valid(name, count):
    """Every example validates; its map files exist (quick.toml and all_materials.toml read ../shared/materials:
    their files are checked only where that folder is, the README's manifest.toml always)."""
    from tests.conftest import SHARED_MATERIALS

    ex = Path(__file__).resolve().parents[1] / "examples" / name
    man = load_manifest(ex)
    assert len(man.materials) == count
    for m in man.materials:
        for spec in m.maps.values():
            if not SHARED_MATERIALS.is_dir() and spec.file.resolve().is_relative_to(SHARED_MATERIALS.resolve()):
                continue
            assert spec.file.is_file(), spec.file


def test_spec_hash_changes_when_an_input_file_changes(tmp_path):
    img = tmp_path / "a.png"
    img.write_bytes(b"one")
    doc = {"job": {"name": "j", "output": "o"}, "materials": [{"name": "m", "albedo": "a.png"}]}
    h0 = validate(doc, root=tmp_path).materials[0].spec_hash()
    assert validate(doc, root=tmp_path).materials[0].spec_hash() == h0
    img.write_bytes(b"two!")
    assert validate(doc, root=tmp_path).materials[0].spec_hash() != h0
