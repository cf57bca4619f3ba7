"""`Outcome`: how a trace, a render or a fit ended, one enumeration for all of them.

Results carry an `outcome`; entry points with `throw=True` (the default of `fit`) raise
`OutcomeError` instead of returning anything but `Outcome.SUCCESSFUL`.
"""

from __future__ import annotations

import enum


class Outcome(enum.Enum):
    """How a computation ended (the value is the message a report shows)."""

    SUCCESSFUL = "successful"
    BUDGET_EXHAUSTED = "the step budget (TraceOptions.max_steps) ran out before every photon finished"
    NOT_CONVERGED = "the fit did not settle within max_retraces re-traces"
    SINGULAR = "the Gauss-Newton matrix is singular: a parameter does not affect the residuals"
    NON_FINITE = "a step left the parameters non-finite"

    @property
    def successful(self) -> bool:
        return self is Outcome.SUCCESSFUL


class OutcomeError(RuntimeError):
    """Raised with `throw=True` when a computation ends in anything but `Outcome.SUCCESSFUL`."""

    def __init__(self, outcome: Outcome, detail: str = ""):
        self.outcome = outcome
        super().__init__(outcome.value + (f": {detail}" if detail else ""))
