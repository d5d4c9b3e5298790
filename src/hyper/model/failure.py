"""How a coupled run fails for good: an exception free of the finite elements, so that
whoever runs a model catches it without loading DOLFINx."""

from __future__ import annotations


class GrowthFailure(RuntimeError):
    """A growth step failed for good (Newton after every allowed cut, or the signaling
    ODEs); the model is back at the state after its last completed step."""

    def __init__(self, message: str, *, step: int, t0: float, t1: float):
        super().__init__(message)
        self.step = step  # the step that failed (1-based: steps done before it + 1)
        self.t0 = t0  # h, its start
        self.t1 = t1  # h, its end
