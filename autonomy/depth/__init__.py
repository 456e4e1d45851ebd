"""Depth: the network's relative disparity, its rescaling to metric depth, and depth metrics."""
