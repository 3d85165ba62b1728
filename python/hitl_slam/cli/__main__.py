"""``python -m hitl_slam.cli``: the ``hitl-slam`` command."""

import sys

from hitl_slam.cli import main

if __name__ == "__main__":
    sys.exit(main())
