"""Who hears whom among named agents (SPEC section 8): a topology given as a word, a list of edges, a rule
or the matrix itself becomes the `(n, n)` recipient matrix that `bitcomm.config.slot_table` and `Channel` read.

Kept apart from any environment so that a wrapper, a learner or a test can build the same matrix.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TypeAlias

import numpy as np

from bitcomm.errors import bad_value

Edge: TypeAlias = tuple[str, str] | list[str]
"""One `(sender, receiver)` pair of agent names, a tuple or, as JSON (`--topology`, config.json) writes it, a list."""

Topology: TypeAlias = str | Iterable[Edge] | Callable[[str, str], bool] | np.ndarray
"""`"all"`, `"ring"`, `(sender, receiver)` name pairs, a rule `(sender, receiver) -> bool`, or an `(n, n)` bool
recipient matrix."""

ALLOWED = (
    "must be 'all', 'ring', (sender, receiver) name pairs, a callable (sender, receiver) -> bool, "
    "or an (n, n) bool recipient matrix"
)


def recipients_of(agents: Sequence[str], topology: Topology) -> np.ndarray:
    """`(n, n)` bool in the order of `agents`: `[j, x]` is True when agent x hears agent j.

    - `"all"`: every agent hears every other one (never itself).
    - `"ring"`: agent i sends to agent (i + 1) % n, the goal-exchange convention (i sees i + 1's goal
      and tells it).
    - pairs `(sender, receiver)`: exactly those edges; names must be agents, no self edge, no duplicate.
    - a callable `rule(sender, receiver) -> bool`, asked once for each ordered pair of distinct agents.
    - an `(n, n)` bool numpy array: the matrix itself, in the order of `agents` (a wrapper's `recipients`, or one a
      graph library made), with a False diagonal.
    """
    names = list(agents)
    n = len(names)
    index = {a: i for i, a in enumerate(names)}
    mat = np.zeros((n, n), dtype=bool)
    if isinstance(topology, str):
        if topology == "all":
            return ~np.eye(n, dtype=bool)
        if topology == "ring":
            if n < 2:
                raise bad_value("topology", topology, f"a ring needs at least 2 agents, the env has {n}")
            mat[np.arange(n), (np.arange(n) + 1) % n] = True
            return mat
        raise bad_value("topology", topology, ALLOWED)
    if isinstance(topology, np.ndarray):
        return _checked_matrix(topology, n)
    if callable(topology):
        for s in names:
            for r in names:
                if s != r:
                    mat[index[s], index[r]] = _ask(topology, s, r)
        return mat
    if not isinstance(topology, Iterable):
        raise bad_value("topology", topology, ALLOWED)
    for edge in topology:
        if isinstance(edge, str) or not isinstance(edge, Sequence) or len(edge) != 2:
            raise bad_value("topology", edge, "each edge must be a (sender, receiver) pair of agent names")
        s, r = edge
        for name in (s, r):
            if name not in index:
                raise bad_value("topology", edge, f"{name!r} is not an agent; agents are {names}")
        if s == r:
            raise bad_value("topology", edge, "an agent cannot send to itself")
        if mat[index[s], index[r]]:
            raise bad_value("topology", edge, "this edge is listed twice")
        mat[index[s], index[r]] = True
    return mat


def _checked_matrix(matrix: np.ndarray, n: int) -> np.ndarray:
    """A copy of a recipient matrix given as an array, or one error line naming what is wrong with it."""
    if matrix.shape != (n, n):
        raise bad_value("topology", f"array of shape {matrix.shape}", f"a recipient matrix must be ({n}, {n}) here")
    if matrix.dtype != np.bool_:
        raise bad_value("topology", f"array of dtype {matrix.dtype}", "a recipient matrix must be of dtype bool")
    if matrix.diagonal().any():
        who = int(np.flatnonzero(matrix.diagonal())[0])
        raise bad_value("topology", f"array with [{who}, {who}] True", "an agent cannot send to itself")
    return matrix.copy()


def _ask(rule: Callable[[str, str], bool], sender: str, receiver: str) -> bool:
    """One answer of a topology rule, or one error line if it raises or answers something else than a bool."""
    call = f"topology({sender!r}, {receiver!r})"
    try:
        answer = rule(sender, receiver)
    except Exception as e:  # the user's rule: any failure becomes one line naming the call
        reason = " ".join(str(e).split())
        raise bad_value("topology", call, f"the rule raised {type(e).__name__}: {reason}") from e
    if not isinstance(answer, (bool, np.bool_)):
        raise bad_value("topology", call, f"the rule must return a bool, it returned {answer!r}")
    return bool(answer)
