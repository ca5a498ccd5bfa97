"""A log is never overwritten or shared, and files of different runs are never read as one run (issue 41).

- ``dtpf launch -o`` of an existing file, or of a name whose segments exist, is refused before anything
  starts (one line, exit code 2); ``--overwrite`` removes them and says so.
- The recorder creates its file exclusively and holds a lock on it: a second recorder on the same path
  fails at once, naming the path and that another recorder holds it.
- ``dtpf summary`` / ``verify`` / ``cat`` of files of different runs are refused in one line naming them;
  a run's own segments still read as one.

Every process a test starts goes through the ``processes`` fixture (stopped even on failure); ports are
free ones; waits are on events (a file being locked, a process's line, a process's end), bounded.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT
from dtpf.recording.logfile import MixedRunsError, read_log, read_logs
from dtpf.recording.writer import LogExistsError, McapRecording, claim_log, existing_log_files, held_by_writer
from dtpf.shell.bus import free_port

RUN = ("-q", "--particles", "200", "--timeout", "1.0", "--policy", "fixed")


def dtpf(*args: str, cwd: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def launch_args(*extra: str) -> list[str]:
    return ["-m", "dtpf.scripts.cli", "launch", *RUN, "--port", str(free_port()), *extra]


def errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if "error" in line.lower()]


def wait_for(condition, timeout: float, what: str, process: subprocess.Popen | None = None, output=None) -> None:
    """Until ``condition()`` (an event: a file locked, a line written); fails naming ``what``."""
    deadline = time.monotonic() + timeout
    while not condition():
        if process is not None and process.poll() is not None:
            pytest.fail(f"{what}: the process ended first (code {process.returncode}): "
                        f"{output() if output else ''}")
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout:g} s {output() if output else ''}")
        time.sleep(0.02)


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            found += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


# --- the library: claim_log, existing_log_files, McapRecording(exclusive=True) ---

def test_claim_refuses_a_log_and_its_segments_and_overwrite_removes_them(tmp_path):
    log = tmp_path / "run.mcap"
    assert claim_log(log) == [] and existing_log_files(log) == []
    for name in ("run.2.mcap", "run.1.mcap", "run.x.mcap", "other.1.mcap", "run.1.mcap.bak"):
        (tmp_path / name).write_bytes(b"x")
    assert existing_log_files(log) == [tmp_path / "run.1.mcap", tmp_path / "run.2.mcap"]
    with pytest.raises(LogExistsError, match=r"run\.mcap has segments on disk: .*run\.1\.mcap, .*run\.2\.mcap"):
        claim_log(log)
    log.write_bytes(b"y")
    with pytest.raises(LogExistsError, match=r"run\.mcap and its segments .* exist: a log is never overwritten"):
        claim_log(log)
    assert claim_log(log, overwrite=True) == [log, tmp_path / "run.1.mcap", tmp_path / "run.2.mcap"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.1.mcap", "run.1.mcap.bak", "run.x.mcap"]


def test_an_exclusive_recording_never_opens_an_existing_file_and_a_held_one_is_named(tmp_path):
    log = tmp_path / "run.mcap"
    log.write_bytes(b"earlier")
    with pytest.raises(LogExistsError, match=r"it exists; a log is never overwritten"):
        McapRecording(log, exclusive=True)
    assert log.read_bytes() == b"earlier"
    log.unlink()
    with McapRecording(log, exclusive=True) as first:
        first.write("dtpf/t/entity/estimate", b"not decoded here")
        assert held_by_writer(log)
        with pytest.raises(LogExistsError, match=r"it exists and another recorder is writing it"):
            McapRecording(log, exclusive=True)
        with pytest.raises(LogExistsError, match=r"another recorder is writing it"):
            McapRecording(log)  # not even a writer that would replace the file
        with pytest.raises(LogExistsError, match=r"being written by another recorder"):
            claim_log(log, overwrite=True)  # --overwrite never removes a log being written
    assert not held_by_writer(log)
    assert read_log(log).complete and len(read_log(log).messages) == 1


# --- the recorder service ---

def test_a_second_recorder_on_the_same_path_fails_at_once_and_the_first_log_is_whole(processes, tmp_path):
    log = tmp_path / "rec.mcap"
    first = processes.start("recorder-1", ["-m", "dtpf.scripts.record", "--listen", f"tcp/127.0.0.1:{free_port()}",
                                           "--twin", "t-one", "--log-level", "INFO", "-o", str(log)])
    wait_for(lambda: held_by_writer(log), 60, "the first recorder holds its log", first,
             lambda: processes.output(first))
    started = time.monotonic()
    second = subprocess.run([sys.executable, "-m", "dtpf.scripts.record", "--listen",
                             f"tcp/127.0.0.1:{free_port()}", "--twin", "t-one", "-o", str(log)],
                            cwd=ROOT, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - started
    assert second.returncode == 2, second.stderr
    said = errors(second.stderr)
    assert len(said) == 1 and "Traceback" not in second.stderr, second.stderr
    assert str(log) in said[0] and "another recorder is writing it" in said[0], said
    assert took < 30, took  # at once: no waiting for a run
    assert first.poll() is None and held_by_writer(log)
    first.send_signal(signal.SIGINT)
    assert first.wait(timeout=30) == 0, processes.output(first)
    assert read_log(log).complete, read_log(log).problem  # the first recorder's file, finished, nobody else's


# --- dtpf launch -o ---

def test_a_second_launch_on_the_same_log_fails_at_once_and_the_first_log_verifies(processes, tmp_path):
    log = tmp_path / "run.mcap"
    first = processes.start("launch-1", launch_args("--steps", "30", "--rate", "15", "--seed", "4", "-o", str(log)))
    wait_for(lambda: held_by_writer(log), 90, "the first launch's recorder holds the log", first,
             lambda: processes.output(first))
    # While the first launch records: refused before anything starts, naming the recorder that holds it.
    second = dtpf("launch", *RUN, "--steps", "10", "--seed", "9", "-o", str(log), cwd=tmp_path, timeout=60)
    assert second.returncode == 2, second.stderr
    assert len(errors(second.stderr)) == 1 and "launching" not in second.stderr, second.stderr
    assert f"the log {log} is being written by another recorder" in second.stderr, second.stderr
    assert first.wait(timeout=180) == 0, processes.output(first)
    # After it: the file exists, and is still refused (a log is never overwritten).
    third = dtpf("launch", *RUN, "--steps", "10", "--seed", "9", "-o", str(log), cwd=tmp_path, timeout=60)
    assert third.returncode == 2 and "launching" not in third.stderr, third.stderr
    said = errors(third.stderr)
    assert len(said) == 1 and f"the log {log} exists: a log is never overwritten" in said[0], third.stderr
    assert "--overwrite" in said[0]
    verified = dtpf("verify", str(log), cwd=tmp_path)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert "OK: 30 steps reproduced exactly" in verified.stdout, verified.stdout
    summary = dtpf("summary", str(log), cwd=tmp_path)
    assert "seed 4" in summary.stdout and "steps         30 of 30 (1-30)" in summary.stdout, summary.stdout
    assert "state         complete" in summary.stdout


def test_overwrite_replaces_the_log_and_its_segments_and_says_so(tmp_path):
    log = tmp_path / "run.mcap"
    assert dtpf("launch", *RUN, "--steps", "10", "--seed", "1", "-o", str(log), cwd=tmp_path).returncode == 0
    stale = tmp_path / "run.1.mcap"
    shutil.copy(log, stale)  # as if a segment of that earlier launch
    done = dtpf("launch", *RUN, "--steps", "12", "--seed", "2", "-o", str(log), "--overwrite", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert f"--overwrite: removed {log}, {stale}" in done.stderr, done.stderr
    assert not stale.exists()
    summary = dtpf("summary", str(log), cwd=tmp_path)
    assert "seed 2" in summary.stdout and "steps         12 of 12" in summary.stdout, summary.stdout


def test_a_launch_on_a_name_whose_segments_exist_is_refused_and_touches_nothing(tmp_path):
    for name in ("seg.1.mcap", "seg.2.mcap"):
        (tmp_path / name).write_bytes(b"an earlier launch's segment")
    done = dtpf("launch", *RUN, "--steps", "10", "-o", "seg.mcap", cwd=tmp_path, timeout=60)
    assert done.returncode == 2, done.stderr
    said = errors(done.stderr)
    assert len(said) == 1 and "launching" not in done.stderr, done.stderr
    assert "the log seg.mcap has segments on disk: seg.1.mcap, seg.2.mcap" in said[0], said
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seg.1.mcap", "seg.2.mcap"]
    assert (tmp_path / "seg.1.mcap").read_bytes() == b"an earlier launch's segment"


# --- tools that read several files ---

def test_summary_and_verify_refuse_files_of_two_runs_naming_them(tmp_path):
    a, b, c = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    from concurrent.futures import ThreadPoolExecutor

    def launched(log, seed, steps):  # three launches at once, each on a free port of its own
        return dtpf("launch", *RUN, "--steps", steps, "--seed", seed, "--port", str(free_port()), "-o", str(log),
                    cwd=tmp_path)

    with ThreadPoolExecutor(3) as pool:
        done = list(pool.map(launched, (a, b, c), ("0", "3", "0"), ("12", "8", "12")))
    assert [d.returncode for d in done] == [0, 0, 0], [d.stderr for d in done]
    for command in ("summary", "verify", "cat"):
        done = dtpf(command, str(a), str(b), cwd=tmp_path)
        assert done.returncode == 2, (command, done.stdout, done.stderr)
        said = errors(done.stdout + done.stderr)
        assert len(said) == 1, (command, said)
        assert f"{b} and {a} are not of one run: seed 3 vs 0, steps 8 vs 12 (twin ungm-1)" in said[0], said
    # The same configuration launched twice is two runs all the same: another entity process.
    done = dtpf("summary", str(a), str(c), cwd=tmp_path)
    assert done.returncode == 2 and "two runs of one configuration" in done.stderr, done.stderr
    with pytest.raises(MixedRunsError, match="not of one run"):
        read_logs([a, c])
    # Each file alone, and a file given twice, still read.
    assert dtpf("summary", str(a), str(a), cwd=tmp_path).returncode == 0
    assert len(read_logs([b]).messages) == len(read_log(b).messages)


def test_a_runs_own_segments_read_as_one_and_another_runs_file_beside_them_is_refused(processes, tmp_path):
    """The tester's case: a launch whose recorder was killed leaves seg.mcap, seg.1.mcap, seg.2.mcap; they
    summarise and verify as one run. A later launch cannot write seg.mcap; another run's file put there by
    hand is refused by summary and verify, naming it."""
    steps = 60
    launcher = processes.start("launch", launch_args("--steps", str(steps), "--rate", "15", "-o",
                                                     str(tmp_path / "seg.mcap")))
    log = tmp_path / "seg.mcap"
    wait_for(lambda: held_by_writer(log) and log.stat().st_size > 4096, 90, "the recorder writes", launcher,
             lambda: processes.output(launcher))
    recorders = [pid for pid in children(launcher.pid) if "dtpf.scripts.record" in cmdline(pid)]
    assert len(recorders) == 1, [cmdline(pid) for pid in children(launcher.pid)]
    os.kill(recorders[0], signal.SIGKILL)
    assert launcher.wait(timeout=180) == 0, processes.output(launcher)
    output = processes.output(launcher)
    assert "the recorder service died" in output, output
    segments = [tmp_path / name for name in ("seg.mcap", "seg.1.mcap", "seg.2.mcap")]
    assert all(path.exists() for path in segments), sorted(p.name for p in tmp_path.iterdir())
    names = [str(path) for path in sorted(tmp_path.glob("seg*.mcap"))]  # as a shell's seg*.mcap
    summary = dtpf("summary", *names, cwd=tmp_path)
    assert summary.returncode == 0, summary.stderr
    # One run across its three files; the killed recorder's open chunk may hold a step or two that no segment
    # has (a killed writer loses only its open chunk: steps 1-2, 4-60 once, under a parallel suite).
    found = re.search(rf"steps\s+(\d+) of {steps} ", summary.stdout)
    assert found and int(found.group(1)) >= steps - 5, summary.stdout
    assert "segments" in summary.stdout and all(name in summary.stdout for name in names), summary.stdout
    verified = dtpf("verify", *names, cwd=tmp_path)
    assert verified.returncode == 0 and "steps reproduced exactly" in verified.stdout, verified.stdout
    # A later launch on seg.mcap (its segments exist) is refused; so is writing the run's file away.
    refused = dtpf("launch", *RUN, "--steps", "20", "--seed", "7", "-o", "seg.mcap", cwd=tmp_path, timeout=60)
    assert refused.returncode == 2 and "seg.mcap and its segments" in refused.stderr, refused.stderr
    other = dtpf("launch", *RUN, "--steps", "20", "--seed", "7", "-o", "other.mcap", cwd=tmp_path)
    assert other.returncode == 0, other.stderr
    log.unlink()
    shutil.move(tmp_path / "other.mcap", log)  # another run's file under the name, by hand
    for command in ("summary", "verify"):
        done = dtpf(command, *names, cwd=tmp_path)
        assert done.returncode == 2, (command, done.stdout, done.stderr)
        said = errors(done.stdout + done.stderr)
        assert len(said) == 1 and f"{log} and " in said[0] and "are not of one run: seed 7 vs 0, steps 20 vs 60" \
            in said[0], said
