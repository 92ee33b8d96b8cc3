"""Command-line interface (``topoloc``)."""
