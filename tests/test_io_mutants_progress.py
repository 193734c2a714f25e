"""io.progress tests that kill mutants the behaviour tests let through (docs/mutation.md): the exact
lines on a terminal and elsewhere, the delay and the rate limit at their boundaries (a fake clock),
the bar, the estimate, notes, `close`, and streams without `isatty` or that fail."""

from __future__ import annotations

import sys

import pytest

from m3t1r.io import progress as progress_module
from m3t1r.io.progress import Progress, set_quiet


class Clock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Stream:
    def __init__(self, tty: bool) -> None:
        self.tty = tty
        self.writes: list[str] = []
        self.flushes = 0

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> None:
        self.writes.append(text)

    def flush(self) -> None:
        self.flushes += 1


@pytest.fixture()
def clock(monkeypatch) -> Clock:
    fake = Clock()
    monkeypatch.setattr(progress_module.time, "monotonic", fake)
    set_quiet(False)
    yield fake
    set_quiet(False)


def _at(clock: Clock, progress: Progress, t: float, done: int, note: str | None = None) -> None:
    clock.now = 100.0 + t
    progress.update(done, note)


def test_plain_lines_after_the_delay_and_every_5_s(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 1.999, 1)
    assert stream.writes == []
    _at(clock, progress, 2.0, 1, note="cost 3")  # exactly the delay: shown
    assert stream.writes == ["fit: 1/10 (2 s, about 18 s left) cost 3\n"] and stream.flushes == 1
    _at(clock, progress, 2.1, 2)
    _at(clock, progress, 6.999, 2)
    assert len(stream.writes) == 1
    _at(clock, progress, 7.0, 2)  # exactly the interval after the last line
    assert stream.writes[-1] == "fit: 2/10 (7 s, about 28 s left) cost 3\n"
    clock.now = 109.0
    progress.advance(8)
    progress.close()
    assert stream.writes[-1] == "fit: 10/10 (9 s) cost 3\n"


def test_terminal_bar_every_tenth_of_a_second_and_a_final_newline(clock):
    stream = Stream(tty=True)
    progress = Progress("fit", total=4, stream=stream)
    _at(clock, progress, 2.0, 1, note="x")
    expected = "\rfit: [" + "#" * 6 + "-" * 18 + "] 1/4 (2 s, about 6 s left) x"
    assert stream.writes == [expected.ljust(80)]
    _at(clock, progress, 2.05, 2)  # within 0.1 s of the last line
    assert len(stream.writes) == 1
    _at(clock, progress, 2.2, 3)
    assert stream.writes[-1] == ("\rfit: [" + "#" * 18 + "-" * 6 + "] 3/4 (2 s, about 1 s left) x").ljust(80)
    clock.now = 103.0
    progress.advance(note="done")
    progress.close()
    assert stream.writes[-1] == ("\rfit: [" + "#" * 24 + "] 4/4 (3 s) done").ljust(80) + "\n"


def test_terminal_lines_are_cut_at_200_characters(clock):
    stream = Stream(tty=True)
    progress = Progress("L" * 300, total=None, stream=stream)
    _at(clock, progress, 2.0, 5)
    assert stream.writes == ["\r" + "L" * 199]


def test_without_total_a_count_only(clock):
    terminal, plain = Stream(tty=True), Stream(tty=False)
    for stream in (terminal, plain):
        progress = Progress("poses", stream=stream)
        clock.now = 100.0
        progress.start = 100.0
        progress.advance()
        progress.advance(2)
        _at(clock, progress, 2.0, progress.done + 2)
    assert terminal.writes == ["\rposes: 5 (2 s)".ljust(80)]
    assert plain.writes == ["poses: 5 (2 s)\n"]


def test_an_overrun_total_shows_a_full_bar_without_estimate(clock):
    plain, terminal = Stream(tty=False), Stream(tty=True)
    for stream in (plain, terminal):
        clock.now = 100.0
        _at(clock, Progress("fit", total=2, stream=stream), 3.0, 5)
    assert plain.writes == ["fit: 5/2 (3 s)\n"]
    assert terminal.writes == [("\rfit: [" + "#" * 24 + "] 5/2 (3 s)").ljust(80)]


def test_nothing_done_yet_has_no_estimate(clock):
    stream = Stream(tty=False)
    _at(clock, Progress("fit", total=10, stream=stream), 2.0, 0)
    assert stream.writes == ["fit: 0/10 (2 s)\n"]


def test_the_bar_rounds_its_filled_part_down(clock):
    stream = Stream(tty=True)
    _at(clock, Progress("fit", total=25, stream=stream), 2.0, 24)  # 23.04 of 24 cells
    assert stream.writes == [("\rfit: [" + "#" * 23 + "-] 24/25 (2 s, about 0 s left)").ljust(80)]


def test_explicit_interval(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream, delay=0.5, interval=1.0)
    _at(clock, progress, 0.4, 1)
    _at(clock, progress, 0.5, 1)
    _at(clock, progress, 1.4, 2)
    _at(clock, progress, 1.5, 3)
    assert [line.split(" (")[0] for line in stream.writes] == ["fit: 1/10", "fit: 3/10"]


def test_a_quick_loop_shows_nothing_even_at_close(clock):
    stream = Stream(tty=True)
    with Progress("quick", total=3, stream=stream) as progress:
        _at(clock, progress, 1.0, 3)
    assert stream.writes == [] and stream.flushes == 0


def test_quiet_silences_updates_and_close(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 2.0, 1)
    set_quiet(True)
    _at(clock, progress, 9.0, 2)
    progress.close()
    assert len(stream.writes) == 1


def test_a_stream_without_isatty_gets_plain_lines(clock):
    class Bare:
        def __init__(self) -> None:
            self.text = ""

        def write(self, text):
            self.text += text

        def flush(self):
            pass

    stream = Bare()
    progress = Progress("fit", total=10, stream=stream)
    assert progress.tty is False and progress.interval == 5.0
    _at(clock, progress, 2.0, 1)
    assert stream.text == "fit: 1/10 (2 s, about 18 s left)\n"


def test_default_stream_is_stderr(clock, capsys):
    progress = Progress("fit", total=10)
    assert progress.stream is sys.stderr
    _at(clock, progress, 2.0, 1)
    assert capsys.readouterr().err == "fit: 1/10 (2 s, about 18 s left)\n"


def test_a_failing_stream_is_ignored_and_never_counts_as_shown(clock):
    class Closed(Stream):
        def write(self, text):
            raise ValueError("I/O operation on closed file")

    stream = Closed(tty=False)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 2.0, 1)
    progress.close()
    assert progress._shown is False
