"""Integration layer: pybullet rigid scenes, contact, coupling and rerun recording.

The FEM core (``softbody``) never imports pybullet or rerun; everything that does lives here.
"""
