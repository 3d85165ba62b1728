"""The browser UI of ``hitl-slam serve``: one editing session served over HTTP on loopback, drawn
with WebGL by the static front end in ``static/``. :func:`create_app` builds the ASGI app over a
:class:`SessionHost`; :func:`run_server` is what the command line runs.
"""

from __future__ import annotations

from hitl_slam.web.app import create_app
from hitl_slam.web.host import SessionHost
from hitl_slam.web.server import run_server

__all__ = ["SessionHost", "create_app", "run_server"]
