"""Contact-before-motion planning (Escande et al.): scenes, contacts and stances, collision
and static-equilibrium models, the posture generator, the potential field on a rough
trajectory, contact search volumes, the best-first planner and an independent verifier.
ROS-free like the rest of the library."""

from .coal_order import make_first_box_query

make_first_box_query()  # before any other coal query of this process (coal_order)
