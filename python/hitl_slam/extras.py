"""Optional dependencies, installed as extras: ``[web]`` (fastapi, uvicorn, pydantic) for
``hitl-slam serve``, ``[plot]`` (matplotlib) for figures and ``[ros]`` (rosbags) for ROS bags.
``import hitl_slam`` imports none of them; what needs one calls :func:`require` first, so a
missing extra is one line naming it instead of a traceback from deep inside.
"""

from __future__ import annotations

import importlib

from hitl_slam.errors import MissingExtra

__all__ = ["EXTRAS", "missing_extra", "require"]

EXTRAS: dict[str, tuple[str, ...]] = {
    "web": ("fastapi", "uvicorn", "pydantic"),
    "plot": ("matplotlib",),
    "ros": ("rosbags",),
}
"""The modules each extra installs (the ``[project.optional-dependencies]`` of pyproject.toml)."""


def missing_extra(extra: str, who: str) -> MissingExtra:
    """The error saying that ``who`` (a command or a module) needs ``extra``."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; the extras are {', '.join(EXTRAS)}")
    return MissingExtra(f"{who} needs the {extra} extra: pip install 'hitl-slam[{extra}]'")


def require(extra: str, who: str) -> None:
    """Import the modules of ``extra``; raises :class:`~hitl_slam.errors.MissingExtra` naming
    ``who`` (e.g. ``"hitl-slam serve"``) and the extra when one of them cannot be imported."""
    error = missing_extra(extra, who)
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise error from exc
