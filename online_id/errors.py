"""One exception hierarchy for the whole package.

Every error a user can cause (bad file, bad config, bad frame, no excitation)
is an :class:`OnlineIdError`; the CLI prints its message on one line and exits
with status 2.  The subclasses also derive from the matching built-in
exception so that callers using plain ``except ValueError`` keep working.
"""

from __future__ import annotations

import unicodedata


class OnlineIdError(Exception):
    """Base class of every error raised on purpose by online-id."""


class ConfigError(OnlineIdError, ValueError):
    """A configuration file or setting is invalid (names key, value and file)."""


class DbcError(OnlineIdError, ValueError):
    """A DBC file cannot be used (names file, message and signal)."""


class BusError(OnlineIdError, OSError):
    """The CAN bus cannot be opened, read or written."""


class InputDataError(OnlineIdError, ValueError):
    """Input data is unusable (names file, line and column where known)."""


class EstimationError(OnlineIdError, ArithmeticError):
    """The estimation cannot produce a result from the given data."""


def printable(text: str) -> str:
    """``text`` with control and other non-printing characters escaped (``\\x1b``, ``\\n``): one safe line."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() or (c == " ") else
                   (repr(c)[1:-1] if unicodedata.category(c)[0] in "CZ" else c) for c in text)


class FieldError(ConfigError):
    """A dataclass field failed its own validation; ``key`` is relative to the dataclass.

    :func:`online_id.config.build` turns it into a message with the full key
    path and the file.
    """

    def __init__(self, key: str, value: object, reason: str) -> None:
        super().__init__(f"{key} = {value!r}: {reason}")
        self.key, self.value, self.reason = key, value, reason
