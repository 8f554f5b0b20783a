"""The errors every layer of the bake may raise."""


class Cancelled(Exception):
    """The bake was cancelled (its cancel event set); nothing was written."""


class BakeError(RuntimeError):
    """A bake could not run; the message says why (nothing was written)."""
