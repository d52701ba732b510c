"""``python -m softbody`` hands over to the command line in integration.cli."""
import sys

from integration.cli import main

sys.exit(main())
