"""Route modules, one per resource: ``objects`` (objects, poses, actions, Q-values,
batch transitions) and ``plan`` (planning from an observed pose, batch plans)."""
