"""Pictures of a recording from rerun's own viewer, without a display (integration.render).

    python benchmarks/render_recording.py RECORDING.rrd --at 1.0 [--at 2.0] [--out docs/img/sheet] \
        [--size 1600x1000] [--view scene] [--settle 8]

Starts rerun's native viewer headless, bound to 127.0.0.1 on a free port, opens the recording with its own
blueprint, saves a screenshot at each ``--at`` time [s] to ``<out>_t<time>.png`` and shuts the viewer down.
Needs a Vulkan driver: without a GPU, Mesa's software one (``apt-get install mesa-vulkan-drivers``).
"""
import sys

from integration.render import main

if __name__ == "__main__":
    sys.exit(main())
