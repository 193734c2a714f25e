"""Progress of long loops on stderr, silent for quick commands and under `--quiet`."""

from __future__ import annotations

import math
import sys
import threading
import time

__all__ = ["Progress", "Heartbeat", "set_quiet"]

_QUIET = False


def set_quiet(quiet: bool) -> None:
    """Silence (True) or allow (False) every `Progress` of this process (the CLI's `--quiet`)."""
    global _QUIET
    _QUIET = bool(quiet)


class Progress:
    """Progress of a long loop on stderr: a bar on a terminal, a plain line every few seconds otherwise.

    Shows nothing during the first `delay` seconds (default 2 s), so quick commands stay silent,
    and nothing at all after `set_quiet(True)`. Usage::

        with Progress("calibrating", total=n_iterations) as progress:
            for k in range(n_iterations):
                ...
                progress.update(k + 1, note=f"cost {cost:.3g}")   # or progress.advance()

    `total=None` shows a count without a bar. Cheap to call every step: output is rate-limited.
    """

    def __init__(
        self,
        label: str,
        total: int | None = None,
        *,
        stream=None,
        delay: float = 2.0,
        interval: float | None = None,
        counted: bool = True,
    ) -> None:
        self.label = label
        self.total = total
        self.counted = counted  # False: "working" in place of a count (a `Heartbeat`)
        self.stream = stream if stream is not None else sys.stderr
        self.delay = delay
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if interval is not None else (0.1 if self.tty else 5.0)
        self.done = 0
        self.note = ""
        self.start = time.monotonic()
        self._last = -math.inf
        self._shown = False

    def advance(self, steps: int = 1, note: str | None = None) -> None:
        self.update(self.done + steps, note)

    def update(self, done: int, note: str | None = None) -> None:
        self.done = int(done)
        if note is not None:
            self.note = note
        now = time.monotonic()
        if _QUIET or now - self.start < self.delay or now - self._last < self.interval:
            return
        self._last = now
        self._emit(now, final=False)

    def close(self) -> None:
        if self._shown and not _QUIET:
            self._emit(time.monotonic(), final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _emit(self, now: float, final: bool) -> None:
        elapsed = now - self.start
        if self.total:
            fraction = min(1.0, self.done / self.total)
            count = f"{self.done}/{self.total}"
            eta = f", about {elapsed / fraction - elapsed:.0f} s left" if 0 < fraction < 1 else ""
        else:
            fraction, count, eta = None, f"{self.done}", ""
        if not self.counted:
            count = "working"
        note = f" {self.note}" if self.note else ""
        try:
            if self.tty:
                bar = (
                    "" if fraction is None else "[" + "#" * int(24 * fraction) + "-" * (24 - int(24 * fraction)) + "] "
                )
                line = f"\r{self.label}: {bar}{count} ({elapsed:.0f} s{eta}){note}"
                self.stream.write(line[:200].ljust(80) + ("\n" if final else ""))
            else:
                self.stream.write(f"{self.label}: {count} ({elapsed:.0f} s{eta}){note}\n")
            self.stream.flush()
        except (OSError, ValueError):
            return
        self._shown = True


class Heartbeat:
    """Elapsed time of one long step that reports no count (a planning, a batch solve), shown by a
    background thread in the manner of `Progress`: nothing during the first `delay` seconds, then
    a line every few seconds (a tick on a terminal), and nothing under `--quiet`. Usage::

        with Heartbeat("planning", note="selecting 60 of 1200 candidates"):
            plan = plan_closed_loop(...)

    The step itself runs in the calling thread, so signals (Ctrl-C, SIGTERM) act on it as before.
    """

    def __init__(
        self, label: str, note: str = "", *, stream=None, delay: float = 2.0, interval: float | None = None
    ) -> None:
        self.progress = Progress(label, None, stream=stream, delay=delay, interval=interval, counted=False)
        self.progress.note = note
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat {label}", daemon=True)

    def _beat(self) -> None:
        tick = min(self.progress.interval, 1.0)
        while not self._stop.wait(tick):
            self.progress.update(0)

    def __enter__(self) -> "Heartbeat":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.progress.close()
