"""The graph benchmark's host steal time: the share of all CPU time, between two readings of
/proc/stat's first line, that the virtual machine's host gave to something else."""

from __future__ import annotations

import pytest

pytest.importorskip("fluxdrive_bringup")


def test_steal_is_the_share_of_all_cpu_time_between_two_readings():
    from fluxdrive_bringup.measure.bench import steal_pct

    # 2 CPUs x 100 jiffies/s x 5 s = 1000 jiffies, 50 of them stolen: 5 %
    assert steal_pct((120, 40_000), (170, 41_000)) == 5.0
    assert steal_pct((0, 0), (0, 1000)) == 0.0
    assert steal_pct(None, (1, 2)) is None  # no /proc/stat (not Linux)
    assert steal_pct((5, 100), (5, 100)) is None  # no time passed


def test_this_machine_reports_steal_and_total_in_order():
    from fluxdrive_bringup.measure.bench import host_cpu_times

    t = host_cpu_times()  # Linux, the project's only platform: /proc/stat is there
    assert t is not None
    steal, total = t
    assert 0 <= steal <= total
