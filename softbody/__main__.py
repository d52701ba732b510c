"""``python -m softbody`` hands over to the command line in experiments.cli."""
import sys

from experiments.cli import main

sys.exit(main())
