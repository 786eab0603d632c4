"""The nodes' choices: every Enum a node's parameter table offers (``settings.py`` types its
fields with them), in one module below the nodes so that nothing imports in a circle.
"""

from __future__ import annotations

from enum import StrEnum


class ControllerStepTrigger(StrEnum):
    TIMER = "timer"  # rate_hz on the node clock
    SAMPLE = "sample"  # one step per displacement sample (the lockstep plant)


class PublishIn(StrEnum):
    """rig_loop: which thread publishes what the loop queued (bench/control_loop.py --designs
    measures each)."""

    LOOP = "loop"  # the loop thread, right after a write, every publish_period (shipped)
    PUBLISHER = "publisher"  # a thread of its own below the loop's priority, in slices
    EXECUTOR = "executor"  # a wall-clock timer of the executor
    INLINE = "inline"  # every publication at once, in the loop thread


class SensorQos(StrEnum):
    BEST_EFFORT = "best_effort"  # matches every publisher: the rig's laser_reader
    RELIABLE = "reliable"  # the lockstep plant: no sample lost, no step waits for its timeout


class ExcitationStepTrigger(StrEnum):
    TIMER = "timer"  # rate_hz on the node clock
    CLOCK = "clock"  # one command per /clock tick (the lockstep plant)


class ExcitationOnDone(StrEnum):
    HOLD = "hold"  # keep publishing the hold value
    EXIT = "exit"


class Input(StrEnum):
    VOLTAGE = "voltage"  # ch. 10: voltage -> displacement
    DISPLACEMENT = "displacement"  # ch. 11: displacement -> voltage


class StreamQos(StrEnum):
    AUTO = "auto"  # adapted to the publishers, as rosbag2 does
    BEST_EFFORT = "best_effort"  # matches every publisher
    RELIABLE = "reliable"  # no loss from reliable publishers


class CyclesFrom(StrEnum):
    STREAMS = "streams"  # the cycles it extracts from voltage/displacement/excitation
    TOPIC = "topic"  # the cycles received on limit_cycles
    BOTH = "both"  # either: one from each is a pair too

    @property
    def streams(self) -> bool:
        """Whether the raw streams are taken."""
        return self is not CyclesFrom.TOPIC

    @property
    def topic(self) -> bool:
        """Whether ``limit_cycles`` is taken."""
        return self is not CyclesFrom.STREAMS


class IdentifierOnDone(StrEnum):
    STAY = "stay"  # the result stays latched
    EXIT = "exit"  # status 0 when identified, 1 when it failed


class ClockMode(StrEnum):
    REALTIME = "realtime"  # a wall timer at rate_hz
    LOCKSTEP = "lockstep"  # owns /clock: one step per voltage_command
