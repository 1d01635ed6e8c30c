"""The driver's pacing on a clock the test owns: at ``rate > 0`` a stalled driver does not
send its backlog in one burst (best-effort readers drop it), and no set is skipped; at
``rate: 0`` it waits for the tensor node."""
from __future__ import annotations

import numpy as np
from ros_helpers import unique_domain

RATE = 8.0
SAMPLE_RATE_HZ = 20.0  # the default scenario's


def _driver(context):
    from rclpy.parameter import Parameter

    from tetra_gradiometer.nodes.driver import DriverNode

    return DriverNode(parameter_overrides=[
        Parameter('mode', value='sim'), Parameter('rate', value=RATE),
        Parameter('max_duration_s', value=30.0), Parameter('start_paused', value=True)],
        context=context)


def test_a_stalled_driver_restarts_its_pacing_instead_of_bursting_and_skips_no_set(monkeypatch):
    import rclpy

    from tetra_gradiometer.nodes import driver as driver_module

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain())
    node = _driver(context)
    try:
        # Every set of the mission, in order, as the simulator makes them (no pacing).
        expected = [f.mag1_stamp for f in [node._next, *node._frames] if f.mag1_stamp is not None]
        node.destroy_node()  # its frames consumed above: a fresh driver plays them
        node = _driver(context)
        published: list[list[int]] = []
        monkeypatch.setattr(node, '_publish', lambda frame: published[-1].append(frame.mag1_stamp)
                            if frame.mag1_stamp is not None else None)
        now = [1000.0]
        monkeypatch.setattr(driver_module.time, 'monotonic', lambda: now[0])
        from std_srvs.srv import Trigger

        assert node._on_resume(Trigger.Request(), Trigger.Response()).success
        stall_tick = 15
        for tick in range(400):
            now[0] += 1.0 if tick == stall_tick else 0.05  # a 1 s stall of the process
            published.append([])
            node._tick()
            if node.state == 'finished':
                break
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)

    per_tick = np.array([len(p) for p in published])
    due_per_tick = RATE * SAMPLE_RATE_HZ * 0.05  # 8 sets every 0.05 s
    played = np.array([s for p in published for s in p])
    # Every set once, in order (the stamps start at each driver's start time: compared from it).
    np.testing.assert_array_equal(played - played[0], np.array(expected) - expected[0])
    assert np.all(per_tick[5:stall_tick] <= due_per_tick + 1)  # paced before the stall
    # The stall's tick sends at most the catch-up allowance, not the second's 160 sets.
    allowance = driver_module.MAX_CATCH_UP_S * RATE * SAMPLE_RATE_HZ
    assert per_tick[stall_tick] <= allowance + 1, per_tick[stall_tick]
    assert np.all(per_tick[stall_tick + 1:] <= due_per_tick + 1)
    assert node.pace_restarts == 1


def test_at_rate_0_the_driver_waits_for_the_tensor_node(monkeypatch):
    """``rate: 0``: at most 4 sets ahead of the last gradient/raw received; 0.5 s without one,
    the driver moves on and counts a timeout (WARN)."""
    from in_process import node_in_process

    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.io.scenario import load_scenario_or_default
    from tetra_gradiometer.nodes import driver as driver_module
    from tetra_gradiometer.nodes.driver import DriverNode

    now = [1000.0]
    monkeypatch.setattr(driver_module.time, 'monotonic', lambda: now[0])
    types = cv.rclpy_types()

    def back(stamp: int):
        return gt.gradient_tensor_msg(types, gt.TensorSet(stamp, np.zeros((3, 3))))

    with node_in_process(DriverNode, monkeypatch, mode='sim', rate=0.0, max_duration_s=5.0) as (node, published):
        def sets() -> list[int]:  # mag1 stamps published so far, ns
            return [cv.stamp_to_ns(m.header.stamp) for t, m in published if t == '/tetra/mag1']

        node._tick()
        assert len(sets()) == 4  # the window: nothing came back yet
        now[0] += 0.4
        node._tick()
        assert len(sets()) == 4
        node._on_ack(back(sets()[1]))  # the tensor node gave sets 1 and 2 back: two more go
        assert len(sets()) == 6 and node.ack_timeouts == 0
        now[0] += 0.6  # nothing back: the driver moves on, a window at a time, and says so
        node._tick()
        assert len(sets()) == 10 and node.ack_timeouts == 1
        node._publish_diagnostics()
        (array,) = [m for t, m in published if t == '/diagnostics'][-1:]
        (playback,) = [s for s in array.status if s.name.endswith('playback')]
        assert playback.level == bytes([driver_module.WARN])
        assert {v.key: v.value for v in playback.values}['ack_timeouts'] == '1'
    # Every set once, in sample order (the built-in scenario's sample period apart).
    scenario, _ = load_scenario_or_default()
    np.testing.assert_allclose(np.diff(sets()), 1e9 / scenario.sample_rate_hz, rtol=0, atol=1)
