"""LoopSamples bags (rig_loop's ``loop_samples``: every sample of the loop, in batches) read back
as one array per column, and as series through ``read_series(bag, "TOPIC.COLUMN")``."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.bag import (
    BagWriter,
    CorruptBagError,
    UnknownTopicError,
    read_loop_samples,
    read_series,
    serialize,
    types,
)

pytestmark = pytest.mark.unit

TYPE = "piezo_stage_msgs/msg/LoopSamples"
TOPIC = "/piezo/loop_samples"
T0 = 1_700_000_000_000_000_000


def batch(first: int, n: int, **broken):
    k = np.arange(first, first + n)
    fields = dict(
        stamp=T0 + k * 100_000,
        displacement=np.where(k % 7 == 3, np.nan, 1e-9 * k),
        status=np.where(k % 7 == 3, 4, 0).astype(np.uint8),
        reference=np.full(n, 5e-6),
        u=200.0 + 0.01 * k,
        u_ff=np.zeros(n),
        loop_closed=k % 2 == 1,
        applied=200.0 + 0.01 * k,
    )
    fields.update(broken)
    return types.message_class(TYPE)(header=types.header(int(fields["stamp"][0])), **fields)


def write(path, batches):
    with BagWriter(path) as bag:
        bag.add_topic(TOPIC, TYPE)
        # written out of order (a recorder writes in receive order): read back in stamp order
        for msg in batches:
            bag.write(TOPIC, serialize(msg, TYPE), int(msg.stamp[0]))


def test_batches_read_back_as_every_sample_in_stamp_order(tmp_path):
    write(tmp_path / "bag", [batch(50, 37), batch(0, 50), batch(87, 13)])
    samples = read_loop_samples(tmp_path / "bag", TOPIC)
    k = np.arange(100)
    assert np.array_equal(samples["stamp"], T0 + k * 100_000)
    assert np.array_equal(samples["status"], np.where(k % 7 == 3, 4, 0))
    assert np.array_equal(samples["loop_closed"], k % 2 == 1)
    np.testing.assert_allclose(samples["u"], 200.0 + 0.01 * k)
    t, x, status = read_series(tmp_path / "bag", TOPIC)  # default column: displacement
    assert t[1] - t[0] == pytest.approx(1e-4, abs=1e-6)  # float seconds since 1970: ~0.2 us
    assert np.array_equal(status, samples["status"])
    assert np.isnan(x[3]) and x[4] == pytest.approx(4e-9)
    t, applied, status = read_series(tmp_path / "bag", f"{TOPIC}.applied")
    assert status is None and applied[-1] == pytest.approx(200.99)


def test_a_batch_whose_columns_disagree_is_reported_as_damaged(tmp_path):
    write(tmp_path / "bag", [batch(0, 10, u=np.zeros(9))])
    with pytest.raises(CorruptBagError, match="10 stamps but 9 u values"):
        read_loop_samples(tmp_path / "bag", TOPIC)


def test_an_unknown_column_says_which_there_are(tmp_path):
    write(tmp_path / "bag", [batch(0, 10)])
    with pytest.raises(UnknownTopicError, match="no column 'x1'.*applied"):
        read_series(tmp_path / "bag", f"{TOPIC}.x1")
