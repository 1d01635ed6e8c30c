"""ros_helpers.domain_range: the ROS domains of the pytest-xdist workers of one run are
disjoint, inside 1..100 (never 0, the default every other ROS user on the machine is on, nor
the 101+ manual runs take), and unique_domain stays in its worker's range."""
from __future__ import annotations

import ros_helpers


def test_every_worker_of_a_run_has_its_own_domains(monkeypatch):
    for count in (1, 2, 3, 7, 16):
        seen: set[int] = set()
        for index in range(count):
            monkeypatch.setenv('PYTEST_XDIST_WORKER_COUNT', str(count))
            monkeypatch.setenv('PYTEST_XDIST_WORKER', f'gw{index}')
            domains = set(ros_helpers.domain_range())
            assert domains and min(domains) >= 1 and max(domains) <= 100, (count, index)
            assert not domains & seen, (count, index)
            seen |= domains
            assert {ros_helpers.unique_domain() for _ in range(30)} <= domains
    monkeypatch.delenv('PYTEST_XDIST_WORKER')
    monkeypatch.delenv('PYTEST_XDIST_WORKER_COUNT')
    assert set(ros_helpers.domain_range()) == set(range(1, 101))  # a serial run: all of them
