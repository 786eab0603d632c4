"""The plant node over a stage file, over real DDS: the xy scanner's axes in their namespaces,
stepped together (one stamp per tick on every axis), y's sensor seeing 2 % of x's motion, NaN
commands refused, a stage file that does not load refused with exit 2."""

from __future__ import annotations

import math

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS

from ros_support import ROOT, spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/scanner_sim"  # the probe node's namespace (conftest)
RATE = 100.0


def _ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_x_moves_y_by_the_coupling_and_nan_moves_nothing(node):
    from piezo_stage_msgs.msg import Displacement, Voltage

    proc = start_node("plant", "stage_file:=xy_scanner.yaml", f"rate_hz:={RATE}", namespace=NS)
    xs: dict[str, list] = {"x": [], "y": []}
    vs: dict[str, list] = {"x": [], "y": []}
    diags: list = []
    cmd = {}
    for axis in "xy":
        node.create_subscription(Displacement, f"{axis}/displacement", xs[axis].append, SENSOR_QOS)
        node.create_subscription(Voltage, f"{axis}/voltage", vs[axis].append, SENSOR_QOS)
        cmd[axis] = node.create_publisher(Voltage, f"{axis}/voltage_command", COMMAND_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    try:
        assert spin_until(node, lambda: len(xs["x"]) > 20 and len(xs["y"]) > 20, 60.0)
        assert spin_until(node, lambda: cmd["x"].get_subscription_count() == 1, 30.0)
        # refused: NaN on x, inf on y; both hold 0 V and neither moves
        cmd["x"].publish(Voltage(voltage=math.nan))
        cmd["y"].publish(Voltage(voltage=math.inf))
        spin_until(node, lambda: False, 0.5)
        for axis in "xy":
            assert vs[axis][-1].voltage == 0.0
            assert xs[axis][-1].displacement == 0.0 and xs[axis][-1].status == Displacement.OK
        assert spin_until(
            node,
            lambda: any(
                s.level == DiagnosticStatus.WARN
                and "2 rejected" in s.message
                and {(v.key, v.value) for v in s.values}
                >= {("x.rejected_commands", "1"), ("y.rejected_commands", "1")}
                for d in diags
                for s in d.status
            ),
            30.0,
        )
        cmd["x"].publish(Voltage(voltage=100.0))
        # through the amplifier's 500 Hz low-pass
        assert spin_until(node, lambda: abs(vs["x"][-1].voltage - 100.0) < 1e-6, 30.0)
        spin_until(node, lambda: False, 0.5)  # the stage settles
        assert vs["y"][-1].voltage == 0.0
    finally:
        out, err = stop(proc)
    # the warning is throttled (1 s): y's, right after x's, is counted on /diagnostics only
    assert "rejected non-finite voltage command nan on axis x" in err
    # one tick, one stamp on every axis: pair the samples by stamp
    by_stamp = {axis: {_ns(m): m for m in xs[axis]} for axis in "xy"}
    common = sorted(set(by_stamp["x"]) & set(by_stamp["y"]))
    assert len(common) >= 0.8 * min(len(xs["x"]), len(xs["y"]))
    period = round(1e9 / RATE)
    assert all((b - a) % period == 0 and b > a for a, b in zip(common, common[1:]))
    x, y = by_stamp["x"][common[-1]].displacement, by_stamp["y"][common[-1]].displacement
    # ~10 um at 100 V (kappa_x ~ 1e-7 m/V); y's own displacement is 0, so its sensor reads
    # C[1][0] x = 2 % of x's
    assert 5e-6 < x < 20e-6
    assert y == pytest.approx(0.02 * x, rel=1e-9)


def _bad_coupling(tmp_path) -> str:
    data = yaml.safe_load((ROOT / "config" / "xy_scanner.yaml").read_text())
    data["coupling"] = [[1.0, 0.01, 0.0], [0.02, 1.0, 0.0]]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.mark.parametrize(
    "stage_file, why",
    [
        (lambda tmp: "no_such_stage.yaml", "not found"),
        (_bad_coupling, "coupling: must be square"),
    ],
)
def test_a_stage_file_that_does_not_load_exits_2_with_one_line(stage_file, why, tmp_path):
    proc = start_node("plant", f"stage_file:={stage_file(tmp_path)}", namespace=NS)
    proc.wait(timeout=30.0)
    _, err = proc.communicate()
    assert proc.returncode == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "stage_file" in lines[0] and why in lines[0], err


def _lockstep_drive(node, ns: str, steps: int) -> tuple[list, list, float]:
    """plant (xy scanner, 100 Hz) in lockstep, driven from the probe node: at each tick of
    its /clock, both axes' commands stamped with it (x a ramp to 100 V, y 50 V after 20 steps);
    step 0 is answered on x alone first, and how long the plant then waits for y is returned
    with every sample of each axis (step 0 once: it is offered again while y holds it)."""
    from rosgraph_msgs.msg import Clock

    from piezo_stage.nodes.qos import LOCKSTEP_QOS
    from piezo_stage_msgs.msg import Displacement, Voltage

    proc = start_node(
        "plant",
        "stage_file:=xy_scanner.yaml",
        f"rate_hz:={RATE}",
        "clock_mode:=lockstep",
        "lockstep_timeout:=60.0",
        "wait_for_subscribers:=1",
        namespace=ns,
        extra=("-r", f"/clock:={ns}/clock"),
    )
    ticks: list = []
    xs: dict[str, list] = {"x": [], "y": []}
    node.create_subscription(Clock, f"{ns}/clock", ticks.append, LOCKSTEP_QOS)
    cmd = {}
    for axis in "xy":
        node.create_subscription(
            Displacement, f"{ns}/{axis}/displacement", xs[axis].append, LOCKSTEP_QOS
        )
        node.create_subscription(Voltage, f"{ns}/{axis}/voltage", lambda m: None, LOCKSTEP_QOS)
        cmd[axis] = node.create_publisher(Voltage, f"{ns}/{axis}/voltage_command", LOCKSTEP_QOS)

    try:
        assert spin_until(node, lambda: bool(ticks), 60.0), "no /clock"
        stamp = ticks[0].clock
        cmd["x"].publish(Voltage(voltage=0.0, header=_header(stamp)))
        spin_until(node, lambda: False, 1.0)
        held = {t.clock.sec * 10**9 + t.clock.nanosec for t in ticks}  # y holds step 0
        again = len(ticks)
        cmd["y"].publish(Voltage(voltage=0.0, header=_header(stamp)))
        period = round(1e9 / RATE)
        start = _tick_ns(ticks[0])
        for k in range(1, steps):
            # step k's tick by its time: step 0 may still be offered again after `again`
            due = start + k * period
            assert spin_until(
                node, lambda due=due: any(_tick_ns(t) == due for t in ticks[again:]), 30.0
            ), f"no step {k}"
            stamp = next(t.clock for t in ticks[again:] if _tick_ns(t) == due)
            for axis in "xy":
                value = 100.0 * min(k, 40) / 40 if axis == "x" else (50.0 if k >= 20 else 0.0)
                cmd[axis].publish(Voltage(voltage=value, header=_header(stamp)))
        last = (steps - 1) * round(1e9 / RATE)  # every step's sample, step 0's repeats aside
        assert spin_until(node, lambda: all(v and _ns(v[-1]) >= last for v in xs.values()), 30.0)
    finally:
        stop(proc)
    once = {
        a: [m for i, m in enumerate(v) if i == 0 or _ns(m) > _ns(v[i - 1])] for a, v in xs.items()
    }
    return once["x"][:steps], once["y"][:steps], held


def _tick_ns(tick) -> int:
    return tick.clock.sec * 1_000_000_000 + tick.clock.nanosec


def _header(stamp):
    from std_msgs.msg import Header

    return Header(stamp=stamp)


def test_lockstep_steps_once_every_axis_has_answered_and_repeats_exactly(node):
    """clock_mode lockstep: step k is taken once each axis's command stamped t_k has come (x's
    alone holds it: step 0 is offered again, never step 1), the samples are stamped
    t0 + k/rate_hz on both axes, and a second run of the same commands gives the same samples,
    bit for bit."""
    x1, y1, held = _lockstep_drive(node, "/stage_lockstep_a", 60)
    assert held == {0}  # step 0 only, however long y took
    period = round(1e9 / RATE)
    assert [_ns(m) for m in x1] == [_ns(m) for m in y1] == [k * period for k in range(60)]
    assert x1[-1].displacement > 5e-6  # x driven to 100 V
    assert y1[-1].displacement > x1[-1].displacement * 0.02  # y its own 50 V, plus 2 % of x
    x2, y2, _ = _lockstep_drive(node, "/stage_lockstep_b", 60)
    assert [m.displacement for m in x1] == [m.displacement for m in x2]
    assert [m.displacement for m in y1] == [m.displacement for m in y2]
