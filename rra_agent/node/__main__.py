"""``python -m rra_agent.node``: one component node as its own process."""

import sys

from rra_agent.node.process import main

sys.exit(main())
