"""QoS profiles of the piezo_stage topics, and the subscription QoS adapted to publishers' offers.

Sensor streams use a SensorDataQoS-compatible profile (best effort, keep last), commands are
reliable, latched results transient-local, lockstep streams reliable and deep.
"""

from __future__ import annotations

from typing import Sequence

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

#: displacement / voltage streams: best effort, keep last 10 (SensorDataQoS-compatible)
SENSOR_QOS: QoSProfile = qos_profile_sensor_data
#: commands and state: reliable, keep last 10
COMMAND_QOS = QoSProfile(
    depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
)
#: lockstep streams (the plant's samples and /clock, the controller's state): reliable, because a
#: lost sample would stall a step until the timeout, and deep, because a reader busy for a while
#: (the identifier extracting a cycle, a recorder, an experiment's collector) must not lose what
#: the graph produced meanwhile: a reliable KEEP_LAST writer drops what a reader has not yet
#: acknowledged once its history is full, and a lockstep graph runs at several thousand steps per
#: wall second, so the history holds a whole experiment (0.4 s at 100 kHz: 40 000 steps; the ch. 10
#: identification: 20 000). Its entries are allocated as they are used.
#: A reliable publisher also serves the best-effort (SensorDataQoS) subscribers of the rig.
LOCKSTEP_DEPTH = 100_000
LOCKSTEP_QOS = QoSProfile(depth=LOCKSTEP_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
#: batches of samples (rig_loop's loop_samples): reliable, a few seconds of batches queued
BATCH_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
#: identified parameters and other results: reliable + transient local (latched)
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)


def adapted_qos(offers: Sequence[QoSProfile], queue_depth: int) -> QoSProfile:
    """Subscription QoS that matches every offer (rosbag2's adapt_request_to_offers): reliable
    if all publishers are reliable, transient-local if all are; KEEP_ALL when reliable."""
    reliable = bool(offers) and all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    latched = bool(offers) and all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
    if reliable:
        return QoSProfile(
            history=HistoryPolicy.KEEP_ALL,
            depth=queue_depth,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=durability,
        )
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=queue_depth,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=durability,
    )
