"""The package's version (core: the caches and run folders a release writes record it)."""

__version__ = "0.1.0"
