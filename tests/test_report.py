"""`proceduralize report` on a real small job (local Ray, real SQLite): every image and link exists, the
pages hold the job's numbers, errors and metrics, and headless Chromium renders them."""
from __future__ import annotations

import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

from service.cli import main
from service.manifest import validate
from service.scheduler import Scheduler
from service.store import Store
from tests.conftest import real_material_files
from workers import graph
from workers.edit import apply_edits, suggest_edit

pytestmark = pytest.mark.ray
CHROMIUM = Path("/usr/bin/chromium")
GOOD = "castle_brick_broken_06"


@pytest.fixture(scope="module")
def small_job(ray_session, materials_dir, tmp_path_factory):
    """One real material through the whole pipeline at 64 px with tiny budgets, plus one with a missing map."""
    root = tmp_path_factory.mktemp("report_job")
    f = real_material_files(GOOD)
    good = {"name": GOOD, "albedo": str(f["albedo"]), "normal": str(f["normal"]),
            "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"]}, "seed": 1}
    bad = dict(good, name="broken", albedo=str(root / "missing_diff.png"))
    doc = {"job": {"name": "rep", "output": "out"},
           "defaults": {"working_size": 64, "decompose": {"mode": "auto", "layers": 2},
                        "masks": {"max_evals": 8, "rounds": 1}, "recompose": {"iterations": 4},
                        "outputs": {"sizes": [[64, 64]], "seeds": [0]}},
           "materials": [good, bad]}
    man = validate(doc, root=root)
    with Store(man.database) as store:
        rep = Scheduler(man, store=store, progress=False).run()
    assert rep.materials == {GOOD: "done", "broken": "failed"}, rep.errors
    return man.output


class _Refs(HTMLParser):
    """Collects img src and a href values."""

    def __init__(self):
        super().__init__()
        self.imgs, self.links = [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a.get("src"))
        elif tag == "a":
            self.links.append(a.get("href"))


def _refs(page: Path) -> _Refs:
    p = _Refs()
    p.feed(page.read_text(encoding="utf-8"))
    return p


def test_report_pages_reference_existing_files_and_show_the_job(small_job, capsys):
    assert main(["report", str(small_job)]) == 0
    root = small_job / "report"
    assert str(root / "index.html") in capsys.readouterr().out
    pages = sorted(root.glob("*.html"))
    assert [p.name for p in pages] == ["broken.html", f"{GOOD}.html", "index.html"]
    for page in pages:
        refs = _refs(page)
        for ref in refs.imgs + refs.links:
            assert ref and (root / ref).is_file(), f"{page.name}: {ref} missing"
        assert all(ref.endswith(".png") for ref in refs.imgs)
    idx = _refs(root / "index.html")
    assert {f"{GOOD}.html", "broken.html"} <= set(idx.links)
    good = _refs(root / f"{GOOD}.html")
    names = {Path(s).name for s in good.imgs}
    expected = {f"{t}_{m}.png" for t in ("input", "procedural") for m in ("albedo", "normal", "roughness", "height")}
    expected |= {"render_input.png", "render_procedural.png", "mask_root.png"}
    expected |= {f"edit_{k}_albedo.png" for k in ("original", "superres", "extension", "scale2", "seed")}
    expected |= {"edit_param_before_albedo.png", "edit_param_after_albedo.png"}
    assert expected <= names, expected - names
    # editing images at the advertised sizes (working size 64: base 64 px, 2x for super-resolution/extension)
    img = root / f"img/{GOOD}"
    from workers.maps import read_image

    assert read_image(img / "edit_superres_albedo.png").shape[:2] == (128, 128)
    assert read_image(img / "edit_scale2_albedo.png").shape[:2] == (64, 64)
    assert read_image(img / "render_procedural.png").shape[:2] == (64, 128)
    html = (root / f"{GOOD}.html").read_text()
    rec = json.loads((small_job / GOOD / "recompose" / "report.json").read_text())
    assert f"{rec['loss_before']:.4g}" in html and f"{rec['loss_after']:.4g}" in html
    assert "proceduralize evaluate" in html  # no metrics yet -> the hint
    for stage in ("load", "decompose", "noise", "masks", "recompose", "output"):
        assert f"<td>{stage}</td>" in html
    broken = (root / "broken.html").read_text()
    assert "missing_diff.png" in broken and "not found" in broken
    assert "missing_diff.png" not in (root / f"{GOOD}.html").read_text()


def test_report_shows_metrics_and_the_parameter_edit(small_job, tmp_path):
    ev = small_job / "evaluation"
    ev.mkdir(exist_ok=True)
    rows = [{"material": GOOD, "map": "albedo", "method": "procedural", "swd": 0.0123, "spectrum": 0.456,
             "histogram": 0.0789},
            {"material": GOOD, "map": "albedo", "method": "random_phase", "swd": 0.0321, "spectrum": 0.654,
             "histogram": 0.0987}]
    (ev / "metrics.json").write_text(json.dumps({"job": "rep", "protocol": "lower is better (test protocol)",
                                                 "rows": rows}))
    try:
        assert main(["report", str(small_job / "proceduralize.db"), "--out", str(tmp_path / "r")]) == 0
    finally:
        shutil.rmtree(ev)
    html = (tmp_path / "r" / f"{GOOD}.html").read_text()
    assert "0.0123" in html and "0.654" in html and "random_phase" in html and "(test protocol)" in html
    index = (tmp_path / "r" / "index.html").read_text()
    assert "proceduralize evaluate" not in index and "0.0123" in index  # one material: mean = its value
    for ref in _refs(tmp_path / "r" / f"{GOOD}.html").links:  # relative links from another folder still work
        assert (tmp_path / "r" / ref).is_file(), ref
    # the suggested edit really brightens the albedo of the job's own graph
    mat = graph.load(small_job / GOOD / "material.json")
    edit = suggest_edit(mat, 0.1)
    assert edit is not None and edit.path.endswith(".d")
    m0 = graph.evaluate(mat, 64, 64)["albedo"].mean()
    apply_edits(mat, [(edit.path, edit.after)])
    assert graph.evaluate(mat, 64, 64)["albedo"].mean() > m0 + 0.08
    assert "mean albedo (linear)" in html and edit.path in html


def test_copied_job_folder_reports_and_lists_its_own_files(small_job, tmp_path, capsys):
    """A job folder copied elsewhere (the database records absolute paths) is read where it now is."""
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(small_job, moved, ignore=shutil.ignore_patterns("report", "evaluation"))
    assert main(["results", str(moved), "--json"]) == 1          # one material failed on purpose
    doc = json.loads(capsys.readouterr().out)
    good = next(m for m in doc["materials"] if m["name"] == GOOD)
    assert good["material_json"].startswith(str(moved)) and Path(good["material_json"]).is_file()
    assert all(Path(p).is_dir() and p.startswith(str(moved)) for p in good["maps"])
    assert main(["report", str(moved)]) == 0
    assert (moved / "report" / "index.html").is_file() and not (small_job / "report" / "moved").exists()
    refs = _refs(moved / "report" / f"{GOOD}.html")
    assert refs.imgs and all((moved / "report" / ref).is_file() for ref in refs.imgs)


def test_report_bad_job_exits_2(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nothing")]) == 2
    assert "not found" in capsys.readouterr().err


@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (Debian package 'chromium') not installed")
def test_headless_chromium_renders_the_report(small_job, tmp_path):
    root = small_job / "report"
    if not (root / "index.html").exists():
        assert main(["report", str(small_job), "--no-editing"]) == 0
    from workers.maps import read_image

    for page in ("index.html", f"{GOOD}.html"):
        shot = tmp_path / f"{page}.png"
        cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}", "--window-size=1200,900",
               (root / page).resolve().as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
        assert proc.returncode == 0 and shot.is_file(), proc.stderr[-2000:]
        img = read_image(shot)
        assert img.shape[:2] == (900, 1200)
        # not blank: text, tables and images give contrast; a blank page has ~0 variance
        assert img[..., :3].std() > 0.05, img.std()
        assert (img[..., :3].mean(-1) < 0.3).mean() > 0.005  # some dark pixels (text / images)
