"""The identifier node identifies from cycles received on ``limit_cycles`` over real DDS: a
replay of only a bag's recorded cycles (graph ``replay_cycles``) gives what `piezo-stage
identify --source cycles` gives on the same bag; cycles published by a test node give the ch. 9
parameters back; every unusable cycle is refused with its reason on /diagnostics and in the
log."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from piezo_stage.cli import main
from piezo_stage.identification.cycles import extract_cycle
from piezo_stage.identification.synthetic import CH9_EXAMPLE, triangle_pair
from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.nodes.qos import COMMAND_QOS, LATCHED_QOS
from piezo_stage.nodes.runtime import MATCH_SETTLE

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
NS = "/cycles"
CH9 = BoucWenParameters(**CH9_EXAMPLE)
NAMES = ("y0", "kappa_w", "rho", "sigma", "n")


@pytest.mark.slow
def test_replaying_only_the_cycles_gives_what_identify_gives_on_them(tmp_path, capsys):
    bag = ROOT / "bags" / "ch10_identification"
    assert main(["identify", str(bag), "--source", "cycles", "--degree", "2", "--json"]) == 0
    offline = json.loads(capsys.readouterr().out)
    out_file = tmp_path / "replayed.yaml"
    cmd = [sys.executable, "-m", "piezo_stage.cli", "launch", "replay_cycles", "--color", "never"]
    proc = subprocess.run(
        [*cmd, "--param", f"identifier.output_file:={out_file}"],
        cwd=tmp_path,  # the graph's bag is found in the repository from any folder
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stdout[-4000:]
    assert "identifier exited with code 0" in proc.stdout
    assert proc.stdout.count("holding limit cycle") == 2 and "refused" not in proc.stdout
    p = load_parameter_set(out_file).bouc_wen
    assert list(p.kappa) == pytest.approx(offline["kappa"], rel=1e-9)
    for name in NAMES:
        assert getattr(p, name) == pytest.approx(offline[name], rel=1e-9), name
    assert p.input_sign == offline["input_sign"]


def _cycle_msg(offset: float, period: float, inputs, outputs, stamp: float = 1.0):
    from piezo_stage_msgs.msg import LimitCycle

    msg = LimitCycle(offset=float(offset), period=float(period))
    msg.input = [float(v) for v in inputs]
    msg.output = [float(v) for v in outputs]
    msg.header.stamp.sec = int(stamp)
    return msg


@pytest.fixture(scope="module")
def ch9_cycles():
    a, b = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=300, periods=3)
    return [(0.0, extract_cycle(a)), (0.1, extract_cycle(b))]


def _publish_when_matched(node, pub, msgs) -> None:
    assert spin_until(node, lambda: pub.get_subscription_count() > 0, 60.0)
    spin_until(node, lambda: False, MATCH_SETTLE)  # both sides of the match settled
    for k, msg in enumerate(msgs):
        msg.header.stamp.sec = 1 + k
        pub.publish(msg)


def test_two_published_cycles_of_the_ch9_example_give_its_parameters(node, ch9_cycles):
    from piezo_stage_msgs.msg import BoucWenParameters as ParamsMsg
    from piezo_stage_msgs.msg import LimitCycle

    proc = start_node("identifier", "degree:=1", namespace=NS)  # cycles_from both (default)
    try:
        params: list = []
        node.create_subscription(ParamsMsg, "bouc_wen_parameters", params.append, LATCHED_QOS)
        pub = node.create_publisher(LimitCycle, "limit_cycles", COMMAND_QOS)
        msgs = [_cycle_msg(q, c.period, c.input, c.output) for q, c in ch9_cycles]
        _publish_when_matched(node, pub, msgs)
        if not spin_until(node, lambda: bool(params), 60.0):
            raise AssertionError(f"no parameters; node log:\n{stop(proc)[1][-3000:]}")
    finally:
        _, err = stop(proc)
    got = params[0]
    assert got.kappa[0] == pytest.approx(CH9.kappa[0], rel=1e-8)
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert getattr(got, name) == pytest.approx(getattr(CH9, name), rel=1e-8), name
    assert abs(got.y0) < 1e-8 and got.input_sign == 1
    assert got.samples == sum(len(c.input) for _, c in ch9_cycles)  # from the cycles
    assert err.count("holding limit cycle") == 2, err[-3000:]


def _bad(ch9_cycles, case: str):
    """(messages to publish, the reason the last one is refused with)."""
    q, c = ch9_cycles[0]
    v, y = np.asarray(c.input), np.asarray(c.output)
    wiggle = v.copy()
    i = len(v) // 4
    wiggle[i : i + 20] = wiggle[i - 20]
    wiggle[i + 20 : i + 40] += 0.3 * np.ptp(v)
    nan = y.copy()
    nan[3] = np.nan
    good = _cycle_msg(q, c.period, v, y)
    return {
        "lengths": ([_cycle_msg(q, c.period, v, y[:-1])], "same instants"),
        "non-finite samples": ([_cycle_msg(q, c.period, v, nan)], "NaN or inf"),
        "period": ([_cycle_msg(q, float("inf"), v, y)], "period inf"),
        "offset": ([_cycle_msg(float("nan"), c.period, v, y)], "offset nan"),
        "not a T-wave": ([_cycle_msg(q, c.period, wiggle, y)], "not a T-wave"),
        "same offset": ([good, _cycle_msg(q, c.period, v, 1.01 * y)], "already held"),
    }[case]


@pytest.mark.parametrize(
    "case", ["lengths", "non-finite samples", "period", "offset", "not a T-wave", "same offset"]
)
def test_an_unusable_cycle_is_refused_with_its_reason(node, ch9_cycles, case):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from piezo_stage_msgs.msg import BoucWenParameters as ParamsMsg
    from piezo_stage_msgs.msg import LimitCycle

    space = f"{NS}_{case.replace(' ', '_').replace('-', '_')}"
    proc = start_node("identifier", "cycles_from:=topic", namespace=space)
    statuses: list = []
    try:
        pub = node.create_publisher(LimitCycle, f"{space}/limit_cycles", COMMAND_QOS)
        params: list = []
        node.create_subscription(
            ParamsMsg, f"{space}/bouc_wen_parameters", params.append, LATCHED_QOS
        )
        node.create_subscription(
            DiagnosticArray,
            "/diagnostics",
            lambda m: statuses.extend(s for s in m.status if s.name == f"{space}/identifier"),
            10,
        )
        msgs, why = _bad(ch9_cycles, case)
        _publish_when_matched(node, pub, msgs)
        assert spin_until(
            node,
            lambda: any(s.level == DiagnosticStatus.WARN and why in s.message for s in statuses),
            30.0,
        ), [s.message for s in statuses]
        values = {kv.key: kv.value for kv in statuses[-1].values}
        assert values["refused_cycles"] == "1"
        assert values["held_cycles"] == str(len(msgs) - 1)
        assert not params  # nothing identified
    finally:
        _, err = stop(proc)
    assert "refused" in err and why in err, err[-3000:]


def test_a_cycle_arriving_during_the_identification_starts_no_second_one(node, ch9_cycles):
    """The identification of a held pair runs beside the executor; a further usable cycle (a
    third offset) that arrives meanwhile is held, and the pair is identified once."""
    import threading
    import time

    from rclpy.executors import SingleThreadedExecutor

    import piezo_stage.nodes.identifier as module
    from piezo_stage_msgs.msg import LimitCycle

    calls, release = [], threading.Event()
    identify_cycle_pair = module.identify_cycle_pair

    def held(*args, **kwargs):
        calls.append(time.monotonic())
        release.wait(15.0)
        return identify_cycle_pair(*args, **kwargs)

    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(module, "identify_cycle_pair", held)
    identifier = module.IdentifierNode()
    executor = SingleThreadedExecutor()
    executor.add_node(identifier)
    executor.add_node(node)

    def spin_for(condition, seconds: float) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not condition():
            executor.spin_once(timeout_sec=0.01)
        return condition()

    try:
        pub = node.create_publisher(
            LimitCycle, f"{identifier.get_namespace()}/limit_cycles", COMMAND_QOS
        )
        assert spin_for(lambda: pub.get_subscription_count() > 0, 60.0)
        spin_for(lambda: False, 0.5)
        (q0, a), (q1, b) = ch9_cycles
        third = _cycle_msg(2 * q1 - q0, b.period, np.asarray(b.input) + (q1 - q0), b.output)
        for k, msg in enumerate(
            [
                _cycle_msg(q0, a.period, a.input, a.output),
                _cycle_msg(q1, b.period, b.input, b.output),
            ]
        ):
            msg.header.stamp.sec = 1 + k
            pub.publish(msg)
        assert spin_for(lambda: bool(calls), 30.0), "the identification never started"
        third.header.stamp.sec = 3
        pub.publish(third)
        assert spin_for(lambda: len(identifier._cycles.held) == 3, 10.0)
        release.set()
        assert spin_for(lambda: identifier.result is not None, 30.0)
        spin_for(lambda: False, 0.5)
        assert len(calls) == 1, calls
    finally:
        release.set()
        monkeypatch.undo()
        executor.remove_node(identifier)
        identifier.destroy_node()


def test_a_replay_that_never_reaches_the_identifier_ends_with_what_it_listened_to():
    """``on_done: exit`` with ``wait_timeout``: nothing received within it is a failure (exit 1)
    naming the topic and its publishers, not a run that waits for ever."""
    proc = start_node(
        "identifier",
        "cycles_from:=topic",
        "on_done:=exit",
        "wait_timeout:=1.0",
        namespace="/never_fed",
    )
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        out, err = stop(proc)
    err = out + err
    assert proc.returncode == 1, err[-3000:]
    line = next(x for x in err.splitlines() if "identification failed" in x)
    assert "nothing received within wait_timeout = 1 s on /never_fed/limit_cycles" in line, err
    assert "(0 publisher(s))" in line, line
