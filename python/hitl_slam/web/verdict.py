"""The front end's verdict on the map it built and the stretches of it that it doubts, as its
metadata carries them (``front_end_verdict``: "good" or "doubtful"; ``front_end_doubtful``: a list
of ``{"first", "last", "reason"}``, 0-based inclusive scan ranges), checked for the page and
summed up in a line ("front end: doubtful map: 3 stretches, scans 1200-1260, ...").
"""

from __future__ import annotations

import logging
import numbers
from typing import Any

from hitl_slam.map import Map

__all__ = ["DOUBTFUL", "VERDICT", "doubtful_stretches", "summary", "verdict"]

logger = logging.getLogger(__name__)

VERDICT = "front_end_verdict"
DOUBTFUL = "front_end_doubtful"
_SHOWN = 3  # stretches named in the summary line


def verdict(m: Map) -> str | None:
    """The front end's verdict on ``m`` ("good", "doubtful"), or None when it gave none."""
    value = m.metadata.get(VERDICT)
    return value if isinstance(value, str) and value else None


def doubtful_stretches(m: Map) -> list[dict[str, Any]]:
    """The doubtful stretches of ``m``, each ``{"first", "last", "reason"}`` with ``0 <= first <=
    last < num_poses``, in the front end's order. An entry that is not such a range (a session
    file from another version, a hand-edited one) is left out with a warning: the map is still
    served; a range reaching past the last scan is cut there."""
    items = m.metadata.get(DOUBTFUL)
    if items is None:
        return []
    if not isinstance(items, list | tuple):
        logger.warning("%s: metadata %s is not a list; ignored", m.name, DOUBTFUL)
        return []
    out = []
    for k, item in enumerate(items):
        scans = _scan_range(item, m.num_poses)
        if scans is None:
            logger.warning(
                "%s: doubtful stretch %d (%r) is not a scan range 0 <= first <= last < %d; ignored",
                m.name,
                k,
                item,
                m.num_poses,
            )
            continue
        reason = item.get("reason")
        reason = reason if isinstance(reason, str) else ""
        out.append({"first": scans[0], "last": scans[1], "reason": reason})
    return out


def _scan_range(item: object, n: int) -> tuple[int, int] | None:
    """``(first, last)`` of a stretch, ``last`` cut at the last scan, or None when it is not a
    range of these ``n`` scans (numpy integers count: the front end may write them)."""
    if not isinstance(item, dict):
        return None
    first, last = item.get("first"), item.get("last")
    for value in (first, last):
        if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 0:
            return None
    assert isinstance(first, numbers.Integral)
    assert isinstance(last, numbers.Integral)
    if not int(first) <= int(last) or int(first) >= n:
        return None
    return int(first), min(int(last), n - 1)


def summary(m: Map) -> str | None:
    """One line on the front end's verdict ("front end: good map", "front end: doubtful map: 2
    stretches, scans 1200-1260 (match failed), 3400-3410 (ambiguous match)"), or None when it
    gave none."""
    said = verdict(m)
    stretches = doubtful_stretches(m)
    if said is None and not stretches:
        return None
    text = f"front end: {said or 'doubtful'} map"
    if stretches:
        count = len(stretches)
        shown = ", ".join(
            f"{s['first']}-{s['last']}" + (f" ({s['reason']})" if s["reason"] else "")
            for s in stretches[:_SHOWN]
        )
        more = f", ... {count - _SHOWN} more" if count > _SHOWN else ""
        text += f": {count} stretch{'' if count == 1 else 'es'}, scans {shown}{more}"
    return text
