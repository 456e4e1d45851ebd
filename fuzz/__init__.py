"""Fuzz harnesses of the project's own readers of outside input (fuzz/README.md)."""
