"""Worker processes that end with the process that started them.

A study's runs (`bitcomm compare`) train in a pool of spawned processes. Ctrl-C reaches the whole terminal's
process group, and the parent stops them; but a parent killed alone (`kill PID`, `pkill -f "bitcomm compare"`,
the OOM killer) used to leave its workers training on, unseen, sharing the cores with whatever ran next (an
a3c run's workers watch their parent themselves, `bitcomm.learn.a3c`). On Linux a worker asks the kernel for
SIGTERM when its parent ends (`prctl(PR_SET_PDEATHSIG)`); its checkpoints are written atomically, so the run
resumes from the last one. Elsewhere this is a no-op.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # <sys/prctl.h>


def end_with_parent(parent: int) -> bool:
    """Call first thing in a worker, with the pid of the process that started it (`os.getpid()` there);
    returns whether the kernel will end this process with its parent. A worker whose parent is already
    gone exits at once."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        armed = ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
    if os.getppid() != parent:  # the parent ended before the request was made: nobody will signal
        os._exit(1)
    return armed
