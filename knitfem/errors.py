"""The error every layer raises on bad input."""

__all__ = ["KnitError"]


class KnitError(Exception):
    """Bad input: the message is one line saying what is wrong and what to do."""
