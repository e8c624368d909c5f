"""The critic's gradient step beside the policy's, on a second core.

Within one minibatch step the policy's update and the critic's share no parameters, no optimizer and no
random numbers: the critic regresses on returns fixed before the update, the policy follows advantages fixed
before it. So they can run at once, one on a helper thread, and the parameters after the update are the
same bit for bit as one after the other on one thread (tested): a run on two threads is the run on one. On an
idle machine this is as fast as one step at a time on torch's two threads; with another process busy on a core
it is 2.3x faster, as two torch threads then wait on each other (docs/tuning.md, session 14).

    with critic_beside_policy(learner, threads):   # the synchronous trainers, with their torch threads
        learner.update(batch)
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol, TypeVar

import torch

from bitcomm.policies.denormals import denormals_flushed

T = TypeVar("T")


class HasHelper(Protocol):
    helper: ThreadPoolExecutor | None


def start(helper: ThreadPoolExecutor | None, work: Callable[[], T]) -> Callable[[], T]:
    """Start `work` on `helper` (or, without one, do it now); the returned function waits for its result."""
    if helper is None:
        result = work()
        return lambda: result
    return helper.submit(work).result


@contextlib.contextmanager
def critic_beside_policy(learner: HasHelper, threads: int) -> Iterator[None]:
    """With `threads` >= 2 torch threads, give `learner` a helper thread for its critic steps and each of the
    two steps half the threads (restored on exit); with fewer, leave everything as it is."""
    if threads < 2:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(threads // 2)
    learner.helper = ThreadPoolExecutor(  # in the trainer's denormal mode (bitcomm.policies.denormals)
        1, thread_name_prefix="bitcomm-critic", initializer=torch.set_flush_denormal, initargs=(denormals_flushed(),)
    )
    try:
        yield
    finally:
        learner.helper.shutdown()
        learner.helper = None
        torch.set_num_threads(previous)
