"""``python -m haptic_collab.cli``: the ``haptic`` command run as a module (as the demo, the
server process and the tests start it)."""

import sys

from haptic_collab.cli import main

if __name__ == "__main__":
    sys.exit(main())
