"""Random problems shared by the hierarchy and limit tests."""

import numpy as np
from hypothesis import strategies as st
from stance.hierarchy import Level


@st.composite
def hierarchy_problems(draw):
    """(levels, nv, fixed_index, fixed_dq, rng): random levels of random rank, some fixed
    joints, and the generator that drew them (for further random data)."""
    nv = draw(st.integers(2, 12))
    shapes = draw(st.lists(
        st.integers(1, 8).flatmap(lambda rows: st.tuples(st.just(rows),
                                                         st.integers(0, min(rows, nv)))),
        min_size=1, max_size=4))
    fixed = draw(st.lists(st.booleans(), min_size=nv, max_size=nv))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    levels = [Level(rng.normal(size=(rows, rank)) @ rng.normal(size=(rank, nv)),
                    rng.normal(size=rows))
              for rows, rank in shapes]
    fixed_index = np.flatnonzero(fixed)
    return levels, nv, fixed_index, rng.normal(size=len(fixed_index)), rng


def residual(level: Level, dq: np.ndarray) -> float:
    """|J dq - target| of one level."""
    return float(np.linalg.norm(level.jacobian @ dq - level.target))


def random_offset(rng, reachable: bool) -> np.ndarray:
    """A target displacement (m): < 0.3 m per axis if reachable, else 1-3 m away."""
    if reachable:
        return rng.uniform(-0.3, 0.3, 3)
    direction = rng.normal(size=3)
    return rng.uniform(1.0, 3.0) * direction / np.linalg.norm(direction)
