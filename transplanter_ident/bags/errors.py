"""The error every bag operation raises: one line naming the bag and the reason."""

from __future__ import annotations

from transplanter_ident.files import one_line


class BagError(ValueError):
    """A bag that cannot be read or written; the message is one line naming the bag and the reason."""

    def __init__(self, message: str) -> None:
        super().__init__(one_line(message))
