"""A user's own resampler, move and policy, from files and from an installed package, end to end.

Each member is named by reference (``path/to/file.py:NAME``) or by the name an installed package registers
in the family's entry-point group; ``dtpf run`` and ``dtpf launch`` give the same numbers with it, the log
records its reference and file digest, and ``dtpf verify`` re-runs it (the entity's propagated sets bit for
bit, so the resampling and the move are checked too). A model file may import the modules beside it, from
any working directory, in ``run``, ``launch`` and a fleet.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

EXAMPLES = ROOT / "docs" / "examples"
#: A launch on a loaded machine: the first one of a process tree may compile numba's kernels.
LAUNCH_SECONDS = 300


def dtpf(*args: str, cwd: Path, env: dict | None = None, timeout: float = LAUNCH_SECONDS) -> subprocess.CompletedProcess:
    """``dtpf ARGS`` in ``cwd``; its process group is killed if it outlives ``timeout``. A launch waits up to 30 s
    for a layer's answer (the default 2 s can run out on a loaded machine while a shared service loads a user's
    code, and a degraded step changes the numbers compared here)."""
    if args and args[0] == "launch" and "--help" not in args:
        args = (*args, "--timeout", "30", "--startup-timeout", "120")
    environment = dict(os.environ, **(env or {}))
    process = subprocess.Popen([sys.executable, "-P", "-m", "dtpf", *args], cwd=cwd, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=environment, start_new_session=True)
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        out, err = process.communicate()
        raise AssertionError(f"dtpf {' '.join(args)} still running after {timeout} s:\n{err[-3000:]}") from None
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(process.args, process.returncode, out, err)


def figures(output: str) -> list[str]:
    """The summary lines that hold a run's numbers (not its time, log path or layout)."""
    keep = ("RMSE", "mean ESS", "resamplings", "PS range", "degraded")
    return [" ".join(line.split()[:3]) for line in output.splitlines() if line.strip().startswith(keep)]


@pytest.fixture(scope="module")
def user(tmp_path_factory) -> Path:
    """A user's folder: the example components, and a model that imports the module beside it."""
    folder = tmp_path_factory.mktemp("user")
    for path in (EXAMPLES / "components").glob("*.py"):
        shutil.copy(path, folder / path.name)
    shutil.copy(EXAMPLES / "range_bearing.py", folder / "rb_base.py")
    (folder / "tracked.py").write_text("from rb_base import RangeBearingTarget\n\nMODEL = RangeBearingTarget(q=0.1)\n")
    return folder


COMPONENTS = {
    "resampler": ("--resampler", "resampler.py:systematic_numpy"),
    "move": ("--move", "move.py:gaussian_shake"),
    "policy": ("--policy", "policy.py:LowEssPS"),
}
#: The range-bearing example's observations, space separated, for a user's reader.
READER_ARGS = ("--model", str(EXAMPLES / "range_bearing.py:RangeBearingTarget"),
               "--observations", str(EXAMPLES / "components" / "range_bearing.txt"))


def test_a_users_members_run_launch_with_the_same_numbers_and_verify(user, tmp_path):
    """A resampler, a move and a policy of the user's, all in one run: dtpf launch gives dtpf run's numbers, the
    log records each member with its file's SHA-256, and dtpf verify re-runs them bit for bit."""
    members = [value for family in sorted(COMPONENTS) for value in
               (COMPONENTS[family][0], str(user / COMPONENTS[family][1]))]
    base = ("-q", "-n", "300", "-T", "25", "--seed", "5")
    ran = dtpf("run", *base, *members, cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    launched = dtpf("launch", *base, *members, "-o", "run.mcap", cwd=tmp_path)
    assert launched.returncode == 0, launched.stderr
    assert figures(launched.stdout) == figures(ran.stdout) and len(figures(ran.stdout)) == 5
    plain = dtpf("run", *base, cwd=tmp_path)
    assert figures(plain.stdout) != figures(ran.stdout)
    # The numpy resampler alone is the built-in systematic, bit for bit.
    flag, reference = COMPONENTS["resampler"]
    resampled = dtpf("run", *base, flag, str(user / reference), cwd=tmp_path)
    assert figures(resampled.stdout) == figures(plain.stdout)
    verified = dtpf("verify", "run.mcap", cwd=tmp_path)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert "OK: 25 steps reproduced exactly" in verified.stdout
    assert "entity: 25 propagated sets reproduced bit for bit" in verified.stdout

    from dtpf.recording.logfile import read_log
    statuses = [m for _, m in read_log(tmp_path / "run.mcap").decoded(lambda topic: topic.endswith("/status"))]
    recorded = {(c.field, c.reference, c.sha256) for s in statuses for c in s.components}
    import hashlib
    fields = {"resampler": "resampler", "move": "jitter", "policy": "policy"}
    assert recorded == {(fields[family], str(user / reference),
                         hashlib.sha256((user / reference.split(":")[0]).read_bytes()).hexdigest())
                        for family, (_, reference) in COMPONENTS.items()}


def test_a_users_reader_runs_launches_with_the_csvs_numbers_and_verifies(user, tmp_path):
    args = ("-q", "-n", "300", "-T", "30", "--seed", "2", *READER_ARGS, "--reader", str(user / "reader.py:read_spaced"))
    ran = dtpf("run", *args, cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    launched = dtpf("launch", *args, "-o", "run.mcap", cwd=tmp_path)
    assert launched.returncode == 0, launched.stderr
    keep = ("log predictive", "mean ESS", "innovation")
    numbers = [[line.split("(")[0].split() for line in out.splitlines() if line.startswith(keep)]
               for out in (ran.stdout, launched.stdout)]
    assert numbers[0] == numbers[1] and len(numbers[0]) == 3
    csv = dtpf("run", "-q", "-n", "300", "-T", "30", "--seed", "2", "--model", READER_ARGS[1], "--observations",
               str(EXAMPLES / "range_bearing_no_truth.csv"), cwd=tmp_path)
    assert [line for line in csv.stdout.splitlines() if line.startswith("log predictive")] == \
        [line for line in ran.stdout.splitlines() if line.startswith("log predictive")]
    verified = dtpf("verify", "run.mcap", cwd=tmp_path)
    assert verified.returncode == 0 and "entity: 30 propagated sets reproduced bit for bit" in verified.stdout


@pytest.mark.parametrize("source, problem", [
    ("def read(source):\n    return [[1.0, float('nan')]]\n", "returned a value that is not finite at row 1"),
    ("def read(source):\n    return [[1.0, 2.0, 3.0]]\n", "returned 3 observation columns; the model observes 2"),
    ("def read(source):\n    return {'z': [1.0]}\n", "returned a dict with keys ['z']"),
    ("def read(source):\n    raise OSError('no such device')\n", "raised OSError: no such device"),
])
def test_a_reader_that_breaks_the_contract_is_one_line(tmp_path, source, problem):
    (tmp_path / "mine.py").write_text(source)
    done = dtpf("run", "-q", *READER_ARGS, "--reader", "mine.py:read", cwd=tmp_path, timeout=120)
    assert done.returncode == 2, done.stdout
    assert problem in done.stderr.strip().splitlines()[-1] and "Traceback" not in done.stderr


def test_a_users_move_is_an_arm_of_the_choosing_policy(tmp_path):
    """With --policy choose a user's move is one more arm, 'own': scored on the real observations, put in force
    when it has the evidence, applied by the entity, and re-run by dtpf verify."""
    (tmp_path / "strong.py").write_text(
        "import numpy as np\n\n\ndef wide(resampled, particles, weights, rng):\n"
        "    mean = weights @ particles\n    spread = np.sqrt(weights @ (particles - mean) ** 2)\n"
        "    return resampled + rng.standard_normal(resampled.shape) * (0.5 * spread)\n")
    args = ("-q", "--model", str(EXAMPLES / "range_bearing.py:RangeBearingTarget"), "-n", "100", "-T", "100",
            "--seed", "1", "--twin", "ungm-1", "--policy", "choose", "--choose-base", "plain", "--move", "strong.py:wide")
    ran = dtpf("run", *args, cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    launched = dtpf("launch", *args, "-o", "run.mcap", cwd=tmp_path)
    assert launched.returncode == 0, launched.stderr
    assert figures(launched.stdout) == figures(ran.stdout)
    from dtpf.recording.logfile import read_log
    arms = [m.arm for _, m in read_log(tmp_path / "run.mcap").decoded(lambda topic: topic.endswith("/system/ps"))]
    assert "own" in arms and "plain" in arms  # the own move was chosen at some steps (4 of 100 with this seed and twin)
    verified = dtpf("verify", "run.mcap", cwd=tmp_path)
    assert verified.returncode == 0 and "entity: 100 propagated sets reproduced bit for bit" in verified.stdout


def test_verify_names_a_members_file_that_changed_since_the_run(user, tmp_path):
    move = tmp_path / "move.py"
    shutil.copy(user / "move.py", move)
    launched = dtpf("launch", "-q", "-n", "200", "-T", "10", "--move", "move.py:gaussian_shake", "-o", "run.mcap",
                    cwd=tmp_path)
    assert launched.returncode == 0, launched.stderr
    move.write_text(move.read_text().replace("FRACTION = 0.1", "FRACTION = 0.3"))
    verified = dtpf("verify", "run.mcap", cwd=tmp_path)
    assert verified.returncode == 1
    assert "note: the move move.py:gaussian_shake has changed (SHA-256" in verified.stdout
    assert "MISMATCH step 2: dtpf/ungm-1/entity/particles particles[" in verified.stdout


def test_a_biased_resampler_is_refused_with_its_measured_bias(user, tmp_path):
    done = dtpf("run", "-q", "-T", "5", "--resampler", str(user / "resampler.py:greedy"), cwd=tmp_path)
    assert done.returncode == 2
    line = done.stderr.strip().splitlines()[-1]
    assert "is biased: particle 0 of weight 0.3 got 8.0000 offspring on average over 4000 draws" in line
    assert "expected N w = 2.4000" in line and "Traceback" not in done.stderr


@pytest.mark.parametrize("source, problem", [
    ("def f(weights, rng):\n    return [0, 1]\n", "of shape (2,), expected (8,) ancestor indices"),
    ("def f(weights, rng):\n    return weights\n", "returned float64 values, expected integer ancestor indices"),
    ("def f(weights, rng):\n    import numpy as np\n    return np.arange(len(weights)) + 1\n",
     "returned an ancestor out of range: 1 .. 8, expected 0 .. 7"),
    ("def f(weights):\n    return weights\n", None),
    ("f = 3\n", "expected a function (weights, rng) -> ancestors, got an int"),
])
def test_a_resampler_that_breaks_the_contract_is_one_line(tmp_path, source, problem):
    (tmp_path / "mine.py").write_text(source)
    done = dtpf("run", "-q", "-T", "5", "--resampler", "mine.py:f", cwd=tmp_path, timeout=120)
    assert done.returncode == 2, done.stdout
    line = done.stderr.strip().splitlines()[-1]
    assert line.startswith("dtpf run: error: resampler 'mine.py:f'") and "Traceback" not in done.stderr
    if problem is not None:
        assert problem in line


def test_a_policy_that_breaks_the_contract_is_one_line(tmp_path):
    (tmp_path / "mine.py").write_text("class P:\n    pass\n")
    done = dtpf("run", "-q", "-T", "5", "--policy", "mine.py:P", cwd=tmp_path, timeout=120)
    assert done.returncode == 2
    assert "expected a subclass of dtpf.system.policy.PSPolicy, got the class P" in done.stderr


@pytest.fixture(scope="module")
def installed_extension(tmp_path_factory) -> Path:
    """A package of a user's members, installed (not editable) into a folder of its own: it registers a
    resampler and a move in dtpf's entry-point groups."""
    source, target = tmp_path_factory.mktemp("extension"), tmp_path_factory.mktemp("site")
    (source / "dtpf_extra").mkdir()
    shutil.copy(EXAMPLES / "components" / "resampler.py", source / "dtpf_extra" / "resampler.py")
    shutil.copy(EXAMPLES / "components" / "move.py", source / "dtpf_extra" / "move.py")
    (source / "dtpf_extra" / "__init__.py").write_text("")
    (source / "pyproject.toml").write_text(
        '[build-system]\nrequires = ["setuptools>=77"]\nbuild-backend = "setuptools.build_meta"\n'
        '[project]\nname = "dtpf-extra"\nversion = "1.0"\n'
        '[project.entry-points."dtpf.resamplers"]\nnumpy-systematic = "dtpf_extra.resampler:systematic_numpy"\n'
        '[project.entry-points."dtpf.moves"]\nshake = "dtpf_extra.move:gaussian_shake"\n'
        '[tool.setuptools]\npackages = ["dtpf_extra"]\n')
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                           "--target", str(target), str(source)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return target


def test_an_installed_packages_members_are_named_like_built_ins(installed_extension, tmp_path):
    env = {"PYTHONPATH": str(installed_extension)}
    helped = dtpf("run", "--help", cwd=tmp_path, env=env, timeout=120)
    assert "'numpy-systematic'(fromdtpf_extra.resampler:systematic_numpy)" in "".join(helped.stdout.split())
    args = ("-q", "-n", "300", "-T", "20", "--seed", "2")
    ran = dtpf("run", *args, "--resampler", "numpy-systematic", "--move", "shake", cwd=tmp_path, env=env)
    assert ran.returncode == 0, ran.stderr
    launched = dtpf("launch", *args, "--resampler", "numpy-systematic", "--move", "shake", "-o", "run.mcap",
                    cwd=tmp_path, env=env)
    assert launched.returncode == 0, launched.stderr
    assert figures(launched.stdout) == figures(ran.stdout)
    verified = dtpf("verify", "run.mcap", cwd=tmp_path, env=env)
    assert verified.returncode == 0 and "entity: 20 propagated sets reproduced" in verified.stdout
    missing = dtpf("run", *args, "--resampler", "numpy-systematic", cwd=tmp_path, timeout=120)
    assert missing.returncode == 2 and "unknown resampler 'numpy-systematic'" in missing.stderr


def test_a_model_that_imports_the_module_beside_it_runs_from_any_folder(user, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    model = os.path.relpath(user / "tracked.py", elsewhere) + ":MODEL"
    args = ("-q", "--model", model, "-n", "200", "-T", "15", "--seed", "1")
    ran = dtpf("run", *args, cwd=elsewhere)
    assert ran.returncode == 0, ran.stderr
    launched = dtpf("launch", *args, "-o", "run.mcap", cwd=elsewhere)
    assert launched.returncode == 0, launched.stderr
    assert figures(launched.stdout) == figures(ran.stdout) and len(figures(ran.stdout)) == 5
    fleet = dtpf("launch", *args, "--twins", "2", "--entities", "1", "-o", "fleet.mcap", cwd=elsewhere)
    assert fleet.returncode == 0, fleet.stderr
    # Both twins load the model (and its helper module) in the fleet's entity and shared services, which serve
    # every step: the launcher lets its shared services load the fleet's own model.
    assert "degraded steps  0" in fleet.stdout and "twin-steps      30 of 30" in fleet.stdout, \
        fleet.stdout + fleet.stderr
    assert not (elsewhere / "rb_base.py").exists()


def test_a_fleet_runs_a_users_members_in_its_shared_services_and_verifies(user, tmp_path):
    """The shared information and system services learn each twin's members from its entity and load them."""
    members = ("--resampler", "resampler.py:systematic_numpy", "--move", "move.py:gaussian_shake",
               "--policy", "policy.py:LowEssPS")
    for name in ("resampler.py", "move.py", "policy.py"):
        shutil.copy(user / name, tmp_path / name)
    args = ("-q", "-n", "200", "-T", "15", "--seed", "1", *members)
    fleet = dtpf("launch", *args, "--twins", "2", "--entities", "1", "-o", "fleet.mcap", cwd=tmp_path)
    assert fleet.returncode == 0, fleet.stderr
    assert "degraded steps  0" in fleet.stdout and "twin-steps      30 of 30" in fleet.stdout
    solo = dtpf("run", *args, "--twin", "ungm-1-2", cwd=tmp_path)
    rmse = next(line.split()[1] for line in solo.stdout.splitlines() if line.startswith("RMSE"))
    row = next(line.split() for line in fleet.stdout.splitlines() if line.startswith("ungm-1-2 "))
    assert row[2] == rmse  # the twin's numbers are its solo run's
    verified = dtpf("verify", "fleet.mcap", cwd=tmp_path)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert "2 of 2 twins reproduced exactly" in verified.stdout
