"""Pushing in clutter (thesis chapter 3): the heap state and the five planar push policies.

numpy only, like ``schema/``: the service's heap planner imports it, and so do the pybullet
heap simulation and the experiment in ``pipeline/heaps/``.
"""
