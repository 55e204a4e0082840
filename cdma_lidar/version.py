"""The toolkit's version: one constant every layer may import (the package's
``__init__`` re-exports it, and also loads the quick-start API, which sits at the top)."""

__all__ = ["__version__"]

#: The distribution's version (pyproject.toml's ``version``).
__version__ = "0.1.0"
