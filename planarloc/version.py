"""planarloc's version (one place: the package, the CLI's --version and every map's meta read it)."""

__version__ = "0.1.0"
