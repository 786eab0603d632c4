"""The identifier node over real DDS: limit cycles per run, parameters latched, equal to the
offline identification of the same samples."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy

from piezo_stage.identification.io import intervals_from_marks, recordings_from_series
from piezo_stage.identification.pipeline import IdentifyOptions, identify
from piezo_stage.identification.synthetic import CH9_EXAMPLE, triangle_run
from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.nodes.qos import COMMAND_QOS, LATCHED_QOS

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/ident"


def _stamp(msg, t):
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = int(round((t - int(t)) * 1e9))
    return msg


def _two_runs(period: float = 1.0, t0: float = 10.0):
    """Samples (t, v, y) of x(t) then x(t)+q (q = 0.1), three periods each, and the excitation's
    marks (stamp, run, steady) as the excitation node sends them."""
    true = BoucWenParameters(**CH9_EXAMPLE)
    runs = []
    for k, q in enumerate((0.0, 0.1)):  # x(t) then x(t)+q, one after the other
        rec = triangle_run(
            true, -0.2 + q, 0.2 + q, period=period, samples_per_branch=300, periods=3.0
        )
        runs.append((rec.t + t0 + (3.0 + 1e-3) * k, rec.input, rec.output))  # no shared stamp
    t = np.concatenate([r[0] for r in runs])
    v = np.concatenate([r[1] for r in runs])
    y = np.concatenate([r[2] for r in runs])
    t1 = runs[1][0][0]  # run 1 starts with its first sample, as the excitation node marks it
    marks = [
        (t0, 0, False),
        (t0 + 1.0, 0, True),
        (t1, 1, False),
        (t1 + 1.0, 1, True),
        (t1 + 3.0, 1, False),
    ]
    return t, v, y, marks


def _publish_runs(spin, pub_v, pub_y, pub_e, t, v, y, marks, period: float = 1.0) -> None:
    """The samples with the marks interleaved at their stamps, then the plan's end mark;
    ``spin()`` every 200 samples."""
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    def mark(stamp: float, run: int, steady: bool) -> None:
        info = ExcitationInfo(
            waveform="triangle", period=period, amplitude=0.4, offset=0.1 * run, run=run
        )
        info.steady = steady
        pub_e.publish(_stamp(info, stamp))

    pending = iter(marks[:-1])
    next_mark = next(pending)
    for i in range(len(t)):
        while next_mark is not None and next_mark[0] <= t[i]:
            mark(*next_mark)
            next_mark = next(pending, None)
        pub_v.publish(_stamp(Voltage(voltage=float(v[i])), t[i]))
        pub_y.publish(_stamp(Displacement(displacement=float(y[i]), status=0), t[i]))
        if i % 200 == 0:
            spin()
    mark(*marks[-1])


def test_identifier_publishes_cycles_and_parameters_equal_to_offline(node, tmp_path):
    from piezo_stage_msgs.msg import BoucWenParameters as ParamsMsg
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, LimitCycle, Voltage

    period = 1.0
    t, v, y, marks = _two_runs(period)

    out_file = tmp_path / "identified.yaml"
    proc = start_node(
        "identifier", f"output_file:={out_file}", namespace=NS
    )  # stream_qos auto: reliable here
    try:
        reliable = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        pub_v = node.create_publisher(Voltage, "voltage", reliable)
        pub_y = node.create_publisher(Displacement, "displacement", reliable)
        pub_e = node.create_publisher(ExcitationInfo, "excitation", COMMAND_QOS)
        cycles, params = [], []
        node.create_subscription(LimitCycle, "limit_cycles", cycles.append, COMMAND_QOS)
        node.create_subscription(ParamsMsg, "bouc_wen_parameters", params.append, LATCHED_QOS)
        assert spin_until(
            node,
            lambda: (
                pub_v.get_subscription_count()
                and pub_y.get_subscription_count()
                and pub_e.get_subscription_count()
            ),
            60.0,  # the node imports scipy and numba: slow on a loaded host
        )
        spin_until(
            node, lambda: False, 1.0
        )  # both sides of the match settled: no early sample lost
        _publish_runs(
            lambda: rclpy.spin_once(node, timeout_sec=0),
            pub_v,
            pub_y,
            pub_e,
            t,
            v,
            y,
            marks,
            period,
        )
        ok = spin_until(node, lambda: len(params) == 1, 60.0)
        if not ok:
            out, err = stop(proc)
            raise AssertionError(
                f"no parameters published; cycles {len(cycles)}; node log:\n{err[-3000:]}"
            )
        assert len(cycles) == 2 and [c.offset for c in cycles] == [0.0, 0.1]
        assert cycles[0].period == pytest.approx(period, rel=1e-3)
        assert max(cycles[1].input) - max(cycles[0].input) == pytest.approx(0.1, rel=1e-3)

        stamped = np.array(
            [
                (m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec)
                for m in (_stamp(Voltage(), ti) for ti in t)
            ]
        )  # what the node receives
        recs = recordings_from_series(
            stamped,
            v,
            stamped,
            y,
            np.zeros(len(t), np.uint8),
            intervals_from_marks([(m[0], m[1]) for m in marks]),
            "offline",
        )
        offline = identify(recs[0], recs[1], IdentifyOptions())
        got = params[0]
        p = offline.parameters
        assert got.samples == offline.samples
        assert list(got.kappa) == pytest.approx(list(p.kappa), rel=1e-9)
        for name in ("kappa_w", "rho", "sigma", "n", "y0"):
            assert getattr(got, name) == pytest.approx(getattr(p, name), rel=1e-9, abs=1e-15), name
        assert (
            got.input_sign == 1 and got.input_name == "voltage" and got.samples == offline.samples
        )
        for name, value in (("kappa_w", 2.0), ("rho", 1.0), ("sigma", 3.0), ("n", 1.5)):
            assert getattr(got, name) == pytest.approx(value, rel=1e-4)
        assert out_file.exists() and "kappa_w" in out_file.read_text()
    finally:
        _, err = stop(proc)
    # its own cycles came back on limit_cycles (cycles_from both): known as its own, neither
    # held as received cycles nor refused as a second cycle at a held offset
    assert "holding limit cycle" not in err and "refused" not in err, err[-3000:]


def test_identifier_keeps_collecting_while_it_identifies(node, monkeypatch):
    """The automatic identification runs beside the node's executor: samples that arrive
    meanwhile are taken and /diagnostics says ``identifying`` (a fit takes a minute or more on
    a small PC; a node blocked in it was deaf to its streams and to a stop for that long)."""
    from rclpy.executors import SingleThreadedExecutor

    import piezo_stage.nodes.identifier as module
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    started, release = threading.Event(), threading.Event()
    identify_runs = module.identify_runs

    def held_identification(*args, **kwargs):
        started.set()
        release.wait(15.0)  # bounded: a node that blocks its executor here still ends the test
        return identify_runs(*args, **kwargs)

    monkeypatch.setattr(module, "identify_runs", held_identification)
    identifier = module.IdentifierNode()
    said: list[str] = []
    logger = identifier.get_logger()

    class Said:  # the node's logger, keeping what it says at info
        def info(self, text: str) -> None:
            said.append(text)
            logger.info(text)

        def __getattr__(self, name: str):
            return getattr(logger, name)

    identifier.get_logger = Said  # type: ignore[method-assign]
    executor = SingleThreadedExecutor()
    executor.add_node(identifier)
    executor.add_node(node)
    ns = identifier.get_namespace()
    try:
        reliable = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        pub_v = node.create_publisher(Voltage, f"{ns}/voltage", reliable)
        pub_y = node.create_publisher(Displacement, f"{ns}/displacement", reliable)
        pub_e = node.create_publisher(ExcitationInfo, f"{ns}/excitation", COMMAND_QOS)

        def spin_for(condition, seconds: float) -> bool:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                if condition():
                    return True
                executor.spin_once(timeout_sec=0.01)
            return condition()

        assert spin_for(
            lambda: pub_v.get_subscription_count() and pub_y.get_subscription_count(), 30
        )
        t, v, y, marks = _two_runs()
        _publish_runs(
            lambda: executor.spin_once(timeout_sec=0), pub_v, pub_y, pub_e, t, v, y, marks
        )
        assert spin_for(started.is_set, 30.0), "the identification never started"
        before = identifier._diagnose()
        assert before.message == "identifying", before
        t_late = t[-1] + 1e-3 * (1 + np.arange(50))
        for k in t_late:  # arriving while the identification runs
            pub_v.publish(_stamp(Voltage(voltage=0.0), k))
        taken = lambda: identifier._diagnose().values["voltage_samples"]  # noqa: E731
        assert spin_for(lambda: taken() == before.values["voltage_samples"] + 50, 10.0), (
            "samples that arrived during the identification were not taken before it ended",
            taken(),
            before.values,
        )
        assert not release.is_set()
        release.set()
        assert spin_for(lambda: identifier.result is not None, 30.0)
        assert identifier._diagnose().message == "identified"
        # a user of a small PC sees the wait begin and how long it took
        began = [k for k, text in enumerate(said) if text.startswith("identifying (2 complete")]
        took = [
            k for k, text in enumerate(said) if re.match(r"identification took \d+\.\d s$", text)
        ]
        assert began and took and began[0] < took[0], said
    finally:
        release.set()
        executor.remove_node(identifier)
        identifier.destroy_node()


def test_identifier_adapts_its_stream_qos_to_the_publishers():
    """stream_qos auto (default): reliable while every publisher is (the lockstep plant, a player),
    best effort once a SensorDataQoS publisher (the rig's laser reader) is there, and samples
    flow."""
    from diagnostic_msgs.msg import DiagnosticArray

    from piezo_stage_msgs.msg import Displacement, Voltage

    ns = "/ident_qos"
    rclpy.init()
    node = rclpy.create_node("probe", namespace=ns)
    proc = start_node("identifier", namespace=ns)
    try:

        def sub_reliability(topic: str):
            infos = [
                i
                for i in node.get_subscriptions_info_by_topic(f"{ns}/{topic}")
                if i.node_name == "identifier"
            ]
            return infos[0].qos_profile.reliability if len(infos) == 1 else None

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        node.create_publisher(Voltage, "voltage", reliable)
        pub_y = node.create_publisher(Displacement, "displacement", best_effort)
        assert spin_until(
            node,
            lambda: (
                sub_reliability("voltage") == ReliabilityPolicy.RELIABLE
                and sub_reliability("displacement") == ReliabilityPolicy.BEST_EFFORT
            ),
            30.0,
        ), (sub_reliability("voltage"), sub_reliability("displacement"))
        pub_v2 = node.create_publisher(
            Voltage, "voltage", best_effort
        )  # a publisher that offers less
        assert spin_until(
            node,
            lambda: (
                sub_reliability("voltage") == ReliabilityPolicy.BEST_EFFORT
                and pub_v2.get_subscription_count() == 1
            ),
            30.0,
        ), sub_reliability("voltage")

        counts: dict[str, int] = {}

        def on_diag(msg: DiagnosticArray) -> None:
            for status in msg.status:
                if status.name == f"{ns}/identifier":
                    counts.update(
                        {
                            kv.key: int(kv.value)
                            for kv in status.values
                            if kv.key.endswith("_samples")
                        }
                    )

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
        for k in range(20):
            pub_v2.publish(_stamp(Voltage(voltage=float(k)), 1.0 + 0.01 * k))
            pub_y.publish(_stamp(Displacement(displacement=1e-6 * k, status=0), 1.0 + 0.01 * k))
            spin_until(node, lambda: False, 0.02)
        assert spin_until(
            node,
            lambda: (
                counts.get("voltage_samples", 0) > 0 and counts.get("displacement_samples", 0) > 0
            ),
            15.0,
        ), counts
    finally:
        stop(proc)
        node.destroy_node()
        rclpy.shutdown()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["analytic", "auto"])
def test_identifier_says_when_the_streams_end_with_one_run_only(method, tmp_path):
    """A replay of a bag holding one run: once the streams are silent for settle_time (5 s: a
    publishing loop on a loaded host can pause for more than a second, and the node must not
    decide on part of the run), the node
    with method analytic reports that identification needs two runs (in its log, as an error)
    and, with on_done=exit, exits 1 instead of waiting for ever; with method auto it
    fits the simulated model to the one run, writes the parameters and exits 0."""
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    true = BoucWenParameters(**CH9_EXAMPLE)
    rec = triangle_run(true, -0.2, 0.2, period=1.0, samples_per_branch=100, periods=3.0)
    t = rec.t + 10.0
    marks = [
        (t[0], 0, False),
        (t[0] + 1.0, 0, True),
        (t[-1], 0, False),
    ]  # one run, then the plan's end
    rclpy.init()
    node = rclpy.create_node("probe", namespace=NS + "_one")
    out_file = tmp_path / "one_run.yaml"
    proc = start_node(
        "identifier",
        "on_done:=exit",
        "settle_time:=5.0",
        "stream_qos:=reliable",
        f"method:={method}",
        f"output_file:={out_file}",
        namespace=NS + "_one",
    )
    try:
        reliable = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        pub_v = node.create_publisher(Voltage, "voltage", reliable)
        pub_y = node.create_publisher(Displacement, "displacement", reliable)
        pub_e = node.create_publisher(ExcitationInfo, "excitation", COMMAND_QOS)
        assert spin_until(
            node,
            lambda: (
                pub_v.get_subscription_count()
                and pub_y.get_subscription_count()
                and pub_e.get_subscription_count()
            ),
            60.0,  # the node imports scipy and numba: slow on a loaded host
        )
        spin_until(node, lambda: False, 0.5)
        k = 0
        for i in range(len(t)):
            while k < len(marks) and marks[k][0] <= t[i]:
                pub_e.publish(
                    _stamp(
                        ExcitationInfo(
                            waveform="triangle", period=1.0, run=marks[k][1], steady=marks[k][2]
                        ),
                        marks[k][0],
                    )
                )
                k += 1
            pub_v.publish(_stamp(Voltage(voltage=float(rec.input[i])), t[i]))
            pub_y.publish(_stamp(Displacement(displacement=float(rec.output[i]), status=0), t[i]))
        exited = spin_until(node, lambda: proc.poll() is not None, 60.0)
    finally:
        out, err = stop(proc)
        node.destroy_node()
        rclpy.shutdown()
    assert exited, "the identifier kept waiting"
    assert proc.returncode == (1 if method == "analytic" else 0), err[-3000:]
    if method == "analytic":
        assert (
            "silent for 5 s" in err
            and "1 complete run(s)" in err
            and "needs two steady runs" in err
        ), err[-2000:]
        return
    found = load_parameter_set(out_file).bouc_wen
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert getattr(found, name) == pytest.approx(getattr(true, name), rel=1e-6), name
