"""The version of forestreg, in one place: the package, the plugin hosts and the packaging read it
here (a module of its own, so that reading the version imports nothing else)."""

__version__ = "0.2.0"
