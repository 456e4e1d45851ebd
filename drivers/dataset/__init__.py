"""Recorded datasets on disk, in the EuRoC/ASL folder layout (DESIGN.md)."""
