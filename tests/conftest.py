"""Shared fixtures: real materials from ../shared/materials, an artefact folder, one Ray per session."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("RAY_AUTH_MODE", "disabled")
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")

REPO = Path(__file__).resolve().parents[1]
SHARED_MATERIALS = Path(os.environ.get("PROCEDURALIZE_MATERIALS", REPO.parent / "shared" / "materials"))
ARTIFACTS = Path(os.environ.get("PROCEDURALIZE_TEST_ARTIFACTS", REPO / "test-artifacts"))

# name -> (albedo, normal, roughness file, roughness channel or None)
REAL_MATERIALS = {
    "castle_brick_broken_06": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_arm_1k.jpg", "G"),
    "roof_slates_02": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_arm_1k.jpg", "G"),
    "metal_plate_02": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_rough_1k.jpg", None),
    "plastered_stone_wall": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_arm_1k.jpg", "G"),
    "coast_sand_rocks_02": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_arm_1k.jpg", "G"),
    "rusty_metal_05": ("_diff_1k.jpg", "_nor_gl_1k.jpg", "_rough_1k.jpg", None),
}


def real_material_files(name: str) -> dict:
    """Paths (and the roughness channel pick) of one of the shared real materials."""
    a, n, r, ch = REAL_MATERIALS[name]
    d = SHARED_MATERIALS / name
    return {"albedo": d / f"{name}{a}", "normal": d / f"{name}{n}", "roughness": d / f"{name}{r}",
            "roughness_channel": ch}


@pytest.fixture(scope="session")
def materials_dir() -> Path:
    if not SHARED_MATERIALS.is_dir():
        pytest.skip(f"shared materials not found at {SHARED_MATERIALS}")
    return SHARED_MATERIALS


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def ray_session():
    """One local Ray instance (2 CPUs) for the whole test session, always shut down."""
    import ray

    start_local_ray()
    yield ray
    ray.shutdown()


def start_local_ray() -> None:
    """The session's local Ray (2 CPUs); also how a test that needed its own cluster gives the session back."""
    import ray

    if not ray.is_initialized():
        # address="local": always a fresh instance (never a `ray start` cluster found on this host), on loopback
        ray.init(address="local", _node_ip_address="127.0.0.1", num_cpus=2, include_dashboard=False,
                 logging_level="WARNING",
                 runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}})


def small_material(path: Path, **edit) -> Path:
    """A tiny valid material.json: constant albedo/roughness, a blurred height, normals from the height."""
    from workers import graph

    m = graph.new_material(seed=3, working_size=(32, 32))
    m.add("alb", "constant", {"value": [0.5, 0.3, 0.2]})
    m.add("rough", "constant", {"value": 0.6})
    m.add("h0", "constant", {"value": 0.5})
    m.add("height", "blur", {"sigma": 1.0}, input="h0")
    m.maps = [{"name": "albedo", "node": "alb"}, {"name": "roughness", "node": "rough"},
              {"name": "height", "node": "height"}, {"name": "normal", "from_height": "height", "strength": 2.0}]
    doc = m.to_json()
    doc.update(edit)
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path
