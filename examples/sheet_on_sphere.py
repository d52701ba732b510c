"""The sheet-on-sphere scene of docs/method.md section 5: build it, run it and print the monitored node.

    python examples/sheet_on_sphere.py [--element tet4|hex8|tet10] [--cells NX NY NZ] [--duration S] [--record [PATH]]

The scene itself is built in experiments/scenes.py (sheet_on_sphere()); this script only parses flags.
"""
import sys

from experiments.cli import scene_main

if __name__ == "__main__":
    sys.exit(scene_main("sheet-on-sphere", __doc__))
