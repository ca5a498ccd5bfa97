"""A helper process of a rehearsal: simulated runs of a model filtered by every arm, on another core.

``python -P -m dtpf.system._rehearse_worker`` reads one pickled task from its standard input (the user's files to
import first, then the model, the arms, the run numbers and the settings of
:func:`dtpf.system.rehearse.simulated_runs`) and writes the pickled list of each run's errors to its standard
output. Only :func:`dtpf.system.rehearse.rehearse` starts it, with a task it
pickled itself; it reads nothing else.
"""
from __future__ import annotations

import pickle
import sys


def main() -> int:
    from dtpf.messages.references import load_file
    from dtpf.system.rehearse import simulated_runs

    outer = pickle.load(sys.stdin.buffer)
    for path in outer["files"]:   # a user's files, under the module names they have in the rehearsing process
        load_file(path, "rehearsal helper")
    task = pickle.loads(outer["payload"])
    errors = simulated_runs(task["model"], task["arms"], task["runs"], **task["settings"])
    pickle.dump(errors, sys.stdout.buffer, protocol=pickle.HIGHEST_PROTOCOL)
    sys.stdout.buffer.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
