"""The package version, on the ground so every layer can name it."""

__version__ = "0.1.0"
