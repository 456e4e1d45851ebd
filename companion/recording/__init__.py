"""The flight recorder: each flight into one MCAP file, and the tools that read it back."""
