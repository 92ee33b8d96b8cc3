"""The package's version, in a foundation module: code inside the package reads it from here, never from
``topoloc`` itself, whose ``__init__`` sits above every layer (issue #41)."""

__version__ = "0.1.0"
