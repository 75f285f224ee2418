"""``python -m rra_agent``: the ``rra`` command line."""

import sys

from rra_agent.cli import main

sys.exit(main())
