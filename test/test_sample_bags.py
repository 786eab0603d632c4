"""The committed sample bags: small, readable by rosbags, identified to the true parameters
offline."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from piezo_stage.cli import main
from piezo_stage.model.parameter_set import shipped_parameter_set

from ros_support import to_plain

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
BAGS = {"ch10_identification": ("ch10_patch", 2), "ch9_identification": ("ch9_example", 1)}
#: every committed bag (a folder with metadata.yaml)
ALL_BAGS = sorted(p.parent.name for p in (ROOT / "bags").glob("*/metadata.yaml"))
#: noiseless samples at 50 Hz (500 per 0.1 Hz period): refined errors measured ~1e-4;
#: the corners of the triangles between samples limit it
TOLERANCE = 2e-3


def _values(p) -> dict[str, float]:
    d = {f"kappa_{i + 1}": k for i, k in enumerate(p["kappa"] if isinstance(p, dict) else p.kappa)}
    for name in ("y0", "kappa_w", "rho", "sigma", "n"):
        d[name] = p[name] if isinstance(p, dict) else getattr(p, name)
    return d


@pytest.mark.parametrize("name", sorted(BAGS))
def test_sample_bag_is_small_and_readable_by_rosbags(name):
    from rosbags.highlevel import AnyReader

    path = ROOT / "bags" / name
    size = sum(f.stat().st_size for f in path.iterdir())
    assert size < 1.5e6, f"{name} is {size / 1e6:.2f} MB"
    counts: dict[str, int] = {}
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic.endswith("/displacement"):
                assert msg.status == 0 and np.isfinite(msg.displacement)
    assert counts["/piezo/voltage"] > 2000 and counts["/piezo/displacement"] > 2000
    assert counts["/piezo/excitation"] > 100


def _by_topic(items) -> dict[str, list[tuple[int, str]]]:
    """{topic: sorted [(log time, message as plain data)]}: equal for two readers that decode
    every message alike (ties of log time are not ordered the same by every reader)."""
    out: dict[str, list[tuple[int, str]]] = {}
    for topic, log_time, msg in items:
        out.setdefault(topic, []).append((log_time, repr(to_plain(msg))))
    return {topic: sorted(values) for topic, values in out.items()}


@pytest.mark.parametrize("name", ALL_BAGS)
def test_sample_bag_reads_the_same_with_rosbags_and_with_mcap_ros2(name):
    """Every message of the bag, decoded by rosbags' AnyReader and by the mcap reader + mcap_ros2
    decoder (neither is the project's reader), is the same, and the counts are the metadata's."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    path = ROOT / "bags" / name
    with AnyReader([path]) as reader:
        by_rosbags = _by_topic(
            (c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()
        )

    def mcap_messages():
        for file in sorted(path.glob("*.mcap")):
            with open(file, "rb") as stream:
                decoded = make_reader(
                    stream, decoder_factories=[DecoderFactory()]
                ).iter_decoded_messages()
                for _, channel, message, msg in decoded:
                    yield channel.topic, message.log_time, msg

    by_mcap = _by_topic(mcap_messages())
    counts = {
        t["topic_metadata"]["name"]: t["message_count"]
        for t in yaml.safe_load((path / "metadata.yaml").read_text())[
            "rosbag2_bagfile_information"
        ]["topics_with_message_count"]
    }
    assert {t: len(v) for t, v in by_rosbags.items()} == {t: n for t, n in counts.items() if n}
    assert by_rosbags.keys() == by_mcap.keys()
    for topic in by_rosbags:
        assert by_rosbags[topic] == by_mcap[topic], topic


@pytest.mark.parametrize("name", sorted(BAGS))
def test_identify_recovers_the_true_parameters(name, capsys):
    preset, degree = BAGS[name]
    assert main(["identify", str(ROOT / "bags" / name), "--degree", str(degree), "--json"]) == 0
    found = _values(json.loads(capsys.readouterr().out))
    true = _values(shipped_parameter_set(preset).bouc_wen)
    for key, value in true.items():
        if key == "y0" and value == 0.0:  # ch. 9: no offset; compare with the output span (~0.8)
            assert abs(found[key]) < 1e-5
            continue
        assert found[key] == pytest.approx(value, rel=TOLERANCE), key


#: The live result in a committed bag was computed on another machine (another CPU, another BLAS
#: kernel): the fresh offline fit agrees to rounding, not to the last digit (seen: y0 differing
#: by 5e-14 of the output span). Tolerances on the physical scale: y0 within 1e-9 of the output
#: span, every other parameter within 1e-7 relative -- still far below what a different cut of
#: the samples or a changed method moves them by (the fit itself is 1e-5..1e-4 from the truth).
Y0_SPAN_TOLERANCE = 1e-9
PARAMETER_TOLERANCE = 1e-7


@pytest.mark.parametrize("name", sorted(BAGS))
def test_recorded_live_result_is_the_offline_identification_of_the_bag(name, capsys):
    """The identifier node identified live while the bag was recorded (its bouc_wen_parameters are
    in the bag): the same samples, cut the same way, give the offline result, to rounding."""
    from piezo_stage.bag.reader import read_messages

    _, degree = BAGS[name]
    path = ROOT / "bags" / name
    live = [msg for _, _, msg in read_messages(path, ["/piezo/bouc_wen_parameters"])]
    assert len(live) == 1
    span = np.ptp([msg.displacement for _, _, msg in read_messages(path, ["/piezo/displacement"])])
    assert main(["identify", str(path), "--degree", str(degree), "--json"]) == 0
    offline = json.loads(capsys.readouterr().out)
    assert list(live[0].kappa) == pytest.approx(offline["kappa"], rel=PARAMETER_TOLERANCE)
    assert abs(live[0].y0 - offline["y0"]) <= Y0_SPAN_TOLERANCE * span
    for key in ("kappa_w", "rho", "sigma", "n"):
        assert getattr(live[0], key) == pytest.approx(offline[key], rel=PARAMETER_TOLERANCE), key
    assert live[0].samples == offline["samples"]


def test_perturbation_bag_opens_and_closes_the_loop_and_u_returns():
    """The closed-loop sample (ch. 11 perturbation under the time-varying PID): the loop is
    closed, opened once for 10 ms with u forced to 72 V, closed again; u before and after (the
    experiment's figures, kept in the bag's metadata) agree with the recorded u and with each
    other within 1 %, as §11.5 expects of (11.18)."""
    from piezo_stage.bag.reader import read_messages

    path = ROOT / "bags" / "perturbation_pid_tv"
    assert sum(f.stat().st_size for f in path.iterdir()) < 2e6
    custom = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"][
        "custom_data"
    ]
    assert custom["experiment"] == "piezo-stage experiment perturbation --mode pid_tv"
    msgs = [msg for _, _, msg in read_messages(path, ["/piezo/controller_state"])]
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
    closed = np.array([m.loop_closed for m in msgs])
    u = np.array([m.u for m in msgs])
    dt = 1.0 / float(custom["rate_hz"]) * int(custom["keep_every"])
    assert {m.mode for m in msgs} == {"pid_tv"} and np.allclose(np.diff(t), dt)

    edges = np.flatnonzero(np.diff(closed.astype(int)))
    assert closed[0] and closed[-1] and len(edges) == 2  # opened once, closed again
    opened, reclosed = t[edges[0] + 1], t[edges[1] + 1]
    assert reclosed - opened == pytest.approx(0.010, abs=1.01 * dt)
    assert np.all(u[~closed] == 72.0)  # u forced while the loop is open
    u_before = u[(t >= opened - 0.002) & (t < opened)].mean()
    u_after = u[t > t[-1] - 0.010].mean()  # the last period 1/f of the sine (f = 100 Hz)
    assert u_before == pytest.approx(float(custom["u_before"]), rel=1e-3)
    assert u_after == pytest.approx(float(custom["u_after"]), rel=2e-3)
    assert abs(u_after - u_before) / u_before < 0.01
    x1 = np.array([m.x1 for m in msgs])
    assert (
        np.abs(x1[~closed]).max() > 20 * np.abs(x1[t > t[-1] - 0.010]).max()
    )  # perturbed, then regulated
