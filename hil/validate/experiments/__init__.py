"""Importing this package registers every experiment (one module per topic)."""
