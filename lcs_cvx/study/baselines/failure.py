"""The one error a baseline raises for a result of its method rather than a bug."""

__all__ = ["BaselineFailed"]


class BaselineFailed(RuntimeError):
    """The baseline's own fitting algorithm (a third-party package's fit) failed on this
    problem: a result of the method, not a bug. The message names the method and the original
    exception (``"PARC failed: ValueError: ..."``), which is chained as ``__cause__``."""
