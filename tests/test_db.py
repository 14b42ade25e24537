"""PPTBF database: Ray build (resume after an interruption gives the same database), index load/query/errors,
round trip of known parameters, CLI `db rebuild`, and the bundled default database."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pptbf_db import pptbf
from pptbf_db.build import BuildConfig, clear_database, with_dim
from pptbf_db.descriptor import DescriptorConfig
from pptbf_db.errors import DatabaseError
from pptbf_db.index import PPTBFIndex, default_database_path
from service.db_build import build_database

pytestmark = pytest.mark.ray

TINY = BuildConfig(size=240, resolution=64, seed=11, chunk=30, descriptor=DescriptorConfig(dim=32),
                   regular_share=0.25)
N_CHUNKS = 8
STOP_AFTER = 3


class Stop(RuntimeError):
    """Injected failure after some chunks."""


def _chunk_runs(folder) -> dict[int, int]:
    import sqlite_utils

    return {r["id"]: r["runs"] for r in sqlite_utils.Database(folder / "db.sqlite")["chunks"].rows}


@pytest.fixture(scope="module")
def builds(ray_session, tmp_path_factory):
    """One uninterrupted build and one killed after STOP_AFTER chunks then resumed (same settings)."""
    base = tmp_path_factory.mktemp("pptbf_db")
    full = build_database(base / "full", TINY, workers=2, progress=False)
    seen: list[int] = []

    def stop(cid: int, n_done: int) -> None:
        seen.append(cid)
        if n_done == STOP_AFTER:
            raise Stop(f"injected after chunk {cid}")

    with pytest.raises(Stop):
        build_database(base / "resumed", TINY, workers=2, on_chunk=stop, progress=False)
    first_runs = _chunk_runs(base / "resumed")
    resumed = build_database(base / "resumed", TINY, workers=2, progress=False)
    return {"base": base, "full": full, "resumed": resumed, "first_done": list(seen), "first_runs": first_runs}


def test_uninterrupted_build(builds):
    rep = builds["full"]
    assert rep.complete and rep.chunks_total == N_CHUNKS and sorted(rep.computed) == list(range(N_CHUNKS))
    assert rep.entries == TINY.size and rep.entries_per_core_minute > 0
    folder = rep.folder
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["format"] == "proceduralize-pptbf-db/1" and meta["size"] == TINY.size
    assert meta["resolution"] == 64 and meta["seed"] == 11 and meta["dim"] == 32
    assert DescriptorConfig.from_dict(meta["descriptor"]) == TINY.descriptor
    assert np.load(folder / "params.npy").shape == (TINY.size, 29)
    assert np.load(folder / "reduced.npy").shape == (TINY.size, 32)
    assert sorted(p.name for p in folder.glob("raw_*.npy")) == [f"raw_{c:04d}.npy" for c in range(N_CHUNKS)]
    # the parameters are the seeded sample, in order
    np.testing.assert_array_equal(np.load(folder / "params.npy"),
                                  pptbf.sample_params(np.random.default_rng(11), TINY.size, ref_width=64,
                                                      regular_share=TINY.regular_share, crisp_share=TINY.crisp_share,
                                                      balanced_tiling=True))
    assert TINY.regular_share == 0.25 and meta["regular_share"] == 0.25 and meta["crisp_share"] == TINY.crisp_share
    # every tiling family gets the same number of entries; the descriptor is the pretrained VGG-19 one
    counts = np.bincount(np.load(folder / "params.npy")[:, 1].astype(int), minlength=18)
    assert counts.max() - counts.min() <= 1, counts
    assert meta["descriptor"]["extractor"] == "vgg19" and meta["blocks"]["gram"][1] - meta["blocks"]["gram"][0] == 544
    # the lattice of every entry is recorded; crisp cells and regular layouts repeat far more often than the rest
    lat = np.load(folder / "lattice.npy")
    assert lat.shape == (TINY.size, 2) and np.isfinite(lat).all()
    shares = meta["lattice_share"]
    assert shares["crisp"] > shares["uniform"] + 0.2, shares
    assert set(_chunk_runs(folder).values()) == {1}


def test_resumed_build_matches_and_skips_finished_chunks(builds):
    first_done, resumed = builds["first_done"], builds["resumed"]
    assert len(first_done) == STOP_AFTER
    # the resumed call computed exactly the chunks that were not finished before the interruption
    assert sorted(resumed.skipped) == sorted(first_done)
    assert sorted(resumed.computed) == sorted(set(range(N_CHUNKS)) - set(first_done))
    runs = _chunk_runs(resumed.folder)
    assert all(runs[c] == 1 for c in first_done), runs         # finished chunks were never run again
    assert all(builds["first_runs"][c] == 1 for c in first_done)
    full, res = builds["full"].folder, resumed.folder
    for name in ["params.npy", "reduced.npy", "white.npy"] + [f"raw_{c:04d}.npy" for c in range(N_CHUNKS)]:
        np.testing.assert_allclose(np.load(res / name), np.load(full / name), rtol=1e-5, atol=1e-6, err_msg=name)
    # a third call finds it complete and computes nothing
    again = build_database(res, TINY, workers=2, progress=False)
    assert again.complete and again.computed == [] and len(again.skipped) == N_CHUNKS


def test_other_settings_are_refused(builds, tmp_path):
    folder = tmp_path / "db"
    shutil.copytree(builds["full"].folder, folder)
    with pytest.raises(DatabaseError, match="other settings.*seed"):
        build_database(folder, BuildConfig(size=TINY.size, resolution=64, seed=12, chunk=30,
                                           descriptor=TINY.descriptor), progress=False)
    # another PCA dimension only refits the PCA from the kept raw chunks
    rep = build_database(folder, with_dim(TINY, 16), progress=False)
    assert rep.complete and rep.computed == []
    assert PPTBFIndex.load(folder).reduced.shape == (TINY.size, 16)


def test_database_of_another_extractor_is_refused(builds, tmp_path):
    """A database records the Gram extractor that built it; querying it with another one fails, naming the fix
    (an old meta without the field was built with the weight-free random features)."""
    folder = tmp_path / "db"
    shutil.copytree(builds["full"].folder, folder)
    with pytest.raises(DatabaseError, match="'vgg19' Gram feature extractor.*'random'.*db rebuild"):
        PPTBFIndex.load(folder, extractor="random")
    meta = json.loads((folder / "meta.json").read_text())
    del meta["descriptor"]["extractor"]
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatabaseError, match="'random' Gram feature extractor.*'vgg19'"):
        PPTBFIndex.load(folder)
    assert PPTBFIndex.load(folder, extractor=None).config.extractor == "random"


def test_index_query_and_distance(builds):
    idx = PPTBFIndex.load(builds["full"].folder)
    assert len(idx) == TINY.size and idx.resolution == 64
    entry = int(np.flatnonzero(idx.usable)[5])
    mask = pptbf.render_mask(idx.params[entry], 64)
    hits = idx.query(mask, k=5)
    assert len(hits) == 5 and hits[0].entry_id == entry and hits[0].distance < 1e-3
    assert all(a.distance <= b.distance for a, b in zip(hits, hits[1:]))
    np.testing.assert_array_equal(hits[0].params, idx.params[entry])
    assert all(idx.usable[h.entry_id] for h in idx.query(mask, k=50))
    # a larger mask is resized to the database resolution: same pattern at 2x, same neighbour (most of the time:
    # the area-averaged, re-binarised mask is not the 64 px render)
    found = [e in [h.entry_id for h in idx.query(pptbf.render_mask(idx.params[e], 128, ref_width=64,
                                                                    pixel_scale=2.0), k=3)]
             for e in np.flatnonzero(idx.usable)[:10]]
    assert np.mean(found) >= 0.8, found
    other = pptbf.render_mask(idx.params[hits[-1].entry_id], 64)
    d = idx.distance(mask, other)
    assert d > 0 and idx.distance(mask, mask) == pytest.approx(0.0, abs=1e-5)
    assert d == pytest.approx(idx.distance(other, mask), rel=1e-5)
    valid = np.ones_like(mask)
    valid[:, 40:] = False
    assert np.isfinite(idx.distance(mask, other, valid)) and idx.describe(mask, valid).shape == (32,)


def test_round_trip_known_parameters(builds):
    """Masks rendered from known parameters (new realisations) query back to their own parameters, and fresh
    parameters query to parameters whose (re-rendered) mask is within the nearest 1% of the database."""
    idx = PPTBFIndex.load(builds["full"].folder)
    n_usable = int(idx.usable.sum())
    top1pct = max(1, int(np.ceil(0.01 * n_usable)))
    probes = np.flatnonzero(idx.usable)[:16]
    ranks = []
    for e in probes:
        d = idx.distances_to(pptbf.render_mask(idx.params[e], 64, shift=(3.7, 1.3)))
        ranks.append(int((d < d[e]).sum()))
    own = np.mean(np.array(ranks) < top1pct)
    fresh = pptbf.sample_params(np.random.default_rng(99), 16, ref_width=64)
    inside = []
    for p in fresh:
        q = pptbf.render_mask(p, 64)
        if not 0.01 < q.mean() < 0.99:
            continue
        best = idx.query(q, k=1)[0]
        again = pptbf.render_mask(best.params, 64, shift=(5.1, 2.3))
        d_all = idx.distances_to(q)
        inside.append(idx.distance(q, again) <= np.quantile(d_all[idx.usable], 0.01))
    print(f"own-entry top-1% rate {own:.2f} (ranks {ranks}); fresh re-render within 1%: {np.mean(inside):.2f}")
    assert own >= 0.7
    assert np.mean(inside) >= 0.5


def test_load_errors(builds, tmp_path):
    with pytest.raises(DatabaseError, match="not found"):
        PPTBFIndex.load(tmp_path / "nowhere")
    folder = tmp_path / "db"
    shutil.copytree(builds["full"].folder, folder)
    (folder / "pca.npz").unlink()
    with pytest.raises(DatabaseError, match="incomplete.*pca.npz"):
        PPTBFIndex.load(folder)
    shutil.copy(builds["full"].folder / "pca.npz", folder / "pca.npz")
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "format": "proceduralize-pptbf-db/0"}))
    with pytest.raises(DatabaseError, match="format"):
        PPTBFIndex.load(folder)
    (folder / "meta.json").write_text(json.dumps({**meta, "size": 5}))
    with pytest.raises(DatabaseError, match="inconsistent"):
        PPTBFIndex.load(folder)
    (folder / "notes.txt").write_text("not a build file")
    assert clear_database(folder) == 7 + 3 * N_CHUNKS
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]


def test_cli_db_rebuild_and_info(ray_session, tmp_path, capsys):
    from service.cli import main

    out = tmp_path / "clidb"
    args = ["db", "rebuild", "--out", str(out), "--size", "40", "--resolution", "48", "--chunk", "20",
            "--dim", "8", "--seed", "3", "--float16", "--drop-raw"]
    assert main(args + ["--max-chunks", "1"]) == 0
    assert not (out / "meta.json").exists() and len(list(out.glob("raw_*.npy"))) == 1
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "complete" in text and "1 / 1 / 2" in text
    idx = PPTBFIndex.load(out)
    assert idx.reduced.shape == (40, 8) and np.load(out / "reduced.npy").dtype == np.float16
    assert not list(out.glob("raw_*.npy"))
    assert main(["db", "info", str(out)]) == 0
    assert "proceduralize-pptbf-db/1" in capsys.readouterr().out
    assert main(["db", "rebuild", "--out", str(out), "--size", "1"]) == 2
    assert main(["db", "info", str(tmp_path / "missing")]) == 2


def test_bundled_default_database():
    idx = PPTBFIndex.load(default_database_path())
    assert len(idx) >= 1000 and idx.resolution == 128
    assert idx.meta["format"] == "proceduralize-pptbf-db/1"
    assert not list(default_database_path().glob("raw_*.npy"))
    e = int(np.flatnonzero(idx.usable)[0])
    assert idx.query(pptbf.render_mask(idx.params[e], 128), k=1)[0].entry_id == e
