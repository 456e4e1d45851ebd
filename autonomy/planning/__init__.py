"""Planning: the forward-arc motion primitives of Lee et al. (2024), "Rapid Quadrotor Navigation
in Diverse Environments using an Onboard Depth Camera", as the paper flies them."""
