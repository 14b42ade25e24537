"""Nothing lost, nothing written outside, bounded memory, a clear error for every bad input.

Each test here reproduces one way a careless or hostile input used to lose data, write outside its folder,
exhaust memory or fail with a raw error; it runs the real CLI (subprocesses with a real local Ray where a
job runs) on small synthetic maps, so it needs nothing beside the repository.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from tests.conftest import small_material
from workers.maps import write_image

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled",
       "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}


def synthetic_maps(folder: Path, seed: int, w: int = 48, h: int = 48, normal: bool = True) -> dict:
    """Albedo, normal and roughness PNGs of a random bumpy surface (distinct per seed)."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    hgt = rng.random((h, w)).astype(np.float32)
    gy, gx = np.gradient(hgt)
    n = np.stack([-gx, gy, np.ones_like(hgt)], axis=2)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    files = {"albedo": write_image(folder / "albedo.png", rng.random((h, w, 3)).astype(np.float32)),
             "roughness": write_image(folder / "rough.png", rng.random((h, w)).astype(np.float32))}
    if normal:
        files["normal"] = write_image(folder / "normal.png", n * 0.5 + 0.5)
    return {k: str(v) for k, v in files.items()}


def manifest(path: Path, job: str, output: str, materials: list[dict], stages=("load", "decompose"),
             **job_keys) -> Path:
    """A JSON manifest file with small fast defaults."""
    doc = {"job": {"name": job, "output": output, **({"stages": list(stages)} if stages else {}), **job_keys},
           "defaults": {"working_size": 32, "decompose": {"mode": "none"}, "outputs": {"sizes": [32]}},
           "materials": materials}
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path


def cli(*args: str, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=cwd or REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


# ----------------------------------------------------------------------------- 1. data loss


@pytest.mark.ray
def test_two_concurrent_jobs_sharing_a_material_folder_lose_nothing(tmp_path):
    """Two real concurrent runs, one output folder, a material called `tile` in each: the folder belongs to
    whichever job claimed it first; the other job's `tile` fails naming the owner, its own other material
    finishes, and the first job's files and `results` stay intact (also after the second job is rerun)."""
    a = manifest(tmp_path / "a.json", "job_a", "out", [{"name": "tile", **synthetic_maps(tmp_path / "ma", 1)}])
    b = manifest(tmp_path / "b.json", "job_b", "out", [{"name": "tile", **synthetic_maps(tmp_path / "mb", 2)},
                                                        {"name": "other", **synthetic_maps(tmp_path / "mc", 3)}])
    procs = [subprocess.Popen([sys.executable, "-m", "service.cli", "run", str(m), "--quiet", "--num-cpus", "1"],
                              cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for m in (a, b)]
    outs = [p.communicate(timeout=300)[0] for p in procs]
    codes = [p.returncode for p in procs]
    owner = json.loads((tmp_path / "out/tile/.proceduralize-owner.json").read_text())["job"]
    loser = "job_b" if owner == "job_a" else "job_a"
    assert sorted(codes) == [0, 1], outs
    assert "belongs to job" in outs[["job_a", "job_b"].index(loser)]
    r_owner = cli("results", str(a if owner == "job_a" else b), "--json")
    assert r_owner.returncode == 0, r_owner.stdout + r_owner.stderr
    tile = next(m for m in json.loads(r_owner.stdout)["materials"] if m["name"] == "tile")
    assert tile["status"] == "done" and tile["artefacts"] and {x["state"] for x in tile["artefacts"]} == {"ok"}
    if loser == "job_b":  # the loser's other material still finished
        rb = json.loads(cli("results", str(b), "--json").stdout)
        assert {m["name"]: m["status"] for m in rb["materials"]} == {"tile": "failed", "other": "done"}
    # rerunning the refused job is refused again and leaves the owner's files as they were
    before = {x["path"]: x["checksum"] for x in tile["artefacts"]}
    again = cli("run", str(b if loser == "job_b" else a), "--quiet", "--num-cpus", "1")
    assert again.returncode == 1 and "belongs to job" in again.stdout + again.stderr
    after = json.loads(cli("results", str(a if owner == "job_a" else b), "--json").stdout)
    tile2 = next(m for m in after["materials"] if m["name"] == "tile")
    assert {x["path"]: x["checksum"] for x in tile2["artefacts"]} == before
    assert {x["state"] for x in tile2["artefacts"]} == {"ok"}


@pytest.mark.ray
def test_results_rechecks_checksums(tmp_path, capsys):
    """`results` reads every artefact again: a file changed or deleted after the job wrote it turns the
    material to `changed` and the exit code to 1."""
    m = manifest(tmp_path / "m.json", "chk", "out", [{"name": "tile", **synthetic_maps(tmp_path / "ma", 1)}])
    assert cli("run", str(m), "--quiet", "--num-cpus", "1").returncode == 0
    assert main(["results", str(m)]) == 0
    png = tmp_path / "out/tile/load/maps/albedo.png"
    png.write_bytes(png.read_bytes() + b"x")
    capsys.readouterr()
    assert main(["results", str(m), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    tile = doc["materials"][0]
    assert tile["status"] == "changed" and "changed or missing" in tile["error"]
    assert [x["state"] for x in tile["artefacts"] if x["path"].endswith("load/maps/albedo.png")] == ["changed"]


# ----------------------------------------------------------------------------- 2. writes stay inside --out


@pytest.mark.parametrize("bad", ["../../escaped", "/tmp/proceduralize_abs_escape", "sub/dir", "..", "a b"])
def test_map_names_cannot_write_outside_out(tmp_path, capsys, bad):
    """A shared material.json whose map name is a path is refused (exit 2, the field named); nothing is
    written anywhere."""
    doc = json.loads(small_material(tmp_path / "ok.json").read_text())
    doc["maps"][1]["name"] = bad
    mat = tmp_path / "evil" / "material.json"
    mat.parent.mkdir()
    mat.write_text(json.dumps(doc))
    out = tmp_path / "a" / "b" / "out"
    before = set(tmp_path.rglob("*"))
    assert main(["render", str(mat), "--size", "16x16", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "maps[1].name" in err and str(mat) in err
    assert set(tmp_path.rglob("*")) == before and not Path("/tmp/proceduralize_abs_escape.png").exists()


def test_export_name_cannot_escape(tmp_path, capsys):
    mat = small_material(tmp_path / "material.json")
    out = tmp_path / "deep" / "out"
    assert main(["export", str(mat), "--size", "16x16", "--out", str(out), "--name", "../../x"]) == 2
    assert "'../../x'" in capsys.readouterr().err
    assert not (tmp_path / "x_basecolor.png").exists() and not list(tmp_path.rglob("x_*"))


# ----------------------------------------------------------------------------- 4. manifests: confined, no hooks


@pytest.mark.parametrize("db", ["../../x.db", "/tmp/proceduralize_abs.db", "..", "."])
def test_manifest_database_stays_in_the_output_folder(tmp_path, capsys, db):
    m = manifest(tmp_path / "m.json", "j", "out", [{"name": "t", "albedo": "a.png"}], database=db)
    assert main(["run", str(m)]) == 2
    assert "job.database" in capsys.readouterr().err
    assert not (tmp_path.parent / "x.db").exists() and not Path("/tmp/proceduralize_abs.db").exists()


def test_manifest_cannot_carry_fault_hooks(tmp_path, capsys):
    """[debug] used to create any file it named and kill a worker; a manifest can no longer name it."""
    doc = json.loads(manifest(tmp_path / "m.json", "j", "out", [{"name": "t", "albedo": "a.png"}]).read_text())
    doc["debug"] = {"crash_once": {"stage": "load", "marker": str(tmp_path / "pwned")}, "sleep": {
        "stage": "load", "seconds": 1e9}}
    (tmp_path / "m.json").write_text(json.dumps(doc))
    assert main(["run", str(tmp_path / "m.json")]) == 2
    assert "debug: unknown key" in capsys.readouterr().err and not (tmp_path / "pwned").exists()


@pytest.mark.parametrize("bad", [0, -1, "long", 1e12, True])
def test_stage_timeout_is_validated(tmp_path, capsys, bad):
    m = manifest(tmp_path / "m.json", "j", "out", [{"name": "t", "albedo": "a.png"}], stage_timeout=bad)
    assert main(["run", str(m)]) == 2
    assert "job.stage_timeout" in capsys.readouterr().err


@pytest.mark.ray
def test_a_hanging_stage_times_out_and_the_batch_goes_on(tmp_path):
    """A stage that sleeps 1e9 s (injected from the environment, as tests do) is cancelled after
    job.stage_timeout; its material fails with a StageTimeout naming the field, the other finishes."""
    m = manifest(tmp_path / "m.json", "hang", "out", [{"name": "stuck", **synthetic_maps(tmp_path / "a", 1)},
                                                      {"name": "fine", **synthetic_maps(tmp_path / "b", 2)}],
                 stage_timeout=20)  # room for a cold worker's imports on a loaded machine
    env = {**ENV, "PROCEDURALIZE_FAULTS": json.dumps({"sleep": {"stage": "decompose", "seconds": 1e9,
                                                                "material": "stuck"}})}
    t0 = __import__("time").perf_counter()
    r = subprocess.run([sys.executable, "-m", "service.cli", "run", str(m), "--quiet", "--num-cpus", "2"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 1, r.stdout + r.stderr
    assert __import__("time").perf_counter() - t0 < 120
    res = json.loads(cli("results", str(m), "--json").stdout)
    st = {x["name"]: x for x in res["materials"]}
    assert st["fine"]["status"] == "done" and st["stuck"]["status"] == "failed"
    assert "StageTimeout" in st["stuck"]["error"] and "job.stage_timeout" in st["stuck"]["error"]


# ----------------------------------------------------------------------------- 6, 7. odd materials, aspect


def _flat(folder: Path, w: int, h: int) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    n = np.broadcast_to(np.array([0.5, 0.5, 1.0], np.float32), (h, w, 3)).copy()
    return {"albedo": str(write_image(folder / "a.png", np.full((h, w, 3), 0.5, np.float32))),
            "normal": str(write_image(folder / "n.png", n)),
            "roughness": str(write_image(folder / "r.png", np.full((h, w), 0.4, np.float32)))}


@pytest.mark.ray
def test_flat_tiny_albedo_only_and_long_materials_go_through(tmp_path):
    """The whole pipeline on a flat uniform material, 1x1 maps (at working_size 16), an albedo-only material
    and a 1024x16 strip: all finish (they used to fail at recompose with IndexError, at output because the
    preview needed normals, or were squashed square). 1x1 maps without a working size are refused at load
    naming the file and the fix."""
    rng = np.random.default_rng(5)
    (tmp_path / "alb").mkdir()
    strip = rng.random((16, 1024, 3)).astype(np.float32)
    mats = [{"name": "flat", **_flat(tmp_path / "flat", 32, 32)},
            {"name": "one_px", **_flat(tmp_path / "one", 1, 1), "working_size": 16},
            {"name": "albedo_only", "albedo": str(write_image(tmp_path / "alb/a.png",
                                                               rng.random((32, 32, 3)).astype(np.float32)))},
            {"name": "strip", "albedo": str(write_image(tmp_path / "alb/strip.png", strip)), "working_size": 64,
             "decompose": {"mode": "none"}},
            {"name": "one_px_native", **_flat(tmp_path / "one2", 1, 1), "working_size": None}]
    m = manifest(tmp_path / "m.json", "odd", "out", mats, stages=None)
    doc = json.loads(m.read_text())
    doc["defaults"].update(decompose={"mode": "auto"}, recompose={"iterations": 2},
                           masks={"max_evals": 8, "rounds": 1})
    m.write_text(json.dumps(doc))
    r = cli("run", str(m), "--quiet", "--num-cpus", "2", timeout=900)
    res = {x["name"]: x for x in json.loads(cli("results", str(m), "--json").stdout)["materials"]}
    assert {k: v["status"] for k, v in res.items()} == {"flat": "done", "one_px": "done", "albedo_only": "done",
                                                        "strip": "done", "one_px_native": "failed"}, r.stdout
    err = res["one_px_native"]["error"]
    assert "one2/a.png" in err and "1x1" in err and "working_size" in err
    info = json.loads((tmp_path / "out/strip/load/material.json").read_text())
    assert info["size"] == [64, 8]  # the longer side is 64, the 128:1 aspect kept down to the 8 px minimum
    assert any("preview.png" in a["path"] for a in res["albedo_only"]["artefacts"])


# ----------------------------------------------------------------------------- 3. memory budget


def _peak_rss_mb(*args: str) -> tuple[int, float, str]:
    """Exit code, peak RSS (MB, from getrusage of the child) and stderr of one CLI run."""
    code = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
            "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024); "
            "print(r.stderr, file=sys.stderr)")
    r = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "service.cli", *args], env=ENV,
                       capture_output=True, text=True, timeout=120)
    rc, rss = r.stdout.split()
    return int(rc), float(rss), r.stderr


def test_render_over_the_memory_budget_is_refused_before_allocating(tmp_path):
    """32768x32768 used to ask for 8 GiB at once: now refused (exit 2, the estimate and the budget named)
    with the peak RSS of the whole process far below what the render would need."""
    mat = small_material(tmp_path / "m.json")
    rc, rss, err = _peak_rss_mb("render", str(mat), "--size", "32768x32768", "--out", str(tmp_path / "o"),
                                "--memory-budget", "2G")
    assert rc == 2 and "memory budget of 2.00 GiB" in err and "32768x32768" in err
    assert rss < 400, rss  # the imports alone; the render would need > 100 GiB
    rc, _, err = _peak_rss_mb("export", str(mat), "--size", "8192x8192", "--out", str(tmp_path / "x"),
                              "--memory-budget", "256M")
    assert rc == 2 and "memory budget" in err
    assert not (tmp_path / "o").exists() and not (tmp_path / "x").exists()      # a refusal writes nothing
    assert main(["render", str(mat), "--size", "64", "--out", str(tmp_path / "ok"), "--memory-budget", "1G"]) == 0


@pytest.mark.parametrize("scale", ["1e9", "inf", "nan", "0", "-1", "1e-9"])
def test_render_scale_is_bounded(tmp_path, scale):
    assert main(["render", str(small_material(tmp_path / "m.json")), "--size", "64", "--scale", scale,
                 "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()


def test_compressed_arrays_are_bounded_before_inflating():
    """A 1 MB material.json whose array inflated to 805 MB took render to 5 GB: the declared size is checked
    first, and inflation stops at the declared size."""
    import base64
    import resource
    import zlib

    from workers.arrays import decode_array, encode_array
    from workers.errors import GraphError

    raw = zlib.compress(b"\0" * (805 * 2**20), 9)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(GraphError, match="more than the 16 MiB"):
        decode_array({"__array__": True, "dtype": "float32", "shape": [805 * 2**18],
                      "data": base64.b64encode(raw).decode()})
    with pytest.raises(GraphError, match="does not match its declared shape"):  # the shape lies
        decode_array({"__array__": True, "dtype": "float32", "shape": [16],
                      "data": base64.b64encode(raw).decode()})
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200 * 1024  # KB: no 805 MB buffer
    assert np.array_equal(decode_array(encode_array(np.arange(6.0).reshape(2, 3), "float32")),
                          np.arange(6.0).reshape(2, 3))


def test_manifest_memory_budget_refuses_at_validation(tmp_path, capsys):
    m = manifest(tmp_path / "m.json", "big", "out", [{"name": "t", "albedo": "a.png",
                                                      "outputs": {"sizes": [[16384, 16384]]}}],
                 memory_budget="1G")
    assert main(["run", str(m)]) == 2
    assert "outputs.sizes: 16384x16384" in capsys.readouterr().err
    m = manifest(tmp_path / "m.json", "big", "out", [{"name": "t", "albedo": "a.png"}], memory_budget="lots")
    assert main(["run", str(m)]) == 2
    assert "job.memory_budget" in capsys.readouterr().err


@pytest.mark.ray
def test_load_over_the_budget_fails_its_material_only(tmp_path):
    """working_size = 32768 used to allocate 12 GiB at load: refused from the image headers, that material
    only, and not retried."""
    m = manifest(tmp_path / "m.json", "mem", "out", [{"name": "huge", **synthetic_maps(tmp_path / "a", 1),
                                                      "working_size": 32768},
                                                     {"name": "fine", **synthetic_maps(tmp_path / "b", 2)}],
                 stages=("load",), memory_budget="2G")
    r = cli("run", str(m), "--quiet", "--num-cpus", "1")
    assert r.returncode == 1
    res = {x["name"]: x for x in json.loads(cli("results", str(m), "--json").stdout)["materials"]}
    assert res["fine"]["status"] == "done" and res["huge"]["status"] == "failed"
    assert "MemoryBudgetError" in res["huge"]["error"] and "32768x32768" in res["huge"]["error"]
    st = json.loads(cli("status", str(m), "--json").stdout)
    assert [s["attempts"] for s in st["stages"] if s["material"] == "huge"] == [1]


# ----------------------------------------------------------------------------- 8. render/edit/export inputs


@pytest.mark.parametrize("label,args_fn,field", [
    ("nan sigma", lambda p, o: ["render", str(_variant(p, "height", sigma=float("nan"))), "--size", "16", "--out", o],
     "blur.sigma"),
    ("huge sigma", lambda p, o: ["render", str(_variant(p, "height", sigma=1e300)), "--size", "16", "--out", o],
     "blur.sigma"),
    ("out is a file", lambda p, o: ["render", str(small_material(p / "m.json")), "--size", "16", "--out",
                                    str(p / "m.json")], "--out"),
    ("export out is a file", lambda p, o: ["export", str(small_material(p / "m.json")), "--size", "16", "--out",
                                           str(p / "m.json")], "--out"),
    ("edit 1e9 sigma", lambda p, o: ["edit", str(small_material(p / "m.json")), "--set", "height.sigma=1e9"],
     "height.sigma"),
    ("edit NaN", lambda p, o: ["edit", str(small_material(p / "m.json")), "--set", "height.sigma=NaN"],
     "height.sigma"),
    ("edit seed inf", lambda p, o: ["edit", str(small_material(p / "m.json")), "--set", "seed=1e400"], "seed"),
    ("edit out unwritable", lambda p, o: ["edit", str(small_material(p / "m.json")), "--set", "height.sigma=2",
                                          "--out", "/proc/nope/x.json"], "/proc/nope/x.json"),
    ("seed string in file", lambda p, o: ["render", str(_variant(p, None, seed="x")), "--size", "16", "--out", o],
     "seed"),
    ("strength string", lambda p, o: ["render", str(_variant(p, None, strength="x")), "--size", "16", "--out", o],
     "maps[3].strength"),
    ("constant string", lambda p, o: ["render", str(_variant(p, "alb", value="red")), "--size", "16", "--out", o],
     "node 'alb'"),
])
def test_bad_render_edit_export_inputs_exit_2_naming_the_field(tmp_path, capsys, label, args_fn, field):
    before = (tmp_path / "m.json").read_bytes() if (tmp_path / "m.json").exists() else None
    assert main(args_fn(tmp_path, str(tmp_path / "o"))) == 2, label
    err = capsys.readouterr().err
    assert field in err, err
    if before is None and (tmp_path / "m.json").exists() and label.startswith("edit"):
        assert json.loads((tmp_path / "m.json").read_text())["nodes"][3]["params"]["sigma"] == 1.0


def test_non_utf8_material_file_exit_2(tmp_path, capsys):
    bad = tmp_path / "latin.json"
    bad.write_bytes('{"format": "caf\xe9"}'.encode("latin-1"))
    for cmd in (["render", str(bad), "--size", "8", "--out", str(tmp_path / "o")], ["edit", str(bad), "--list"],
                ["export", str(bad), "--size", "8", "--out", str(tmp_path / "o")]):
        assert main(cmd) == 2
        assert "latin.json: not a UTF-8 text file" in capsys.readouterr().err


def _variant(folder: Path, node: str | None, **params) -> Path:
    doc = json.loads(small_material(folder / "base.json").read_text())
    if node is None:
        if "strength" in params:
            doc["maps"][3]["strength"] = params["strength"]
        else:
            doc.update(params)
    else:
        next(n for n in doc["nodes"] if n["id"] == node)["params"].update(params)
    p = folder / "variant.json"
    p.write_text(json.dumps(doc))
    return p


def test_read_commands_never_write(tmp_path, capsys):
    """status on a 0-byte database used to write a schema into it."""
    z = tmp_path / "zero.db"
    z.write_bytes(b"")
    for cmd in ("status", "results", "report", "evaluate"):
        assert main([cmd, str(z)]) == 2
        assert "zero.db" in capsys.readouterr().err
    assert z.stat().st_size == 0 and sorted(p.name for p in tmp_path.iterdir()) == ["zero.db"]


def test_corrupt_database_and_missing_pptbf_db_refused_before_ray(tmp_path, capsys, monkeypatch):
    m = manifest(tmp_path / "m.json", "c", "out", [{"name": "t", "albedo": "a.png"}])
    (tmp_path / "out").mkdir()
    (tmp_path / "out/proceduralize.db").write_bytes(b"SQLite format 3\0" + bytes(range(256)) * 16)
    import ray

    started = []   # Ray may already run in this test session: record any attempt to start or join one
    monkeypatch.setattr(ray, "init", lambda *a, **k: started.append(k))
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    assert main(["run", str(m)]) == 2 and not started
    assert "not a usable SQLite job database" in capsys.readouterr().err
    (tmp_path / "out/proceduralize.db").unlink()
    assert main(["run", str(m), "--pptbf-db", str(tmp_path / "nodb")]) == 2 and not started
    assert "--pptbf-db" in capsys.readouterr().err


def test_every_stage_option_is_validated_with_its_field(tmp_path, capsys):
    opts = {"recompose": {"iterations": -3, "lr": "fast", "optimizer": "sgd"}, "masks": {"max_evals": -5},
            "noise": {"kernel_sizes": [15, -2]}}
    m = manifest(tmp_path / "m.json", "v", "out", [{"name": "t", "albedo": "a.png", **opts}])
    assert main(["run", str(m)]) == 2
    err = capsys.readouterr().err
    for f in ("recompose.iterations", "recompose.lr", "recompose.optimizer", "masks.max_evals",
              "noise.kernel_sizes"):
        assert f"(t).{f}:" in err, (f, err)


# ----------------------------------------------------------------------------- 5. local runs bind to loopback


def _listeners() -> list[tuple[str, int, int]]:
    """(address, port, pid) of every listening TCP socket on this host, from `ss -ltnpH`."""
    import re

    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True).stdout
    found = []
    for line in out.splitlines():
        parts = line.split()
        addr, _, port = parts[3].rpartition(":")
        for pid in re.findall(r"pid=(\d+)", line):
            found.append((addr.strip("[]"), int(port), int(pid)))
    return found


def _descendants(root: int) -> set[int]:
    """``root`` and every process below it (from /proc)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    tree, grew = {root}, True
    while grew:
        new = {p for p, pp in parent.items() if pp in tree} - tree
        tree |= new
        grew = bool(new)
    return tree


@pytest.mark.ray
@pytest.mark.skipif(not Path("/usr/bin/ss").exists() and not Path("/bin/ss").exists(), reason="needs ss")
def test_a_local_run_listens_on_loopback_only(tmp_path):
    """During a real local run (a stage held for 15 s), every TCP port the driver's Ray processes listen on
    (GCS, raylet, object manager, agents, workers) is bound to 127.0.0.1, none to all interfaces."""
    import time

    m = manifest(tmp_path / "m.json", "ports", "out", [{"name": "t", **synthetic_maps(tmp_path / "a", 1)}],
                 stages=("load",))
    env = {**ENV, "PROCEDURALIZE_FAULTS": json.dumps({"sleep": {"stage": "load", "seconds": 15}})}
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "run", str(m), "--quiet", "--num-cpus", "1"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen: dict[tuple[str, int], str] = {}
        deadline = time.time() + 150
        while time.time() < deadline and proc.poll() is None:
            tree = _descendants(proc.pid)
            for addr, port, pid in _listeners():
                if pid in tree:
                    seen[(addr, port)] = Path(f"/proc/{pid}/comm").read_text().strip() if Path(
                        f"/proc/{pid}/comm").exists() else "?"
            time.sleep(1.0)  # until the run ends: the listeners of every phase (start, workers) are seen
    finally:
        out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 0, out
    assert len(seen) >= 4, seen  # GCS, raylet, object manager, agents at least: the check saw the run
    print("listeners:", sorted(seen.items()))
    exposed = {k: v for k, v in seen.items() if k[0] not in ("127.0.0.1", "::1", "::ffff:127.0.0.1")}
    assert not exposed, f"listening beyond loopback: {exposed}"


def test_deploy_configs_require_a_token_and_keep_the_dashboard_private():
    import yaml

    d = REPO / "deploy"
    rc = yaml.safe_load((d / "kuberay/raycluster.yaml").read_text())
    assert rc["spec"]["authOptions"] == {"mode": "token"}
    rj = yaml.safe_load((d / "kuberay/rayjob.yaml").read_text())
    assert rj["spec"]["rayClusterSpec"]["authOptions"] == {"mode": "token"}
    up = yaml.safe_load((d / "cluster.yaml").read_text())
    assert "-e RAY_AUTH_MODE=token" in up["docker"]["run_options"] and up["file_mounts"]
    head = " ".join(up["head_start_ray_commands"])
    assert "--dashboard-host=127.0.0.1" in head and "0.0.0.0" not in head
    for f in ("kuberay/raycluster.yaml", "kuberay/rayjob.yaml"):  # no public Service type anywhere
        assert "LoadBalancer" not in (d / f).read_text().replace("never a public\n# LoadBalancer", "")
    assert "What must not be exposed" in (d / "README.md").read_text()


# ----------------------------------------------------------------------------- 10. the example ships its data


def test_example_manifest_needs_nothing_outside_the_repository():
    """The README's main command on a bare clone: every file examples/manifest.toml reads is inside the
    repository (under examples/maps, with its licence note), readable, and small."""
    from service.manifest import load_manifest
    from workers.maps import image_header

    man = load_manifest(REPO / "examples" / "manifest.toml")
    files = [f for m in man.materials for f in m.input_files()]
    assert len(files) == 9
    for f in files:
        assert f.resolve().is_relative_to(REPO / "examples" / "maps"), f
        w, h, _ = image_header(f)
        assert (w, h) == (512, 512)
    assert sum(f.stat().st_size for f in files) < 4 * 2**20
    assert "CC0" in (REPO / "examples" / "maps" / "LICENCE.md").read_text()


def test_report_shows_tracebacks_only_for_internal_errors():
    from service.report import _message

    tb = 'Traceback (most recent call last):\n  File "x.py", line 1\nInputError: /data/a.png: file not found'
    assert _message(tb, "InputError") == "InputError: /data/a.png: file not found"
    assert "<details>" in _message(tb.replace("InputError", "KeyError"), "KeyError")
