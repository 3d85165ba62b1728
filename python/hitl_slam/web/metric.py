"""The map's inconsistency (:func:`hitl_slam.metrics.inconsistency`) computed off the request
path: one background thread works on the newest map only, and values are remembered by pose
hash so that undo and redo show theirs at once.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.errors import HitlSlamError
from hitl_slam.map import Map

__all__ = ["MetricWorker"]

logger = logging.getLogger(__name__)

_CACHE = 64  # inconsistency values remembered by pose hash
DELAY_S = 0.3
"""[s] How long a new map waits before its inconsistency is computed: the page's own requests
right after a change (the new poses, the long poll) are served first, without a computation
competing for the cores."""


def _pose_key(poses: NDArray[np.float64]) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(poses).tobytes(), digest_size=16).digest()


class MetricWorker:
    """Computes the inconsistency of the newest requested map in a thread and reports it with
    ``done(map_version, poses, total_m2)``."""

    def __init__(
        self,
        map: Map,
        config: Config,
        done: Callable[[int, NDArray[np.float64], float], None],
        delay: float = DELAY_S,
    ) -> None:
        self._delay = delay
        self._requested = 0.0  # time.monotonic() of the newest request
        self._map = map
        self._config = config
        self._done = done
        self._values: OrderedDict[bytes, float] = OrderedDict()
        self._job: tuple[int, NDArray[np.float64]] | None = None
        self._closing = False
        self._wake = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name="hitl-slam-metric", daemon=True)
        self._thread.start()

    def known(self, poses: NDArray[np.float64]) -> float | None:
        """The value already computed for these poses, if any."""
        with self._wake:
            return self._values.get(_pose_key(poses))

    def request(self, map_version: int, poses: NDArray[np.float64]) -> None:
        """Compute for ``poses`` next (replacing any job not yet started: only the newest map
        matters)."""
        with self._wake:
            self._job = (map_version, poses)
            self._requested = time.monotonic()
            self._wake.notify_all()

    def close(self) -> None:
        """Stop the thread (waits for a running computation, up to 30 s)."""
        with self._wake:
            self._closing = True
            self._wake.notify_all()
        self._thread.join(timeout=30.0)

    def _loop(self) -> None:
        from hitl_slam.metrics import inconsistency

        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._job is not None or self._closing)
                # Let the page's requests that follow a change go first (a newer request
                # restarts the wait).
                while not self._closing:
                    left = self._requested + self._delay - time.monotonic()
                    if left <= 0:
                        break
                    self._wake.wait(left)
                if self._closing:
                    return
                job = self._job
                self._job = None
            assert job is not None
            map_version, poses = job
            try:
                # One thread: the cores are left to the solver of the next correction.
                total = inconsistency(self._map, poses, self._config, threads=1).total_m2
            except HitlSlamError as exc:
                logger.warning("inconsistency not computed: %s", exc)
                continue
            with self._wake:
                self._values[_pose_key(poses)] = float(total)
                while len(self._values) > _CACHE:
                    self._values.popitem(last=False)
            self._done(map_version, poses, float(total))
