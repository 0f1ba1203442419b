"""difftex: differentiable texturing of planar architectural proxies from registered photos."""

from difftex.errors import DifftexError

__all__ = ["DifftexError", "__version__"]
__version__ = "0.1.0"
