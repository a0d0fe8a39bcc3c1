"""One object at a time: everything the toppling database computes for a mesh.

config -> mesh -> poses (edges) -> contacts (sampling, collision) -> topple
(checked against reference) -> suction -> mdp; ``evaluation`` runs them for one
object.  Depends on ``schema`` only, never on ``pipeline.build`` or ``studies``.
"""
