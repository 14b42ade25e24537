"""Job manifests (TOML, JSON or YAML): schema, strict validation listing every problem, path resolution.

A manifest names a job, its output folder, defaults, and materials::

    [job]
    name = "example"
    output = "../out/example"            # relative paths resolve against the manifest's folder
    stages = ["load", "decompose", "noise", "masks", "recompose", "output"]   # optional

    [defaults]                            # any material key; a material's own value wins
    working_size = 256
    outputs = { sizes = [[512, 512]], seeds = [0] }

    [[materials]]
    name = "castle"
    albedo = "maps/castle_diff.jpg"
    normal = { file = "maps/castle_nor_gl.jpg", convention = "opengl" }
    roughness = { file = "maps/castle_arm.jpg", channel = "G" }
    decompose = { mode = "auto", layers = 2 }

Every problem is collected and raised at once as ``ManifestError(problems)``, each naming its field.
Map files are *not* required to exist here: a missing file fails only its material, at the load stage.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import nlopt
import yaml

from pptbf_db.errors import ProceduralizeError
from service.placement import DEVICES
from service.stages import STAGE_NAMES, STAGES, Stage
from workers import budget
from workers.decompose import validate_spec
from workers.errors import ManifestError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

#: stages with an options table (key = the stage name), in pipeline order
OPTION_STAGES = tuple(s.name for s in STAGES if s.config is not None)
MAP_KEYS = ("albedo", "normal", "roughness", "height", "metallic")
NORMAL_CONVENTIONS = ("opengl", "directx", "auto", "rot90", "swap_xy")
COLORSPACES = ("srgb", "linear")
DECOMPOSE_MODES = ("none", "auto", "scribbles")
DEFAULT_DATABASE = "proceduralize.db"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
_CHANNEL_RE = re.compile(r"^([RGBA]|[0-9]|[A-Za-z][A-Za-z0-9_.]*)$")

JOB_KEYS = {"name", "output", "stages", "database", "max_attempts", "mask_actors", "description", "pptbf_database",
            "gpu_wait_s", "recompose_cpus", "stage_timeout", "memory_budget"}
#: seconds one stage item may run before it is cancelled and its material fails (job.stage_timeout)
DEFAULT_STAGE_TIMEOUT_S = 3600.0
MATERIAL_KEYS = {"name", "folder", "output", *MAP_KEYS, "roughness_channel", "metallic_channel",
                 "albedo_colorspace", "normal_convention", "working_size", "decompose", "outputs", "seed",
                 *OPTION_STAGES, "stages"}
DEFAULT_KEYS = MATERIAL_KEYS - {"name", "output", *MAP_KEYS}
OUTPUT_KEYS = {"sizes", "seeds", "scales", "preview", "bits", "materialx", "procedural"}
DEBUG_KEYS = {"crash_once", "sleep"}


@dataclass
class MapSpec:
    """One input map file with its channel pick (grey maps) or colour space / normal convention."""

    file: Path
    channel: str | int | None = None


@dataclass
class OutputSpec:
    """What the output stage renders: every size x seed x scale, plus a preview."""

    sizes: list[tuple[int, int]] = field(default_factory=lambda: [(1024, 1024)])
    seeds: list[int] = field(default_factory=lambda: [0])
    scales: list[float] = field(default_factory=lambda: [1.0])
    preview: bool = True
    bits: int = 8
    materialx: bool = True   # a material.mtlx (standard_surface + UsdPreviewSurface) beside each map set
    procedural: bool = False  # material.mtlx also holds M_<name>_procedural (workers.mtlx: our node library)


@dataclass
class MaterialSpec:
    """One material of a job: resolved map paths, options and per-stage configs.

    ``decompose`` and ``options`` (stage name -> its options table) hold JSON values: what :meth:`to_json` writes
    is what the stage bodies read."""

    name: str
    output: str
    maps: dict[str, MapSpec]
    albedo_colorspace: str = "srgb"
    normal_convention: str = "opengl"
    working_size: int | tuple[int, int] | None = 512
    decompose: dict = field(default_factory=lambda: {"mode": "auto"})
    outputs: OutputSpec = field(default_factory=OutputSpec)
    seed: int = 0
    options: dict[str, dict] = field(default_factory=dict)
    stages: list[str] | None = None

    def stage_options(self, stage: str) -> dict:
        """The options table of a stage ({} when the material gives none)."""
        return self.options.get(stage, {})

    def with_options(self, stage: str, **changes: Any) -> MaterialSpec:
        """A copy whose options of ``stage`` have ``changes`` set."""
        return dataclasses.replace(self, options={**self.options, stage: {**self.stage_options(stage), **changes}})

    def to_json(self) -> dict:
        """JSON-able form (paths as strings), also what workers receive."""
        return {
            "name": self.name, "output": self.output,
            "maps": {k: {"file": str(m.file), "channel": m.channel} for k, m in self.maps.items()},
            "albedo_colorspace": self.albedo_colorspace, "normal_convention": self.normal_convention,
            "working_size": list(self.working_size) if isinstance(self.working_size, tuple) else self.working_size,
            "decompose": _jsonable(self.decompose),
            "outputs": {"sizes": [list(s) for s in self.outputs.sizes], "seeds": list(self.outputs.seeds),
                        "scales": list(self.outputs.scales), "preview": self.outputs.preview,
                        "bits": self.outputs.bits, "materialx": self.outputs.materialx,
                        "procedural": self.outputs.procedural},
            "seed": self.seed, **{s: _jsonable(self.stage_options(s)) for s in OPTION_STAGES},
            "stages": self.stages,
        }

    def input_files(self) -> list[Path]:
        """Every file the material reads: maps and scribble images."""
        files = [m.file for m in self.maps.values()]

        def scribbles(node: dict) -> None:
            if isinstance(node.get("scribbles"), str):
                files.append(Path(node["scribbles"]))
            for c in (node.get("children") or {}).values():
                if isinstance(c, dict):
                    scribbles(c)

        scribbles(self.decompose)
        return files

    def spec_hash(self) -> str:
        """Hash of everything that determines this material's results: options and the input files' size and
        modification time (a change invalidates its finished stages)."""
        doc = self.to_json()
        doc.pop("stages", None)
        stamps = {}
        for f in self.input_files():
            try:
                st = f.stat()
                stamps[str(f)] = [st.st_size, st.st_mtime_ns]
            except OSError:
                stamps[str(f)] = None
        doc["input_stamps"] = stamps
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class JobManifest:
    """A validated job: where it came from, where it writes, and its materials."""

    name: str
    source: Path | None
    root: Path
    output: Path
    database: Path
    stages: list[str] | None
    materials: list[MaterialSpec]
    max_attempts: int = 3
    mask_actors: int | None = None
    stage_timeout: float = DEFAULT_STAGE_TIMEOUT_S
    memory_budget: int | None = None   # bytes per stage item; None: half the worker machine's memory
    description: str = ""
    pptbf_database: Path | None = None
    gpu_wait_s: float = 600.0    # how long GPU recompositions wait for a GPU node before "auto" runs them on CPU
    recompose_cpus: int = 2      # CPUs (= torch threads) one CPU recomposition actor reserves

    def material(self, name: str) -> MaterialSpec:
        """The material called ``name`` (KeyError if absent)."""
        for m in self.materials:
            if m.name == name:
                return m
        raise KeyError(name)

    def material_dir(self, m: MaterialSpec) -> Path:
        """The folder a material's artefacts go to (always inside the job's output folder)."""
        return self.output / m.output

    def to_json(self) -> dict:
        """JSON-able form (stored in the job row)."""
        return {"name": self.name, "source": str(self.source) if self.source else None, "root": str(self.root),
                "output": str(self.output), "database": str(self.database), "stages": self.stages,
                "max_attempts": self.max_attempts, "mask_actors": self.mask_actors,
                "stage_timeout": self.stage_timeout, "memory_budget": self.memory_budget,
                "description": self.description, "pptbf_database": str(self.pptbf_database or ""),
                "gpu_wait_s": self.gpu_wait_s, "recompose_cpus": self.recompose_cpus,
                "materials": [m.to_json() for m in self.materials]}


def _jsonable(x: Any) -> Any:
    """Deep copy with paths as strings and tuples as lists."""
    return json.loads(json.dumps(x, default=str))


# ----------------------------------------------------------------------------- reading


def read_document(path: str | Path) -> dict:
    """Parse a TOML (.toml), JSON (.json) or YAML (.yaml/.yml) manifest file into a dict."""
    p = Path(path)
    if not p.is_file():
        raise ManifestError("file not found (check the path)" if not p.exists() else "not a regular file", str(p))
    suffix = p.suffix.lower()
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"cannot read ({exc})", str(p)) from None
    try:
        if suffix == ".toml":
            doc = tomllib.loads(text)
        elif suffix == ".json":
            doc = json.loads(text)
        elif suffix in (".yaml", ".yml"):
            doc = yaml.safe_load(text)
        else:
            raise ManifestError(f"unknown manifest type {suffix!r}; use .toml, .json, .yaml or .yml", str(p))
    except ManifestError:
        raise
    except Exception as exc:  # noqa: BLE001 - each parser has its own error type; all mean "bad syntax"
        raise ManifestError(f"not valid {suffix[1:].upper()}: {exc}", str(p)) from None
    if not isinstance(doc, dict):
        raise ManifestError("top level must be a table/object with [job] and [[materials]]", str(p))
    return doc


def load_manifest(path: str | Path, output: str | Path | None = None) -> JobManifest:
    """Read and validate a manifest file; ``output`` overrides its ``job.output`` folder."""
    p = Path(path).resolve()
    out = Path(output).expanduser().resolve() if output is not None else None  # an override is relative to cwd
    return validate(read_document(p), root=p.parent, source=p, output_override=out)


# ----------------------------------------------------------------------------- validation


class _Problems(list):
    """Collects problems as ``field: message`` strings."""

    def add(self, where: str, msg: str) -> None:
        self.append(f"{where}: {msg}")

    def unknown(self, where: str, keys: set, allowed: set) -> None:
        for k in sorted(keys - allowed, key=str):
            close = difflib.get_close_matches(str(k), sorted(allowed), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(sorted(allowed))})"
            self.add(f"{where}.{k}" if where else str(k), f"unknown key{hint}")


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _inside(path: Path, folder: Path) -> bool:
    """True when ``path`` is ``folder`` or below it (after resolving ``..``)."""
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def _size(v: Any, where: str, probs: _Problems, lo: int = 8) -> tuple[int, int] | None:
    """A size as N (square) or [W, H]."""
    if _is_int(v) and lo <= v <= 32768:
        return (v, v)
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(_is_int(x) and lo <= x <= 32768 for x in v):
        return (int(v[0]), int(v[1]))
    probs.add(where, f"must be an integer N or [W, H] with {lo} <= N <= 32768, got {v!r}")
    return None


def _map_spec(v: Any, key: str, where: str, base: Path, channel: Any, probs: _Problems) -> MapSpec | None:
    """A map entry: a path string or {file, channel} (normal: convention; albedo: colorspace handled by caller)."""
    extra: dict = {}
    if isinstance(v, dict):
        allowed = {"file", "channel"} | ({"colorspace"} if key == "albedo" else set()) | (
            {"convention"} if key == "normal" else set())
        probs.unknown(where, set(v), allowed)
        extra = v
        v = v.get("file")
        channel = extra.get("channel", channel)
    if not isinstance(v, str) or not v.strip():
        probs.add(where if not extra else f"{where}.file", f"must be a file path string, got {v!r}")
        return None
    if channel is not None:
        if key not in ("roughness", "metallic", "height"):
            probs.add(f"{where}.channel", "a channel pick applies to grey maps (roughness, metallic, height) only")
        elif not (_is_int(channel) and 0 <= channel < 64) and not (
                isinstance(channel, str) and _CHANNEL_RE.match(channel)):
            probs.add(f"{where}.channel", f"must be R, G, B, A, a channel name or an index, got {channel!r}")
    file = Path(v).expanduser()
    return MapSpec(file=(file if file.is_absolute() else base / file).resolve(strict=False), channel=channel)


def _stage_list(v: Any, where: str, probs: _Problems) -> list[str] | None:
    if v is None:
        return None
    if not isinstance(v, list) or not v or not all(isinstance(s, str) for s in v):
        probs.add(where, f"must be a non-empty list of stage names from {list(STAGE_NAMES)}, got {v!r}")
        return None
    bad = [s for s in v if s not in STAGE_NAMES]
    if bad:
        probs.add(where, f"unknown stage(s) {bad}; stages are {list(STAGE_NAMES)}")
        return None
    if len(set(v)) != len(v):
        probs.add(where, "lists a stage twice")
        return None
    return [s for s in STAGE_NAMES if s in v]


def _outputs(v: Any, where: str, probs: _Problems) -> OutputSpec:
    out = OutputSpec()
    if not isinstance(v, dict):
        probs.add(where, f"must be a table with {sorted(OUTPUT_KEYS)}, got {type(v).__name__}")
        return out
    probs.unknown(where, set(v), OUTPUT_KEYS)
    if "sizes" in v:
        sizes = v["sizes"]
        if not isinstance(sizes, list) or not sizes:
            probs.add(f"{where}.sizes", "must be a non-empty list of N or [W, H]")
        else:
            got = [_size(s, f"{where}.sizes[{i}]", probs, lo=1) for i, s in enumerate(sizes)]
            out.sizes = [s for s in got if s is not None]
    if "seeds" in v:
        seeds = v["seeds"]
        if not isinstance(seeds, list) or not seeds or not all(_is_int(s) and s >= 0 for s in seeds):
            probs.add(f"{where}.seeds", f"must be a non-empty list of integers >= 0, got {seeds!r}")
        else:
            out.seeds = [int(s) for s in seeds]
    if "scales" in v:
        sc = v["scales"]
        if not isinstance(sc, list) or not sc or not all(_is_num(s) and s > 0 for s in sc):
            probs.add(f"{where}.scales", f"must be a non-empty list of numbers > 0, got {sc!r}")
        else:
            out.scales = [float(s) for s in sc]
    for flag in ("preview", "materialx", "procedural"):
        if flag in v:
            if not isinstance(v[flag], bool):
                probs.add(f"{where}.{flag}", "must be true or false")
            else:
                setattr(out, flag, v[flag])
    if "bits" in v:
        if v["bits"] not in (8, 16):
            probs.add(f"{where}.bits", f"must be 8 or 16, got {v['bits']!r}")
        else:
            out.bits = int(v["bits"])
    return out


def _resolve_scribbles(node: dict, where: str, base: Path, probs: _Problems) -> int:
    """Resolve every ``scribbles`` file path in a spec tree (in place); returns how many there are."""
    n = 0
    sc = node.get("scribbles")
    if sc is not None:
        if not isinstance(sc, str) or not sc:
            probs.add(f"{where}.scribbles", f"must be an image file path (each colour one layer), got {sc!r}")
        else:
            node["scribbles"] = str((base / Path(sc).expanduser()).resolve(strict=False))
            node.setdefault("scribbles_source", Path(sc).name)
            n += 1
    children = node.get("children")
    if isinstance(children, dict):
        for k, c in children.items():
            if isinstance(c, dict):
                n += _resolve_scribbles(c, f"{where}.children.{k}", base, probs)
    return n


def _decompose(v: Any, where: str, base: Path, probs: _Problems) -> dict:
    """Decomposition spec: ``mode`` none|auto|scribbles plus the workers.decompose spec keys (method, layers,
    children, scribbles = file, ...); scribble files resolve against the material's folder."""
    if isinstance(v, str):
        v = {"mode": v}
    if not isinstance(v, dict):
        probs.add(where, f"must be a table like {{ mode = \"auto\", layers = 2 }}, got {v!r}")
        return {"mode": "none"}
    d = copy.deepcopy(v)
    mode = d.pop("mode", None)
    if mode is None:
        mode = "none" if d.get("method") == "leaf" else "scribbles" if "scribbles" in d else "auto"
    if mode not in DECOMPOSE_MODES:
        probs.add(f"{where}.mode", f"must be one of {list(DECOMPOSE_MODES)}, got {mode!r}")
        return {"mode": "none"}
    if mode == "none":
        extra = set(d) - {"method"}
        if extra:
            probs.add(where, f"mode \"none\" (no split) takes no other keys, got {sorted(extra)}")
        return {"mode": "none"}
    n = _resolve_scribbles(d, where, base, probs)
    if mode == "scribbles" and n == 0:
        probs.add(f"{where}.scribbles", "mode \"scribbles\" needs scribbles = an image file (black = unknown, "
                                        "each other colour one layer)")
    if mode == "auto" and n:
        probs.add(f"{where}.scribbles", "given with mode \"auto\"; use mode \"scribbles\" (or drop the file)")
    try:
        validate_spec(_unread_scribbles(d), where=where)
    except ManifestError as exc:
        for prob in exc.problems:
            probs.append(prob)
    return {"mode": mode, **d}


def _unread_scribbles(node: dict) -> dict:
    """Copy of a decomposition spec tree for workers.decompose.validate_spec: it takes scribble images, which the
    decompose stage reads from the files checked above, so each file path stands as None (not read yet)."""
    node = {k: None if k == "scribbles" and isinstance(v, str) else v for k, v in node.items()}
    if isinstance(node.get("children"), dict):
        node["children"] = {k: _unread_scribbles(c) if isinstance(c, dict) else c
                            for k, c in node["children"].items()}
    return node


def _material(raw: Any, i: int, defaults: dict, root: Path, output: Path, probs: _Problems) -> MaterialSpec | None:
    where = f"materials[{i}]"
    if not isinstance(raw, dict):
        probs.add(where, "must be a table with at least name and albedo")
        return None
    probs.unknown(where, set(raw), MATERIAL_KEYS)
    merged = {**copy.deepcopy(defaults), **raw}
    name = raw.get("name")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        probs.add(f"{where}.name", f"required; letters, digits, '_', '.', '-' (got {name!r})")
        name = None
    else:
        where = f"materials[{i}] ({name})"
    base = root
    if "folder" in merged:
        f = merged["folder"]
        if not isinstance(f, str) or not f:
            probs.add(f"{where}.folder", f"must be a folder path string, got {f!r}")
        else:
            base = (root / Path(f).expanduser()).resolve(strict=False)
    cs = merged.get("albedo_colorspace", "srgb")
    conv = merged.get("normal_convention", "opengl")
    maps: dict[str, MapSpec] = {}
    if "albedo" not in raw:
        probs.add(f"{where}.albedo", "required (the albedo/base colour map file)")
    for key in MAP_KEYS:
        if key not in raw:
            continue
        ch = merged.get(f"{key}_channel") if key in ("roughness", "metallic") else None
        ms = _map_spec(raw[key], key, f"{where}.{key}", base, ch, probs)
        if ms is not None:
            maps[key] = ms
        if isinstance(raw[key], dict):
            cs = raw[key].get("colorspace", cs) if key == "albedo" else cs
            conv = raw[key].get("convention", conv) if key == "normal" else conv
    if cs not in COLORSPACES:
        probs.add(f"{where}.albedo_colorspace", f"must be one of {list(COLORSPACES)}, got {cs!r}")
    if conv not in NORMAL_CONVENTIONS:
        probs.add(f"{where}.normal_convention", f"must be one of {list(NORMAL_CONVENTIONS)}, got {conv!r}")
    for key in ("roughness_channel", "metallic_channel"):
        if key in raw and raw[key] is not None and key.split("_")[0] not in raw:
            probs.add(f"{where}.{key}", f"given but the material has no {key.split('_')[0]} map")
    ws = merged.get("working_size", 512)
    if _is_int(ws) and 8 <= ws <= 32768:  # N is the longer side; the aspect ratio is kept at load
        working = int(ws)
    else:
        working = None if ws is None else _size(ws, f"{where}.working_size", probs)
    dec = _decompose(merged.get("decompose", {"mode": "auto"}), f"{where}.decompose", base, probs)
    outs = _outputs(merged.get("outputs", {}), f"{where}.outputs", probs)
    seed = merged.get("seed", 0)
    if not (_is_int(seed) and seed >= 0):
        probs.add(f"{where}.seed", f"must be an integer >= 0, got {seed!r}")
        seed = 0
    options = {}
    for st in STAGES:
        if st.config is None:
            continue
        c = merged.get(st.name, {})
        if not isinstance(c, dict):
            probs.add(f"{where}.{st.name}", f"must be a table of {st.name} stage options, got {c!r}")
            c = {}
        if c:
            probs.unknown(f"{where}.{st.name}", set(c), st.config_fields())
            _check_options(st, c, f"{where}.{st.name}", probs)
        options[st.name] = _jsonable(c)
    stages = _stage_list(merged.get("stages"), f"{where}.stages", probs)
    out_name = raw.get("output", name or f"material_{i}")
    if not isinstance(out_name, str) or not out_name.strip():
        probs.add(f"{where}.output", f"must be a folder name inside the job's output folder, got {out_name!r}")
        out_name = name or f"material_{i}"
    else:
        p = Path(out_name)
        target = p if p.is_absolute() else output / p
        if not _inside(target, output) or target.resolve() == output.resolve():
            probs.add(f"{where}.output", f"{out_name!r} escapes the job's output folder {output}; use a "
                                         "relative folder name without '..'")
        else:
            out_name = str(target.resolve().relative_to(output.resolve()))
    if name is None:
        return None
    return MaterialSpec(name=name, output=out_name, maps=maps, albedo_colorspace=cs, normal_convention=conv,
                        working_size=working, decompose=_jsonable(dec), outputs=outs, seed=int(seed),
                        options=options, stages=stages)


#: the largest count or size any stage option may take (iterations, evaluations, windows, kernel sizes...)
MAX_OPTION_INT = 1_000_000
#: the largest magnitude of a real-valued stage option (rates, weights, sigmas, budgets in seconds)
MAX_OPTION_FLOAT = 1e6


def _option_problem(value: Any, kind: str) -> str | None:
    """Why ``value`` does not fit a config field annotated ``kind`` (None when it fits). Counts and reals are
    never negative (every stage option's default is >= 0); pairs of reals (offsets) may be."""
    kind = kind.replace(" ", "")
    optional = kind.endswith("|None")
    kind = kind[:-5] if optional else kind
    if value is None:
        return None if optional else "must not be null"
    if kind == "bool":
        return None if isinstance(value, bool) else "must be true or false"
    if kind == "int":
        ok = _is_int(value) and 0 <= value <= MAX_OPTION_INT
        return None if ok else f"must be an integer from 0 to {MAX_OPTION_INT}"
    if kind == "float":
        ok = _is_num(value) and math.isfinite(value) and 0 <= value <= MAX_OPTION_FLOAT
        return None if ok else f"must be a finite number from 0 to {MAX_OPTION_FLOAT:g}"
    if kind == "str":
        return None if isinstance(value, str) and value else "must be a non-empty string"
    if kind.startswith("tuple[") or kind.startswith("list["):
        if not isinstance(value, (list, tuple)) or not value or len(value) > 64:
            return "must be a non-empty list (at most 64 entries)"
        inner = kind[kind.index("[") + 1:-1].split(",")
        if inner[-1] != "...":
            if len(value) != len(inner):
                return f"must be a list of {len(inner)} values"
            if inner[0] == "float":  # a pair of reals (an offset): any sign
                ok = all(_is_num(v) and math.isfinite(v) and abs(v) <= MAX_OPTION_FLOAT for v in value)
                return None if ok else "must hold finite numbers"
        probs = {_option_problem(v, inner[0]) for v in value} - {None}
        return f"each entry {sorted(probs)[0]}" if probs else None
    if kind.startswith("dict"):
        if not isinstance(value, dict):
            return "must be a table"
        bad = [k for k, v in value.items() if _option_problem(v, "float")]
        return f"entries {bad} must be finite numbers from 0 to {MAX_OPTION_FLOAT:g}" if bad else None
    return None


def _check_options(stage: Stage, options: dict, where: str, probs: _Problems) -> None:
    """Type and range of every option of a stage against its config dataclass, each problem naming its field;
    then the config's own checks (choices such as the optimiser) when it has them."""
    cls = stage.config_class()
    types = {f.name: str(f.type) for f in dataclasses.fields(cls)}
    bad = False
    for k, v in options.items():
        why = _option_problem(v, types[k]) if k in types else None
        if why:
            probs.add(f"{where}.{k}", f"{why}, got {v!r}")
            bad = True
        allowed = _CHOICES.get((stage.name, k))
        values = v if isinstance(v, list) else [v]
        if k in types and not why and allowed is not None and not all(allowed(x) for x in values):
            probs.add(f"{where}.{k}", f"{v!r} is not one of the known values ({allowed.__doc__})")
            bad = True
    if bad or set(options) - set(types):
        return
    try:
        conf = cls.from_dict(options) if hasattr(cls, "from_dict") else cls(**{
            k: tuple(v) if isinstance(v, list) else v for k, v in options.items()})
        if callable(getattr(conf, "validate", None)):
            conf.validate()
    except (TypeError, ValueError, ProceduralizeError) as exc:
        probs.add(where, str(exc))


def _one_of(*values: str) -> Callable[[str], bool]:
    def check(v: str) -> bool:
        return v in values
    check.__doc__ = ", ".join(values)
    return check


def _nlopt_algorithm(v: str) -> bool:
    """a local derivative-free NLopt algorithm name such as LN_SBPLX, LN_NELDERMEAD, LN_BOBYQA"""
    return bool(re.fullmatch(r"LN_[A-Z_]+", v)) and hasattr(nlopt, v)


#: string options with a closed set of values (stage, option) -> check
_CHOICES: dict[tuple[str, str], Callable[[str], bool]] = {
    ("recompose", "optimizer"): _one_of("adam", "lbfgs"), ("recompose", "device"): _one_of(*DEVICES),
    ("masks", "algorithm"): _nlopt_algorithm, ("masks", "incomplete"): _one_of("known", "inpaint")}


def parse_faults(v: Any, root: Path, probs: _Problems) -> dict:
    """Fault injection for tests, never part of a manifest (the scheduler reads it from the environment
    variable PROCEDURALIZE_FAULTS): crash_once = {stage, marker} (os._exit once), sleep = {stage, seconds}."""
    if not isinstance(v, dict):
        probs.add("debug", "must be a table")
        return {}
    probs.unknown("debug", set(v), DEBUG_KEYS)
    out: dict = {}
    c = v.get("crash_once")
    if c is not None:
        if not (isinstance(c, dict) and c.get("stage") in STAGE_NAMES and isinstance(c.get("marker"), str)):
            probs.add("debug.crash_once", "must be { stage = <stage>, marker = <file> }")
        else:
            out["crash_once"] = {"stage": c["stage"], "marker": str((root / c["marker"]).resolve(strict=False)),
                                 "material": c.get("material")}
    s = v.get("sleep")
    if s is not None:
        if not (isinstance(s, dict) and s.get("stage") in STAGE_NAMES and _is_num(s.get("seconds"))):
            probs.add("debug.sleep", "must be { stage = <stage>, seconds = <number> }")
        else:
            out["sleep"] = {"stage": s["stage"], "seconds": float(s["seconds"]), "material": s.get("material")}
    return out


#: node count assumed when a manifest's output sizes are checked against the memory budget (real graphs: 10-40)
NOMINAL_GRAPH_NODES = 32


def _check_memory(materials: list[MaterialSpec], limit: int, probs: _Problems) -> None:
    """Refuse at validation what is certain to exceed the budget: the fitting stages at a [W, H] working size
    and every output render (at a nominal graph size). A working size N (the longer side) is checked at load,
    where the maps' aspect ratio is known."""
    for i, m in enumerate(materials):
        where = f"materials[{i}] ({m.name})"
        ws = m.working_size
        if isinstance(ws, tuple):
            need = budget.fit_bytes(*ws)
            if need > limit:
                probs.add(f"{where}.working_size", f"{ws}: the fitting stages need about {budget.gib(need)}, "
                                                   f"over the memory budget of {budget.gib(limit)}")
        for w, h in m.outputs.sizes:
            need = budget.render_bytes(NOMINAL_GRAPH_NODES, w, h)
            if need > limit:
                probs.add(f"{where}.outputs.sizes", f"{w}x{h}: a render needs about {budget.gib(need)}, over the "
                                                    f"memory budget of {budget.gib(limit)}")


def validate(doc: dict, root: str | Path, source: str | Path | None = None,
             output_override: str | Path | None = None) -> JobManifest:
    """Validate a parsed manifest; relative paths resolve against ``root``. Raises ManifestError with all problems."""
    root = Path(root).resolve()
    probs = _Problems()
    probs.unknown("", set(doc), {"job", "defaults", "materials"})
    job = doc.get("job")
    if not isinstance(job, dict):
        probs.add("job", "required table with name and output")
        job = {}
    probs.unknown("job", set(job), JOB_KEYS)
    name = job.get("name")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        probs.add("job.name", f"required; letters, digits, '_', '.', '-' (got {name!r})")
        name = "job"
    out_raw = output_override if output_override is not None else job.get("output")
    if not isinstance(out_raw, (str, Path)) or not str(out_raw).strip():
        probs.add("job.output", "required: the folder this job writes to (relative to the manifest)")
        output = root / "out"
    else:
        output = (root / Path(out_raw).expanduser()).resolve(strict=False)
        if output == Path(output.anchor):
            probs.add("job.output", "must not be the filesystem root")
    db_raw = job.get("database", DEFAULT_DATABASE)
    if not isinstance(db_raw, str) or not db_raw:
        probs.add("job.database", f"must be a file path, got {db_raw!r}")
        db_raw = DEFAULT_DATABASE
    database = (output / Path(db_raw).expanduser()).resolve(strict=False)
    if not _inside(database, output) or database == output:
        probs.add("job.database", f"{db_raw!r} is outside the job's output folder {output}; use a file name "
                                  "relative to it, without '..'")
    mem = job.get("memory_budget")
    if mem is not None:
        try:
            mem = budget.parse_bytes(mem, "job.memory_budget")
        except ProceduralizeError as exc:
            probs.append(str(exc))
            mem = None
    timeout = job.get("stage_timeout", DEFAULT_STAGE_TIMEOUT_S)
    if not (_is_num(timeout) and 1 <= timeout <= 7 * 86400):
        probs.add("job.stage_timeout", f"must be a number of seconds from 1 to 604800 (a week), got {timeout!r}")
        timeout = DEFAULT_STAGE_TIMEOUT_S
    stages = _stage_list(job.get("stages"), "job.stages", probs)
    max_attempts = job.get("max_attempts", 3)
    if not (_is_int(max_attempts) and 1 <= max_attempts <= 20):
        probs.add("job.max_attempts", f"must be an integer 1..20, got {max_attempts!r}")
        max_attempts = 3
    mask_actors = job.get("mask_actors")
    if mask_actors is not None and not (_is_int(mask_actors) and 1 <= mask_actors <= 1024):
        probs.add("job.mask_actors", f"must be an integer 1..1024, got {mask_actors!r}")
        mask_actors = None
    gpu_wait = job.get("gpu_wait_s", 600.0)
    if not (_is_num(gpu_wait) and 0 <= gpu_wait <= 86400):
        probs.add("job.gpu_wait_s", f"must be a number of seconds 0..86400, got {gpu_wait!r}")
        gpu_wait = 600.0
    rec_cpus = job.get("recompose_cpus", 2)
    if not (_is_int(rec_cpus) and 1 <= rec_cpus <= 256):
        probs.add("job.recompose_cpus", f"must be an integer 1..256, got {rec_cpus!r}")
        rec_cpus = 2
    pdb = job.get("pptbf_database")
    if pdb is not None and (not isinstance(pdb, str) or not pdb):
        probs.add("job.pptbf_database", f"must be a PPTBF database folder path, got {pdb!r}")
        pdb = None
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        probs.add("defaults", "must be a table")
        defaults = {}
    probs.unknown("defaults", set(defaults), DEFAULT_KEYS)
    mats_raw = doc.get("materials")
    materials: list[MaterialSpec] = []
    if not isinstance(mats_raw, list) or not mats_raw:
        probs.add("materials", "required: a non-empty list ([[materials]] tables)")
        mats_raw = []
    for i, raw in enumerate(mats_raw):
        m = _material(raw, i, {k: v for k, v in defaults.items() if k in DEFAULT_KEYS}, root, output, probs)
        if m is not None:
            materials.append(m)
    seen: dict[str, int] = {}
    outs: dict[str, str] = {}
    for m in materials:
        if m.name in seen:
            probs.add(f"materials ({m.name})", "name used twice; material names must be unique in a job")
        seen[m.name] = 1
        if m.output in outs and outs[m.output] != m.name:
            probs.add(f"materials ({m.name}).output", f"folder {m.output!r} is also used by {outs[m.output]!r}")
        outs[m.output] = m.name
    if not probs:
        _check_memory(materials, budget.budget(mem), probs)
    if probs:
        raise ManifestError(list(probs), str(source) if source else None)
    return JobManifest(name=name, source=Path(source) if source else None, root=root, output=output,
                       database=database, stages=stages, materials=materials, max_attempts=int(max_attempts),
                       mask_actors=mask_actors, stage_timeout=float(timeout), memory_budget=mem,
                       description=str(job.get("description", "")),
                       pptbf_database=(root / Path(pdb).expanduser()).resolve(strict=False) if pdb else None,
                       gpu_wait_s=float(gpu_wait), recompose_cpus=int(rec_cpus))
