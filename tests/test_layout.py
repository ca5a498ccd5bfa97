"""The house's rules of import, checked over the source, not by convention.

Floors, bottom up: the wire contract (dtpf.messages), the log files
(dtpf.recording), the service shell (dtpf.shell), then the paper's layers as
its Fig. 3 reads them (dtpf.entity < dtpf.information < dtpf.system), the
commands (dtpf.scripts) and the package's one page of API (dtpf). A module may
import its own floor and the floors below, never above; no module imports
another package's service module; no two modules import each other, directly
or around a longer cycle. Imports inside functions count as much as those at
the top of a module.
"""
from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

#: Each floor: its installed name and the repository folder that holds it, bottom up.
FLOORS = (("dtpf.messages", "messages"), ("dtpf.recording", "dtpf/recording"), ("dtpf.shell", "dtpf/shell"),
          ("dtpf.entity", "entity"), ("dtpf.information", "information"), ("dtpf.system", "system"),
          ("dtpf.scripts", "scripts"), ("dtpf", "dtpf"))
#: The layer processes: only a launcher starts them, by module name, never by import.
SERVICE_MODULES = {"dtpf.entity.service", "dtpf.information.service", "dtpf.system.service", "dtpf.scripts.record"}


def _modules() -> dict[str, Path]:
    found = {}
    for name, folder in FLOORS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found.setdefault(".".join((name, *parts)), path)
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
            # "from dtpf.entity import models" imports the module dtpf.entity.models; "from dtpf.entity.models
            # import get" imports dtpf.entity.models, the module that holds get.
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
    """The index of the floor ``module`` stands on: the longest floor name it starts with."""
    matches = [(len(name), i) for i, (name, _) in enumerate(FLOORS) if module == name or module.startswith(name + ".")]
    return max(matches)[1]


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
    # The check itself can fail: a made-up module of the wire contract importing a layer and the shell.
    source = "from dtpf.entity import models\n\ndef late():\n    import dtpf.system.policy\n    from dtpf.shell import bus\n"
    MODULES["dtpf.messages._probe"] = tmp_path / "probe.py"
    (tmp_path / "probe.py").write_text(source)
    try:
        found = imports_of("dtpf.messages._probe")
        assert found == {"dtpf.entity.models", "dtpf.system.policy", "dtpf.shell.bus"}
        assert all(floor_of(target) > floor_of("dtpf.messages._probe") for target in found)
    finally:
        del MODULES["dtpf.messages._probe"]


def test_every_package_says_what_it_holds_and_what_it_may_import():
    for module, path in MODULES.items():
        if path.name == "__init__.py":
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            assert "import" in doc, f"{module}/__init__.py does not say what it may import"


ROOMS = ("dtpf.scripts.logs", "dtpf.scripts.paper", "dtpf.scripts.bench")


def room_of(module: str) -> str | None:
    return next((room for room in ROOMS if module == room or module.startswith(room + ".")), None)


def test_the_rooms_of_scripts_import_the_commands_never_each_other_and_the_product_never_research():
    found = []
    for module, targets in GRAPH.items():
        for target in targets:
            mine, theirs = room_of(module), room_of(target)
            if theirs is not None and mine != theirs and not (mine is None and theirs == "dtpf.scripts.logs"):
                found.append(f"{module} imports {target}")
    assert found == [], "\n".join(found)


def test_the_contract_names_what_the_layers_implement():
    from dtpf.entity import models
    from dtpf.information import rules
    from dtpf.messages import names

    assert set(names.SCENARIOS) == set(models.MODELS)
    assert names.CANNOT_SAMPLE == {name for name in models.MODELS if not models.get(name).samples_observations}
    from dtpf.information import layer
    assert set(names.ARMS) == set(layer.arms_for("my.py:move")) == set(layer.ARMS) | {names.OWN_ARM}
    # The information layer's rules are registries: names written once, by the modules that implement them.
    from dtpf.messages.family import THRESHOLDS
    for registry, package in ((THRESHOLDS, "dtpf.information.thresholds"),
                              (names.WEIGHT_RULE_REGISTRY, "dtpf.information.weight_rules"),
                              (names.MOVE_RULE_REGISTRY, "dtpf.information.move_rules")):
        members = registry.builtins()
        assert registry.package == package and len(members) >= 2
        assert all(obj.__module__.startswith(package + ".") for obj in members.values())
    assert not hasattr(names, "THRESHOLD_RULES") and not hasattr(rules, "THRESHOLD_RULES")
    assert rules.WEIGHT_RULES == tuple(names.WEIGHT_RULE_REGISTRY.names())
    assert rules.MOVE_RULES == tuple(names.MOVE_RULE_REGISTRY.names())
    assert names.WEIGHT_RULE_REGISTRY.entry_points() == {} and names.MOVE_RULE_REGISTRY.entry_points() == {}
    # The arms of the choosing policy name rules the registries hold.
    assert all(arm.weight_rule in names.WEIGHT_RULE_REGISTRY.names() and arm.move_rule in
               names.MOVE_RULE_REGISTRY.names() for arm in layer.ARMS.values())


def test_every_test_the_long_tier_names_exists():
    """conftest.LONG names files and tests; a renamed one would fall back into the default run unnoticed."""
    from conftest import LONG

    tests = Path(__file__).resolve().parent
    for entry in sorted(LONG):
        name, _, test = entry.partition("::")
        assert (tests / name).exists(), entry
        assert not test or f"def {test}(" in (tests / name).read_text(), entry
