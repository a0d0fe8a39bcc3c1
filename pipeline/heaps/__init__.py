"""Pushing in clutter, the simulation half (thesis chapter 3): heaps of corpus objects
dropped into a bin in pybullet, pushed by a finger, and scored by the confidence of the best
accessible suction and parallel-jaw grasp.  See docs/HEAPS.md."""
