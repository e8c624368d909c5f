"""One torch thread per pytest-xdist process: `make test` runs one process per core, and a second thread on
a busy core costs more than it gives (a run with 2 threads beside another busy core trained 2.9x slower)."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
