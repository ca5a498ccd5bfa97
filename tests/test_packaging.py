"""dtpf installs one import name, and no process it starts imports from the user's folder."""
from __future__ import annotations

import ast
import re
import shutil
import site
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from conftest import ROOT

#: The repository's package folders and the names they install as.
FOLDERS = {"entity": "dtpf.entity", "information": "dtpf.information", "system": "dtpf.system",
           "messages": "dtpf.messages", "scripts": "dtpf.scripts", "dtpf": "dtpf"}
#: The research rooms of scripts/: the paper's reproduction and the benchmarks. Not product, so not installed;
#: they run from a checkout (README.md, "Reproduce the paper and run the benchmarks").
RESEARCH = ("dtpf.scripts.paper", "dtpf.scripts.bench")


def _is_research(module: str) -> bool:
    return any(module == room or module.startswith(room + ".") for room in RESEARCH)


def _package_names() -> set[str]:
    """Every package of the repository by its installed name (a folder with an ``__init__.py``)."""
    names = set()
    for folder, name in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT / folder).parts
            names.add(".".join((name, *parts)))
    return names


def test_pyproject_lists_every_package_but_the_research_rooms_and_maps_every_folder():
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages = _package_names()
    assert set(RESEARCH) <= packages  # the exceptions name folders that exist
    assert set(setuptools["packages"]) == {name for name in packages if not _is_research(name)}
    assert setuptools["package-dir"] == {name: folder for folder, name in FOLDERS.items() if folder != name}


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """dtpf installed from this checkout, not editable, into a folder of its own (no dependencies)."""
    source, target = tmp_path_factory.mktemp("source") / "dtpf", tmp_path_factory.mktemp("site")
    # A copy, so that the build leaves nothing in the checkout (setuptools builds in build/ beside the source).
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv", "build", "*.egg-info", "runs",
                                                                 "__pycache__", ".pytest_cache"))
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                           "--target", str(target), str(source)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return target


def test_an_install_adds_one_import_name(installed):
    tops = {path.name for path in installed.iterdir() if not path.name.endswith((".dist-info", ".egg-info"))}
    tops.discard("bin")  # the dtpf script
    assert tops == {"dtpf"}


def research_references(source: str, module: str) -> list[str]:
    """What ``module``'s source imports from the research rooms, or names as a module to run or import."""
    package = module if module.endswith(".__init__") else module.rpartition(".")[0]
    package = package.removesuffix(".__init__")
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names = [base, *(f"{base}.{alias.name}" for alias in node.names)]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            # importlib.import_module("dtpf.scripts.bench.x") or [sys.executable, "-m", "dtpf.scripts.paper.y"]
            names = [node.value] if re.fullmatch(r"[\w.]+", node.value) else []
        else:
            continue
        found += [name for name in names if _is_research(name)]
    return found


def test_the_research_reference_reader_sees_imports_and_module_names():
    source = ("from dtpf.scripts import bench\nfrom .paper import common\n\ndef f():\n    import dtpf.scripts.paper.x\n"
              "    return ['-m', 'dtpf.scripts.bench.fleet', 'see dtpf.scripts.paper in a sentence']\n"
              "from dtpf.scripts import cli, logs\n")
    assert sorted(research_references(source, "dtpf.scripts.launch")) == [
        "dtpf.scripts.bench", "dtpf.scripts.bench.fleet", "dtpf.scripts.paper", "dtpf.scripts.paper.common",
        "dtpf.scripts.paper.x"]
    assert research_references("from . import logs\nfrom .bench import x\n", "dtpf.scripts.__init__") == [
        "dtpf.scripts.bench", "dtpf.scripts.bench.x"]


def test_an_install_leaves_the_research_rooms_out_and_nothing_installed_names_them(installed):
    package = installed / "dtpf"
    assert not (package / "scripts" / "paper").exists() and not (package / "scripts" / "bench").exists()
    assert (package / "scripts" / "cli.py").is_file() and (package / "scripts" / "logs" / "__init__.py").is_file()
    files = sorted(package.rglob("*.py"))
    assert len(files) >= 50
    found = [f"{path.relative_to(installed)}: {name}" for path in files
             for name in research_references(path.read_text(),
                                             ".".join(path.relative_to(installed).with_suffix("").parts))]
    assert found == [], "\n".join(found)


def _run_installed(installed: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``python -S *args`` with the install first on the path, then the environment's own packages.

    -S keeps out the environment's .pth files, the hook of an editable install among them: what runs is
    the install and whatever the current folder holds, as it would be beside a plain ``pip install .``.
    """
    packages = [path for path in [*site.getsitepackages(), site.getusersitepackages()] if Path(path).is_dir()]
    return subprocess.run([sys.executable, "-S", *args], cwd=cwd, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": ":".join([str(installed), *packages]), "PATH": ""})


@pytest.mark.parametrize("module", ["dtpf.scripts.bench.resampling", "dtpf.scripts.paper.experiments"])
def test_beside_an_install_the_research_runs_with_python_m_from_the_repository_root_only(installed, tmp_path,
                                                                                         module):
    done = _run_installed(installed, ROOT, "-m", module, "--help")
    assert done.returncode == 0 and done.stdout.startswith(f"usage: python -m {module}"), done.stderr[-3000:]
    # -P (or PYTHONSAFEPATH) leaves the current folder off the path, and another folder has no checkout in it.
    room = module.rpartition(".")[0]
    for cwd, flags in ((ROOT, ["-P"]), (tmp_path, [])):
        done = _run_installed(installed, cwd, *flags, "-m", module, "--help")
        assert done.returncode != 0 and f"No module named '{room}'" in done.stderr, (cwd, flags, done.stderr)


def test_the_installed_package_imports_from_its_own_folder(installed, tmp_path):
    code = ("import dtpf, dtpf.entity.filter, dtpf.scripts.cli, dtpf.shell.bus\n"
            "print(dtpf.entity.filter.__file__)\n"
            "print(dtpf.systematic.__module__, dtpf.run.__module__, dtpf.read_log.__module__)\n")
    done = subprocess.run([sys.executable, "-P", "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, env={"PYTHONPATH": str(installed), "PATH": ""})
    assert done.returncode == 0, done.stderr[-3000:]
    where, modules = done.stdout.splitlines()
    assert Path(where).is_relative_to(installed)
    assert modules == "dtpf.entity.resamplers.systematic dtpf.scripts.inprocess dtpf.recording.logfile"


def test_the_public_api_names_what_it_exports():
    import dtpf

    for name in dtpf.__all__:
        assert getattr(dtpf, name) is not None, name
    assert set(dtpf.__all__) <= set(dir(dtpf))
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        dtpf.nothing_here  # noqa: B018


def test_every_error_a_user_can_meet_falls_under_one_root():
    """Every exception class of the product derives from DtpfError (private helpers excepted)."""
    from dtpf.messages.errors import DtpfError

    found = []
    for folder in FOLDERS:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and not node.name.startswith("_") and re.search(
                        r"(Error|Exception)$", node.name):
                    found.append((path, node.name))
    assert len(found) >= 10
    import importlib
    for path, name in found:
        folder = path.relative_to(ROOT).parts[0]
        parts = path.relative_to(ROOT / folder).with_suffix("").parts
        module = importlib.import_module(".".join((FOLDERS[folder], *parts)))
        assert issubclass(getattr(module, name), DtpfError), f"{module.__name__}.{name}"


# --- a user's folder holding files named like dtpf's own packages --------------------------------------------

_SHADOWS = {
    "messages.py": "raise ImportError('the user messages.py was imported')\n",
    "entity.py": "raise ImportError('the user entity.py was imported')\n",
    "dtpf_marker.txt": "",
}


def _user_folder(path: Path) -> Path:
    path.mkdir()
    shutil.copy(ROOT / "docs" / "examples" / "range_bearing.py", path / "mymodel.py")
    shutil.copy(ROOT / "docs" / "examples" / "range_bearing_no_truth.csv", path / "obs.csv")
    return path


def _dtpf(folder: Path, *args: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("dtpf")
    command = [str(script)] if script.exists() else [sys.executable, "-P", "-m", "dtpf"]
    done = subprocess.run([*command, *args], cwd=folder, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{args}: {done.stderr[-3000:]}"
    return done


def _figures(output: str) -> list[str]:
    """The lines of a run's summary that hold its numbers (not its time or its log's path)."""
    keep = ("log predictive", "innovation", "mean ESS", "resamplings", "degraded")
    return [line for line in output.splitlines() if line.strip().startswith(keep)]


def test_a_user_folder_with_messages_entity_and_scripts_gives_the_same_numbers(tmp_path):
    plain = _user_folder(tmp_path / "plain")
    hostile = _user_folder(tmp_path / "hostile")
    for name, text in _SHADOWS.items():
        (hostile / name).write_text(text)
    (hostile / "scripts").mkdir()
    (hostile / "scripts" / "__init__.py").write_text(
        "import pathlib\npathlib.Path(__file__).parent.parent.joinpath('scripts-ran').write_text('yes')\n"
        "raise ImportError('the user scripts package was imported')\n")
    args = ("-q", "--policy", "fixed", "--model", "mymodel.py:RangeBearingTarget", "--observations", "obs.csv", "-n", "300",
            "--steps", "30", "--seed", "4")
    runs = {}
    for folder in (plain, hostile):
        runs[folder.name, "run"] = _figures(_dtpf(folder, "run", *args).stdout)
        runs[folder.name, "launch"] = _figures(_dtpf(folder, "launch", *args, "-o", "run.mcap").stdout)
    assert runs["hostile", "run"] == runs["plain", "run"] and len(runs["plain", "run"]) >= 4
    assert runs["hostile", "launch"] == runs["plain", "launch"] and len(runs["plain", "launch"]) >= 4
    assert not (hostile / "scripts-ran").exists()
    assert (hostile / "run.mcap").stat().st_size > 0


def test_a_bad_run_configuration_is_a_dtpf_error_naming_every_bad_field():
    import dtpf

    with pytest.raises(dtpf.DtpfError, match=r"^particles: .*; ps: .*less than or equal to 1$"):
        dtpf.RunConfig(particles=0, ps=2.0)
