"""A helper process of a rehearsal: simulated runs of a model filtered by every arm, on another core.

``python -P -m dtpf.system._rehearse_worker`` reads one pickled task from its standard input (the model, the arms,
the run numbers and the settings of :func:`dtpf.system.rehearse.simulated_runs`) and writes the pickled list of
each run's errors to its standard output. Only :func:`dtpf.system.rehearse.rehearse` starts it, with a task it
pickled itself; it reads nothing else.
"""
from __future__ import annotations

import pickle
import sys


def main() -> int:
    from dtpf.system.rehearse import simulated_runs

    task = pickle.load(sys.stdin.buffer)
    errors = simulated_runs(task["model"], task["arms"], task["runs"], **task["settings"])
    pickle.dump(errors, sys.stdout.buffer, protocol=pickle.HIGHEST_PROTOCOL)
    sys.stdout.buffer.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
