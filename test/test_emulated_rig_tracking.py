"""Tracking on the rig's loop: the emulated rig (``piezo-stage emulate rig`` around the ch. 11 rig,
GCS amplifier on TCP + optoNCDT on a pty) with voltage_driver and laser_reader from
config/graphs/emulated_rig.yaml and the controller composed in one process (``rig_loop``),
stepping on each 1 kHz sensor sample and generating a triangle (``reference_source:
trajectory``) with the Bouc-Wen feedforward plus the PID (``both``).

The feedforward's model is fitted from recordings of the simulated rig (never its file). What is
checked: every sensor sample is answered, x_d goes out on ``reference``, u_ff (the voltage the
model asks for, ~125-145 V at the top here), and after the first period the stage follows x_d:
within 5 % of the 10 µm range on 80 % of the samples. Scale of that bound: the hysteresis alone is
κw/κx ≈ 4 µm; at a 1 kHz loop the command is a staircase whose steps ring the rig's 7 kHz
resonance, and the ringing wears w down (the ch. 11 dither: |w| peaks at 0.11 instead of 0.61), so
the model's hysteresis term over-compensates: the feedforward alone leaves 0.9 µm RMS (9 %,
pure-core simulation at 1 kHz; 0.26 µm at 10 kHz, nothing at 100 kHz) and the PID takes it to 0.3 %
on the development host, 1.2 % on one measuring the minimal loop 2.5x slower (three runs:
1.19-1.24 %; the amplifier's writes land later in the sensor's period). The sensor's quantum is
7.8 nm. The figure comes from ``loop_samples``, the loop's own record of every sample. Runs ~10
s of real time.
"""

from __future__ import annotations

import socket

import numpy as np
import pytest

from piezo_stage.bag import loop_columns
from piezo_stage.control.model_fit import fit_feedforward_model, rig_recordings
from piezo_stage.control.tracking import tracking_errors
from piezo_stage.launch import Launcher
from piezo_stage.launch.graph import find_graph, parse_graph
from piezo_stage.model.parameter_set import save_parameter_set, shipped_parameter_set
from piezo_stage.nodes.qos import BATCH_QOS, COMMAND_QOS
from piezo_stage.yaml_values import load_yaml

from ros_support import spin_until

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.realtime]

NS = "/emulated_tracking"
AMPLITUDE, OFFSET, FREQUENCY, PERIODS = 5e-6, 7e-6, 2.0, 3


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tracking_graph(port: int, link: str, model_file: str):
    """emulated_rig.yaml's emulator (on the ch. 11 rig), driver and reader, plus the controller."""
    source = find_graph("emulated_rig")
    data = load_yaml(source.read_text())
    nodes = []
    for entry in data["nodes"]:
        if entry.get("name") == "rig":
            command = ["ch11_rig.yaml" if a == "ch10_patch.yaml" else a for a in entry["command"]]
            command += ["--amp-tcp", str(port), "--sensor-link", link]
            nodes.append({**entry, "command": command})
        elif entry.get("executable") == "voltage_driver":  # commands applied on arrival
            nodes.append(
                {
                    **entry,
                    "process": "rig_loop",
                    "overrides": {**entry["overrides"], "apply_at_stamp": False},
                }
            )
        elif entry.get("executable") == "laser_reader":
            nodes.append({**entry, "process": "rig_loop"})
    nodes.append(
        {
            "executable": "controller",
            "process": "rig_loop",
            "overrides": {
                "trigger": "sample",
                "rate_hz": 1000.0,
                "mode": "pid",
                "start_closed": True,
                "u_min": 0.0,
                "u_max": 400.0,
                "reference_source": "trajectory",
                "trajectory": "triangle",
                "trajectory_amplitude": AMPLITUDE,
                "trajectory_offset": OFFSET,
                "trajectory_frequency": FREQUENCY,
                "compensation": "both",
                "feedforward_model": model_file,
            },
        }
    )
    return parse_graph({**data, "nodes": nodes}, source)


def test_emulated_rig_tracks_a_triangle_with_the_feedforward(probe, tmp_path):
    from piezo_stage_msgs.msg import ControllerState, Displacement, LoopSamples

    model = tmp_path / "model.yaml"
    rig = shipped_parameter_set("ch11_rig")  # recorded as a simulated rig: the model is fitted
    save_parameter_set(fit_feedforward_model(rig_recordings(rig)), model)
    port, link = free_port(), str(tmp_path / "sensor")
    # the measurement is the loop's own record: loop_samples, every sample in batches (the
    # per-sample topics are reliable but keep only the last 10: a Python probe taking them one
    # spin at a time loses runs of them on a slow host, which would read as gaps in the loop)
    batches: list = []
    states: list = []
    refs: list = []
    probe.create_subscription(LoopSamples, "loop_samples", batches.append, BATCH_QOS)
    probe.create_subscription(ControllerState, "controller_state", states.append, COMMAND_QOS)
    probe.create_subscription(Displacement, "reference", refs.append, COMMAND_QOS)
    lines: list[str] = []
    launch = Launcher(
        tracking_graph(port, link, str(model)),
        namespace=NS,
        timeout=30.0,
        params=[f"voltage_driver.url:=tcp://127.0.0.1:{port}", f"laser_reader.url:={link}"],
        sink=lambda name, line, is_err: lines.append(f"[{name}] {line}"),
    )
    n_wanted = int(PERIODS / FREQUENCY * 1000)

    def driven() -> int:
        """Samples answered in closed loop since the driver first applied a command (the
        controller may close the loop before the driver's command subscription has matched:
        the driver then ramps to 0 V for lack of commands)."""
        driving = np.concatenate([np.asarray(b.applied) > 1.0 for b in batches] or [[]])
        closed = np.concatenate([np.asarray(b.loop_closed) for b in batches] or [[]])
        return 0 if not driving.any() else int(closed[int(np.argmax(driving)) :].sum())

    try:
        launch.start()
        launch.wait_ready(timeout=30.0)
        done = spin_until(probe, lambda: driven() >= n_wanted, 60.0)
    finally:
        launch.stop()
    log = "\n".join(lines[-40:])
    assert done, log
    record = loop_columns(batches)
    begin = int(np.argmax(record["applied"] > 1.0))
    closed = {k: v[begin:][record["loop_closed"][begin:]] for k, v in record.items()}
    t = (closed["stamp"] - closed["stamp"][0]) * 1e-9
    # every sample of the 1 kHz sensor is answered (a gap would be the reader's or the loop's)
    assert np.diff(t).max() < 1.5e-3, np.diff(t).max()
    x, x_d = closed["displacement"], closed["reference"]
    assert x_d.max() == pytest.approx(OFFSET + AMPLITUDE, rel=0.02)
    assert np.ptp(x_d) == pytest.approx(2 * AMPLITUDE, rel=0.02)
    assert 100.0 < closed["u_ff"].max() < 180.0  # κx·12 µm = 124 V, plus κw·w
    # the per-sample topics carry what the loop recorded at the same stamp. A Python probe on
    # a slow host loses runs of each topic (reliable, keep last 10, taken one spin at a time),
    # and which runs differs between topics: in one CI run none of the 142 reference messages
    # it kept fell on a loop_samples batch it kept. So every message whose stamp the record
    # holds must agree with it, and every message must lie within the trajectory's range; how
    # many matched is printed, not required
    for messages, column, value in (
        (refs, "reference", lambda m: m.displacement),
        (states, "u_ff", lambda m: m.u_ff),
    ):
        assert messages, column
        stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in messages])
        found = np.isin(stamps, record["stamp"])
        print(f"{column}: {found.sum()} of {len(messages)} received messages in the record")
        at = np.searchsorted(record["stamp"], stamps[found])
        sent = np.array([value(m) for m, f in zip(messages, found) if f])
        np.testing.assert_allclose(sent, record[column][at], rtol=1e-9, atol=1e-12)
    received = np.array([m.displacement for m in refs])
    assert (
        received.min() >= OFFSET - AMPLITUDE - 1e-9 and received.max() <= OFFSET + AMPLITUDE + 1e-9
    )
    errors = tracking_errors(t, x, x_d, t_from=1.0 / FREQUENCY)
    print(
        f"emulated rig tracking: RMS {errors.rms_error * 1e9:.1f} nm = "
        f"{100 * errors.relative:.2f} % of the range, max {errors.max_error * 1e9:.1f} nm "
        f"over {errors.samples} samples"
    )
    assert errors.samples > 0.9 * (PERIODS - 1) / FREQUENCY * 1000, errors
    # the stage follows x_d within 5 % of the range on at least 80 % of the samples: a host that
    # holds the loop off the CPU for 0.1-0.3 s (its samples then answered in bursts of 5-30, seen
    # in about one run of three on a 2-core host) spoils that stretch and not the rest; the RMS
    # figure over runs is bench/live.py's
    e = np.abs(x - x_d)[t >= 1.0 / FREQUENCY]
    assert np.quantile(e, 0.8) <= 0.05 * errors.range, (np.quantile(e, 0.8), log)


# what holds on every run: the learning's figure is the host's timing (0.07-0.15 % on the
# development host; 1.4-36 % over five runs on this 2-core one, where stalls of 0.1-0.3 s feed
# the table bursts of late samples), measured over runs by bench/live.py
def test_emulated_rig_learns_the_triangle_and_replays_what_it_learned(tmp_path, capsys):
    """`piezo-stage experiment tracking --graph emulated_rig --learn 20`: the controller in
    rig_loop at the 1 kHz sensor's rate learns the feedforward of a 10 Hz triangle over 20 µm,
    saves the table and says whether learning worked (exit 1, "learning diverged", when it
    ended above its first period); a second run replays the table without learning. The first
    period starts from rest at 0 V and costs ~0.9 µm RMS (one start-up stall, a 70 ms garbage
    collection while the loop thread already ran, once made it 12-17 µm by replaying 70 stale
    samples at once). The sensor's quantum is 7.8 nm (0.04 % of the range)."""
    import json

    from piezo_stage.cli import main
    from piezo_stage.control.learning import FeedforwardTable

    model, table = tmp_path / "model.yaml", tmp_path / "table.json"
    save_parameter_set(
        fit_feedforward_model(rig_recordings(shipped_parameter_set("ch11_rig"))), model
    )
    base = [
        "experiment",
        "tracking",
        "--graph",
        "emulated_rig",
        "--rate-hz",
        "1000",
        "--model",
        str(model),
        "--json",
    ]
    code = main(base + ["--learn", "20", "--table-out", str(table)])
    learned = json.loads(capsys.readouterr().out)
    errors = learned["learning"]
    assert len(errors) == 20 and np.isfinite(errors).all(), learned
    assert errors[0] < 0.1 * learned["range"], errors  # no stale start
    # the run says whether learning worked: done (0) when it ended below its first period,
    # else failed (1) with the reason, the figures still reported
    if learned["rms_error"] <= errors[0]:
        assert code == 0 and "failed" not in learned, learned
    else:
        assert code == 1 and learned["failed"].startswith("learning diverged"), learned
    assert len(FeedforwardTable.load(table)) == 100
    code = main(base + ["--table", str(table)])
    replayed = json.loads(capsys.readouterr().out)
    assert replayed["learning"] == [] and np.isfinite(replayed["rms_error"]), replayed
    assert code == (1 if "failed" in replayed else 0), replayed
