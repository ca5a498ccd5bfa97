"""``python -m dtpf``: the ``dtpf`` command."""
import sys

from dtpf.scripts.cli import main

sys.exit(main())
