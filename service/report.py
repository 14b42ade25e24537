"""Static HTML report of a job: ``<out>/index.html`` + one page per material + images under ``img/``.

Per material: input vs procedural maps and renders side by side, the decomposition tree with its masks,
PPTBF fits, recomposition loss, metrics (from ``proceduralize evaluate``), per-stage timings, errors, and
the paper's editing operations (super-resolution, extension, pattern scale, new seed, a parameter edit),
rendered from the published ``material.json`` at small sizes. All links are relative; no server needed.
"""
from __future__ import annotations

import copy
import html
import json
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pptbf_db.errors import ProceduralizeError
from service.folder import MaterialFolder, safe_name
from service.pipeline import load_working_material
from service.stages import STAGE_NAMES
from workers.errors import InputError

logger = logging.getLogger(__name__)

MAP_ORDER = ("albedo", "normal", "roughness", "height", "metallic")
CSS = """
body{font-family:system-ui,sans-serif;margin:1.2em 2em;color:#222;background:#fafafa}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.4em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:left;
vertical-align:top;font-size:.9em}th{background:#eee}
img{image-rendering:pixelated;border:1px solid #bbb;background:#fff}
figure{display:inline-block;margin:4px 10px 8px 0;vertical-align:top}
figcaption{font-size:.8em;color:#555;max-width:420px}
.ok{color:#161}.bad{color:#a11;font-weight:bold}.warn{color:#a60}.muted{color:#777}
ul.tree{list-style:none;padding-left:1.4em}ul.tree li{margin:4px 0}ul.tree img{vertical-align:middle}
pre{white-space:pre-wrap;background:#f3f3f3;padding:6px;font-size:.85em}
"""


@dataclass
class ReportOptions:
    """What to render: editing previews at ``edit_size`` (working size capped), shown ``display`` px wide."""

    edit_size: int = 192
    display: int = 128
    editing: bool = True
    param_delta: float = 0.1
    thumb: int = 96


@dataclass
class _Page:
    """One HTML page being written: its folder, image sub-folder and the sections so far."""

    root: Path
    img_dir: str
    parts: list[str] = field(default_factory=list)

    def image(self, name: str, array: np.ndarray) -> str:
        """Write an sRGB/display-ready [0,1] array as PNG and return its relative src."""
        from workers.maps import write_image

        rel = f"{self.img_dir}/{name}.png"
        write_image(self.root / rel, np.clip(array, 0.0, 1.0), bits=8)
        return rel

    def link(self, target: Path) -> str | None:
        """Relative href to an existing file, else None."""
        return os.path.relpath(target, self.root) if target.exists() else None


# ----------------------------------------------------------------------------- small HTML helpers


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    if isinstance(v, list):
        return "[" + ", ".join(_num(x, digits) for x in v) + "]"
    return _e(v)


def _table(header: tuple, rows: list[tuple]) -> str:
    """A table; cells are already HTML."""
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _fig(src: str, caption: str, width: int) -> str:
    return (f'<figure style="max-width:{max(int(width), 160)}px"><img src="{_e(src)}" width="{int(width)}" '
            f'alt="{_e(caption)}"><figcaption>{caption}</figcaption></figure>')


def _status(s: str | None) -> str:
    cls = "ok" if s == "done" else "bad" if s in ("failed", "unavailable") else "warn"
    return f'<span class="{cls}">{_e(s or "-")}</span>'


def _fmt_time(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def _html(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
            f"<style>{CSS}</style></head><body>{body}</body></html>\n")


def _section(title: str, fn: Callable[[], str]) -> str:
    """``<h2>title</h2>`` + fn(); a missing or broken artefact shows as a note instead of failing the report."""
    try:
        content = fn()
    except FileNotFoundError as exc:
        logger.info("report section %r: %s missing", title, exc.filename)
        content = f'<p class="muted">not available: {_e(Path(exc.filename or "?").name)} not written yet</p>'
    except (OSError, KeyError, ValueError, ProceduralizeError) as exc:
        logger.warning("report section %r: %s", title, exc)
        content = f'<p class="muted">not available: {_e(exc)}</p>'
    return f"<h2>{_e(title)}</h2>{content}"


# ----------------------------------------------------------------------------- map display


def display_map(name: str, arr: np.ndarray, height_range: tuple[float, float] | None = None) -> np.ndarray:
    """A map as a displayable [0,1] image: albedo to sRGB, normal encoded, height normalised to a range."""
    from workers.maps import linear_to_srgb

    a = np.asarray(arr, dtype=np.float32)
    if name == "albedo":
        return linear_to_srgb(np.clip(a[..., :3], 0.0, 1.0))
    if name == "normal":
        return np.clip(a[..., :3] * 0.5 + 0.5, 0.0, 1.0)
    a = a[..., 0] if a.ndim == 3 else a
    if name == "height":
        lo, hi = height_range or (float(a.min()), float(a.max()))
        return np.clip((a - lo) / max(hi - lo, 1e-8), 0.0, 1.0)
    return np.clip(a, 0.0, 1.0)


def _preview(maps: dict[str, np.ndarray]) -> np.ndarray | None:
    """preview_image (top | side light), or None if the maps cannot be rendered."""
    from workers.render import preview_image

    if "albedo" not in maps or "normal" not in maps:
        return None
    return preview_image(maps)


def _load_graph(mdir: Path):
    """The published material.json, else the recomposed one; None if neither exists."""
    from workers import graph

    for p in (MaterialFolder(mdir).published, MaterialFolder(mdir).recomposed):
        if p.is_file():
            return graph.load(p), p
    return None, None


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


# ----------------------------------------------------------------------------- material sections


def _maps_section(page: _Page, mdir: Path, opts: ReportOptions, summary: dict) -> str:
    """Input maps (load stage) vs procedural maps at the working size, and their renders."""
    from workers import graph

    inp = load_working_material(mdir).maps() if MaterialFolder(mdir).working_maps.is_file() else {}
    mat, _ = _load_graph(mdir)
    proc = {}
    if mat is not None:
        w, h = mat.working_size
        proc = graph.evaluate(mat, w, h, scale=mat.working_scale, seed=mat.seed)  # the working maps' pattern size
    if not inp and not proc:
        return '<p class="muted">no input or procedural maps yet (load / recompose not done)</p>'
    hr = None
    if "height" in inp:
        hr = (float(inp["height"].min()), float(inp["height"].max()))
    names = [n for n in MAP_ORDER if n in inp or n in proc]
    width = opts.display
    rows = []
    for tag, maps in (("input", inp), ("procedural", proc)):
        cells = [f"<b>{tag}</b>"]
        for n in names:
            cells.append(f'<img src="{_e(page.image(f"{tag}_{n}", display_map(n, maps[n], hr)))}" width="{width}" '
                         f'alt="{tag} {n}">' if n in maps else '<span class="muted">-</span>')
        img = _preview(maps) if maps else None
        src = page.image(f"render_{tag}", img) if img is not None else None
        if tag == "procedural" and src:
            summary["thumb"] = src
        cells.append(f'<img src="{_e(src)}" width="{2 * width}" alt="{tag} render">' if src else "-")
        rows.append(tuple(cells))
    note = (f"<p class='muted'>input: the working-size maps of the load stage; procedural: material.json "
            f"evaluated at {mat.working_size[0]}x{mat.working_size[1]} at the working maps' pattern size, seed "
            f"{mat.seed}. Heights share the "
            f"input's range.</p>") if mat is not None else "<p class='muted'>no procedural graph yet</p>"
    return note + _table(("",) + tuple(names) + ("render (top | side light)",), rows)


def _tree_section(page: _Page, mdir: Path, opts: ReportOptions) -> str:
    """The decomposition tree as a nested list with mask thumbnails, split methods and coverage."""
    doc = _read_json(MaterialFolder(mdir).tree)
    fits = {}
    for p in MaterialFolder(mdir).mask_fits():
        d = _read_json(p)
        fits[d.get("node", p.stem)] = d.get("fit", {})

    def item(s: dict) -> str:
        png = MaterialFolder(mdir).mask_png(s["id"])
        img = ""
        if png.is_file():
            from workers.maps import read_image

            img = f'<img src="{_e(page.image("mask_" + safe_name(s["id"]), read_image(png)))}" ' \
                  f'width="{opts.thumb}" alt="mask {_e(s["id"])}"> '
        text = f"<b>{_e(s['id'])}</b> &middot; {_e(s.get('method', 'leaf'))} &middot; coverage " \
               f"{100 * float(s.get('coverage') or 0):.1f}%"
        if s.get("shares"):
            text += f" &middot; shares {_num(s['shares'], 3)}"
        fit = fits.get(s["id"])
        if fit:
            text += (f" &middot; PPTBF fit loss {_num(fit.get('loss_query'))} &rarr; {_num(fit.get('loss_final'))}"
                     f" ({fit.get('evaluations', '-')} evaluations, {_num(fit.get('seconds'), 3)} s)")
        kids = "".join(item(c) for c in s.get("children", []))
        return f"<li>{img}{text}" + (f"<ul class='tree'>{kids}</ul>" if kids else "") + "</li>"

    return f"<ul class='tree'>{item(doc.get('summary') or doc['tree'])}</ul>"


def _recompose_section(mdir: Path, material: dict | None = None) -> str:
    """Loss before/after the recomposition, iterations, device (and why, when not the one asked for), seconds."""
    rep = _read_json(MaterialFolder(mdir).recompose_report)
    before, after = rep.get("loss_before"), rep.get("loss_after")
    change = f"{100 * (after - before) / before:+.1f}%" if before and after is not None else "-"
    rows = [("loss before", _num(before)), ("loss after", _num(after)), ("change", change),
            ("iterations", _num(rep.get("iterations"))), ("device", _num(rep.get("device"))),
            ("kept original", _num(rep.get("kept_original"))), ("seconds", _num(rep.get("seconds_total")))]
    if material and material.get("device_note"):
        rows.insert(5, ("placement", _e(material["device_note"])))
    return _table(("recomposition", "value"), rows)


def read_metrics(job_out: Path) -> dict | None:
    """``<job output>/evaluation/metrics.json`` as {"rows": [...], "protocol": str}; None if absent.

    Accepts the file of ``proceduralize evaluate`` ({"rows": [...], "protocol": ...}) or a bare list of rows.
    """
    p = job_out / "evaluation" / "metrics.json"
    if not p.is_file():
        return None
    doc = _read_json(p)
    rows = doc.get("rows", []) if isinstance(doc, dict) else doc
    protocol = doc.get("protocol", "") if isinstance(doc, dict) else ""
    return {"rows": [r for r in rows if isinstance(r, dict)], "protocol": str(protocol)}


def _metrics_table(rows: list[dict], keys: tuple[str, ...]) -> str:
    cols = keys + ("swd", "spectrum", "histogram", "gram")
    return _table(cols, [tuple(_num(r.get(k)) for k in cols) for r in rows])


def _protocol(metrics: dict | None) -> str:
    return f"<p class='muted'>{_e(metrics['protocol'])}</p>" if metrics and metrics.get("protocol") else ""


def _metrics_hint(job_ref: str) -> str:
    return f'<p class="muted">no metrics yet: run <code>proceduralize evaluate {_e(job_ref)}</code></p>'


def _timings_section(store, job: str, material: str) -> str:
    """Per stage item: status, attempts, seconds, worker; and the total per stage."""
    items = store.items(job, material)
    if not items:
        return '<p class="muted">no stage has run yet</p>'
    rank = {s: i for i, s in enumerate(STAGE_NAMES)}
    items.sort(key=lambda r: (rank.get(r["stage"], 99), r["item"] or ""))
    rows = [(_e(r["stage"]), _e(r["item"] or "-"), _status(r["status"]), _num(r["attempts"]),
             _num(r["duration"], 3), _e(r["worker"] or "-")) for r in items]
    totals: dict[str, float] = {}
    for r in items:
        totals[r["stage"]] = totals.get(r["stage"], 0.0) + float(r["duration"] or 0.0)
    rows.append(("<b>total</b>", "", "", "", f"<b>{sum(totals.values()):.3g}</b>", ""))
    return _table(("stage", "item", "status", "attempts", "seconds", "worker"), rows)


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


#: error kinds that are about the input (bad file, option, budget, timeout), not about the code: the report
#: shows their message only; any other kind is an internal error and keeps its traceback for a developer
USER_ERRORS = {"InputError", "ManifestError", "GraphError", "DatabaseError", "WeightsError", "MemoryBudgetError",
               "StageTimeout"}


def _message(text: str, kind: str | None = None) -> str:
    """An error message: its last line, with the whole text (a traceback) folded below for internal errors."""
    clean = _ANSI.sub("", text).strip()
    lines = [ln for ln in clean.splitlines() if ln.strip()]
    if len(lines) <= 1 or kind in USER_ERRORS:
        return _e(lines[-1] if lines else clean)
    return f"{_e(lines[-1])}<details><summary>details</summary><pre>{_e(clean)}</pre></details>"


def _errors_section(store, job: str, material: dict) -> str:
    """The material's final error and every failed attempt."""
    errs = store.errors(job, material["name"])
    head = f"<p class='bad'>{_e(_ANSI.sub('', material['error']))}</p>" if material.get("error") else ""
    if not errs:
        return head + ("" if head else '<p class="ok">no errors</p>')
    rows = [(_fmt_time(e["time"]), _e(e["stage"]), _e(e["item"] or "-"), _num(e["attempt"]), _e(e["kind"] or "-"),
             "final" if e["final"] else "retried", _message(e["message"] or "", e["kind"])) for e in errs]
    return head + _table(("time", "stage", "item", "attempt", "kind", "outcome", "message"), rows)


def _outputs_section(page: _Page, mdir: Path, opts: ReportOptions) -> str:
    """The job's own renders (maps/<tag>/preview.png) and a link to the published material.json."""
    figs = []
    for prev in MaterialFolder(mdir).previews():
        href = page.link(prev)
        figs.append(f'<figure><a href="{_e(href)}"><img src="{_e(href)}" width="{2 * opts.display}" '
                    f'alt="{_e(prev.parent.name)}"></a><figcaption>{_e(prev.parent.name)}</figcaption></figure>')
    link = page.link(MaterialFolder(mdir).published)
    head = f'<p>graph: <a href="{_e(link)}">material.json</a></p>' if link else ""
    return head + ("".join(figs) or '<p class="muted">no output renders</p>')


# ----------------------------------------------------------------------------- editing


@dataclass
class EditingCase:
    """One editing demonstration: evaluation arguments and a caption."""

    key: str
    title: str
    size: tuple[int, int]
    scale: float = 1.0
    seed: int | None = None
    caption: str = ""


def editing_cases(working_size: tuple[int, int], seed: int, base: int) -> list[EditingCase]:
    """Original, super-resolution (2x size, scale 2), extension (2x size), pattern scale 2, new seed."""
    w, h = working_size
    k = min(1.0, base / max(w, h))
    bw, bh = max(8, int(round(w * k))), max(8, int(round(h * k)))
    return [
        EditingCase("original", "original", (bw, bh), 1.0, seed, f"{bw}x{bh}, scale 1, seed {seed}"),
        EditingCase("superres", "super-resolution", (2 * bw, 2 * bh), 2.0, seed,
                    f"{2 * bw}x{2 * bh}, scale 2: the same view with twice the pixels"),
        EditingCase("extension", "extension", (2 * bw, 2 * bh), 1.0, seed,
                    f"{2 * bw}x{2 * bh}, scale 1: a larger canvas, features keep their size"),
        EditingCase("scale2", "pattern scale 2", (bw, bh), 2.0, seed,
                    f"{bw}x{bh}, scale 2: features twice as big"),
        EditingCase("seed", "new realisation", (bw, bh), 1.0, seed + 1, f"{bw}x{bh}, seed {seed + 1}"),
    ]


def _editing_section(page: _Page, mdir: Path, opts: ReportOptions) -> str:
    """Each editing case as albedo + render, images at one zoom so sizes compare; then a parameter edit."""
    from workers import graph
    from workers.edit import apply_edits, suggest_edit

    mat, path = _load_graph(mdir)
    if mat is None:
        return '<p class="muted">no material.json yet</p>'
    cases = editing_cases(tuple(mat.working_size), int(mat.seed), opts.edit_size)
    zoom = opts.display / cases[0].size[0]
    blocks = []
    for c in cases:
        maps = graph.evaluate(mat, c.size[0], c.size[1], scale=c.scale, seed=c.seed)
        w = int(round(c.size[0] * zoom))
        alb = page.image(f"edit_{c.key}_albedo", display_map("albedo", maps["albedo"]))
        figs = _fig(alb, f"albedo &middot; {_e(c.caption)}", w)
        img = _preview(maps)
        if img is not None:
            figs += _fig(page.image(f"edit_{c.key}_render", img), "render (top | side light)", 2 * w)
        blocks.append(f"<h3>{_e(c.title)}</h3>{figs}")
    edit = suggest_edit(mat, opts.param_delta)
    if edit is not None:
        base = cases[0]
        edited = copy.deepcopy(mat)
        apply_edits(edited, [(edit.path, edit.after)], str(path))
        figs, means = "", []
        for tag, m in (("before", mat), ("after", edited)):
            maps = graph.evaluate(m, base.size[0], base.size[1], seed=base.seed)
            means.append(float(maps["albedo"].mean()))
            w = int(round(base.size[0] * zoom))
            figs += _fig(page.image(f"edit_param_{tag}_albedo", display_map("albedo", maps["albedo"])),
                         f"albedo {tag}", w)
            img = _preview(maps)
            if img is not None:
                figs += _fig(page.image(f"edit_param_{tag}_render", img), f"render {tag}", 2 * w)
        cmd = f"proceduralize edit {path.name} --set {edit.path}={json.dumps(edit.after)}"
        blocks.append(f"<h3>parameter edit: {_e(edit.label)}</h3><p><code>{_e(cmd)}</code> &middot; "
                      f"<code>{_e(edit.path)}</code>: {_num(edit.before)} &rarr; {_num(edit.after)}; "
                      f"mean albedo (linear) {means[0]:.4f} &rarr; {means[1]:.4f}</p>{figs}")
    note = ("<p class='muted'>Rendered from the procedural graph (no pixels of the input are used); "
            f"images share one zoom ({zoom:.2g} screen px per pixel) so sizes compare. "
            "Commands: <code>proceduralize render material.json --size WxH --scale S --seed N</code>.</p>")
    return note + "".join(blocks)


# ----------------------------------------------------------------------------- pages


def _material_page(store, job: dict, material: dict, root: Path, opts: ReportOptions,
                   metrics: dict | None, job_ref: str) -> dict:
    """Write ``<root>/<material>.html``; return what the index shows about it."""
    key = safe_name(material["name"])
    mdir = Path(job["output"]) / (material["output"] or material["name"])
    page = _Page(root=root, img_dir=f"img/{key}")
    summary: dict[str, Any] = {"name": material["name"], "page": f"{key}.html", "status": material["status"],
                               "device": material.get("device"), "device_note": material.get("device_note")}
    t0 = time.perf_counter()
    parts = [f"<p><a href='index.html'>&larr; job {_e(job['name'])}</a></p>",
             f"<h1>{_e(material['name'])}</h1><p>status {_status(material['status'])} &middot; "
             f"folder <code>{_e(mdir)}</code></p>",
             _section("Input vs procedural maps", lambda: _maps_section(page, mdir, opts, summary)),
             _section("Decomposition tree", lambda: _tree_section(page, mdir, opts)),
             _section("Recomposition", lambda: _recompose_section(mdir, material))]
    mine = [r for r in (metrics or {}).get("rows", []) if r.get("material") == material["name"]]
    parts.append(_section("Metrics", lambda: _metrics_table(mine, ("map", "method")) + _protocol(metrics) if mine
                          else _metrics_hint(job_ref) if metrics is None else
                          '<p class="muted">no metrics rows for this material</p>'))
    if opts.editing:
        parts.append(_section("Editing", lambda: _editing_section(page, mdir, opts)))
    parts += [_section("Job outputs", lambda: _outputs_section(page, mdir, opts)),
              _section("Timings", lambda: _timings_section(store, job["name"], material["name"])),
              _section("Errors", lambda: _errors_section(store, job["name"], material))]
    parts.append(f"<p class='muted'>page built in {time.perf_counter() - t0:.1f} s</p>")
    (root / summary["page"]).write_text(_html(f"{material['name']} - {job['name']}", "".join(parts)),
                                        encoding="utf-8")
    rec = MaterialFolder(mdir).recompose_report
    if rec.is_file():
        r = _read_json(rec)
        summary["loss"] = (r.get("loss_before"), r.get("loss_after"))
    summary["seconds"] = sum(float(i["duration"] or 0) for i in store.items(job["name"], material["name"]))
    summary["errors"] = len(store.errors(job["name"], material["name"]))
    return summary


def _metrics_summary(rows: list[dict]) -> str:
    """Mean of each metric per (map, method) over the job's materials."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r.get("map"), r.get("method")), []).append(r)
    out = []
    for (m, meth), rs in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), str(kv[0][1]))):
        mean = {k: float(np.mean([r[k] for r in rs if isinstance(r.get(k), (int, float))] or [np.nan]))
                for k in ("swd", "spectrum", "histogram")}
        out.append({"map": m, "method": meth, "materials": len(rs), **mean})
    return _metrics_table(out, ("map", "method", "materials"))


def _device(summary: dict) -> str:
    """The recomposition device, with why it is not the one asked for (fallback, GPU without CUDA)."""
    dev = _e(summary.get("device") or "-")
    note = summary.get("device_note")
    return f"{dev} <span class='muted'>({_e(note)})</span>" if note else dev


def _index_page(store, job: dict, summaries: list[dict], metrics: dict | None, job_ref: str) -> str:
    """The job page: job facts, one row per material (linked), stage summary, mean metrics."""
    dur = (job["finished"] - job["started"]) if job.get("finished") and job.get("started") else None
    facts = _table(("job", "value"), [
        ("name", _e(job["name"])), ("status", _status(job["status"])), ("manifest", _e(job.get("manifest") or "-")),
        ("output", f"<code>{_e(job['output'])}</code>"), ("started", _fmt_time(job.get("started"))),
        ("finished", _fmt_time(job.get("finished"))), ("wall seconds", _num(dur, 4)),
        ("driver runs", _num(job.get("runs")))])
    rows = []
    for s in summaries:
        thumb = f'<img src="{_e(s["thumb"])}" height="64" alt="render">' if s.get("thumb") else "-"
        loss = s.get("loss")
        rows.append((f'<a href="{_e(s["page"])}">{_e(s["name"])}</a>', _status(s["status"]), thumb,
                     f"{_num(loss[0])} &rarr; {_num(loss[1])}" if loss else "-", _device(s),
                     _num(s.get("seconds"), 3),
                     f"<span class='bad'>{s['errors']}</span>" if s.get("errors") else "0"))
    mats = _table(("material", "status", "procedural render", "recompose loss", "recompose device", "stage seconds",
                   "errors"), rows)
    stages = _table(("material", "stage", "status", "items done", "attempts", "seconds", "workers"), [
        (_e(r["material"]), _e(r["stage"]), _status(r["status"]), f"{r['done']}/{r['items']}", _num(r["attempts"]),
         _num(r["seconds"], 3), _e(r["workers"] or "-")) for r in store.stage_summary(job["name"])])
    met = _metrics_summary(metrics["rows"]) + _protocol(metrics) if metrics else _metrics_hint(job_ref)
    body = (f"<h1>Job {_e(job['name'])}</h1>{facts}<h2>Materials</h2>{mats}<h2>Stages</h2>{stages}"
            f"<h2>Metrics (mean over materials)</h2>{met}"
            f"<p class='muted'>report written {_fmt_time(time.time())}</p>")
    return _html(f"proceduralize job {job['name']}", body)


def build_report(store, job_name: str, out: Path | None = None, options: ReportOptions | None = None,
                 job_ref: str | None = None) -> Path:
    """Write the report of job ``job_name`` (default folder ``<job output>/report``); returns index.html."""
    opts = options or ReportOptions()
    job = store.job(job_name)
    if job is None:
        raise InputError(f"no job named {job_name!r} in the database")
    job = dict(job, output=str(store.output_root(job_name)))  # where the files are now (a copied job too)
    root = Path(out) if out is not None else Path(job["output"]) / "report"
    root.mkdir(parents=True, exist_ok=True)
    ref = job_ref or job["output"]
    metrics = read_metrics(Path(job["output"]))
    summaries = []
    for m in store.materials(job_name):
        t0 = time.perf_counter()
        summaries.append(_material_page(store, job, m, root, opts, metrics, ref))
        logger.info("report: %s in %.1f s", m["name"], time.perf_counter() - t0)
    index = root / "index.html"
    index.write_text(_index_page(store, job, summaries, metrics, ref), encoding="utf-8")
    return index
