"""Camera drivers: each delivers frames with intrinsics and timestamps on the companion's clock."""
