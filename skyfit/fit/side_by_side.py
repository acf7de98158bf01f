"""Independent branches of one fit run side by side on a multi-core CPU, each in its own process.

A photo fit decides between two projections by fitting both (:func:`skyfit.fit.photo.fit_scene`'s short fits and
race). The fits share nothing until they are compared, so on a machine with two cores they can run at once. Why
processes, forked here, and not threads or a library: a photo fit's objective with its gradient is several thousand
small tensor operations on 1 000 blocks, and Python holds the GIL between them. On held-out synthetic photo 14
(2 cores, one torch thread per branch) the race took 66 s one fit after the other, 53 s in two threads and 35 s in
two forked processes (docs/photos.md, "The race side by side"). ``concurrent.futures`` and ``multiprocessing.Pool``
pickle the function and start helper threads before they fork; a fit's branches are closures over the scene and its
tables, which a fork inherits as they are, so the one child per extra branch is started by hand
(``multiprocessing``'s fork context) and sends its result back pickled. Many photos on many machines go through
``skyfit batch`` on Dask; this only splits the independent branches inside one photo's fit.

It falls back to one branch after the other, in this process, wherever a fork is not safe or not useful: not on
Linux (macOS's system libraries are not fork-safe), a device other than the CPU (CUDA cannot be forked), a single
torch thread (nothing to share out), a daemonic process (Dask's and multiprocessing's workers may not have
children), other Python threads running (a fork copies their locks, held or not; :data:`BENIGN_THREADS` aside),
or :data:`ENABLED` off. A branch whose child dies without a result is run again here, with a
:class:`BranchLostWarning`.
"""

from __future__ import annotations

import multiprocessing
import pickle
import sys
import threading
import warnings
from typing import Any, Callable, Sequence

import torch

ENABLED = True
"""Whether :func:`side_by_side` may fork (False: every branch in this process, one after the other)."""

BENIGN_THREADS = ("tqdm_monitor",)
"""Python threads a fork may copy: tqdm's monitor, which tqdm starts with a process's first bar and keeps for good,
takes tqdm's lock for microseconds every 10 s, and a child draws no bar (:func:`in_child`), so never takes it."""

_IN_CHILD = False


class BranchLostWarning(RuntimeWarning):
    """A branch's child died or could not send its result back; the branch was run again in this process."""


def in_child() -> bool:
    """Whether this process is a branch's child (its progress bars would garble the parent's)."""
    return _IN_CHILD


def can_fork(device="cpu") -> bool:
    """Whether :func:`side_by_side` would run branches at once here (see the module docstring)."""
    return (ENABLED and sys.platform.startswith("linux") and torch.device(device).type == "cpu"
            and torch.get_num_threads() >= 2 and not multiprocessing.current_process().daemon
            and all(t is threading.current_thread() or t.name in BENIGN_THREADS for t in threading.enumerate()))


def _child(call: Callable[[], Any], conn, threads: int) -> None:
    global _IN_CHILD
    _IN_CHILD = True
    torch.set_num_threads(threads)
    try:
        out = ("ok", call())
    except BaseException as e:  # noqa: BLE001 - handed to the parent, which raises it
        out = ("error", e)
    try:
        # plain pickle, not the connection's own: that one hands torch's tensors over in shared memory files, which
        # vanish with this process before the parent reads them
        data = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as e:  # an unpicklable result or exception: the parent runs the branch itself
        data = pickle.dumps(("lost", f"{type(e).__name__}: {e}"))
    conn.send_bytes(data)
    conn.close()


def side_by_side(calls: Sequence[Callable[[], Any]], device="cpu") -> list:
    """``[call() for call in calls]``, the calls at once where :func:`can_fork` (the first in this process, each
    other in a forked child, torch's threads shared out among them); their results in order.

    The calls must be independent: what a child changes in memory (a list it appends to, a counter) stays in the
    child; only its return value comes back. An exception in a call is raised here, the first call's first.
    """
    calls = list(calls)
    if len(calls) < 2 or not can_fork(device):
        return [c() for c in calls]
    threads = torch.get_num_threads()
    each = max(1, threads // len(calls))
    ctx = multiprocessing.get_context("fork")
    children = []
    for call in calls[1:]:
        recv, send = ctx.Pipe(duplex=False)
        p = ctx.Process(target=_child, args=(call, send, each), daemon=True)
        p.start()
        send.close()
        children.append((p, recv))
    torch.set_num_threads(each)
    try:
        first = calls[0]()
    finally:
        torch.set_num_threads(threads)
        results = []
        for p, recv in children:
            try:
                results.append(pickle.loads(recv.recv_bytes()))
            except EOFError:  # the child died without a word: its exit code once it is gone
                p.join()
                results.append(("lost", f"exit code {p.exitcode}"))
            recv.close()
            p.join()
    out = [first]
    for call, (kind, value) in zip(calls[1:], results):
        if kind == "error":
            raise value
        if kind == "lost":
            warnings.warn(f"a side-by-side branch was lost in its child ({value}); it is run again here",
                          BranchLostWarning, stacklevel=2)
            value = call()
        out.append(value)
    return out
