"""The package version, in one place (read by the build, the files written and the CLI)."""

__version__ = "0.1.0"
