"""The first box query of the process, made the same in every process.

coal's Box support function keeps its tie-breaking factor in a function-local static that
the process's first box support query sets, for every later box query of the process:
1 + 1e-10 when that query's direction has a zero component, 1 otherwise (coal issue #894,
open in coal 3.0.3). The factor moves distances and normals by rounding, which the contact
search amplifies: a posture depended on which process computed it, and 1 and 2 planner
workers gave different plans. The planning package makes one box query on import, before
any of its own, so every process holds the same factor: 1 + 1e-10, the factor the
planner's process held before (its plans are unchanged).
"""

import coal
import numpy as np


def make_first_box_query() -> None:
    """A distance query between two unit boxes 1 m apart along x, the first at the origin:
    GJK's first direction, (1, 0, 0) in the first box's frame, has zero components."""
    box = coal.Box(1.0, 1.0, 1.0)
    apart = coal.Transform3s(np.eye(3), np.array([2.0, 0.0, 0.0]))
    coal.distance(box, coal.Transform3s(), box, apart, coal.DistanceRequest(),
                  coal.DistanceResult())
