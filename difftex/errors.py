"""The one exception type users see: a one-line message naming the file and the problem."""


class DifftexError(Exception):
    """Bad input or a failed stage; the CLI prints ``difftex: error: <message>`` and exits 2."""
