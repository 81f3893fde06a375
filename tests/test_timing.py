"""The one timing helper of benchmarks and latency studies: warm-up excluded, median or minimum."""

import time

import pytest

from metadesign.timing import repeat_seconds


def test_warm_up_is_excluded_and_the_statistic_is_chosen():
    calls = []

    def fn():  # the warm-up call is slow, then 10, 1, 10, 10, 10 ms
        k = len(calls)
        calls.append(k)
        time.sleep([0.2, 0.01, 0.001, 0.01, 0.01, 0.01][k])

    med = repeat_seconds(fn, 5)
    assert len(calls) == 6 and 0.009 <= med < 0.1
    calls.clear()
    assert 0.0009 <= repeat_seconds(fn, 5, stat="min") < 0.009
    synced = []
    repeat_seconds(lambda: None, 3, sync=lambda: synced.append(1))
    assert len(synced) == 4
    with pytest.raises(ValueError):
        repeat_seconds(fn, 1, stat="mean")
