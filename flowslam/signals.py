"""Signals that stop a run: SIGTERM handled like Ctrl-C, and both held back while
results are written.

A job scheduler, ``timeout`` or ``docker stop`` sends SIGTERM, whose default action
kills the process before anything is written. Inside :func:`terminate_as_interrupt`
SIGTERM raises :class:`Terminated` instead, a ``KeyboardInterrupt``, so every path
that keeps the work done on Ctrl-C (``run_pipeline`` stores it in
``RunResult.error``) keeps it on SIGTERM too. Inside :func:`deferred_signals` (the
writing of a run folder) SIGINT and SIGTERM are recorded and raised only when the
block ends, so a run folder is never half written because of a signal.

Inside :func:`terminate_as_interrupt`, the scan loop (:func:`flowslam.pipeline.drive`)
takes SIGTERM at its own safe points instead (:func:`sigterm_at_safe_points`): between
two scans, so an exception never surfaces inside a native library's callback or a
finaliser, where Python cannot pass it on (it is printed and lost there, and the
library's state may be left half changed).

All are no-ops outside the main thread (Python delivers signals to it only).
``flowslam run`` turns SIGTERM into ``Terminated`` for the whole command; library
callers keep their own handlers (``run_sequence`` only defers signals while writing).
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

__all__ = ["Terminated", "terminate_as_interrupt", "sigterm_at_safe_points", "deferred_signals", "describe_stop",
           "exit_code", "stop_behind"]


class Terminated(KeyboardInterrupt):
    """The process was asked to stop by a signal other than SIGINT (e.g. SIGTERM)."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_terminated(signum: int, _frame=None):
    raise Terminated(signum)


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` (a ``KeyboardInterrupt``) inside the block."""
    if not _in_main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def sigterm_at_safe_points() -> Iterator[Callable[[], None]]:
    """Yields ``check()``. Where SIGTERM would raise :class:`Terminated` (inside
    :func:`terminate_as_interrupt`), inside this block it is only recorded, and ``check()``
    raises it: call it where stopping is safe (between two scans). Elsewhere (other
    handlers, other threads) ``check()`` does nothing and the handlers stay as they are.
    A second SIGTERM before ``check()`` took the first raises at once. On leaving, the
    handler in place before is restored; a SIGTERM recorded but not yet raised is then
    sent again, to that handler."""
    if not _in_main_thread() or signal.getsignal(signal.SIGTERM) is not _raise_terminated:
        yield lambda: None
        return
    pending: list[int] = []

    def check() -> None:
        if pending:
            raise Terminated(pending.pop())

    def record(signum: int, _frame=None) -> None:
        if pending:  # asked twice: at once
            pending.clear()
            raise Terminated(signum)
        pending.append(signum)

    previous = signal.signal(signal.SIGTERM, record)
    try:
        yield check
    finally:
        signal.signal(signal.SIGTERM, previous)
    if pending:
        signal.raise_signal(pending[0])


@contextmanager
def deferred_signals() -> Iterator[None]:
    """SIGINT and SIGTERM that arrive inside the block are held; when it ends, the
    handlers in place before it are restored and the first held signal is sent again,
    so whatever would have handled it then (Python's ``KeyboardInterrupt``,
    :func:`terminate_as_interrupt`, a caller's own handler, or the default action)
    handles it now."""
    if not _in_main_thread():
        yield
        return
    pending: list[int] = []
    wanted = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, _frame: pending.append(signum)) for s in wanted}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if pending:
        signal.raise_signal(pending[0])


def stop_behind(error: BaseException) -> BaseException:
    """The ``KeyboardInterrupt`` (Ctrl-C, or :class:`Terminated`) that ``error`` was raised
    from, else ``error`` itself. A signal handler that raises while compiled code calls back
    into Python (numba's dispatcher, for one) can surface as another error, e.g. ``SystemError:
    ... returned a result with an exception set``, whose cause is the interrupt; the run
    stopped because of the signal, and is reported as such."""
    seen: set[int] = set()
    link: BaseException | None = error
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return link
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return error


def describe_stop(error: BaseException) -> str:
    """One line for ``run.json`` and the terminal: why a run stopped."""
    if isinstance(error, Terminated):
        return str(error)
    if isinstance(error, KeyboardInterrupt):
        return "interrupted (SIGINT, Ctrl-C)"
    return str(error) or error.__class__.__name__


def exit_code(error: KeyboardInterrupt) -> int:
    """The shell's convention for a process stopped by a signal: 128 + its number."""
    return 128 + (error.signum if isinstance(error, Terminated) else signal.SIGINT)
