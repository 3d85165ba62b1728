"""Optional dependencies, installed as extras: ``[web]`` (fastapi, uvicorn, pydantic) for
``hitl-slam serve``, ``[plot]`` (matplotlib) for figures and ``[ros]`` (rosbags) for ROS bags.
``import hitl_slam`` imports none of them; what needs one calls :func:`require` first, so a
missing extra is one line naming it instead of a traceback from deep inside.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import re

from hitl_slam.errors import MissingExtra

__all__ = ["EXTRAS", "install_hint", "missing_extra", "require", "requirements"]

EXTRAS: dict[str, tuple[str, ...]] = {
    "web": ("fastapi", "uvicorn", "pydantic"),
    "plot": ("matplotlib",),
    "ros": ("rosbags",),
}
"""The modules each extra installs (the ``[project.optional-dependencies]`` of pyproject.toml)."""


def requirements(extra: str) -> list[str]:
    """The requirements ``extra`` installs, as the installed package's metadata states them
    (``["rosbags>=0.11"]``), or the bare module names of :data:`EXTRAS` without metadata."""
    try:
        stated = importlib.metadata.requires("hitl-slam") or []
    except importlib.metadata.PackageNotFoundError:
        stated = []
    marker = re.compile(rf"""^(.*?)\s*;\s*extra\s*==\s*['"]{re.escape(extra)}['"]\s*$""")
    found = [m.group(1).strip() for r in stated if (m := marker.match(r))]
    return found or list(EXTRAS[extra])


def install_hint(extra: str) -> str:
    """A command that installs ``extra`` however hitl-slam was installed (from a clone, a wheel
    or an index): its requirements by name, or the extra from a clone."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; the extras are {', '.join(EXTRAS)}")
    packages = " ".join(f"'{r}'" for r in requirements(extra))
    return f"pip install {packages} (or, in a clone of hitl-slam: pip install '.[{extra}]')"


def missing_extra(extra: str, who: str) -> MissingExtra:
    """The error saying that ``who`` (a command or a module) needs ``extra``, and how to
    install it (:func:`install_hint`)."""
    return MissingExtra(f"{who} needs the {extra} extra: {install_hint(extra)}")


def require(extra: str, who: str) -> None:
    """Import the modules of ``extra``; raises :class:`~hitl_slam.errors.MissingExtra` naming
    ``who`` (e.g. ``"hitl-slam serve"``) and the extra when one of them cannot be imported."""
    error = missing_extra(extra, who)
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise error from exc
