"""The package's layering: no import cycle between modules, no lower layer importing a
higher one, and no private name imported from another module. Read from the source with ``ast``,
function-level (lazy) imports included."""

from __future__ import annotations

import ast
from pathlib import Path

import escort_rl

ROOT = Path(escort_rl.__file__).parent
# The layer diagram (docs/DESIGN.md, "Layers"): data flows one way, models <- (belief, envs) <-
# transforms <- (modules, planners) <- trainers <- bench <- cli, with config, metrics and reporting
# below trainers and bench. "core" is what every layer may import: the configuration error, the
# parameter checker and where the shipped configs live. A layer may import only the layers listed
# for it (besides itself); a new package must be placed here.
CORE_MODULES = {"escort_rl.config", "escort_rl.config.errors", "escort_rl.config.params", "escort_rl.config.files"}
_SIMULATION = {"core", "models", "belief", "envs", "transforms"}
BELOW = {
    "core": set(),
    "models": {"core"},
    "belief": {"core", "models"},
    "envs": {"core", "models", "belief"},
    "transforms": {"core", "models", "belief", "envs"},
    "modules": _SIMULATION,
    "planners": _SIMULATION,
    "reporting": {"core"},
    "metrics": {"core", "models", "belief", "reporting"},
    "config": _SIMULATION | {"modules", "planners"},
    "trainers": _SIMULATION | {"modules", "planners", "config", "metrics", "reporting"},
    "bench": _SIMULATION | {"modules", "planners", "config", "metrics", "reporting", "trainers"},
    "cli": _SIMULATION | {"modules", "planners", "config", "metrics", "reporting", "trainers", "bench"},
    "": _SIMULATION | {"trainers"},  # the package's own __init__: its entry points (load_policy)
}


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, list[tuple[str, list[str]]]]:
    """module -> [(imported module, names imported from it)] for every escort_rl import."""
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        mod, found = _module(path), []
        package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                    + ([base] if base else []))
                if base.startswith("escort_rl"):
                    names = [a.name for a in node.names]
                    subs = [f"{base}.{n}" for n in names if (ROOT.parent / f"{base}.{n}".replace(".", "/")).exists()
                            or (ROOT.parent / (f"{base}.{n}".replace(".", "/") + ".py")).exists()]
                    found.append((base, [n for n in names if f"{base}.{n}" not in subs]))
                    found += [(s, []) for s in subs]
            elif isinstance(node, ast.Import):
                found += [(a.name, []) for a in node.names if a.name.startswith("escort_rl")]
        out[mod] = found
    return out


def _layer(module: str) -> str:
    if module in CORE_MODULES:
        return "core"
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_no_import_cycle():
    graph = {m: {t for t, _ in deps if t != m and t in _imports_cache} for m, deps in _imports_cache.items()}
    state, cycles = {}, []

    def visit(m, stack):
        state[m] = "open"
        for t in sorted(graph[m]):
            if state.get(t) == "open":
                cycles.append(" -> ".join(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t, stack + [t])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    # a package importing its own submodules (``__init__`` re-exports) is not a cycle between modules
    cycles = [c for c in cycles if not all(x.startswith(c.split(" -> ")[0]) for x in c.split(" -> "))]
    assert not cycles, cycles


def test_every_module_has_a_layer():
    assert {_layer(m) for m in _imports_cache} <= set(BELOW), sorted({_layer(m) for m in _imports_cache} - set(BELOW))


def test_lower_layers_do_not_import_higher_ones():
    # ``from escort_rl import metrics`` imports the subpackage, not the package's own names
    bad = [f"{m} imports {t}" for m, deps in _imports_cache.items() for t, names in deps
           if (t != "escort_rl" or names) and _layer(t) not in BELOW.get(_layer(m), set()) | {_layer(m)}]
    assert not bad, bad


def test_the_core_imports_nothing_heavy():
    """The core (what the lowest layers import) loads neither Hydra nor OmegaConf nor torch."""
    import subprocess
    import sys

    code = ("import sys, escort_rl.config.params, escort_rl.config.files; "
            "print(sorted(m for m in ('hydra', 'omegaconf', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_no_private_name_crosses_modules():
    bad = [f"{m} imports {n} from {t}" for m, deps in _imports_cache.items() for t, names in deps
           for n in names if n.startswith("_") and t != m]
    assert not bad, bad


_imports_cache = _imports()


def test_every_package_is_in_the_distribution():
    """``pyproject.toml`` lists its packages: one left out would be missing from a wheel (an editable
    install hides it)."""
    import tomllib

    listed = set(tomllib.loads((ROOT.parent / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {_module(p) for p in ROOT.rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)
