"""A ROS domain of one's own for a lockstep run: ``/clock`` is global (not namespaced), so two
lockstep simulations on one domain would drive each other's clocks.

Claims are exclusive ``flock``s on ``ros_domains/<id>.lock`` in the per-user run-time folder
(:mod:`piezo_stage.runtime_dir`: mode 0700, never a fixed name in a shared /tmp), one file per id
in 1..100, held while the lock file is open: the demo, the experiments, the sample-bag script and
the test suite (test/conftest.py) all use this one protocol, so they never pick the same id.
"""

from __future__ import annotations

import fcntl
import os
import random
from contextlib import contextmanager
from typing import IO, Iterator

from piezo_stage.runtime_dir import location, runtime_dir

from .errors import LaunchError

#: lock files of claimed ROS domain ids
DOMAIN_LOCK_DIR = location() / "ros_domains"


def claim_domain_id(start: int | None = None) -> tuple[int, IO[str]]:
    """Claim a ROS_DOMAIN_ID in 1..100 that no other process holds; return it and the open lock
    file (the claim lasts until the file is closed or the process exits). The search starts at
    ``start`` (default: a random id) and wraps around."""
    lock_dir = runtime_dir("ros_domains")  # created 0700, refused when not ours
    first = random.SystemRandom().randrange(100) if start is None else start
    for k in range(100):
        domain = 1 + (first + k) % 100
        f = open(lock_dir / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        return domain, f
    raise LaunchError("no free ROS domain id in 1..100 (every one is held by another run)")


@contextmanager
def isolated_domain(domain_id: int | None = None) -> Iterator[int]:
    """Set ROS_DOMAIN_ID (a free one unless given) for this process and its children meanwhile."""
    lock = None
    if domain_id is None:
        domain_id, lock = claim_domain_id()
    saved = os.environ.get("ROS_DOMAIN_ID")
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    try:
        yield domain_id
    finally:
        if saved is None:
            os.environ.pop("ROS_DOMAIN_ID", None)
        else:
            os.environ["ROS_DOMAIN_ID"] = saved
        if lock is not None:
            lock.close()
