"""Integration layer: pybullet rigid scenes, contact, coupling and rerun recording.

The FEM core (``softbody``) never imports pybullet or rerun; everything that does lives here.

    from integration import World, Recorder

``World`` (world.py) couples soft bodies to a pybullet world, its own or the user's (``World(client=cid)``);
``BulletAdapter`` (bullet.py) is the pybullet side; ``RigidLink`` (rigid.py) one rigid link;
``Recorder`` and ``record`` (recording.py) write rerun recordings. The experiment tooling (canonical scenes,
studies, sweeps, bench, the command line) is the package ``experiments``. Names are imported on first use, so that ``import integration`` stays cheap; pybullet
alone is imported here, once, with its build-time banner (written by C at import) sent to /dev/null.
"""
from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import sys
from typing import Iterator


@contextlib.contextmanager
def quiet_c_output(fds: tuple[int, ...] = (1, 2)) -> Iterator[None]:
    """Send whatever C code writes to the file descriptors ``fds`` (stdout, stderr) to /dev/null inside the
    block, and restore them after. Python's own streams are flushed first; descriptors that are not open
    (e.g. stdout replaced by an object without a file) are left alone."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in fds:
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:
                continue
            os.dup2(null, fd)
        yield
    finally:
        with contextlib.suppress(Exception):  # C's stdio buffers go to /dev/null too, not to the restored fd
            ctypes.CDLL(None).fflush(None)
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


if "pybullet" not in sys.modules:
    with quiet_c_output():
        import pybullet  # noqa: F401  (prints "pybullet build time: ..." once per process)

_EXPORTS = {
    "World": "world", "Attachment": "world",
    "BulletAdapter": "bullet",
    "RigidLink": "rigid", "RigidBody": "rigid",
    "Recorder": "recording", "record": "recording",
    "ContactSolver": "contact",
    "WorldState": "state",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'integration' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
