"""The house's rules of import (issue 13), checked over the source, not by convention.

Floors, bottom up as the paper's Fig. 3 reads: messages < entity < information
< system < scripts. A module may import its own floor and the floors below,
never above; no module imports another package's service module; no two
modules import each other, directly or around a longer cycle. Imports inside
functions count as much as those at the top of a module.
"""
from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

FLOORS = ("messages", "entity", "information", "system", "scripts")
#: The layer processes: only a launcher starts them, by module name, never by import.
SERVICE_MODULES = {"entity.service", "information.service", "system.service", "scripts.record"}


def _modules() -> dict[str, Path]:
    found = {}
    for floor in FLOORS:
        for path in sorted((ROOT / floor).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The project module an imported name lives in (None: not ours)."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: str) -> set[str]:
    """Every project module ``module`` imports, anywhere in its source."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            # "from entity import models" imports the module entity.models; "from entity.models
            # import get" imports entity.models, the module that holds get.
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base for alias in node.names]
        else:
            continue
        for name in names:
            target = _resolve(name)
            if target is not None and target != module:
                found.add(target)
    return found


GRAPH = {module: imports_of(module) for module in MODULES}


def floor_of(module: str) -> int:
    return FLOORS.index(module.split(".")[0])


def test_every_floor_imports_only_its_own_and_the_floors_below():
    upward = sorted(f"{module} imports {target}" for module, targets in GRAPH.items() for target in targets
                    if floor_of(target) > floor_of(module))
    assert upward == [], "\n".join(upward)


def test_no_module_imports_a_service_module():
    found = sorted(f"{module} imports {target}" for module, targets in GRAPH.items() for target in targets
                   if target in SERVICE_MODULES)
    assert found == [], "\n".join(found)


def test_no_two_modules_import_each_other_directly_or_around_a_cycle():
    cycles, state = [], {}

    def visit(module: str, path: list[str]) -> None:
        state[module] = "open"
        for target in sorted(GRAPH[module]):
            if state.get(target) == "open":
                cycles.append(" -> ".join(path[path.index(target):] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[module] = "done"

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])
    assert cycles == [], "\n".join(cycles)


def test_the_checker_sees_an_import_against_the_rules(tmp_path):
    # The check itself can fail: a made-up module of the wire contract importing a layer.
    source = "from entity import models\n\ndef late():\n    import system.policy\n"
    MODULES["messages._probe"] = tmp_path / "probe.py"
    (tmp_path / "probe.py").write_text(source)
    try:
        assert imports_of("messages._probe") == {"entity.models", "system.policy"}
    finally:
        del MODULES["messages._probe"]


def test_every_package_says_what_it_holds_and_what_it_may_import():
    for module, path in MODULES.items():
        if path.name == "__init__.py":
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            assert "import" in doc, f"{module}/__init__.py does not say what it may import"


ROOMS = ("scripts.logs", "scripts.paper", "scripts.bench")


def room_of(module: str) -> str | None:
    return next((room for room in ROOMS if module == room or module.startswith(room + ".")), None)


def test_the_rooms_of_scripts_import_the_commands_never_each_other_and_the_product_never_research():
    found = []
    for module, targets in GRAPH.items():
        for target in targets:
            mine, theirs = room_of(module), room_of(target)
            if theirs is not None and mine != theirs and not (mine is None and theirs == "scripts.logs"):
                found.append(f"{module} imports {target}")
    assert found == [], "\n".join(found)


def test_the_contract_names_what_the_layers_implement():
    from entity import models, resampling
    from information import rules
    from messages import names
    from system import policy

    assert set(names.SCENARIOS) == set(models.MODELS)
    assert names.CANNOT_SAMPLE == {name for name in models.MODELS if not models.get(name).samples_observations}
    assert set(names.RESAMPLERS) == set(resampling.RESAMPLERS)
    assert set(names.THRESHOLD_RULES) == set(rules.THRESHOLD_RULES)
    assert set(names.WEIGHT_RULES) == set(rules.WEIGHT_RULES)
    assert set(names.POLICIES) == set(policy.POLICIES)
    assert names.SIMULATING_POLICIES == {name for name, cls in policy.POLICIES.items() if cls.samples_observations}
    assert names.POLICIES_STARTING_OFF == {name for name, cls in policy.POLICIES.items()
                                           if not cls.initial_preprocess}
    assert set(names.MOVE_RULES) == set(rules.MOVE_RULES)
    from entity import jitter
    assert set(names.JITTERS) == set(jitter.JITTERS)
