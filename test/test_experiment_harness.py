"""The experiments' harness (piezo_stage.experiments.harness): stamps read in place from CDR of
either byte order, controller_state decoded into typed columns, the stop rules, a bag written
from a recording; a graph that cannot start fails with its nodes' output."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from piezo_stage.bag.reader import read_messages
from piezo_stage.experiments.harness import (
    ControllerStates,
    HarnessError,
    Recording,
    Stream,
    node_overrides,
    record,
    samples,
    span,
    stamp_ns,
)
from piezo_stage_msgs.msg import ControllerState

pytestmark = pytest.mark.ros


def state(ns: int, x1: float, closed: bool = True) -> bytes:
    msg = ControllerState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
    msg.x1, msg.reference, msg.u, msg.u_ff, msg.loop_closed = x1, 1e-5, 100.0 + x1, 7.0, closed
    return serialize_message(msg)


def test_stamps_are_read_in_place_in_either_byte_order():
    data = state(12_345_678_901, 0.0)
    assert stamp_ns(data) == 12_345_678_901
    big = bytearray(data)  # the same stamp in a big-endian encapsulation
    big[1] = 0
    big[4:8] = (12).to_bytes(4, "big")
    big[8:12] = (345_678_901).to_bytes(4, "big")
    assert stamp_ns(bytes(big)) == 12_345_678_901


def test_controller_state_decodes_into_typed_columns_and_the_stop_rules_count_right():
    raw = [
        (1_000_000_000 + k * 1_000_000, state(1_000_000_000 + k * 1_000_000, k * 1e-9, k > 0))
        for k in range(5)
    ]
    states = ControllerStates.decode(raw)
    assert np.allclose(states.t, 1.0 + np.arange(5) * 1e-3)
    assert np.allclose(states.x, np.arange(5) * 1e-9 + 1e-5) and np.all(states.u_ff == 7.0)
    assert states.loop_closed.dtype == bool and list(states.loop_closed) == [False] + [True] * 4
    relative = Recording("/ns", {"controller_state": raw}, 1.0).states(relative=True)
    assert relative.t[0] == 0.0 and set(states.as_dict()) >= {"t", "x1", "u_ff", "loop_closed"}
    rec = {"controller_state": raw}
    assert samples("controller_state", 5)(rec) and not samples("controller_state", 6)(rec)
    assert span("controller_state", 0.004)(rec) and not span("controller_state", 0.0041)(rec)
    assert not span("controller_state", 0.001)({"controller_state": []})
    assert ControllerStates.decode([]).t.size == 0


def test_a_recording_writes_a_bag_under_its_namespace(tmp_path):
    raw = [(k * 1_000_000, state(k * 1_000_000, 0.0)) for k in (2, 1, 3)]
    recording = Recording("/ns", {"controller_state": raw}, 1.0)
    recording.write_bag(
        tmp_path / "bag", {"controller_state": "piezo_stage_msgs/msg/ControllerState"}, sort=True
    )
    got = list(read_messages(tmp_path / "bag"))
    assert [topic for topic, _, _ in got] == ["/ns/controller_state"] * 3
    assert [ns for _, ns, _ in got] == [1_000_000, 2_000_000, 3_000_000]


def test_a_graph_that_cannot_start_fails_with_its_nodes_output():
    graph = {
        "namespace": "/harness_fail",
        "nodes": [
            {"executable": "controller", "required": True, "overrides": {"compensation": "both"}}
        ],
    }  # no feedforward_model: exits 2 at start
    with pytest.raises(HarnessError) as err:
        record(
            graph,
            [Stream("controller_state", ControllerState)],
            samples("controller_state", 1),
            launch_timeout=20.0,
            wall_timeout=20.0,
        )
    assert "feedforward_model" in err.value.with_output(40)


def test_overrides_are_checked_against_the_nodes_table_before_a_graph_starts():
    from piezo_stage.experiments.errors import ExperimentInputError

    assert node_overrides("controller", {"learn_periods": 3}) == {"learn_periods": 3}
    with pytest.raises(ExperimentInputError, match="learn_periods"):
        node_overrides("controller", {"learn_period": 3})
    with pytest.raises(ExperimentInputError, match="feedforward_form"):
        node_overrides("controller", {"feedforward_form": "exact"})


def _excited_plant(namespace: str, excitation: dict) -> dict:
    """A real-time plant at 1 kHz driven by an excitation (timer trigger, wall clock)."""
    return {
        "namespace": namespace,
        "nodes": [
            {"executable": "plant", "overrides": {"clock_mode": "realtime", "rate_hz": 1000.0}},
            {
                "executable": "excitation",
                "overrides": {"trigger": "timer", "rate_hz": 1000.0, "period": 0.1, **excitation},
            },
        ],
    }


def test_a_start_gate_starts_the_excitation_once_the_record_flows():
    """With ``autostart: false`` the excitation waits for the gate: its first mark comes after
    the samples the gate asked for had reached the recorder, however late the sensor starts."""
    from piezo_stage.experiments.harness import StartGate
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo

    least = 300
    recording = record(
        _excited_plant("/harness_gate", {"autostart": False}),
        [
            Stream("displacement", Displacement, reliable=False),
            Stream("excitation", ExcitationInfo),
        ],
        samples("excitation", 3),
        launch_timeout=30.0,
        wall_timeout=60.0,
        data_timeout=30.0,
        start=StartGate(("excitation/start",), samples("displacement", least)),
    )
    displacement, marks = recording.raw["displacement"], recording.raw["excitation"]
    assert len(displacement) >= least
    assert marks[0][0] > displacement[least - 1][0]


def test_a_start_gate_whose_service_never_answers_fails_the_run():
    from piezo_stage.experiments.harness import StartGate
    from piezo_stage_msgs.msg import Displacement

    with pytest.raises(HarnessError, match="did not start within 3 s"):
        record(
            _excited_plant("/harness_gate_missing", {"autostart": False}),
            [Stream("displacement", Displacement, reliable=False)],
            samples("displacement", 10**9),
            launch_timeout=30.0,
            wall_timeout=60.0,
            data_timeout=3.0,
            required=(),  # the gate's own timeout, however late a loaded host's plant publishes
            start=StartGate(("no_such_node/start",), samples("displacement", 1)),
        )
