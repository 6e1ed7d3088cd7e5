"""Worker threads for the numerical steps that may run beside the fusion's own.

OpenCV releases the GIL in its calls and numpy in its array loops, so a step made of a few
large array operations (the VO's front end into the next frame and its backward LK, its
local bundle adjustment, the landmark window's alternations) runs on the second core while
the fusion goes on. Each step is posed from a snapshot of its inputs and its result taken
back on a fixed later frame (the front end made ahead: on the next frame, and only if its
inputs are still the VO's), so the outcome is the same whatever the machine's speed; only
the wall time depends on the overlap.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

T = TypeVar("T")

_LOCAL = threading.local()


def worker(name: str) -> ThreadPoolExecutor:
    """The worker thread for one kind of step (one thread each, so a long step of one kind
    never queues a short one of another) of the calling thread: two engines driven by two
    threads (a server's session and its scout, niced in the background, whose priority its
    workers inherit) never wait for each other's steps. The workers go with their thread,
    and a forked child (a campaign's workers, the yardstick's jobs), which has none of its
    parent's threads, makes its own."""
    pool = getattr(_LOCAL, "pool", None)
    if pool is None or pool[0] != os.getpid():
        pool = _LOCAL.pool = (os.getpid(), {})
    have = pool[1].get(name)
    if have is None:
        have = pool[1][name] = ThreadPoolExecutor(1, thread_name_prefix=f"estimator-{name}")
    return have


class Pending(Generic[T]):
    """A step under way in a worker, with what its taker needs to apply it. Copied (a
    replay's engine checkpoint) or pickled (a campaign task), it first waits for the result
    and carries that: a copy goes on exactly like the original, and no copy is taken of
    arrays the worker is still writing."""

    def __init__(self, future: Future, **context: Any) -> None:
        self._future: Future | None = future
        self._result: T | None = None
        self.__dict__.update(context)

    def result(self) -> T:
        if self._future is not None:
            self._result, self._future = self._future.result(), None
        return self._result  # type: ignore[return-value]

    def __getstate__(self) -> dict:
        self.result()
        return dict(self.__dict__)
