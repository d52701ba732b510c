"""Integration layer: pybullet rigid scenes, contact, coupling and rerun recording.

The FEM core (``softbody``) never imports pybullet or rerun; everything that does lives here.

    from integration import World, Recorder

``World`` (world.py) couples soft bodies to a pybullet world, its own or the user's (``World(client=cid)``);
``BulletAdapter`` (bullet.py) is the pybullet side; ``RigidLink`` (rigid.py) one rigid link;
``Recorder`` and ``record`` (recording.py) write rerun recordings; ``Scene`` and the canonical scenes
live in scenes.py. Names are imported on first use, so that ``import integration`` stays cheap.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "World": "world", "Attachment": "world",
    "BulletAdapter": "bullet",
    "RigidLink": "rigid", "RigidBody": "rigid",
    "Recorder": "recording", "record": "recording",
    "Scene": "scenes", "build_scene": "scenes", "register_scene": "scenes", "SCENES": "scenes",
    "ContactSolver": "contact",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'integration' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
