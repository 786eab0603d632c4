"""The controller node's parameter table (and its own choices), without rclpy: the node
declares from it, and the experiments that start a controller derive their options from it.
"""

from __future__ import annotations

import math

from piezo_stage.control.controller import THESIS_AMPLIFIER, AntiWindup, OnClose
from piezo_stage.control.feedforward import Compensation
from piezo_stage.control.laws import GAIN_ROWS, LAW_NAMES, PID
from piezo_stage.control.learning import FeedforwardForm
from piezo_stage.control.setpoint import ReferenceSource
from piezo_stage.control.trajectory import DEFAULT_ROUNDING
from piezo_stage.hardware.timing import LOOP_SWITCH_INTERVAL

from .choices import ControllerStepTrigger as StepTrigger
from .choices import PublishIn, SensorQos
from .settings import ControllerSettings
from .spec import Param, ParameterTable

PARAMETERS = ParameterTable(
    "controller",
    (
        Param(
            "mode",
            PID.name,
            "control law, a registered one (the thesis's: pid (11.5), pid_sine (11.17), "
            "pid_tv (11.18))",
            choices=LAW_NAMES,
        ),
        *(Param(g.name, g.default, g.description, g.unit, g.range) for g in GAIN_ROWS),
        Param("u_min", -THESIS_AMPLIFIER, "amplifier lower limit", "V"),
        Param("u_max", THESIS_AMPLIFIER, "amplifier upper limit", "V"),
        Param("anti_windup", "conditional", "anti-windup of the integral x0", choices=AntiWindup),
        Param(
            "tracking_time", 0.0, "back-calculation time constant (0: sqrt(Ti*Td))", "s", (0.0, 1e3)
        ),
        Param(
            "derivative_tau",
            0.0,
            "first-order filter on x2 (0: off, as the thesis)",
            "s",
            (0.0, 1.0),
        ),
        Param(
            "u_bias",
            0.0,
            "feedforward added to the law's output (§11.5 set point)",
            "V",
            read_only=True,
        ),
        Param("hold_voltage", math.nan, "output while the loop is open (NaN: last output)", "V"),
        Param("on_close", "bumpless", "x0 when the loop closes", choices=OnClose),
        Param(
            "rate_hz", 1000.0, "loop rate (trigger=timer; also the rate checked)", "Hz", (1.0, 1e7)
        ),
        Param(
            "trigger",
            "timer",
            "timer (rate_hz) or sample (one step per displacement sample)",
            choices=StepTrigger,
        ),
        Param("delay_samples", 1, "output delay assumed by the sampled-loop check", range=(0, 10)),
        Param(
            "sensor_qos",
            "best_effort",
            "displacement subscription: best_effort (matches every "
            "publisher: the rig's laser_reader) or reliable (the lockstep plant: no sample lost, "
            "so "
            "no step waits for the plant's timeout)",
            choices=SensorQos,
            read_only=True,
        ),
        Param("start_closed", False, "close the loop at the first valid sample"),
        Param(
            "start_grace",
            1.0,
            "after start_closed first closed the loop: a gap or invalid sample this soon "
            "holds and closes again at the next valid sample instead of latching a fault",
            "s",
            range=(0.0, 60.0),
            read_only=True,
        ),
        Param(
            "wait_for_state_subscribers",
            0,
            "trigger=sample and rig_loop: ignore samples until "
            "controller_state has this many subscribers (an experiment's recorder sees step 0)",
            range=(0, 100),
            read_only=True,
        ),
        Param(
            "publish_in",
            "loop",
            "rig_loop: the thread that publishes what the loop queued",
            choices=PublishIn,
            read_only=True,
        ),
        Param(
            "publish_period",
            0.0,
            "rig_loop: time between publications of the queue (0: 20 samples' worth within "
            "[2, 10] ms)",
            "s",
            (0.0, 1.0),
            read_only=True,
        ),
        Param(
            "switch_interval",
            LOOP_SWITCH_INTERVAL,
            "rig_loop: the process's GIL switch interval (how long the executor's thread may "
            "keep the loop's waiting)",
            "s",
            (1e-6, 0.1),
            read_only=True,
        ),
        Param(
            "topics_rate_hz",
            1000.0,
            "rig_loop: most samples per second on displacement, "
            "voltage_command, controller_state and voltage (decimated above it); loop_samples "
            "carries every sample, in batches",
            "Hz",
            (1.0, 1e6),
            read_only=True,
        ),
        Param(
            "max_gap",
            0.02,
            "a sensor silence up to this long holds the output (counted as "
            "gaps_held); a longer one opens the loop",
            "s",
            (1e-5, 60.0),
        ),
        Param(
            "reference_source",
            "topic",
            "where the set point comes from: the reference topic, the "
            "thesis's second-order yr, the reference parameter, or the trajectory_* parameters "
            "(x_d "
            "then published on reference)",
            choices=ReferenceSource,
        ),
        Param(
            "reference",
            0.0,
            "set point for reference_source=constant, and before a reference arrives",
            "m",
        ),
        Param("reference_y0", 20e-6, "second_order: yr(0)", "m"),
        Param("reference_ydot0", 0.0, "second_order: dyr/dt(0)", "m/s"),
        Param(
            "trajectory",
            "triangle",
            "reference_source=trajectory: triangle, sine, steps, the "
            "path of a CSV file (t [s], x [m]) or of a raster scan's axis (JSON)",
            read_only=True,
        ),
        Param(
            "trajectory_amplitude",
            10e-6,
            "half the trajectory's range",
            "m",
            (0.0, 1.0),
            read_only=True,
        ),
        Param(
            "trajectory_frequency", 10.0, "trajectory frequency", "Hz", (1e-6, 1e5), read_only=True
        ),
        Param(
            "trajectory_offset",
            math.nan,
            "mid-range of the trajectory (NaN: the amplitude, so x_d starts at 0)",
            "m",
            read_only=True,
        ),
        Param(
            "trajectory_rounding",
            DEFAULT_ROUNDING,
            "triangle corner / step transition, share of a half period",
            "",
            (1e-3, 1.0),
            read_only=True,
        ),
        Param(
            "trajectory_v_max", math.inf, "velocity limit of the trajectory", "m/s", read_only=True
        ),
        Param(
            "trajectory_a_max",
            math.inf,
            "acceleration limit of the trajectory",
            "m/s^2",
            read_only=True,
        ),
        Param(
            "compensation",
            "feedback",
            "feedback (the law alone), feedforward (u_ff alone) or both (u_ff + the law)",
            choices=Compensation,
            read_only=True,
        ),
        Param(
            "feedforward_model",
            "",
            "dynamic parameter set of the feedforward (input displacement; "
            "name in config/ or path); needed unless compensation=feedback",
            read_only=True,
        ),
        Param(
            "feedforward_form",
            "auto",
            "feedforward of a trajectory: sampled (the command "
            "staircase the model says the loop at rate_hz needs, computed at start), continuous "
            "(the model stepped along x_d) or auto (sampled below 10 times the model's "
            "resonance)",
            choices=FeedforwardForm,
            read_only=True,
        ),
        Param(
            "feedforward_table",
            "",
            "a saved feedforward table (JSON, e.g. learned) replayed "
            "instead; made for this trajectory at rate_hz",
            read_only=True,
        ),
        Param(
            "learn_periods",
            0,
            "learn the feedforward table over this many periods of the "
            "trajectory, then keep it (0: no learning); a raster's slow axis: its lines, "
            "through a correction of one line added to each line of its frame",
            range=(0, 1_000_000),
            read_only=True,
        ),
        Param(
            "learn_gain",
            0.5,
            "learning gain of L = -gain/G (G: the model's loop)",
            "",
            (1e-3, 1.0),
            read_only=True,
        ),
        Param(
            "learn_cutoff_hz",
            0.0,
            "learning Q-filter cutoff (0: a quarter of rate_hz, at most "
            "half the model's resonance)",
            "Hz",
            (0.0, 1e7),
            read_only=True,
        ),
        Param(
            "learn_slew_rate",
            math.inf,
            "slew limit every table value keeps (the amplifier's)",
            "V/s",
            read_only=True,
        ),
        Param(
            "feedforward_table_out",
            "",
            "save the learned table here (JSON) once learning ends",
            read_only=True,
        ),
        Param(
            "bounds_file",
            "thesis_rig_bounds.yaml",
            "Assumption 2 bounds (YAML; name in config/ or path)",
        ),
        Param(
            "open_at",
            -1.0,
            "open the loop at this time of the node clock (< 0: never); "
            "deterministic in lockstep, e.g. the §11.5 perturbation",
            "s",
            read_only=True,
        ),
        Param(
            "open_after",
            -1.0,
            "open the loop this long after start_closed closed it (< 0: "
            "never); the §11.5 perturbation on a rig's wall clock",
            "s",
            read_only=True,
        ),
        Param(
            "open_duration",
            0.0,
            "close it again this long after it opened (0: stay open)",
            "s",
            (0.0, 1e6),
            read_only=True,
        ),
        Param(
            "allow_unverified_gains",
            False,
            "accept gains that fail Theorem 4 or the sampled-loop check",
        ),
    ),
    summary="The thesis's time-varying PID (11.5, 11.17, 11.18) on ROS topics.",
    settings_type=ControllerSettings,
)
