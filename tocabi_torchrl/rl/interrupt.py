"""Stopping a training run cleanly on Ctrl-C (SIGINT) or SIGTERM, shared by ``recipes/ppo_walk.py`` (through
:func:`~tocabi_torchrl.rl.trainer.train`) and the library recipes (:mod:`tocabi_torchrl.adapters.recipe`).

The first signal only sets a flag (:attr:`StopFlag.stop_signal`); the training loop reads it at its next safe point,
saves what it needs to continue, and the recipe exits with :func:`signal_exit_status` (130 for Ctrl-C, 143 for
SIGTERM), as a shell reports a process ended by that signal. A second signal raises ``KeyboardInterrupt`` at once, for
a run that must not wait for the safe point.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from collections.abc import Iterator, Mapping

from .logging import print_line

__all__ = ["Interrupted", "StopFlag", "exit_status", "signal_exit_status", "stop_on_signals"]

#: The signals that ask a run to stop at its next safe point.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(Exception):
    """Raised at a training loop's safe point after Ctrl-C or SIGTERM (:func:`stop_on_signals`); its message is the
    signal's name."""


class StopFlag:
    """What :func:`stop_on_signals` sets: the name of the first stop signal (``None`` until one came)."""

    def __init__(self) -> None:
        self.stop_signal: str | None = None


@contextlib.contextmanager
def stop_on_signals(flag, message: str = "stopping at the next safe point", repeat_grace_s: float = 0.0
                    ) -> Iterator[None]:
    """While the block runs, the first SIGINT or SIGTERM sets ``flag.stop_signal`` to the signal's name and prints
    ``"<SIGNAL>: <message> (send it again to stop at once)"`` to stderr (on a line of its own beside a progress bar:
    :func:`~.logging.print_line`); a second one raises ``KeyboardInterrupt`` at once. ``flag``: any object with a
    ``stop_signal`` attribute (:class:`StopFlag`, the library recipes' ``TrainingClock``). A repeat within
    ``repeat_grace_s`` seconds of the first counts as the same request: torchrun forwards the Ctrl-C its workers
    already got from the terminal, and that copy must not cut the save short.

    The previous handlers are back on exit. Python delivers signals to the main thread only, so elsewhere nothing is
    installed (and the block runs as it would without this)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    first_at: list[float] = []

    def handler(signum, frame):
        if flag.stop_signal is not None:
            if first_at and time.monotonic() - first_at[0] < repeat_grace_s:
                return
            raise KeyboardInterrupt
        flag.stop_signal = signal.Signals(signum).name
        first_at.append(time.monotonic())
        print_line(f"{flag.stop_signal}: {message} (send it again to stop at once)", file=sys.stderr)

    previous = {}
    try:
        for sig in STOP_SIGNALS:
            previous[sig] = signal.signal(sig, handler)
        yield
    finally:
        for sig, old in previous.items():  # None: a handler not set from Python, which cannot be put back
            signal.signal(sig, signal.SIG_DFL if old is None else old)


def signal_exit_status(name: str | None) -> int:
    """The exit status of a run stopped by the signal ``name`` (``"SIGINT"``, ``"SIGTERM"``): the shell's 128 + signal
    number, 130 for Ctrl-C and 143 for SIGTERM, so that a script running it can tell it from a finished run (0 for
    ``None``)."""
    if name is None:
        return 0
    return 128 + int(signal.SIGTERM if name == "SIGTERM" else signal.SIGINT)


def exit_status(result: Mapping) -> int:
    """A recipe's exit status for ``result``: 0, or for an interrupted call (``result["interrupted"]``, the signal's
    name) :func:`signal_exit_status`."""
    return signal_exit_status(result.get("interrupted"))
