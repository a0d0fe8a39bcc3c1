"""The words and codes a dataset is written in, defined once for the pipeline,
the service and the studies.

Action statuses are stored as strings in the tables and as int8 codes in memory
(the code is the position in ``STATUS_NAMES``).  Trial outcomes in the HDF5
``outcomes`` arrays are the base edge an object toppled over (0, 1, ...) or one
of the negative codes below.
"""

from __future__ import annotations

from typing import Literal, get_args

StatusName = Literal["ok", "too_low", "pushes_up", "finger_collision"]
STATUS_NAMES: tuple[str, ...] = get_args(StatusName)
"""``ok``, or why a finger cannot execute a candidate push (thesis 4.4.1)."""
STATUS_OK, STATUS_TOO_LOW, STATUS_PUSHES_UP, STATUS_FINGER_COLLISION = range(len(STATUS_NAMES))

PolicyName = Literal["max_height", "greedy", "value_iteration"]
POLICIES: tuple[str, ...] = get_args(PolicyName)
"""Policies whose choice per pose is stored (thesis 4.3): ``<name>_action``, ``<name>_value``."""

NO_OP = -1
"""Action id a policy returns when it chooses not to push (policy columns, service answers)."""

OUTCOME_NO_EDGE = -1
"""Trial outcome: the object did not topple over any base edge."""
OUTCOME_NOT_EVALUATED = -2
"""Trial outcome of an action whose status is not ``ok``."""
