"""The package version (one place; ``lagsindy.__version__`` re-exports it)."""

__version__ = "0.1.0"
