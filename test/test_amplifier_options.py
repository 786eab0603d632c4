"""The range a graph's emulated amplifier serves, read from its command line by the parser and
device models of ``piezo-stage emulate`` (not from the text): any range given, the models'
defaults otherwise, nothing for other commands."""

from __future__ import annotations

import math

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from piezo_stage.hardware.emulators.amplifier_options import served_range
from piezo_stage.launch.graph import load_graph, parse_graph

pytestmark = pytest.mark.unit

volts = st.floats(-1000.0, 1000.0, allow_nan=False).map(lambda v: round(v, 3))
OTHER = ["--rate", "1000", "--amp-tcp", "0", "--amp-link", "/tmp/a", "--amp-bandwidth", "0"]


@given(low=volts, high=volts, sub=st.sampled_from(["rig", "scanner"]), before=st.booleans())
@example(low=0.0, high=400.0, sub="rig", before=False)
def test_a_given_range_is_the_range_served(low, high, sub, before):
    options = ["--amp-range", repr(low), repr(high)]
    argv = ["piezo-stage", "emulate", sub, *(options + OTHER if before else OTHER + options)]
    assert served_range(argv) == (low, high)


def test_the_device_models_defaults_without_a_range():
    assert served_range(["piezo-stage", "emulate", "rig"]) == (-30.0, 130.0)  # an E-709
    assert served_range(["piezo-stage", "emulate", "rig", "--amplifier", "mdt69x"]) == (0, 150)


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["piezo-stage", "emulate"],
        ["piezo-stage", "emulate", "e727", "--amp-range", "0", "100"],  # its own controller
        ["python", "-m", "something", "--amp-range", "0", "100"],
        ["piezo-stage", "emulate", "rig", "--amp-range", "0"],  # the emulator refuses it
        ["piezo-stage", "emulate", "rig", "--amplifier", "mdt69x", "--amp-range", "0", "100"],
    ],
)
def test_other_commands_serve_no_known_range(argv):
    assert served_range(argv) is None


@pytest.mark.parametrize(
    ("graph", "expected"),
    [
        ("emulated_rig", (0.0, 400.0)),  # the emulator's --amp-range
        ("emulated_scanner_loop", (0.0, 400.0)),
        ("pi_rig_loop", (0.0, 100.0)),  # the driver's v_min/v_max
        ("rig_loop", (-math.inf, math.inf)),  # a real rig's: unknown until it is asked
    ],
)
def test_the_shipped_graphs_ranges(graph, expected):
    assert load_graph(graph, free_ports=False).amplifier_range == expected


def test_an_emulator_without_a_range_is_checked_against_its_defaults():
    """A graph's `emulate rig` with no --amp-range serves an E-709's -30..130 V: a trajectory
    is checked against that, not against an unbounded amplifier."""
    nodes = [{"command": ["piezo-stage", "emulate", "rig", "--rate", "1000"], "name": "rig"}]
    assert parse_graph({"nodes": nodes}).amplifier_range == (-30.0, 130.0)


@given(plant=st.tuples(volts, volts).map(sorted), law=st.tuples(volts, volts).map(sorted))
@example(plant=[0.0, 400.0], law=[-30.0, 130.0])
def test_a_graphs_range_is_the_narrowest_its_entries_set(plant, law):
    """A plant's v_min/v_max and a controller's u_min/u_max: the graph's range is both at once."""
    nodes = [
        {"executable": "plant", "overrides": {"v_min": plant[0], "v_max": plant[1]}},
        {"executable": "controller", "overrides": {"u_min": law[0], "u_max": law[1]}},
    ]
    low, high = parse_graph({"nodes": nodes}).amplifier_range
    assert (low, high) == (max(plant[0], law[0]), min(plant[1], law[1]))
