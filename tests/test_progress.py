"""Progress off a terminal (a log file, CI): a line every interval with the rate and the time left, a last
line for runs that printed any, silence for short runs."""

import io

from metadesign.cliutil import progress_bar


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_progress_lines_at_intervals_off_a_terminal():
    out, clock = io.StringIO(), Clock()
    cb = progress_bar("dataset", "sample", stream=out, interval=30, clock=clock)
    for done in range(0, 101, 5):  # 5 samples per 10 s: 0.5 sample/s
        cb(done, 100)
        clock.t += 10
    lines = out.getvalue().splitlines()
    # t = 30, 60, ..., 180 s pass the interval (6 lines), then the end line at t = 200 s
    assert len(lines) == 7, lines
    assert lines[0].startswith("dataset: 15/100 samples (15 %), 30 s elapsed, 0.5 samples/s; about 2.8 min left")  # (100 - 15) / 0.5 = 170 s
    assert lines[-1].startswith("dataset: 100/100 samples (100 %)") and lines[-1].endswith("done")


def test_short_runs_print_nothing_off_a_terminal():
    out, clock = io.StringIO(), Clock()
    cb = progress_bar("evaluate", "sample", stream=out, interval=30, clock=clock)
    for done in range(11):
        cb(done, 10)
        clock.t += 1
    assert out.getvalue() == ""
