"""The hanging-tube scene of docs/method.md section 5: build it, run it and print the monitored node.

    python examples/hanging_tube.py [--element tet4|hex8|tet10] [--cells NX NY NZ] [--duration S] [--record [PATH]]

The scene itself is built in integration/scenes.py (hanging_tube()); this script only parses flags.
"""
import argparse

from integration.cli import add_scene_arguments, run_scene

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, scene="hanging-tube")
    run_scene(parser.parse_args(), "hanging-tube")
