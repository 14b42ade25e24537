"""Package layering is one-way: service imports workers and pptbf_db, workers imports pptbf_db; pptbf_db imports
neither workers nor service, and workers never imports service (checked statically on every module's source,
including function-local imports)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, top-level package) of every absolute import in a module (relative imports stay in the package)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name.split(".")[0]) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module.split(".")[0]))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) in (
                "import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            out.append((node.lineno, node.args[0].value.split(".")[0]))
    return out


def _violations(package: str, forbidden: set[str]) -> list[str]:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no modules under {package}/"
    return [f"{f.relative_to(ROOT)}:{line} imports {mod}" for f in files for line, mod in _imports(f)
            if mod in forbidden]


@pytest.mark.parametrize("package, forbidden", [("pptbf_db", {"workers", "service"}), ("workers", {"service"})])
def test_layering_is_one_way(package, forbidden):
    assert _violations(package, forbidden) == []


def test_checker_sees_function_local_imports(tmp_path):
    mod = tmp_path / "m.py"
    mod.write_text("import os\n\ndef f():\n    from workers.lattice import analyse_lattice\n    import service.cli\n")
    assert [m for _, m in _imports(mod)] == ["os", "workers", "service"]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_level_edges(path: Path, modules: set[str]) -> set[str]:
    """The repository modules ``path`` imports when it is imported (statements at module level, not under
    ``if TYPE_CHECKING``), relative imports resolved; ``from pkg import mod`` counts the submodule."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        out |= {t for t in targets if t in modules and t != name}
    return out


def test_no_import_cycle_between_modules():
    files = [f for pkg in ("service", "workers", "pptbf_db") for f in sorted((ROOT / pkg).rglob("*.py"))]
    modules = {_module_name(f) for f in files}
    graph = {_module_name(f): _module_level_edges(f, modules) for f in files}
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append(" -> ".join(stack[stack.index(n):] + [n]))
            elif n not in state:
                visit(n, stack + [n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert sum(len(v) for v in graph.values()) > 100  # the checker does see the imports
    assert cycles == []


def test_ruff_is_clean():
    """The linter configured in pyproject.toml ([tool.ruff]) finds nothing (it is in the test extras)."""
    import shutil
    import subprocess

    ruff = shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (pip install -e '.[test]' installs it)")
    res = subprocess.run([ruff, "check", "--no-cache", str(ROOT)], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stdout[-3000:]
